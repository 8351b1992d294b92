"""Checks of runs against the cylinder file they are to be fitted with: what a run may be
read as on its own (files.runs) can still be the wrong unit, origin or cylinder for this
file. Each check refuses with one sentence naming the file (RunFormatError: bad input)."""
from __future__ import annotations

import hashlib
from typing import Sequence

import numpy as np

from sim.cylinder import ConfigError, Cylinder

from .runs import Run, RunFormatError, cylinder_identity, recorded_elsewhere

__all__ = ["check_run_against_cylinder", "check_pressures_absolute", "supply_seen", "check_train_and_valid",
           "same_data", "check_distinct_runs", "check_moves"]


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
    check_pressures_absolute(run, cyl)


# an exhausted chamber sits near the atmosphere; gauge readings sit near 0 for a while
_GAUGE_SHARE = 0.01  # of the samples below half the atmosphere
_REST_SPEED = 2e-3  # m/s: the piston rests (at an end) below this
_OPEN = 0.3  # |u| at which the valve is open enough to bring a resting chamber to the supply
_PLATEAU_S = 0.2  # s at rest with the valve open that show the supply pressure


def check_pressures_absolute(run: Run, cyl: Cylinder) -> None:
    """Refuse chamber pressures that are gauge, and a supply pressure in the cylinder file that
    is gauge. Gauge chambers sit below half the atmosphere for more than 1 % of a run that
    exhausts a chamber. Where the piston rests (at an end) with the valve open for a while,
    the filled chamber shows the supply pressure: a supply one atmosphere above the file's
    means the file's is gauge, one atmosphere below means the run's pressures are. A run that
    never exhausts a chamber nor rests with the valve open cannot tell (docs/formats.md)."""
    pa, ps = cyl.supply.atmosphere, cyl.supply.pressure
    cyl_file = cyl.source or "the cylinder file"
    for name in ("p1", "p2"):
        p = getattr(run, name)
        low = p < 0.5 * pa  # NaN (not measured) is not low
        if low.sum() > _GAUGE_SHARE * np.isfinite(p).sum():
            i = int(np.argmax(low))
            raise RunFormatError(f"{run.source}, column '{name}' at t = {run.t[i]:.6g} s: {p[i]:.4g} Pa, and "
                                 f"{100 * low.mean():.3g} % of the run below half the atmosphere ({pa:g} Pa in "
                                 f"{cyl_file}), look like gauge pressures; a run holds absolute Pa (import converts "
                                 "gauge readings with gauge = true).")
    seen = supply_seen(run)
    if seen is None:
        return
    supply, i = seen
    if supply > ps + 0.5 * pa:
        raise ConfigError(f"{cyl_file}: key 'supply.pressure' = {ps:g} Pa looks like gauge: with the valve open and "
                          f"the piston at rest, the filled chamber of {run.source} holds {supply:.4g} Pa (from t = "
                          f"{run.t[i]:.6g} s), which is the supply; give it absolute (gauge + {pa:g} Pa).")
    if supply < ps - 0.5 * pa:
        raise RunFormatError(f"{run.source}, from t = {run.t[i]:.6g} s: with the valve open and the piston at rest "
                             f"the filled chamber holds {supply:.4g} Pa, about one atmosphere below the supply "
                             f"{ps:g} Pa of {cyl_file}: the run's pressures look gauge (absolute Pa required), or "
                             "the supply in the file is wrong.")


def supply_seen(run: Run) -> tuple[float, int] | None:
    """The supply pressure the run shows, and where: the filled chamber (p1 for u > 0, p2 for
    u < 0) while the valve is open and the piston rests for at least 0.2 s in all; None if
    the run never does so."""
    if run.n < 50:
        return None
    dt = float(np.median(np.diff(run.t)))
    h = 10  # central difference over 2h samples: the sensor noise of x stays far below the rest speed
    v = np.full(run.n, np.inf)
    v[h:-h] = (run.x[2 * h:] - run.x[:-2 * h]) / (run.t[2 * h:] - run.t[:-2 * h])
    rest = (np.abs(v) < _REST_SPEED) & (np.abs(run.u) > _OPEN)
    filled = np.where(run.u > 0, run.p1, run.p2)
    rest &= np.isfinite(filled)
    if rest.sum() * dt < _PLATEAU_S:
        return None
    idx = np.flatnonzero(rest)
    # the chamber is still filling at first: the upper part of its values is the plateau
    return float(np.percentile(filled[idx], 90)), int(idx[0])


_STILL = 0.005  # of the stroke: a piston whose position spans less has not moved


def check_moves(runs: Sequence[Run], cyl: Cylinder, advice: str) -> None:
    """Refuse runs in which the piston never moves (its position spans less than 0.5 % of the
    stroke): nothing that shows only in motion can be fitted to them. `advice` ends the
    sentence ('...; {advice}.')."""
    span = max((float(np.nanmax(r.x) - np.nanmin(r.x)) for r in runs if np.isfinite(r.x).any()), default=0.0)
    if span < _STILL * cyl.geometry.stroke:
        names = ", ".join(str(r.source.name) if r.source is not None else "the run" for r in runs)
        raise RunFormatError(f"{names}: the piston does not move (its position spans {span * 1e6:.3g} um of the "
                             f"{cyl.geometry.stroke:g} m stroke); {advice}.")


def _digest(run: Run) -> bytes:
    """The samples' fingerprint: runs with equal digests hold the same data, whatever their names."""
    h = hashlib.sha256()
    for col in (run.t, run.u, run.x, run.p1, run.p2):
        h.update(np.ascontiguousarray(col, dtype=np.float64).tobytes())
    return h.digest()


def same_data(a: Run, b: Run) -> bool:
    """Whether two runs hold the same samples (t, u, x, p1, p2)."""
    return a.n == b.n and _digest(a) == _digest(b)


def check_distinct_runs(runs: Sequence[Run], names: Sequence[str]) -> None:
    """Refuse the same data given twice (under one name or two): fitted twice, it counts double
    and its standard deviations shrink by the square root of two without any new information."""
    seen: dict[bytes, str] = {}
    for run, name in zip(runs, names):
        key = _digest(run)
        if key in seen:
            same = f"{name} is given twice" if seen[key] == name else f"{seen[key]} and {name} hold the same samples"
            raise RunFormatError(f"{same}; a run fitted twice counts twice (its standard deviations shrink by "
                                 "sqrt 2 without new information), so give each run once.")
        seen[key] = name


def check_train_and_valid(cyl: Cylinder, train: Run, valid: Run, train_name: str, valid_name: str,
                          verb: str = "diagnose") -> str | None:
    """Refuse a TRAIN/VALID pair of which a run does not fit the cylinder file (stroke,
    pressures), is shorter than 1 s at 1 kHz, or was recorded on another cylinder than the
    file describes (its cylinder tag), or VALID sampled at another rate than TRAIN.
    `verb` completes the advice: '... ; {verb} runs of the cylinder they were recorded on.'
    Returns a warning when VALID holds the same samples as TRAIN (a validation that cannot
    fail), else None."""
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
    if same_data(train, valid):
        return (f"{valid_name} holds the same samples as {train_name}: the validation scores the fit on the data it "
                "was fitted to, so it cannot tell a real gain from overfitting; validate on another run.")
    return None
