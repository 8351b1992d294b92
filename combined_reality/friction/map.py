"""The static friction-velocity map (seeds 000 and 004) and fits of the friction models.

Points come from recorded runs or from points tables:

- A run gives the friction Newton's law implies with the measured pressures and a filtered
  acceleration (`identify.friction_from_newton`). Stretches of sustained motion at nearly
  constant velocity (small acceleration, small velocity spread, at least `min_duration`)
  become one point each: mean velocity, mean friction, their spreads, the sample count,
  and the mean pressure conditions (|p1 - p2|, counter pressure). Where the piston
  sticks (|v| below `stuck_speed` for `stuck_duration`) and then breaks away, the largest
  friction before sliding is a breakaway force.
- A points table is a CSV with columns v,F (m/s, N; both directions in one file, the sign
  of v gives the direction), optionally F_std, count, dp, pc, load, and `breakaway` (1 marks
  a breakaway force, the static end of the map, as `procedure breakaway` writes it; 0 or
  no column: a sliding point).

Breakaway rows are not sliding points: every fit and the stick band's dv use the sliding
points only (so that RMSE, R^2 and AICc of all models refer to the same points); the
breakaway rows fix Fs of karnopp, cvs, cvs_delta and lugre (seed 004: Fs from the rest end
of the map, then the Stribeck velocity fitted to the sliding points), with their standard
error. Breakaways detected in runs feed the stick band and karnopp only.

Per direction, the map is fitted with seed 000's linear least squares (F = Fc + B v, R^2)
and with the static curve of every model of sim.friction_models (nonlinear least squares,
scipy), each with standard deviations and 95 % intervals of its parameters from the
Jacobian at the solution (as scipy's curve_fit), RMSE, R^2, the mean absolute error
(seed 003's "mean error") and flags on the parameters the points cannot determine.
"""
from __future__ import annotations

import io
import math
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

from sim.cylinder import Cylinder
from sim.friction_models import DIRECTIONS, FRICTION_MODELS, FrictionModel
from sim.inputs import InputFileError, regular_file_size, shorten

from ..files import Run, atomic_write, split_at_gaps
from ..files.plausibility import MAX_ABS_PRESSURE
from ..identify import derivative_kernels, friction_from_newton, too_uncertain
from ..progress import counter
from .specs import (FIT_SPECS, NOMINAL_LAW, PARSIMONY, PLOT_FORMATS, FitSpec, FrictionMapError, PointsFormatError,
                    SegmentOptions, TooFewPointsError)

__all__ = ["PLOT_FORMATS", "FrictionMapError", "PointsFormatError", "TooFewPointsError", "SegmentOptions", "MapPoint",
           "Breakaway", "RunPoints", "StickBand", "LinearFit", "ModelFit", "FitSpec", "FIT_SPECS", "Confounding",
           "confounded_quantities", "DirectionMap", "FrictionMap", "points_from_run", "read_points", "is_points_table",
           "linear_fit", "fit_model", "build_map", "plot_map", "NOMINAL_LAW", "PARSIMONY"]


# ================================================================ points from runs

@dataclass(frozen=True)
class MapPoint:
    """One point of the map: a constant-velocity segment of a run, or a table row."""

    v: float  # m/s, mean velocity (its sign is the direction)
    F: float  # N, mean friction (opposes motion: same sign as v)
    F_std: float = math.nan  # N, spread of the friction within the segment
    v_std: float = math.nan  # m/s, spread of the velocity within the segment
    count: int = 1  # samples averaged
    dp: float = math.nan  # Pa, mean |p1 - p2|
    pc: float = math.nan  # Pa gauge, mean counter pressure (p2 - pa extending, p1 - pa retracting)
    load: float = math.nan  # N, normal load
    source: str = ""
    t_start: float = math.nan  # s, segment in the run
    t_end: float = math.nan
    breakaway: bool = False  # a breakaway force (F_std, count: spread and number of trials), not a sliding point

    @property
    def direction(self) -> str:
        return "extension" if self.v > 0 else "retraction"

    def to_json(self) -> dict:
        out = {"v": self.v, "F": self.F, "F_std": self.F_std, "v_std": self.v_std, "count": self.count,
               "dp": self.dp, "pc": self.pc, "load": self.load, "source": self.source,
               "t_start": self.t_start, "t_end": self.t_end, "breakaway": self.breakaway}
        return {k: (None if isinstance(x, float) and not math.isfinite(x) else x) for k, x in out.items()}


@dataclass(frozen=True)
class Breakaway:
    """The piston stuck, then slid: the largest friction before it reached min_speed (N, magnitude)."""

    t: float
    direction: str
    force: float
    source: str = ""


@dataclass(frozen=True)
class RunPoints:
    """What one run gives the map."""

    points: tuple[MapPoint, ...]
    breakaways: tuple[Breakaway, ...]
    stuck_time: float  # s the piston stuck (|v| < stuck_speed for at least stuck_duration)
    duration: float  # s of the run
    stuck_speed: float  # m/s
    moving_time: float  # s with |v| >= min_speed


def _true_runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) of the runs of True in a boolean array."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist()))


def _segments(v: np.ndarray, dt: float, opts: SegmentOptions, stuck: float) -> list[tuple[int, int]]:
    """[start, end) of the constant-velocity segments (indices into v)."""
    n_min = max(3, int(math.ceil(opts.min_duration / dt)))
    w = max(1, n_min // 2)  # trend: average over min_duration
    if len(v) < max(n_min, 4 * w + 1):  # (a stretch between channels not measured) too short to hold one
        return []
    trend = np.convolve(v, np.full(2 * w + 1, 1.0 / (2 * w + 1)), mode="same")
    # Savitzky-Golay: its first-derivative kernel is the least-squares slope
    slope = np.convolve(trend, derivative_kernels(w)[0], mode="same") / dt
    slope[:2 * w] = slope[len(slope) - 2 * w:] = np.inf  # no trend at the ends: never steady there
    speed = np.abs(trend)
    steady = (speed >= opts.min_speed) & (np.abs(slope) * opts.min_duration <= opts.spread * speed)
    out = []
    for sign in (1.0, -1.0):
        sliding = steady & (np.sign(trend) == sign) & (np.sign(v) == sign) & (np.abs(v) >= stuck)
        for i0, i1 in _true_runs(sliding):
            n = i1 - i0
            if n < n_min:
                continue
            # a long stretch may drift: cut it into the fewest equal pieces that are each steady
            for m in range(1, n // n_min + 1):
                edges = np.linspace(i0, i1, m + 1).round().astype(int)
                pieces = list(zip(edges[:-1], edges[1:]))
                if all(np.std(trend[p:q]) <= opts.spread * abs(np.mean(trend[p:q])) for p, q in pieces):
                    out.extend(pieces)
                    break
    return sorted(out)


def points_from_run(cyl: Cylinder, run: Run, options: SegmentOptions = SegmentOptions(),
                    load: float | None = None) -> RunPoints:
    """Constant-velocity points and breakaway forces of a recorded run (Newton's law with the
    measured pressures: identify.friction_from_newton). `load`: a constant normal load (N)
    to attach to the points (the load models need one)."""
    name = str(run.source) if run.source is not None else "run"
    pa = cyl.supply.atmosphere
    points: list[MapPoint] = []
    breaks: list[Breakaway] = []
    stuck_time = moving_time = 0.0
    for piece in split_at_gaps(run):  # no derivative across lost samples
        idx_all, v_all, F_all = friction_from_newton(cyl, piece, options.newton_half)
        # where a channel was not measured Newton's law gives nothing: contiguous stretches only
        cuts = np.flatnonzero(np.diff(idx_all) > 1) + 1
        for idx, v, F in zip(*(np.split(a, cuts) for a in (idx_all, v_all, F_all))):
            if len(idx) < 5:
                continue
            dt = piece.sample_period
            t = piece.t[idx]
            stuck = options.stuck_threshold(cyl.sensors.position_noise, dt)
            p1, p2 = piece.p1[idx], piece.p2[idx]
            moving_time += float(np.sum(np.abs(v) >= options.min_speed)) * dt
            for i0, i1 in _segments(v, dt, options, stuck):
                sl = slice(i0, i1)
                forward = v[i0] > 0
                points.append(MapPoint(
                    v=float(np.mean(v[sl])), F=float(np.mean(F[sl])), F_std=float(np.std(F[sl])),
                    v_std=float(np.std(v[sl])), count=i1 - i0, dp=float(np.mean(np.abs(p1[sl] - p2[sl]))),
                    pc=float(np.mean((p2[sl] if forward else p1[sl]) - pa)),
                    load=math.nan if load is None else float(load), source=name,
                    t_start=float(t[i0]), t_end=float(t[i1 - 1])))
            b, st = _breakaways(t, v, F, dt, options, stuck, name)
            breaks.extend(b)
            stuck_time += st
    stuck = options.stuck_threshold(cyl.sensors.position_noise, run.sample_period) if run.n >= 2 else math.nan
    return RunPoints(points=tuple(points), breakaways=tuple(breaks), stuck_time=stuck_time,
                     duration=run.duration, stuck_speed=stuck, moving_time=moving_time)


def _breakaways(t, v, F, dt, opts: SegmentOptions, stuck: float, source: str) -> tuple[list[Breakaway], float]:
    """Breakaway forces after sticking, and the total time stuck. While the piston sticks,
    Newton's friction is the applied force; the largest (10 ms average) before the piston
    reaches min_speed is the breakaway force."""
    stuck_runs = [(i0, i1) for i0, i1 in _true_runs(np.abs(v) < stuck) if (i1 - i0) * dt >= opts.stuck_duration]
    look = int(round(0.1 / dt))  # motion must reach min_speed within 0.1 s of leaving the band
    w = max(1, int(round(0.005 / dt)))
    Fm = np.convolve(F, np.full(2 * w + 1, 1.0 / (2 * w + 1)), mode="same")
    starts: dict[int, int] = {}  # motion onset -> start of the window (the last sticking before it)
    for i0, i1 in stuck_runs:
        ahead = np.abs(v[i1:i1 + look]) >= opts.min_speed
        if ahead.any():
            starts[i1 + int(np.argmax(ahead))] = max(i0, i1 - int(round(opts.stuck_duration / dt)))
    out = []
    for k, start in sorted(starts.items()):
        d = float(np.sign(v[k]))
        force = float(np.max(d * Fm[start:k + 1]))
        if force > 0:
            out.append(Breakaway(t=float(t[k]), direction="extension" if d > 0 else "retraction",
                                 force=force, source=source))
    return out, sum(i1 - i0 for i0, i1 in stuck_runs) * dt


# ================================================================ points tables

_TABLE_OPTIONAL = ("F_std", "v_std", "count", "dp", "pc", "load", "breakaway")
_MAX_SPEED = 10.0  # m/s: above this, v is not in m/s


_POINTS_MAX_BYTES = 64 << 20  # a points table: a point per constant-speed stroke, far below this
_MAX_FORCE = 1.0e6  # N: beyond any pneumatic cylinder (a 320 mm bore at 10 bar makes 80 kN)
_POINTS_MAX_LINE = 1 << 16  # characters


def _lines(path: Path, limit: int | None = _POINTS_MAX_BYTES):
    """The file's lines, lazily; missing, unreadable or special files (a device, a FIFO:
    refused before opening), files beyond `limit` bytes and overlong lines in one sentence."""
    try:
        regular_file_size(path, "a points table" if limit else "a points table or run", limit)
        with open(path, encoding="utf-8-sig") as f:
            for n, line in enumerate(f, 1):
                if len(line) > _POINTS_MAX_LINE:
                    raise PointsFormatError(f"{path}: line {n} is longer than {_POINTS_MAX_LINE} characters.")
                yield line.rstrip("\r\n")
    except InputFileError as e:
        raise PointsFormatError(str(e)) from None
    except FileNotFoundError:
        raise PointsFormatError(f"{path}: file not found.") from None
    except (OSError, UnicodeDecodeError) as e:
        raise PointsFormatError(f"{path}: cannot be read ({shorten(str(e))}).") from None


def _is_data(line: str) -> bool:
    return bool(line.strip()) and not line.lstrip().startswith("#")


def is_points_table(path: str | os.PathLike[str]) -> bool:
    """A points table has v and F in its header (a run has t,u,x,p1,p2); reads up to the header."""
    header = next((line for line in _lines(Path(path), None) if _is_data(line)), None)
    cells = [c.strip() for c in header.split(",")] if header is not None else []
    return "v" in cells and "F" in cells


def read_points(path: str | os.PathLike[str]) -> list[MapPoint]:
    """Points of a CSV table with columns v,F (m/s, N), optionally F_std, v_std, count, dp,
    pc, load, breakaway (1: a breakaway force, 0: a sliding point); `#` lines are comments,
    other columns are ignored."""
    path = Path(path)
    lines = list(_lines(path))
    hline = next((n for n, line in enumerate(lines, 1) if _is_data(line)), None)
    if hline is None:
        raise PointsFormatError(f"{path}: the file is empty (a points table needs a header v,F and rows).")
    header = [c.strip() for c in lines[hline - 1].split(",")]
    if len(set(header)) != len(header):
        dup = next(c for c in header if header.count(c) > 1)
        raise PointsFormatError(f"{path}: line {hline}: column '{shorten(dup)}' appears twice in the header.")
    for col in ("v", "F"):
        if col not in header:
            raise PointsFormatError(f"{path}: line {hline}: the header has no column '{col}' "
                                    f"(a points table needs columns v,F in m/s and N).")
    cols = {c: header.index(c) for c in ("v", "F", *_TABLE_OPTIONAL) if c in header}
    points = []
    for n in range(hline + 1, len(lines) + 1):
        line = lines[n - 1]
        if not _is_data(line):
            continue
        cells = [c.strip() for c in line.split(",")]
        if len(cells) != len(header):
            raise PointsFormatError(f"{path}: line {n} has {len(cells)} cells but the header has {len(header)}.")
        vals = {}
        for c, j in cols.items():
            try:
                x = float(cells[j])
            except ValueError:
                raise PointsFormatError(f"{path}: line {n}, column '{c}': '{shorten(cells[j])}' is not a "
                                        "number.") from None
            if not math.isfinite(x):
                raise PointsFormatError(f"{path}: line {n}, column '{c}': '{shorten(cells[j])}' is not a finite "
                                        "number.")
            vals[c] = x
        for c in ("F_std", "v_std", "dp", "load"):
            if vals.get(c, 0.0) < 0:
                raise PointsFormatError(f"{path}: line {n}, column '{c}': {shorten(cells[cols[c]])} is negative; "
                                        f"{'a spread' if c.endswith('_std') else 'it'} cannot be.")
        for c in ("F", "F_std", "load"):
            if abs(vals.get(c, 0.0)) > _MAX_FORCE:
                raise PointsFormatError(f"{path}: line {n}, column '{c}': {shorten(cells[cols[c]])} N is beyond any "
                                        f"pneumatic cylinder's force ({_MAX_FORCE:g} N); F is in N.")
        for c in ("dp", "pc"):
            if abs(vals.get(c, 0.0)) > MAX_ABS_PRESSURE:
                raise PointsFormatError(f"{path}: line {n}, column '{c}': {shorten(cells[cols[c]])} Pa is beyond any "
                                        f"pneumatic pressure ({MAX_ABS_PRESSURE:g} Pa); pressures are in Pa.")
        if vals["v"] == 0.0:
            raise PointsFormatError(f"{path}: line {n}, column 'v': v = 0 has no direction "
                                    f"(extension v > 0, retraction v < 0).")
        if abs(vals["v"]) > _MAX_SPEED:
            raise PointsFormatError(f"{path}: line {n}, column 'v': {shorten(cells[cols['v']])} m/s is implausibly "
                                    f"fast (v must be in m/s, not mm/s).")
        if "count" in vals and (vals["count"] < 1 or vals["count"] != int(vals["count"])):
            raise PointsFormatError(f"{path}: line {n}, column 'count': {shorten(cells[cols['count']])} is not a "
                                    f"positive whole number.")
        if vals.get("breakaway", 0.0) not in (0.0, 1.0):
            raise PointsFormatError(f"{path}: line {n}, column 'breakaway': {shorten(cells[cols['breakaway']])} is "
                                    f"neither 1 (a breakaway force) nor 0 (a sliding point).")
        points.append(MapPoint(v=vals["v"], F=vals["F"], F_std=vals.get("F_std", math.nan),
                               v_std=vals.get("v_std", math.nan), count=int(vals.get("count", 1)),
                               dp=vals.get("dp", math.nan), pc=vals.get("pc", math.nan),
                               load=vals.get("load", math.nan), source=str(path),
                               breakaway=vals.get("breakaway", 0.0) == 1.0))
    if not points:
        raise PointsFormatError(f"{path}: no points after the header (a points table needs rows v,F).")
    return points


# ================================================================ fits

# families whose Fs is the breakaway force itself (no load or pressure terms): breakaway rows fix it
_FS_FROM_BREAKAWAY_ROWS = frozenset({"cvs", "lugre"})
_CONDITION_HELP = {"dp": "dp (|p1 - p2|, Pa)", "pc": "pc (counter pressure, Pa gauge)", "load": "load (N)"}
_STRONG_CORRELATION = 0.999
_REACH = 0.05  # a static force of which less reaches any point is extrapolated, not measured


@dataclass(frozen=True)
class LinearFit:
    """Seed 000: F = Fc s + B v by linear least squares (s = sign v), one direction."""

    direction: str
    Fc: float
    B: float
    std: Mapping[str, float]
    r2: float
    rmse: float
    mae: float
    n_points: int

    def to_json(self) -> dict:
        return {"params": {"Fc": self.Fc, "B": self.B}, "std": dict(self.std), "r2": self.r2, "rmse": self.rmse,
                "mae": self.mae, "n_points": self.n_points}


@dataclass(frozen=True)
class ModelFit:
    """One model fitted to one direction's points. Parameters under their base names (Fc,
    not Fc_pos), magnitudes; None where the points cannot give a value."""

    model: str
    family: str
    direction: str
    params: Mapping[str, float | None]
    std: Mapping[str, float | None]
    ci95: Mapping[str, tuple[float, float] | None]
    fixed: Mapping[str, str]  # base parameter -> why it was not fitted
    start: Mapping[str, float]  # the start of the best least-squares run (free parameters)
    r2: float
    rmse: float
    mae: float
    n_points: int
    dof: int
    aicc: float | None  # corrected Akaike criterion: lower is better, penalises parameters
    flags: tuple[Mapping[str, str], ...]
    status: str
    nfev: int
    not_determined: tuple[str, ...] = ()  # parameters whose value the points do not pin down
    problems: tuple[str, ...] = ()  # what is wrong with the fitted curve as a whole (shape, order of levels)

    @property
    def free(self) -> tuple[str, ...]:
        return tuple(self.start)

    @property
    def preferable(self) -> bool:
        """May be ranked (by AICc) and preferred: converged, every parameter determined, a
        curve within the data's range with the static level not below the Coulomb level."""
        return self.status == "converged" and not self.not_determined and not self.problems

    def model_values(self) -> dict[str, float]:
        """The fitted values under the model's parameter names (Fc_pos / Fc_neg)."""
        suffix = DIRECTIONS[self.direction][0]
        return {f"{k}_{suffix}": v for k, v in self.params.items()
                if v is not None and f"{k}_{suffix}" in FRICTION_MODELS[self.family].PARAMS}

    def to_json(self) -> dict:
        return {"family": self.family, "params": dict(self.params), "std": dict(self.std),
                "ci95": {k: (list(v) if v is not None else None) for k, v in self.ci95.items()},
                "fixed": dict(self.fixed), "start": dict(self.start), "r2": self.r2, "rmse": self.rmse,
                "mae": self.mae, "n_points": self.n_points, "dof": self.dof, "aicc": self.aicc,
                "flags": [dict(f) for f in self.flags], "status": self.status, "nfev": self.nfev,
                "not_determined": list(self.not_determined), "problems": list(self.problems),
                "preferable": self.preferable}


def _metrics(F: np.ndarray, pred: np.ndarray) -> tuple[float, float, float]:
    """R^2 (seed 000 Eq. 10), RMSE, mean absolute error (seed 003's 'mean error')."""
    r = F - pred
    sst = float(np.sum((F - F.mean()) ** 2))
    r2 = 1.0 - float(np.sum(r * r)) / sst if sst > 0 else math.nan
    return r2, float(np.sqrt(np.mean(r * r))), float(np.mean(np.abs(r)))


def _direction_of(points: Sequence[MapPoint]) -> str:
    dirs = {p.direction for p in points}
    if len(dirs) != 1:
        raise FrictionMapError("a fit takes the points of one direction (all v > 0 or all v < 0).")
    return dirs.pop()


def linear_fit(points: Sequence[MapPoint]) -> LinearFit:
    """Seed 000's least squares, Eq. (8): Theta = (X^T X)^-1 X^T Y with X = [sign v, v], on the
    sliding points (breakaway rows are left out)."""
    direction = _direction_of(points)
    points = [p for p in points if not p.breakaway]
    v = np.array([p.v for p in points])
    F = np.array([p.F for p in points])
    n = len(v)
    if n < 3:
        raise TooFewPointsError(f"the {direction} direction has {n} sliding points, too few for the linear fit "
                                f"(2 parameters, at least 3 points).")
    X = np.column_stack([np.sign(v), v])
    theta, *_ = np.linalg.lstsq(X, F, rcond=None)
    pred = X @ theta
    s2 = float(np.sum((F - pred) ** 2)) / (n - 2)
    cov = np.linalg.pinv(X.T @ X) * s2
    r2, rmse, mae = _metrics(F, pred)
    return LinearFit(direction=direction, Fc=float(theta[0]), B=float(theta[1]),
                     std={"Fc": float(np.sqrt(cov[0, 0])), "B": float(np.sqrt(cov[1, 1]))},
                     r2=r2, rmse=rmse, mae=mae, n_points=n)


def _conditions(spec: FitSpec, points: Sequence[MapPoint], direction: str) -> dict[str, np.ndarray]:
    cond = {}
    for key in spec.needs():
        vals = np.array([getattr(p, key) for p in points], float)
        if not np.all(np.isfinite(vals)):
            raise FrictionMapError(f"model {spec.name} needs {_CONDITION_HELP[key]} for every point, and the "
                                   f"{direction} points lack it (tables: add a column '{key}').")
        cond[key] = vals
    for key in FRICTION_MODELS[spec.family].CONDITIONS:
        cond.setdefault(key, np.zeros(len(points)))  # left out of this fit: its terms are held at 0
    return cond


def _starts(cls: type[FrictionModel], free: Sequence[str], v: np.ndarray, F: np.ndarray,
            cond: Mapping[str, np.ndarray]) -> list[dict[str, float]]:
    """Starting points for the least squares: linear fits where the model is linear, a few
    decades of the velocity scale where it is not."""
    a, f = np.abs(v), np.abs(F)
    order = np.argsort(a)
    fast = order[len(order) // 2:] if len(order) >= 4 else order  # away from a Stribeck hump

    def lin(cols: Sequence[np.ndarray], rows) -> np.ndarray:
        X = np.column_stack([c[rows] for c in cols])
        return np.maximum(np.linalg.lstsq(X, f[rows], rcond=None)[0], 0.0)

    one = np.ones_like(a)
    Fc, B = lin([one, a], fast)
    guess = {"Fc": Fc, "B": B, "delta": 2.0, "mu": 0.0, "mu_s": 0.0, "mu_v": 0.0,
             "Fs": max(float(f[order[0]] - B * a[order[0]]), Fc), "K1": 0.0, "alpha": 1.0, "K2": 0.0, "K3": 0.0}
    guess["FA"] = guess["Fc"]
    if "load" in cond:
        L = cond["load"]
        guess["Fc"], guess["mu"], guess["B"], guess["mu_v"] = lin([one, L, a, a * L], fast)
        guess["Fs"], guess["mu_s"] = max(float(f[order[0]] - guess["B"] * a[order[0]]), guess["Fc"]), guess["mu"]
    if "dp" in cond and "pc" in cond:
        guess["FA"], guess["K2"], guess["K3"] = lin([one, cond["dp"], cond["pc"]], order)
    if "dp" in cond:
        if "kp" in cls.BASE:  # cv_dp, efficiency: linear in their parameters
            cols = {"Fc": one, "kp": cond["dp"], "Fv": a}
            guess.update(zip(cls.BASE, lin([cols[b] for b in cls.BASE], order)))
    scales = [n for n in free if n in cls.SCALES]
    if not scales:
        return [{n: float(guess[n]) for n in free}]
    lo, hi = float(a.min()), float(a.max())
    # first the velocity scale the slow points suggest, then a few decades around the data
    candidates = [_scale_from_points(scales[0], a, f, guess), *np.geomspace(lo / 3, max(hi / 3, lo), 5)]
    out = []
    for vs in candidates:
        if vs is not None:
            g = {**guess, **{n: float(vs) for n in scales}}
            out.append({n: float(g[n]) for n in free})
    return out


def _scale_from_points(name: str, a: np.ndarray, f: np.ndarray, guess: Mapping[str, float]) -> float | None:
    """The velocity scale the points suggest: where the excess over the Coulomb-viscous line
    has decayed (Stribeck: excess = (Fs - Fc) exp(-(v/vs)^2)), or where the rise to it is
    done (Threlfall: F = Fc (1 - exp(-3 v / ve)) / 0.95)."""
    Fc, B = guess["Fc"], guess["B"]
    line = Fc + B * a
    with np.errstate(divide="ignore", invalid="ignore"):
        if name == "vs":
            excess = f - line
            E0 = float(excess[np.argmin(a)])
            ok = (excess > 0.05 * E0) & (excess < 0.95 * E0) if E0 > 0 else np.zeros_like(a, bool)
            est = a[ok] / np.sqrt(np.log(E0 / excess[ok]))
        elif name == "ve" and Fc > 0:
            rise = 0.95 * (f - B * a) / Fc
            ok = (rise > 0.05) & (rise < 0.9)
            est = -3 * a[ok] / np.log(1 - rise[ok])
        else:
            return None
    est = est[np.isfinite(est) & (est > 0)]
    return float(np.median(est)) if est.size else None


def _flags(cls, free, values, std, ci, lower, upper, corr, v, J_full, suffix) -> list[dict[str, str]]:
    """Parameters the points cannot determine, with the reason."""
    flags = []
    a = np.abs(v)
    slowest, fastest = float(a.min()), float(a.max())
    for i, n in enumerate(free):
        x, s = values[n], std[n]
        if not math.isfinite(s):
            flags.append({"param": n, "reason": "not determined by the points (the Jacobian is singular there)"})
            continue
        if n in cls.SCALES and x < slowest:
            flags.append({"param": n, "reason": f"{n} = {x:.3g} m/s lies below the slowest tested speed "
                                                 f"{slowest:.3g} m/s: the curve changes where there are no points "
                                                 f"(its shape there is the model's assumption)"})
        elif n in cls.SCALES and x > fastest:
            flags.append({"param": n, "reason": f"{n} = {x:.3g} m/s lies above the fastest tested speed "
                                                 f"{fastest:.3g} m/s: the curve is still changing at the last point"})
        if abs(x - lower[i]) <= 1e-6 * max(1.0, abs(lower[i])) or abs(x - upper[i]) <= 1e-6 * max(1.0, abs(upper[i])):
            bound = lower[i] if abs(x - lower[i]) <= abs(x - upper[i]) else upper[i]
            flags.append({"param": n, "reason": f"at its bound {bound:g}: the least squares wanted to go beyond"})
        elif ci[n] is not None and ci[n][0] <= 0.0 <= ci[n][1] and x != 0.0:
            flags.append({"param": n, "reason": f"the 95 % interval [{ci[n][0]:.3g}, {ci[n][1]:.3g}] includes 0"})
        elif x != 0.0 and s > abs(x):
            flags.append({"param": n, "reason": f"the standard deviation {s:.3g} exceeds the value {x:.3g}"})
        # how much of the parameter reaches the points at all (e.g. Fs behind a tiny Stribeck velocity)
        col = J_full[:, cls.param_index(f"{n}_{suffix}")]
        if n in ("Fs", "mu_s") and float(np.max(np.abs(col))) < _REACH:
            flags.append({"param": n, "reason": f"at most {100 * float(np.max(np.abs(col))):.2g} % of {n} reaches "
                                                 f"the points: it is extrapolated below the slowest speed"})
    if corr is not None:
        for i in range(len(free)):
            for j in range(i + 1, len(free)):
                if abs(corr[i, j]) > _STRONG_CORRELATION:
                    flags.append({"param": free[j], "reason": f"correlated with {free[i]} (r = {corr[i, j]:.4f}): "
                                                              f"the points cannot separate the two"})
    return flags


# the part of the points' force spread within which a parameter's effect must be pinned
_DETERMINED_SHARE = 0.5  # by effect, not value: a parameter near 0 with a small effect is pinned (small)


def _not_determined(cls, free, values, std, lower, upper, corr, J_full, suffix, F) -> set[str]:
    """Free parameters the points do not pin down: no finite standard deviation, stuck at a
    bound other than zero (the fit wanted beyond), inseparable from another (|r| > 0.999), a
    static force that hardly reaches the points, or an uncertainty whose effect on the curve
    (std x largest sensitivity) is as large as half the spread of the points' forces. A parameter
    near 0 with a small effect is determined: the points say it is small."""
    spread = float(np.ptp(np.abs(F))) or float(np.mean(np.abs(F))) or 1.0
    out = set()
    for n in free:
        x, s = values[n], std[n]
        i = cls.param_index(f"{n}_{suffix}")
        lo, hi = lower[free.index(n)], upper[free.index(n)]
        at_bound = (abs(x - hi) <= 1e-6 * max(1.0, abs(hi))) or (lo != 0 and abs(x - lo) <= 1e-6 * max(1.0, abs(lo)))
        reach = float(np.max(np.abs(J_full[:, i])))
        if too_uncertain(s, spread, share=_DETERMINED_SHARE, sensitivity=reach) or at_bound or \
                (n in ("Fs", "mu_s") and reach < _REACH):
            out.add(n)
    if corr is not None:
        for i in range(len(free)):
            for j in range(i + 1, len(free)):
                if abs(corr[i, j]) > _STRONG_CORRELATION:
                    out.update((free[i], free[j]))
    return out


def fit_model(points: Sequence[MapPoint], spec: FitSpec | str, fixed: Mapping[str, float] | None = None,
              fixed_reason: Mapping[str, str] | None = None) -> ModelFit:
    """Fit one model's static curve to one direction's points by nonlinear least squares
    (scipy.optimize.least_squares, bounds from the model's PARAMS, exact Jacobian from the
    model's CasADi expression, a few starts). `fixed` holds base parameters at values (a
    NaN value: not determined, reported as None). Standard deviations as scipy's curve_fit
    (unweighted: the residual variance scales (J^T J)^-1), 95 % intervals with Student's t.
    Breakaway rows are left out: the fit is of the sliding points (build_map fixes Fs from them)."""
    from scipy.optimize import least_squares
    from scipy.stats import t as student_t

    spec = FIT_SPECS[spec] if isinstance(spec, str) else spec
    cls = FRICTION_MODELS[spec.family]
    direction = _direction_of(points)
    points = [p for p in points if not p.breakaway]
    suffix = DIRECTIONS[direction][0]
    fixed_all = {**spec.fixed, **(fixed or {})}
    reasons = {n: "held fixed by the fit" for n in spec.fixed}
    reasons.update(fixed_reason or {})
    free = [n for n in cls.BASE if n not in fixed_all]
    n, k = len(points), len(free)
    if n < k + 1:
        raise TooFewPointsError(f"the {direction} direction has {n} points, too few to fit {spec.name} with {k} "
                                f"parameters (at least {k + 1} points).")
    v = np.array([p.v for p in points])
    F = np.array([p.F for p in points])
    cond = _conditions(spec, points, direction)
    names = list(cls.PARAMS)
    p_full = np.array([cls.defaults()[m] for m in names])
    for b, val in fixed_all.items():
        if math.isfinite(val):
            p_full[names.index(f"{b}_{suffix}")] = val
    idx = [names.index(f"{b}_{suffix}") for b in free]
    lower = np.array([cls.PARAMS[names[i]].lower for i in idx])
    upper = np.array([cls.PARAMS[names[i]].upper for i in idx])
    kw = {"dp": cond.get("dp"), "pc": cond.get("pc"), "load": cond.get("load")}

    def full(theta: np.ndarray) -> np.ndarray:
        p = p_full.copy()
        p[idx] = theta
        return p

    def residual(theta):
        return cls.static_force(v, full(theta), **kw) - F

    def jacobian(theta):
        return cls.static_jacobian(v, full(theta), **kw)[:, idx]

    best, best_start = None, None
    for start in _starts(cls, free, v, F, cond):
        x0 = np.clip(np.array([start[b] for b in free]), lower, upper)
        sol = least_squares(residual, x0, jac=jacobian, bounds=(lower, upper), method="trf", x_scale="jac",
                            xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=2000)
        # the earliest start (the best informed) that reaches the lowest cost is the one reported
        if best is None or sol.cost < best.cost * (1 - 1e-9):
            best, best_start = sol, dict(zip(free, x0.tolist()))
    theta = best.x
    pred = F + residual(theta)
    r2, rmse, mae = _metrics(F, pred)
    dof = n - k
    std_v, corr = _covariance(jacobian(theta), 2 * best.cost, dof)
    tq = float(student_t.ppf(0.975, dof))
    values: dict[str, float | None] = {}
    std: dict[str, float | None] = {}
    ci: dict[str, tuple[float, float] | None] = {}
    for i, b in enumerate(free):
        values[b], std[b] = float(theta[i]), float(std_v[i])
        ci[b] = (values[b] - tq * std[b], values[b] + tq * std[b]) if math.isfinite(std[b]) else None
    J_all = cls.static_jacobian(v, full(theta), **kw)
    flags = _flags(cls, free, values, std, ci, lower, upper, corr, v, J_all, suffix)
    undetermined = _not_determined(cls, free, values, std, lower, upper, corr, J_all, suffix, F)
    for b, val in fixed_all.items():
        values[b] = float(val) if math.isfinite(val) else None
        std.setdefault(b, None)
        ci.setdefault(b, None)
    for b in sorted(cls.DYNAMIC):
        values[b], std[b], ci[b] = None, None, None
        reasons[b] = "dynamic: a static map does not determine it"
        flags.append({"param": b, "reason": "dynamic parameter: a static friction-velocity map does not "
                                            "determine it (identify it from runs)"})
    # the order of the model's parameters
    order = [b for b in (*cls.BASE, *sorted(cls.DYNAMIC)) if b in values]
    return ModelFit(model=spec.name, family=spec.family, direction=direction,
                    params={b: values[b] for b in order}, std={b: std[b] for b in order},
                    ci95={b: ci[b] for b in order}, fixed={b: reasons.get(b, "held fixed") for b in order
                                                           if b not in free},
                    start=best_start, r2=r2, rmse=rmse, mae=mae, n_points=n, dof=dof, aicc=_aicc(2 * best.cost, n, k),
                    flags=tuple(flags),
                    status="converged" if best.status > 0 else f"not converged ({best.message})", nfev=int(best.nfev),
                    not_determined=tuple(b for b in order if b in undetermined or (b in fixed_all and values[b] is None
                                                                                   and b not in cls.DYNAMIC)))


def _aicc(ssr: float, n: int, k: int) -> float | None:
    """AICc of a least-squares fit with Gaussian residuals: n ln(SSR/n) + 2k + 2k(k+1)/(n-k-1)."""
    if n - k - 1 <= 0 or ssr <= 0:
        return None
    return float(n * math.log(ssr / n) + 2 * k + 2 * k * (k + 1) / (n - k - 1))


def _covariance(J: np.ndarray, ssr: float, dof: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Standard deviations (inf where the Jacobian is rank deficient) and the correlation
    matrix, as scipy's curve_fit: pcov = (J^T J)^+ * ssr / dof by SVD."""
    _, s, VT = np.linalg.svd(J, full_matrices=False)
    k = J.shape[1]
    keep = s > np.finfo(float).eps * max(J.shape) * (s[0] if s.size else 0.0)
    pcov = (VT[keep].T / s[keep] ** 2) @ VT[keep] * (ssr / dof)
    std = np.sqrt(np.clip(np.diag(pcov), 0.0, None))
    if not keep.all():  # parameters touched by the null space are not determined
        null = VT[~keep]
        std[np.max(np.abs(null), axis=0) > 1e-8] = math.inf
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = pcov / np.outer(std, std) if np.all(np.isfinite(std)) and np.all(std > 0) else None
    return std, corr if k > 1 else None


# ================================================================ the whole map

@dataclass(frozen=True)
class StickBand:
    """Where one direction sticks: no steady sliding below dv (Karnopp's band, seed 000's
    minimum speed), and the breakaway forces: single ones seen in runs, and the rows of
    breakaway tables (each the mean of `count` trials with their standard deviation F_std)."""

    direction: str
    dv: float | None  # m/s: slowest steady sliding speed
    at_detector_limit: bool  # dv is the detector's min_speed: the true band may be narrower
    breakaway: tuple[float, ...]  # N, magnitudes (runs)
    stuck_speed: float | None  # m/s (runs)
    stuck_time: float | None  # s in all runs, either direction
    breakaway_rows: tuple[tuple[float, float, int], ...] = ()  # (mean |F| N, std N or NaN, trials) of tables

    def _groups(self) -> list[tuple[float, float, int]]:
        """(mean, std, count) of every source; a row without its spread counts as one value."""
        return [(f, 0.0, 1) for f in self.breakaway] + \
            [(m, s, n) if math.isfinite(s) else (m, 0.0, 1) for m, s, n in self.breakaway_rows]

    @property
    def breakaway_count(self) -> int:
        return sum(n for *_, n in self._groups())

    @property
    def breakaway_mean(self) -> float | None:
        g = self._groups()
        return sum(m * n for m, _, n in g) / self.breakaway_count if g else None

    @property
    def breakaway_std(self) -> float | None:
        """Sample standard deviation of all trials, pooled exactly from the groups' means and spreads."""
        N = self.breakaway_count
        if N < 2:
            return None
        mean = self.breakaway_mean
        ss = sum((n - 1) * s * s + n * (m - mean) ** 2 for m, s, n in self._groups())
        return math.sqrt(ss / (N - 1))

    def to_json(self) -> dict:
        return {"dv": self.dv, "at_detector_limit": self.at_detector_limit, "stuck_speed": self.stuck_speed,
                "stuck_time_s": self.stuck_time,
                "breakaway": {"count": self.breakaway_count, "mean": self.breakaway_mean, "std": self.breakaway_std,
                              "max": max(self.breakaway) if self.breakaway else None,
                              "forces": list(self.breakaway),
                              "rows": [{"mean": m, "std": s, "count": n} for m, s, n in self.breakaway_rows]}}


@dataclass(frozen=True)
class Confounding:
    """Two quantities of a direction's points that changed together: a friction term growing
    with one cannot be told from one growing with the other."""

    first: str  # "speed", "dp", "pc", "load"
    second: str
    r: float  # correlation over the sliding points

    def sentence(self, direction: str) -> str:
        return (f"{_QUANTITY_WORDS[self.first]} and {_QUANTITY_WORDS[self.second]} changed together in the "
                f"{direction} points (r = {self.r:.3f}), so friction growing with one is hard to tell from friction "
                f"growing with the other; their terms are reported only where the points still determine them")

    def to_json(self) -> dict:
        return {"quantities": [self.first, self.second], "r": self.r}


_QUANTITY_WORDS = {"speed": "speed", "dp": "|p1 - p2|", "pc": "the counter pressure", "load": "the normal load"}
_CONFOUNDED = 0.9  # |r| from which two quantities count as changed together


def confounded_quantities(points: Sequence[MapPoint]) -> tuple[Confounding, ...]:
    """Pairs of speed, dp, pc, load that changed together over the sliding points (|r| >= 0.9)."""
    slide = [p for p in points if not p.breakaway]
    if len(slide) < 3:
        return ()
    series = {"speed": np.abs([p.v for p in slide])}
    for key in ("dp", "pc", "load"):
        vals = np.array([getattr(p, key) for p in slide], float)
        if np.all(np.isfinite(vals)):
            series[key] = vals
    series = {k: v for k, v in series.items() if np.std(v) > 1e-12 * max(1.0, float(np.mean(np.abs(v))))}
    names = list(series)
    out = []
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            r = float(np.corrcoef(series[a], series[b])[0, 1])
            if abs(r) >= _CONFOUNDED:
                out.append(Confounding(a, b, r))
    return tuple(out)


@dataclass(frozen=True)
class DirectionMap:
    direction: str
    points: tuple[MapPoint, ...]
    stick_band: StickBand
    linear: LinearFit | None
    fits: Mapping[str, ModelFit]
    skipped: Mapping[str, str]  # model -> why it was not fitted
    confounded: tuple[Confounding, ...] = ()

    @property
    def best(self) -> str | None:
        """Among the fits that may be preferred (every parameter determined, a sound curve), the
        simplest whose AICc lies within PARSIMONY of the lowest: the fewest parameters, then the
        product's own law (cv_dp), then the lower AICc. A parameter must buy more than
        PARSIMONY AICc units (a likelihood ratio of e^2, about 7.4) to be preferred, and another
        law as many over the nominal one: on a sweep of the nominal virtual rig, Threlfall's
        scale bent the curve through the slowest point and won by 0.8 over cv_dp. None without
        a preferable fit."""
        ranked = {n: f for n, f in self.fits.items() if f.preferable and f.aicc is not None}
        if not ranked:
            return None
        lowest = min(f.aicc for f in ranked.values())
        order = list(FIT_SPECS)
        near = [n for n, f in ranked.items() if f.aicc <= lowest + PARSIMONY]
        return min(near, key=lambda n: (len(ranked[n].free), n != NOMINAL_LAW, ranked[n].aicc,
                                        order.index(n) if n in order else len(order)))

    def to_json(self) -> dict:
        return {"models": {k: f.to_json() for k, f in self.fits.items()},
                "best": self.best, "confounded": [c.to_json() for c in self.confounded],
                "notes": [c.sentence(self.direction) for c in self.confounded],
                "linear": self.linear.to_json() if self.linear else None,
                "points": [p.to_json() for p in self.points], "stick_band": self.stick_band.to_json(),
                "skipped": dict(self.skipped)}


@dataclass(frozen=True)
class FrictionMap:
    directions: Mapping[str, DirectionMap]

    def combined(self) -> dict[str, dict]:
        """Per model fitted in both directions: its full parameter set (model names, the
        class defaults where the map gives no value) and the spec string for
        sim.friction_models.parse_friction_spec."""
        out = {}
        for name in FIT_SPECS:
            fits = [d.fits.get(name) for d in self.directions.values()]
            if any(f is None for f in fits):
                continue
            cls = FRICTION_MODELS[fits[0].family]
            values = {k: v for f in fits for k, v in f.model_values().items()}
            defaults = [k for k in cls.PARAMS if k not in values and k not in cls.CONDITIONS]
            full = {k: values.get(k, cls.defaults()[k]) for k in cls.PARAMS}
            out[name] = {"family": cls.name, "params": full, "defaults_used": defaults,
                         "spec": f"{cls.name}:" + ",".join(f"{k}={v:.6g}" for k, v in full.items())}
        return out

    def to_json(self) -> dict:
        return {"directions": {k: d.to_json() for k, d in self.directions.items()}, "models": self.combined()}


def build_map(points: Sequence[MapPoint], models: Sequence[str] | None = None,
              breakaways: Sequence[Breakaway] = (), stuck_speed: float | None = None,
              stuck_time: float | None = None, min_speed: float | None = None,
              strict: bool = False, progress: Callable[[str], None] | None = None) -> FrictionMap:
    """Fit the models (default: all of FIT_SPECS) to each direction's points; `progress`
    hears of each fit done (of models x directions).

    strict: a model that cannot be fitted (too few points, missing conditions) is an
    error; otherwise it is skipped with the reason."""
    names = list(models) if models else list(FIT_SPECS)
    unknown = [m for m in names if m not in FIT_SPECS]
    if unknown:
        raise FrictionMapError(f"unknown model {', '.join(unknown)} (known: {', '.join(FIT_SPECS)}).")
    dirs = {}
    tick = counter(progress, "model fits", len(names) * len(DIRECTIONS))
    for direction in DIRECTIONS:
        pts = tuple(sorted((p for p in points if p.direction == direction), key=lambda p: abs(p.v)))
        slide = [p for p in pts if not p.breakaway]
        forces = tuple(b.force for b in breakaways if b.direction == direction)
        rows = tuple((abs(p.F), p.F_std, p.count) for p in pts if p.breakaway)
        dv = abs(slide[0].v) if slide else None
        band = StickBand(direction=direction, dv=dv,
                         at_detector_limit=bool(dv is not None and min_speed is not None and dv < 1.2 * min_speed),
                         breakaway=forces, stuck_speed=stuck_speed, stuck_time=stuck_time, breakaway_rows=rows)
        fits, skipped = {}, {}
        linear = None
        try:
            linear = linear_fit(pts) if slide else None
        except TooFewPointsError:
            pass
        for name in names:
            try:
                if not slide:
                    what = "no points" if not pts else "no points but breakaway rows (no sliding points)"
                    raise TooFewPointsError(f"the {direction} direction has {what}, so {name} cannot be fitted.")
                fixed, why = {}, {}
                if FIT_SPECS[name].family == "karnopp":
                    # the band is where no steady sliding was seen; every point lies on the sliding branch
                    fixed["dv"] = float(np.nextafter(dv, 0.0))
                    why["dv"] = "the stick band: slowest steady sliding speed (not fitted)"
                    fixed["Fs"] = band.breakaway_mean if band.breakaway_count else math.nan
                    why["Fs"] = (f"mean of {band.breakaway_count} breakaway forces (not fitted)" if band.breakaway_count
                                 else "no breakaway observed: not determined")
                rows_only = replace(band, breakaway=())  # the breakaway table's rows
                if FIT_SPECS[name].family in _FS_FROM_BREAKAWAY_ROWS and rows_only.breakaway_count:
                    fixed["Fs"] = rows_only.breakaway_mean
                    why["Fs"] = (f"mean of {rows_only.breakaway_count} breakaway forces of the breakaway table "
                                 f"(not fitted)")
                fit = fit_model(pts, name, fixed, why)
                if FIT_SPECS[name].family == "karnopp":
                    fit = _fs_from_breakaways(fit, band)
                elif "Fs" in fixed:
                    fit = _fs_from_breakaways(fit, rows_only)
                fits[name] = _assess(fit, pts)
            except FrictionMapError as e:
                if strict:
                    raise
                skipped[name] = str(e)
            if tick:
                tick()
        dirs[direction] = DirectionMap(direction=direction, points=pts, stick_band=band, linear=linear,
                                       fits=fits, skipped=skipped, confounded=confounded_quantities(pts))
    return FrictionMap(directions=dirs)


# how far beyond the points' forces a fitted curve may go (in spreads of those forces)
_RANGE_MARGIN = 0.5


def _assess(fit: ModelFit, points: Sequence[MapPoint]) -> ModelFit:
    """What is wrong with the fitted curve as a whole: between the slowest and the fastest point
    it leaves the range of the points' forces (by more than half their spread), or its static
    level lies below its Coulomb level."""
    problems = list(fit.problems)
    slide = [p for p in points if not p.breakaway]
    curve = _fit_curve(fit, points)
    if curve is not None and slide:
        s = DIRECTIONS[fit.direction][1]
        if FIT_SPECS[fit.model].needs():  # a curve of the points' pressures or loads: the model at the points
            mag = s * _predicted(fit, slide)
        else:
            vv, FF = curve
            speeds = np.abs([p.v for p in slide])
            inside = (np.abs(vv) >= speeds.min()) & (np.abs(vv) <= speeds.max())  # where there are points
            mag = s * FF[inside] if inside.any() else s * FF
        forces = np.abs([p.F for p in points])
        spread = max(float(np.ptp(forces)), 0.1 * float(np.mean(forces)))
        low, high = float(forces.min()) - _RANGE_MARGIN * spread, float(forces.max()) + _RANGE_MARGIN * spread
        if np.any(~np.isfinite(mag)) or mag.min() < low or mag.max() > high:
            problems.append(f"the fitted curve leaves the data's range ({float(np.nanmin(mag)):.3g} to "
                            f"{float(np.nanmax(mag)):.3g} N against points of {forces.min():.3g} to "
                            f"{forces.max():.3g} N)")
    Fs, Fc = fit.params.get("Fs"), fit.params.get("Fc")
    if Fs is not None and Fc is not None and Fs < Fc * (1 - 1e-3):
        problems.append(f"the static level Fs = {Fs:.3g} N lies below the Coulomb level Fc = {Fc:.3g} N")
    return replace(fit, problems=tuple(problems)) if problems != list(fit.problems) else fit


def _fs_from_breakaways(fit: ModelFit, band: StickBand) -> ModelFit:
    """An Fs fixed at the mean breakaway force: its standard error and interval, or a flag."""
    std, ci, flags = dict(fit.std), dict(fit.ci95), list(fit.flags)
    if band.breakaway_count:
        m = band.breakaway_count
        se = band.breakaway_std / math.sqrt(m) if band.breakaway_std is not None else None
        std["Fs"] = se
        if se is not None:
            from scipy.stats import t as student_t

            h = float(student_t.ppf(0.975, m - 1)) * se
            ci["Fs"] = (band.breakaway_mean - h, band.breakaway_mean + h)
            if band.breakaway_std > 0.3 * band.breakaway_mean:
                flags.append({"param": "Fs", "reason": f"the {m} breakaway forces scatter widely (standard "
                                                       f"deviation {band.breakaway_std:.3g} N about "
                                                       f"{band.breakaway_mean:.3g} N): the piston hardly sticks, or "
                                                       f"is driven too fast to show it"})
        else:
            flags.append({"param": "Fs", "reason": "a single breakaway: no spread to judge it by"})
        Fc = fit.params.get("Fc")
        if Fc is not None and band.breakaway_mean < Fc:
            flags.append({"param": "Fs", "reason": f"the breakaway forces (mean {band.breakaway_mean:.3g} N) lie "
                                                   f"below the Coulomb level {Fc:.3g} N: the piston creeps rather "
                                                   f"than sticks"})
    else:
        flags.append({"param": "Fs", "reason": "no breakaway observed (the piston never stuck and then slid); "
                                               "a map of steady speeds cannot show static friction"})
    return replace(fit, std=std, ci95=ci, flags=tuple(flags))


# ================================================================ plot

def plot_map(fmap: FrictionMap, path: str | os.PathLike[str], title: str = "") -> None:
    """The map (points with their friction spread, breakaway rows apart) and every fitted curve, both
    directions (a model of the points' pressures or loads as its value at each point); the
    friction axis spans the points (a curve that runs off beyond them is cut)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise FrictionMapError("--plot needs matplotlib, which is not installed (pip install matplotlib).") from None
    fig, ax = plt.subplots(figsize=(9, 6))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    F_all, labelled = [0.0], set()
    for direction, d in fmap.directions.items():
        for static, marker, label in ((False, "o", "points"), (True, "^", "breakaway")):
            pts = [p for p in d.points if p.breakaway == static]
            if not pts:
                continue
            v = np.array([p.v for p in pts])
            F = np.array([p.F for p in pts])
            err = np.array([p.F_std for p in pts])
            F_all.extend((F - np.nan_to_num(err)).tolist() + (F + np.nan_to_num(err)).tolist())
            ax.errorbar(v * 1e3, F, yerr=np.where(np.isfinite(err), err, 0.0), fmt=marker, color="k", ms=4,
                        capsize=2, label=None if label in labelled else label)
            labelled.add(label)
        if d.stick_band.dv is not None:
            s = DIRECTIONS[direction][1]
            ax.axvspan(0, s * d.stick_band.dv * 1e3, color="0.9", zorder=0,
                       label="stick band" if direction == "extension" else None)
        for name, fit in d.fits.items():
            i = list(FIT_SPECS).index(name)  # one colour (and style) per model in both directions
            # the best bold, fits that may not be preferred (parameters not determined, an unsound curve) faint
            style = {"color": colours[i % len(colours)], "label": name if direction == "extension" else None,
                     "alpha": 1.0 if fit.preferable else 0.35, "lw": 2.5 if name == d.best else 1.2}
            if FIT_SPECS[name].needs():
                # the curve depends on the points' pressures or loads: the model at each point, not one line
                pts = [p for p in d.points if not p.breakaway]
                at = _predicted(fit, pts)
                ax.plot([p.v * 1e3 for p in pts], at, "x" if i < len(colours) else "+", ms=6, ls="none", **style)
                continue
            curve = _fit_curve(fit, d.points)
            if curve is None:
                continue
            vv, FF = curve
            ax.plot(vv * 1e3, FF, ls="-" if i < len(colours) else "--", **style)
    lo, hi = min(F_all), max(F_all)
    ax.set_ylim(lo - 0.15 * (hi - lo), hi + 0.15 * (hi - lo))
    ax.axhline(0, color="0.5", lw=0.5)
    ax.axvline(0, color="0.5", lw=0.5)
    ax.set_xlabel("velocity v [mm/s]")
    ax.set_ylabel("friction F [N]")
    ax.set_title((title or "static friction map") + "\nbold: the best fit; faint: fits not to be preferred")
    ax.legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()  # written atomically, as every output (a failed plot leaves no half file)
    fig.savefig(buf, dpi=120, format=Path(path).suffix.lstrip(".").lower() or "png")
    plt.close(fig)
    atomic_write(path, buf.getvalue())


def _predicted(fit: ModelFit, points: Sequence[MapPoint]) -> np.ndarray:
    """The fitted model at each point (with the point's own conditions)."""
    cls = FRICTION_MODELS[fit.family]
    p = cls.defaults()
    p.update(fit.model_values())
    needs = FIT_SPECS[fit.model].needs()
    cond = {k: np.array([getattr(q, k) if k in needs else 0.0 for q in points], float) for k in cls.CONDITIONS}
    return cls.static_force(np.array([q.v for q in points]), [p[k] for k in cls.PARAMS], **cond)


def _fit_curve(fit: ModelFit, points: Sequence[MapPoint]) -> tuple[np.ndarray, np.ndarray] | None:
    """The fitted curve over the direction's speeds (conditions at their mean over the points)."""
    cls = FRICTION_MODELS[fit.family]
    if not points:
        return None
    s = DIRECTIONS[fit.direction][1]
    a = np.abs([p.v for p in points])
    vv = s * np.linspace(max(a.min() * 0.05, 1e-5), a.max() * 1.05, 300)
    p = cls.defaults()
    p.update(fit.model_values())
    needs = FIT_SPECS[fit.model].needs() if fit.model in FIT_SPECS else cls.CONDITIONS
    cond = {k: float(np.nanmean([getattr(q, k) for q in points])) if k in needs else 0.0 for k in cls.CONDITIONS}
    return vv, cls.static_force(vv, [p[k] for k in cls.PARAMS], **cond)
