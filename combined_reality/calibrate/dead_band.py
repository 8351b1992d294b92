"""A flow characteristic that stays closed beyond its overlap, said again with that dead band
inside the overlap.

A curve whose first grid levels sit at zero is closed up to the last of them, just as a larger
overlap would close it, and fits the runs alike. But there the fits are stuck: the zero rises
sit at their bound, the overlap has no gradient (moving it moves nothing that opens), and the
valve's real opening, often a flat-starting S or power law, is left to the few grid segments
that remain. Measured on a valve closed up to 0.073 of the command (benchmarks/calibration.py,
Norgren seed 431; the earlier grid of 11 openings): both fitting stages ended with an overlap of
0.015 and two closed segments, VALID was reproduced to 16.2 x the sensor noise; with the band
moved before the whole model's fit, it found an overlap of 0.072 and VALID came to 3.7 x (and to
1.2 x on today's grid).
"""
from __future__ import annotations

from scipy.interpolate import PchipInterpolator

from sim.cylinder import OPENING_GRID, VALVE_DIRECTIONS, Cylinder

__all__ = ["CLOSED_LEVEL", "dead_band_in_overlap"]

# a grid level below this fraction of the full opening's level counts as closed (a fit leaves a
# closed segment's rise at its bound, 0)
CLOSED_LEVEL = 1e-4
MAX_OVERLAP = 0.45  # leave room below the parameter's bound (0.5)


def dead_band_in_overlap(cyl: Cylinder) -> dict[str, float]:
    """For each direction whose characteristic is closed at its first grid levels: the overlap
    moved to the last closed grid point and the rises of the same curve (the plant's monotone
    cubic) on the grid beyond it, by parameter name. Empty when no direction has a dead band."""
    v = cyl.valve
    out: dict[str, float] = {}
    grid = (0.0, *OPENING_GRID)
    for d in VALVE_DIRECTIONS:
        levels = getattr(v, f"flow_{d}")
        if levels[-1] <= 0:
            continue
        closed = sum(level <= CLOSED_LEVEL * levels[-1] for level in levels)  # leading: the levels never fall
        if not closed:
            continue
        k0 = closed - 1  # the last closed grid point
        overlap = getattr(v, f"overlap_{d}")
        s0 = OPENING_GRID[k0]
        new_overlap = overlap + s0 * (1.0 - overlap)
        if new_overlap > MAX_OVERLAP:
            continue
        curve = PchipInterpolator(grid, (0.0, *levels))
        # the new grid's openings, as openings of the old curve: a = o' + s'(1 - o') = o + s(1 - o)
        new_levels = [max(float(curve(s0 + s * (1.0 - s0))), 0.0) for s in OPENING_GRID]
        new_levels[-1] = float(levels[-1])
        out[f"overlap_{d}"] = new_overlap
        previous = 0.0
        for k, level in enumerate(new_levels):
            level = max(level, previous)  # monotone, whatever the rounding
            out[f"flow_{d}_{k + 1}"] = level - previous
            previous = level
    return out
