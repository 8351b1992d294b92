"""Before a fit: can these runs determine the chosen friction parameters at all? A fit on a
run that cannot (no motion, one direction only, one speed, one pressure difference) still
"converges", to numbers that mean nothing; this says which parameter and why instead.

- Fc (Coulomb) needs motion in both directions: in one, it is a constant force like a load,
  the mounting angle or a pressure-sensor offset;
- Fv (viscous) needs motion at different speeds;
- kp (seal pressure) needs motion at different |p1 - p2|, not changing in step with the speed
  when Fv is estimated too.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from sim.cylinder import Cylinder

from ..files import Run, RunFormatError, split_at_gaps
from .smoothing import velocity_estimate

__all__ = ["MotionSummary", "motion_summary", "check_determinable"]

FRICTION = ("Fc", "Fv", "kp")
_MIN_MOTION_S = 0.05  # s of motion per direction that Fc needs at least
_MIN_SPEED_RATIO = 1.5  # fastest / slowest decile of the moving speeds that Fv needs at least
_TOGETHER = 0.98  # |r| of speed and |p1 - p2| above which kp and Fv cannot be told apart


@dataclass(frozen=True)
class MotionSummary:
    moving_speed: float  # m/s: faster than this counts as motion
    time_extending: float  # s
    time_retracting: float  # s
    position_range: float  # m
    speeds: np.ndarray  # |v| of the moving samples, m/s
    dp: np.ndarray  # |p1 - p2| at the moving samples, Pa


def motion_summary(cyl: Cylinder, runs: Sequence[Run]) -> MotionSummary:
    threshold = max(5.0 * cyl.friction.v_smooth, 2e-3)
    ext = ret = 0.0
    lo, hi = np.inf, -np.inf
    speeds, dps = [], []
    for piece in (p for r in runs for p in split_at_gaps(r)):
        if piece.n < 3:
            continue
        finite = np.isfinite(piece.x)  # a channel not measured at a sample is NaN
        if finite.sum() < 3:
            continue
        t, x = piece.t[finite], piece.x[finite]
        v = velocity_estimate(t, x)
        dt = np.gradient(t)
        ext += float(dt[v > threshold].sum())
        ret += float(dt[v < -threshold].sum())
        lo, hi = min(lo, float(x.min())), max(hi, float(x.max()))
        moving = np.abs(v) > threshold
        speeds.append(np.abs(v[moving]))
        dps.append(np.abs(piece.p1[finite] - piece.p2[finite])[moving])
    cat = (lambda a: np.concatenate(a) if a else np.empty(0))
    dp = cat(dps)
    ok = np.isfinite(dp)
    return MotionSummary(moving_speed=threshold, time_extending=ext, time_retracting=ret,
                         position_range=max(0.0, hi - lo) if np.isfinite(hi) else 0.0,
                         speeds=cat(speeds)[ok], dp=dp[ok])


def check_determinable(cyl: Cylinder, runs: Sequence[Run], estimate: Sequence[str]) -> None:
    """Refuse (RunFormatError: bad input, exit status 2) runs that cannot determine the
    friction parameters in `estimate`, naming the parameter and why."""
    wanted = [n for n in FRICTION if n in estimate]
    if not wanted or not runs:
        return
    names = [str(r.source.name) if r.source is not None else "the run" for r in runs]
    who = f"{names[0]}: this run" if len(names) == 1 else f"{', '.join(names)}: these runs"
    m = motion_summary(cyl, runs)
    moving = m.time_extending + m.time_retracting
    if moving < _MIN_MOTION_S:
        raise RunFormatError(f"{who} cannot determine {', '.join(wanted)}: the piston does not move (faster than "
                             f"{m.moving_speed * 1e3:.3g} mm/s for {moving:.3g} s in all, position range "
                             f"{m.position_range * 1e6:.4g} um); friction shows only in motion.")
    if "Fc" in wanted and min(m.time_extending, m.time_retracting) < _MIN_MOTION_S:
        only = "extending" if m.time_extending > m.time_retracting else "retracting"
        raise RunFormatError(f"{who} cannot determine Fc: the piston moves only while {only} "
                             f"({m.time_extending:.3g} s extending, {m.time_retracting:.3g} s retracting); in one "
                             "direction Coulomb friction cannot be told from a constant force (load, mounting angle, a "
                             "pressure-sensor offset), so record moves both ways or leave Fc out of --estimate.")
    lo, hi = np.percentile(m.speeds, [10, 90]) if m.speeds.size else (0.0, 0.0)
    if "Fv" in wanted and hi < _MIN_SPEED_RATIO * lo:
        raise RunFormatError(f"{who} cannot determine Fv: the piston moves at nearly one speed ({lo * 1e3:.3g} to "
                             f"{hi * 1e3:.3g} mm/s for 80 % of the motion); viscous friction grows with speed, so "
                             "record moves at different speeds or leave Fv out of --estimate.")
    if "kp" in wanted:
        dlo, dhi = np.percentile(m.dp, [10, 90]) if m.dp.size else (0.0, 0.0)
        if dhi - dlo < max(10.0 * cyl.sensors.pressure_noise, 0.05 * dhi):
            raise RunFormatError(f"{who} cannot determine kp: while the piston moves, |p1 - p2| stays between "
                                 f"{dlo / 1e3:.4g} and {dhi / 1e3:.4g} kPa (80 % of the motion); the seal-pressure "
                                 "term needs motion at different pressure differences, so vary the load or the "
                                 "supply, or leave kp out of --estimate.")
        if "Fv" in wanted and m.speeds.size > 2 and np.std(m.speeds) > 0 and np.std(m.dp) > 0:
            r = float(np.corrcoef(m.speeds, m.dp)[0, 1])
            if abs(r) > _TOGETHER:
                raise RunFormatError(f"{who} cannot determine kp and Fv apart: speed and |p1 - p2| changed together "
                                     f"(correlation {r:.4f}), so friction growing with one cannot be told from "
                                     "friction growing with the other; record moves where they vary independently, "
                                     "or estimate only one of them.")
