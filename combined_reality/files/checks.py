"""Checks of runs against the cylinder file they are to be fitted with: what a run may be
read as on its own (files.runs) can still be the wrong unit, origin or cylinder for this
file. Each check refuses with one sentence naming the file (RunFormatError: bad input)."""
from __future__ import annotations

import numpy as np

from sim.cylinder import Cylinder

from .runs import Run, RunFormatError, cylinder_identity, recorded_elsewhere

__all__ = ["check_run_against_cylinder", "check_train_and_valid"]


def check_run_against_cylinder(run: Run, cyl: Cylinder) -> None:
    """Refuse a run whose positions cannot lie on this cylinder's stroke or whose pressures far
    exceed its supply (a wrong unit, origin or cylinder)."""
    L = cyl.geometry.stroke
    if not (np.isfinite(run.x).any() and np.isfinite(run.p1).any() and np.isfinite(run.p2).any()):
        missing = next(n for n in ("x", "p1", "p2") if not np.isfinite(getattr(run, n)).any())
        raise RunFormatError(f"{run.source}: the channel '{missing}' was not measured at any sample; "
                             "nothing to fit it with.")
    lo, hi = float(np.nanmin(run.x)), float(np.nanmax(run.x))
    if lo < -0.1 * L or hi > 1.1 * L:
        raise RunFormatError(f"{run.source}: position spans {lo:.4g} to {hi:.4g} m but the stroke in "
                             f"{cyl.source or 'the cylinder file'} is {L:g} m (wrong unit, wrong origin or wrong "
                             "cylinder?).")
    pmax = float(max(np.nanmax(run.p1), np.nanmax(run.p2)))
    if pmax > 1.5 * cyl.supply.pressure:
        raise RunFormatError(f"{run.source}: chamber pressure reaches {pmax:.4g} Pa, far above the supply pressure "
                             f"{cyl.supply.pressure:.4g} Pa of {cyl.source or 'the cylinder file'}.")


def check_train_and_valid(cyl: Cylinder, train: Run, valid: Run, train_name: str, valid_name: str,
                          verb: str = "diagnose") -> None:
    """Refuse a TRAIN/VALID pair of which a run does not fit the cylinder file (stroke,
    pressures), is shorter than 1 s at 1 kHz, or was recorded on another cylinder than the
    file describes (its cylinder tag), or VALID sampled at another rate than TRAIN.
    `verb` completes the advice: '... ; {verb} runs of the cylinder they were recorded on.'"""
    for r, what in ((train, train_name), (valid, valid_name)):
        check_run_against_cylinder(r, cyl)
        if r.n < 1000:
            raise RunFormatError(f"{what}: {r.n} samples are too few (at least 1 s at 1 kHz).")
        theirs = recorded_elsewhere(r, cyl)
        if theirs is not None:
            raise RunFormatError(f"{what} was recorded on the cylinder '{theirs}', but the cylinder file "
                                 f"{cyl.source or ''} describes '{cylinder_identity(cyl)}'; {verb} runs of the "
                                 "cylinder they were recorded on.")
    if abs(valid.sample_period / train.sample_period - 1) > 0.01:
        raise RunFormatError(f"{valid_name} is sampled every {valid.sample_period * 1e3:.3g} ms but {train_name} "
                             f"every {train.sample_period * 1e3:.3g} ms; validate with a run of the same rig and rate.")
