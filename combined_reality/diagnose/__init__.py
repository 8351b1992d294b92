"""Why the simulation still differs from the rig: where the gap lies, which unmodelled
effect causes it, how far it shrinks once that effect is added.

- entry: `diagnose`, with the file's values as they are or calibrated with every candidate
- diagnosis: the diagnosis with the file's values as they are (diagnose_as_filed) and its
  document (Diagnosis)
- options: what a diagnosis may do and what it takes to decide (DiagnoseOptions)
- candidates: a candidate effect, its starts, and how it is scored against a baseline
- fits: the candidates' fits on TRAIN, their validation on VALID, the screen, further starts
- verdict: the ranking, the best pair, the verdict's rules
- where: the residual's whiteness (the share of the gap per operating regime: identify.regimes)
- subsystems: the subsystems' share of the gap, equation errors, regressor correlations
- calibrated: calibration and diagnosis together (`diagnose --calibrate`)
- text: the diagnosis in words (console, report, Rerun)
- report: the self-contained HTML report (`diagnose.report.write_report`; imports matplotlib)
- rerun: the diagnosis on Rerun's time line (`diagnose.rerun.log_diagnosis`; imports rerun)
"""
from ..identify import MIN_REGION_FRACTION, operating_regions, regions, untaught_regions
from .calibrated import ABSORBED, Absorption, diagnose_calibrated
from .candidates import (NESTED_START, Candidate, NominalFit, candidate_starts, explained_share, has_nested_start,
                         neutral_start)
from .diagnosis import Diagnosis, diagnose_as_filed
from .entry import diagnose
from .fits import best_of_starts, fit_candidate, further_starts
from .options import DiagnoseOptions
from .subsystems import equation_errors, regressor_correlations, subsystem_split
from .verdict import decide
from .where import whiteness

__all__ = ["ABSORBED", "Absorption", "MIN_REGION_FRACTION", "NESTED_START", "Candidate", "DiagnoseOptions", "Diagnosis", "NominalFit",
           "best_of_starts", "candidate_starts", "decide", "diagnose", "diagnose_as_filed", "diagnose_calibrated",
           "equation_errors", "explained_share", "fit_candidate", "further_starts", "has_nested_start", "neutral_start",
           "operating_regions", "regions", "regressor_correlations", "subsystem_split", "untaught_regions", "whiteness"]
