"""What a run alone shows to be in the wrong unit or range, before any model sees it: a
command outside [-1, 1] (percent, volts), pressures that are bar, kPa, psi or gauge, a
position in millimetres, a time column in milliseconds. One detector, worded by whoever
read the values (the run reader names the CSV's line and cell; `import` the recording's)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

__all__ = ["MIN_ABS_PRESSURE", "MAX_ABS_PRESSURE", "MAX_ABS_POSITION", "COMMAND_LIMIT", "Implausible",
           "first_implausible", "time_unit_problem", "measured_value"]

# Below this no absolute pressure on a pneumatic rig is plausible, while bar (7.0), kPa (700),
# psi (100) and gauge Pa (around 0) all are: catches the usual unit slips.
MIN_ABS_PRESSURE = 2.0e4  # Pa
# Above this no pneumatic pressure is plausible (sensors end near 25 bar): a reading beyond is
# a fault of the sensor or the link, not a pressure.
MAX_ABS_PRESSURE = 1.0e7  # Pa
MAX_ABS_POSITION = 10.0  # m; a stroke in mm exceeds this almost immediately
# u is the fraction of full opening; a hair beyond 1 is rounding of a saturated command
COMMAND_LIMIT = 1.0 + 1e-9
# a servopneumatic cylinder moves within tens of ms: a run sampled this slowly is a time in ms
_SLOWEST_PERIOD = 0.5  # s
_LONGEST_COARSE_RUN = 1.0e4  # s: a run this long sampled at 20 Hz or slower is in ms (e.g. 10 kHz in ms)
_COARSE_PERIOD = 0.05  # s

_PRESSURES = ("p1", "p2", "ps")


@dataclass(frozen=True)
class Implausible:
    column: str
    index: int  # the first offending sample
    reason: str  # what follows the value in a message: "looks like bar or gauge pressure; ..."


def first_implausible(columns: Mapping[str, np.ndarray]) -> Implausible | None:
    """The first value of the standard columns (u, x, p1, p2, ps) that cannot be in the run's
    units, checked in that order; NaN (not measured) passes."""
    u = columns.get("u")
    if u is not None:
        bad = np.flatnonzero(np.abs(u) > COMMAND_LIMIT)
        if bad.size:
            return Implausible("u", int(bad[0]), "is outside [-1, 1]: the command is the valve's opening as a fraction "
                                                 "of full opening (not percent or volts)")
    for name in _PRESSURES:
        p = columns.get(name)
        if p is not None:
            bad = np.flatnonzero((p < MIN_ABS_PRESSURE) | (p > MAX_ABS_PRESSURE))
            if bad.size:
                i = int(bad[0])
                return Implausible(name, i, "looks like bar or gauge pressure; absolute Pa required (bar: times 1e5; "
                                   "gauge: plus the atmosphere)"
                                   if p[i] < MIN_ABS_PRESSURE else
                                   f"is beyond {MAX_ABS_PRESSURE:g} Pa ({MAX_ABS_PRESSURE / 1e5:g} bar), which no "
                                   "pneumatic pressure reaches; absolute Pa required")
    x = columns.get("x")
    if x is not None:
        bad = np.flatnonzero(np.abs(x) > MAX_ABS_POSITION)
        if bad.size:
            return Implausible("x", int(bad[0]), f"is beyond {MAX_ABS_POSITION:g} m, which looks like millimetres; "
                                                 "metres required (divide by 1000)")
    return None


def time_unit_problem(t: np.ndarray) -> str | None:
    """Why a strictly increasing time column looks like milliseconds, or None."""
    if t.size < 2:
        return None
    period = float(np.median(np.diff(t)))
    duration = float(t[-1] - t[0])
    if period >= _SLOWEST_PERIOD or (period >= _COARSE_PERIOD and duration > _LONGEST_COARSE_RUN):
        rate = f"{1 / period:.3g} Hz" if period > 0 and math.isfinite(1 / period) else "?"
        return (f"the samples are {period:.4g} s apart ({rate}) over {duration:.6g} s, which looks like a time in "
                "milliseconds; the time column must be in seconds")
    return None


def measured_value(name: str, value: float | None) -> float:
    """A measured channel's sample as the tool records it: NaN (not measured) where the
    channel was missing, not finite, or beyond what the run reader accepts (a sensor or link
    fault such as 3e38 Pa), so that a recording stays readable and every count agrees."""
    if value is None:
        return math.nan
    v = float(value)
    if not math.isfinite(v):
        return math.nan
    if name in _PRESSURES:
        return v if MIN_ABS_PRESSURE <= v <= MAX_ABS_PRESSURE else math.nan
    if name == "x":
        return v if abs(v) <= MAX_ABS_POSITION else math.nan
    return v
