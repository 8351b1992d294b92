"""Why the simulation still differs from the rig: where the gap lies, which unmodelled
effect causes it, how far it shrinks once that effect is added.

- analysis: the diagnosis itself (`diagnose`), regions, subsystems, regressors
- text: the diagnosis in words (console, report, Rerun)
- report: the self-contained HTML report (`diagnose.report.write_report`; imports matplotlib)
- rerun: the diagnosis on Rerun's time line (`diagnose.rerun.log_diagnosis`; imports rerun)
"""
from .analysis import (MIN_REGION_FRACTION, NESTED_START, Candidate, DiagnoseOptions, Diagnosis, NominalFit,
                       best_of_starts, candidate_starts, decide, diagnose, equation_errors, explained_share,
                       fit_candidate, further_starts, has_nested_start, neutral_start, operating_regions, regions,
                       regressor_correlations, subsystem_split, whiteness)

__all__ = ["MIN_REGION_FRACTION", "NESTED_START", "Candidate", "DiagnoseOptions", "Diagnosis", "NominalFit",
           "best_of_starts", "candidate_starts", "decide", "diagnose", "equation_errors", "explained_share",
           "fit_candidate", "further_starts", "has_nested_start", "neutral_start", "operating_regions", "regions",
           "regressor_correlations", "subsystem_split", "whiteness"]
