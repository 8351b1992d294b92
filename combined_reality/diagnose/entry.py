"""The diagnosis's entry: with the cylinder file's values as they are (diagnosis), or calibrated
with every candidate (calibrated, DiagnoseOptions.calibrate)."""
from __future__ import annotations

from typing import Callable, Sequence

from sim.cylinder import Cylinder

from ..files import Run
from .calibrated import diagnose_calibrated
from .diagnosis import Diagnosis, diagnose_as_filed
from .options import DiagnoseOptions

__all__ = ["diagnose"]


def diagnose(cyl: Cylinder, train: Run | Sequence[Run], valid: Run, options: DiagnoseOptions = DiagnoseOptions(),
             progress: Callable[[str], None] | None = None) -> Diagnosis:
    """Why the simulation differs from the rig. TRAIN is one run, or with `options.calibrate`
    several (a calibration run and an ordinary one are calibrated together); VALID is never fitted."""
    runs = [train] if isinstance(train, Run) else list(train)
    if options.calibrate:
        return diagnose_calibrated(cyl, runs, valid, options, progress)
    if len(runs) != 1:
        raise ValueError("several TRAIN runs are fitted together only with calibrate (DiagnoseOptions.calibrate)")
    return diagnose_as_filed(cyl, runs[0], valid, options, progress)
