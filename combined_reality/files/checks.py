"""Checks of runs against the cylinder file they are to be fitted with: what a run may be
read as on its own (files.runs) can still be the wrong unit, origin or cylinder for this
file. Each check refuses with one sentence naming the file, the likely cause and the fix
(RunFormatError: bad input; ConfigError where the cylinder file is wrong), and says in a
note what it is not sure of. `identify.preflight` runs them with the checks that need the
motion's derivatives; every subcommand that takes a run and a cylinder goes through it."""
from __future__ import annotations

import hashlib
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from sim.cylinder import ConfigError, Cylinder

from .runs import GEOMETRY, Run, RunFormatError, recorded_cylinder, recorded_file, recorded_geometry

__all__ = ["check_run_against_cylinder", "check_run_shape", "check_supply", "check_pressures_absolute", "supply_seen",
           "check_train_and_valid", "run_name", "header_geometry", "header_cylinder_file", "GAUGE_FIX", "same_data",
           "check_distinct_runs"]

# how gauge readings become absolute, for every message that suspects them
GAUGE_FIX = "add the atmosphere to them (or set gauge = true for them in the import map)"
_STROKE_MARGIN = 0.1  # of the stroke: end stops, sensor offsets, noise
# a stroke measured in another unit: (factor, unit, import map unit)
_LENGTH_UNITS = ((1000.0, "millimetres", "mm"), (100.0, "centimetres", "cm"), (1 / 0.0254, "inches", "inch"))


def run_name(run: Run) -> str:
    """How a message names the run: its file, else 'the run'."""
    return str(run.source) if run.source is not None else "the run"


def _mm(v: float) -> str:
    return f"{v * 1e3:.4g} mm"


def header_geometry(run: Run, cyl: Cylinder) -> tuple[list[str], str | None]:
    """What the run's cylinder tag says against the file: the quantities of the geometry that
    differ (bore, rod, stroke), and a note when only the name differs (a calibrated or renamed
    copy of the same cylinder)."""
    theirs = recorded_geometry(run)
    if theirs is None:
        return [], None
    g = cyl.geometry
    differ = [k for k in GEOMETRY if not math.isclose(theirs[k], getattr(g, k), rel_tol=1e-5, abs_tol=1e-9)]
    if differ:
        return differ, None
    identity = recorded_cylinder(run) or ""
    name = identity.rsplit("; bore ", 1)[0]
    note = None
    if name != cyl.name:
        note = (f"{run_name(run)} names the cylinder '{name}', {cyl.source or 'the cylinder file'} '{cyl.name}': "
                "the same bore, rod and stroke, so taken as the same cylinder")
    return [], note


def header_cylinder_file(run: Run) -> Path | None:
    """The cylinder file the run's tag names, where it exists: as written (relative to the
    working folder), else relative to the run's folder; None otherwise."""
    named = recorded_file(run)
    if named is None:
        return None
    path = Path(named)
    candidates = [path]
    if not path.is_absolute() and run.source is not None:
        candidates.append(Path(run.source).parent / path)
    return next((c for c in candidates if c.is_file()), None)


def _check_header(run: Run, cyl: Cylinder) -> str | None:
    differ, note = header_geometry(run, cyl)
    if differ:
        theirs, g = recorded_geometry(run), cyl.geometry
        what = differ[0] if len(differ) == 1 else ", ".join(differ[:-1]) + " and " + differ[-1]
        said = lambda values: ", ".join(f"{k} {_mm(values(k))}" for k in differ)  # noqa: E731
        named = header_cylinder_file(run)
        fix = (f"give it the cylinder file it was recorded on (its header names {named})" if named is not None
               else "give it the cylinder file of the cylinder it was recorded on")
        raise RunFormatError(f"{run_name(run)} was recorded on a cylinder of another {what}: {said(theirs.get)} in "
                             f"its header, {said(lambda k: getattr(g, k))} in {cyl.source or 'the cylinder file'}; "
                             f"{fix}.")
    return note


def _check_stroke(run: Run, cyl: Cylinder) -> None:
    L = cyl.geometry.stroke
    lo, hi = float(np.nanmin(run.x)), float(np.nanmax(run.x))
    m = _STROKE_MARGIN * L
    if lo >= -m and hi <= L + m:
        return
    where = f"{run_name(run)}: the position spans {lo:.4g} to {hi:.4g} m, but {cyl.source or 'the cylinder file'}"
    span = hi - lo
    for factor, unit, short in _LENGTH_UNITS:
        if -m * factor <= lo and hi <= (L + m) * factor and span > 0.2 * L * factor:
            raise RunFormatError(f"{where} has a stroke of {L:g} m: the positions look like {unit}; give them in "
                                 f"metres (divide by {factor:.4g}, or unit = \"{short}\" for x in the import map).")
    if span <= L + m:
        raise RunFormatError(f"{where} has a stroke of {L:g} m (0 = fully retracted): the span fits the stroke but "
                             f"starts at {lo:.4g} m, so the positions are measured from another origin; "
                             + (f"subtract {lo:.4g} m" if lo > 0 else f"add {-lo:.4g} m")
                             + " (or set zero for x in the import map).")
    raise RunFormatError(f"{where} has a stroke of {L:g} m: the piston travels {span:.4g} m, more than this "
                         "cylinder's stroke, so the run is of another cylinder (stroke) or in another unit; give the "
                         "cylinder file it was recorded on.")


def check_run_against_cylinder(run: Run, cyl: Cylinder) -> tuple[str, ...]:
    """Refuse a run that cannot belong to this cylinder file: a channel never measured, the
    geometry its header names (bore, rod, stroke) not the file's, positions off the stroke
    (millimetres, another origin, a longer stroke), gauge chamber pressures, a supply that
    the run shows to be another. Returns notes on what the checks are not sure of.
    (identify.preflight runs the same with the motion's directions between shape and supply.)"""
    return check_run_shape(run, cyl) + check_supply(run, cyl)


def check_run_shape(run: Run, cyl: Cylinder) -> tuple[str, ...]:
    """The checks that need neither the command's sign nor which chamber is which: channels
    measured, the header's geometry, the stroke, chambers below half the atmosphere (gauge)."""
    if not (np.isfinite(run.x).any() and np.isfinite(run.p1).any() and np.isfinite(run.p2).any()):
        missing = next(n for n in ("x", "p1", "p2") if not np.isfinite(getattr(run, n)).any())
        raise RunFormatError(f"{run_name(run)}: the channel '{missing}' was not measured at any sample; "
                             "nothing to fit it with.")
    note = _check_header(run, cyl)
    _check_stroke(run, cyl)
    _check_gauge_chambers(run, cyl)
    return (note,) if note else ()


# an exhausted chamber sits near the atmosphere; gauge readings sit near 0 for a while
_GAUGE_SHARE = 0.01  # of the samples below half the atmosphere
_REST_SPEED = 2e-3  # m/s: the piston rests (at an end) below this
_OPEN = 0.3  # |u| at which the valve is open enough to bring a resting chamber to the supply
_PLATEAU_S = 0.2  # s at rest with the valve open that show the supply pressure
_ABOVE_SUPPLY = 0.05  # share of the run with a chamber above the supply that is worth a note


def check_pressures_absolute(run: Run, cyl: Cylinder) -> tuple[str, ...]:
    """Refuse chamber pressures that are gauge, and a supply pressure in the cylinder file that
    is gauge. Gauge chambers sit below half the atmosphere for more than 1 % of a run that
    exhausts a chamber. Where the piston rests (at an end) with the valve open for a while,
    the filled chamber shows the supply pressure: a supply one atmosphere above the file's
    means the file's is gauge, one atmosphere below means the run's pressures are; a measured
    supply (ps) says so directly. A run that never exhausts a chamber nor rests with the valve
    open cannot tell (docs/formats.md); chambers above the file's supply for a good part of
    the run are noted, not refused (a load can hold a closed chamber above the supply)."""
    _check_gauge_chambers(run, cyl)
    return check_supply(run, cyl)


def _check_gauge_chambers(run: Run, cyl: Cylinder) -> None:
    pa = cyl.supply.atmosphere
    cyl_file = cyl.source or "the cylinder file"
    name = run_name(run)
    for ch in ("p1", "p2"):
        p = getattr(run, ch)
        low = p < 0.5 * pa  # NaN (not measured) is not low
        if low.sum() > _GAUGE_SHARE * np.isfinite(p).sum():
            i = int(np.argmax(low))
            raise RunFormatError(f"{name}, column '{ch}' at t = {run.t[i]:.6g} s: {p[i]:.4g} Pa, and "
                                 f"{100 * low.mean():.3g} % of the run below half the atmosphere ({pa:g} Pa in "
                                 f"{cyl_file}), look like gauge pressures; a run holds absolute Pa: {GAUGE_FIX}.")


def check_supply(run: Run, cyl: Cylinder) -> tuple[str, ...]:
    """The supply the run shows (a chamber filled at rest, or a measured ps) against the
    file's (the command's sign and p1/p2 must be right: the filled chamber is the one the
    command opens to the supply)."""
    pa, ps = cyl.supply.atmosphere, cyl.supply.pressure
    cyl_file = cyl.source or "the cylinder file"
    name = run_name(run)
    seen = supply_seen(run)
    if seen is None and run.ps is not None and np.isfinite(run.ps).any():
        seen = float(np.nanmedian(run.ps)), int(np.argmax(np.isfinite(run.ps)))
        how = "the measured supply (column 'ps')"
    else:
        how = "with the valve open and the piston at rest, the filled chamber"
    notes: list[str] = []
    if seen is not None:
        supply, i = seen
        if supply > ps + 0.5 * pa:
            raise ConfigError(f"{cyl_file}: key 'supply.pressure' = {ps:g} Pa looks like gauge: {how} of {name} "
                              f"holds {supply:.4g} Pa (from t = {run.t[i]:.6g} s), which is the supply; give it "
                              f"absolute (gauge + {pa:g} Pa).")
        if supply < ps - 0.5 * pa:
            raise RunFormatError(f"{name}, from t = {run.t[i]:.6g} s: {how} holds {supply:.4g} Pa, about one "
                                 f"atmosphere below the supply {ps:g} Pa of {cyl_file}: the run's pressures look "
                                 f"gauge ({GAUGE_FIX}), or the supply in the file is wrong.")
        return ()
    pmax = np.fmax(run.p1, run.p2)
    margin = max(0.02 * ps, 5 * cyl.sensors.pressure_noise)
    above = float(np.mean(pmax > ps + margin))
    if above > _ABOVE_SUPPLY:
        notes.append(f"{name}: a chamber holds more than the supply {ps:g} Pa of {cyl_file} for {above:.0%} of the "
                     f"run (up to {np.nanmax(pmax):.4g} Pa): if the file's supply is gauge, give it absolute (gauge + "
                     f"{pa:g} Pa)")
    return tuple(notes)


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


def check_train_and_valid(cyl: Cylinder, train: Run, valid: Run, train_name: str, valid_name: str) -> str | None:
    """Refuse a TRAIN/VALID pair of which a run is shorter than 1 s at 1 kHz, or VALID sampled
    at another rate than TRAIN (each run against the cylinder file: identify.preflight).
    Returns a warning when VALID holds the same samples as TRAIN (a validation that cannot
    fail), else None."""
    for r, what in ((train, train_name), (valid, valid_name)):
        if r.n < 1000:
            raise RunFormatError(f"{what}: {r.n} samples are too few (at least 1 s at 1 kHz).")
    if abs(valid.sample_period / train.sample_period - 1) > 0.01:
        raise RunFormatError(f"{valid_name} is sampled every {valid.sample_period * 1e3:.3g} ms but {train_name} "
                             f"every {train.sample_period * 1e3:.3g} ms; validate with a run of the same rig and rate.")
    if same_data(train, valid):
        return (f"{valid_name} holds the same samples as {train_name}: the validation scores the fit on the data it "
                "was fitted to, so it cannot tell a real gain from overfitting; validate on another run.")
    return None
