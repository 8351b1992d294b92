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

from sim.cylinder import OPENING_GRID, VALVE_DIRECTIONS, Cylinder, flow_levels_at

__all__ = ["CLOSED_LEVEL", "dead_band_in_overlap", "overlap_as_dead_band"]

# a grid level below this fraction of the full opening's level counts as closed (a fit leaves a
# closed segment's rise at its bound, 0)
CLOSED_LEVEL = 1e-4
MAX_OVERLAP = 0.45  # leave room below the parameter's bound (0.5)


def dead_band_in_overlap(cyl: Cylinder) -> dict[str, dict[str, float]]:
    """Per direction whose characteristic is closed at its first grid levels: the overlap moved
    to the last closed grid point and the rises of the same curve on the grid beyond it, by
    parameter name. Directions without a dead band are left out."""
    v = cyl.valve
    out: dict[str, dict[str, float]] = {}
    for d in VALVE_DIRECTIONS:
        levels = getattr(v, f"flow_{d}")
        closed = sum(level <= CLOSED_LEVEL * levels[-1] for level in levels)  # leading: the levels never fall
        if levels[-1] <= 0 or not closed:
            continue
        s0 = OPENING_GRID[closed - 1]  # the last closed grid point
        overlap = getattr(v, f"overlap_{d}")
        new_overlap = overlap + s0 * (1.0 - overlap)
        if new_overlap > MAX_OVERLAP:
            continue
        # the new grid's openings as openings of the old curve: a = o' + s'(1 - o') = o + s(1 - o)
        new_levels = flow_levels_at(OPENING_GRID, levels, [s0 + s * (1.0 - s0) for s in OPENING_GRID])
        out[d] = {f"overlap_{d}": new_overlap,
                  **{f"flow_{d}_{k + 1}": b - a for k, (a, b) in enumerate(zip((0.0, *new_levels), new_levels))}}
    return out


def overlap_as_dead_band(cyl: Cylinder) -> dict[str, dict[str, float]]:
    """The other way round: per direction with an overlap, the overlap at zero and the same
    curve on the grid from there (closed up to the old overlap, then rising as before), by
    parameter name. An overlap and a curve that starts flat fit the runs alike, and a fit can
    stay on the wrong side of that choice: from zero, the rises below the old overlap may grow."""
    v = cyl.valve
    out: dict[str, dict[str, float]] = {}
    for d in VALVE_DIRECTIONS:
        o = getattr(v, f"overlap_{d}")
        if o <= 0:
            continue
        levels = getattr(v, f"flow_{d}")
        # an opening a of the new grid is the opening (a - o) / (1 - o) beyond the old overlap
        beyond = [a for a in OPENING_GRID if a > o]
        at = flow_levels_at(OPENING_GRID, levels, [(a - o) / (1.0 - o) for a in beyond])
        new = [0.0] * (len(OPENING_GRID) - len(beyond)) + list(at)  # levels never fall (flow_levels_at)
        out[d] = {f"overlap_{d}": 0.0,
                  **{f"flow_{d}_{k + 1}": b - a for k, (a, b) in enumerate(zip((0.0, *new), new))}}
    return out
