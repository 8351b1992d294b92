"""The flow characteristic's dead band moved into the overlap: the same curve, said so that a
fit can move it."""
from __future__ import annotations

from dataclasses import replace

import casadi as ca
import numpy as np
import pytest
from conftest import CONFIGS

from combined_reality.calibrate.dead_band import dead_band_in_overlap
from sim.cylinder import OPENING_GRID, load_cylinder
from sim.plant import valve_conductance


def conductance(valve, direction: str, a: np.ndarray) -> np.ndarray:
    """The plant's own curve (C / sonic_conductance) at command magnitudes a."""
    rises = valve.flow_increments(direction)
    return np.array([float(valve_conductance(1.0, float(x), getattr(valve, f"overlap_{direction}"),
                                             [ca.DM(r) for r in rises])) for x in a])


@pytest.fixture
def cyl():
    return load_cylinder(CONFIGS / "cyl_a_32x100.toml")


def test_a_curve_closed_at_its_first_levels_gets_that_band_as_overlap(cyl) -> None:
    grid = np.array(OPENING_GRID)
    # closed up to the third grid point beyond an overlap of 0.02, then a power law
    levels = np.where(grid <= OPENING_GRID[2], 0.0, 1.3 * np.clip((grid - OPENING_GRID[2]) / (1 - OPENING_GRID[2]), 0, 1) ** 1.5)
    start = replace(cyl, valve=replace(cyl.valve, overlap_extend=0.02, flow_extend=tuple(levels)))
    found = dead_band_in_overlap(start)
    assert set(found) == {"extend"}
    moved = found["extend"]
    assert set(moved) == {"overlap_extend", *(f"flow_extend_{k + 1}" for k in range(len(OPENING_GRID)))}
    assert moved["overlap_extend"] == pytest.approx(0.02 + OPENING_GRID[2] * 0.98)
    after = start.with_values(moved)
    assert after.valve.flow_extend[0] > 0 and after.valve.flow_extend[-1] == pytest.approx(1.3)
    assert after.valve.flow_retract == start.valve.flow_retract  # the other direction untouched
    a = np.linspace(0.0, 1.0, 401)
    before, now = conductance(start.valve, "extend", a), conductance(after.valve, "extend", a)
    assert np.all(now[a <= moved["overlap_extend"]] == 0.0)
    # the same curve up to the interpolation between the new grid points (0.3 % of full opening)
    assert np.max(np.abs(now - before)) < 3e-3 * 1.3
    assert dead_band_in_overlap(after) == {}  # said so once, nothing left to move


def test_a_curve_open_from_its_overlap_and_the_linear_law_stay_as_they_are(cyl) -> None:
    assert dead_band_in_overlap(cyl) == {}
    grid = np.array(OPENING_GRID)
    tiny_start = replace(cyl, valve=replace(cyl.valve, overlap_retract=0.05, flow_retract=tuple(0.8 * grid ** 1.5)))
    assert dead_band_in_overlap(tiny_start) == {}  # its first level is small, not closed


def test_the_valve_stage_starts_again_with_both_overlaps_at_zero_then_each_alone(cyl) -> None:
    """A valve that overlaps one way only: a fit that took an overlap both ways is started again
    with each at zero alone (a held-out case had stayed at 1.32 x the noise with a retract
    overlap of 0.06 against a truth of 0, and both at zero ended at 2.67 x)."""
    from combined_reality.calibrate.stages import CALIBRATED, other_chamber_starts

    grid = np.array(OPENING_GRID)
    both = replace(cyl, valve=replace(cyl.valve, overlap_extend=0.06, overlap_retract=0.05,
                                      flow_extend=tuple(grid), flow_retract=tuple(grid)))
    starts = other_chamber_starts(both, set(CALIBRATED), ("overlap",))
    assert [label.split(" (")[0] for label, _ in starts] == ["the overlaps at zero", "the extend overlap at zero",
                                                            "the retract overlap at zero"]
    (_, zero), (_, ext), (_, ret) = starts
    assert zero == {**ext, **ret} and ext["overlap_extend"] == 0.0 and "overlap_retract" not in ext
    one = replace(both, valve=replace(both.valve, overlap_retract=0.0))
    assert [label.split(" (")[0] for label, _ in other_chamber_starts(one, set(CALIBRATED), ("overlap",))] == [
        "the overlaps at zero"]
