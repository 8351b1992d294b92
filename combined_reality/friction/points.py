"""Points of the static friction-velocity map from recorded runs.

A run gives the friction Newton's law implies with the measured pressures and a filtered
acceleration (`identify.friction_from_newton`). Stretches of sustained motion at nearly
constant velocity (small acceleration, small velocity spread, at least `min_duration`)
become one point each: mean velocity, mean friction, their spreads, the sample count,
and the mean pressure conditions (|p1 - p2|, counter pressure). Where the piston
sticks (|v| below `stuck_speed` for `stuck_duration`) and then breaks away, the largest
friction before sliding is a breakaway force.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim.cylinder import Cylinder

from ..files import Run, split_at_gaps
from ..identify import derivative_kernels, friction_from_newton
from .specs import SegmentOptions

__all__ = ["MapPoint", "Breakaway", "RunPoints", "points_from_run"]


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
