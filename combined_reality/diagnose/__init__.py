"""Why the simulation still differs from the rig: where the gap lies, which unmodelled
effect causes it, how far it shrinks once that effect is added.

- entry: `diagnose`, with the file's values as they are or calibrated with every candidate
- diagnosis: the diagnosis itself, regions, subsystems, regressors
- calibrated: calibration and diagnosis together (`diagnose --calibrate`)
- text: the diagnosis in words (console, report, Rerun)
- report: the self-contained HTML report (`diagnose.report.write_report`; imports matplotlib)
- rerun: the diagnosis on Rerun's time line (`diagnose.rerun.log_diagnosis`; imports rerun)
"""
from .diagnosis import (MIN_REGION_FRACTION, NESTED_START, Candidate, DiagnoseOptions, Diagnosis, NominalFit,
                       best_of_starts, candidate_starts, decide, diagnose_as_filed, equation_errors, explained_share,
                       fit_candidate, further_starts, has_nested_start, neutral_start, operating_regions, regions,
                       regressor_correlations, subsystem_split, whiteness)
from .calibrated import ABSORBED, diagnose_calibrated
from .entry import diagnose

__all__ = ["ABSORBED", "MIN_REGION_FRACTION", "NESTED_START", "Candidate", "DiagnoseOptions", "Diagnosis", "NominalFit",
           "best_of_starts", "candidate_starts", "decide", "diagnose", "diagnose_as_filed", "diagnose_calibrated",
           "equation_errors", "explained_share", "fit_candidate", "further_starts", "has_nested_start", "neutral_start",
           "operating_regions", "regions", "regressor_correlations", "subsystem_split", "whiteness"]
