"""The calibration program's segments that keep effects apart from the calibrated quantities:
holds with the valve closed (at both end stops and at mid-stroke), slow moves across the stroke
both ways, pulses of growing command; bounded commands, and every segment in a short run."""
from __future__ import annotations

import numpy as np
import pytest

from combined_reality.live import make_program, run_program
from hw.virtual_rig import VirtualRig
from sim.effects import Leakage

DURATION = 20.0


def record(cyl, effects=(), seed: int = 3):
    prog = make_program("calibration", cyl, DURATION, seed=seed)
    return prog, run_program(VirtualRig(cyl, effects, rate=1000, seed=seed), prog, int(DURATION * 1000))


@pytest.fixture(scope="module")
def nominal(cyl_a):
    return record(cyl_a)


def segments(prog, run, kind: str, sign: float | None = None, settle: float = 0.0):
    """Sample masks of each segment of this kind (and sign): the row of a sample holds the
    command computed at the one before; `settle` s at the start of each are left out."""
    out = []
    for t0, t1, k, s, _ in prog.phases:
        if k == kind and (sign is None or s == sign) and t1 <= run.t[-1]:
            out.append((run.t > t0 + run.sample_period + settle) & (run.t <= t1))
    return out


def test_a_20s_run_holds_every_segment_and_bounded_commands(cyl_a, nominal):
    prog, run = nominal
    kinds = {k for t0, _, k, _, _ in prog.phases if t0 < DURATION}
    assert kinds >= {"creep", "slow", "end", "end_hold", "end_closed", "closed", "pulse", "settle"}
    assert np.all(np.abs(run.u) <= prog.opts.u_max + 1e-12)
    for kind in ("end", "end_hold"):
        for m in segments(prog, run, kind):
            assert np.all(np.abs(run.u[m]) <= prog.END_COMMAND + 1e-12)
    for m in segments(prog, run, "end_hold", settle=0.5):  # at the stop, a constant opening
        assert np.all(np.abs(run.u[m]) == prog.END_COMMAND)
    # pulses of growing command, both ways
    levels = [(s, lvl) for t0, _, k, s, lvl in prog.phases if k == "pulse" and t0 < DURATION]
    assert {s for s, _ in levels} == {1.0, -1.0}
    assert [lvl for s, lvl in levels if s > 0] == sorted(lvl for s, lvl in levels if s > 0)
    # a longer run repeats the cycle, starting the other way
    long = make_program("calibration", cyl_a, 80.0, seed=3)
    first_creeps = [s for _, _, k, s, _ in long.phases if k == "creep"][::2]
    assert first_creeps[:2] == [1.0, -1.0]


def test_the_closed_holds_keep_the_valve_closed_and_the_pressures_where_they_were(cyl_a, nominal):
    prog, run = nominal
    L = cyl_a.geometry.stroke
    for sign in (1.0, -1.0):
        (m,) = segments(prog, run, "end_closed", sign)
        assert np.all(run.u[m] == 0.0)
        # at the stop, supply on one side and atmosphere on the other, the piston still
        assert np.all(run.x[m] > L - 5e-4) if sign > 0 else np.all(run.x[m] < 5e-4)
        high, low = (run.p1, run.p2) if sign > 0 else (run.p2, run.p1)
        assert np.median(high[m]) > 0.9 * cyl_a.supply.pressure and np.median(low[m]) < 1.5 * cyl_a.supply.atmosphere
        # a closed valve and no leak: nothing moves the pressures beyond the noise
        assert abs(np.mean(high[m][-100:]) - np.mean(high[m][:100])) < 5 * cyl_a.sensors.pressure_noise
    closed = segments(prog, run, "closed")
    assert len(closed) >= 5 and all(np.all(run.u[m] == 0.0) for m in closed)


def test_a_leak_shows_in_the_closed_holds_at_the_ends(cyl_a):
    """What the holds are for: with the valve closed, a leak across the piston relaxes the
    pressure difference that the nominal model holds constant."""
    prog, run = record(cyl_a, (Leakage(conductance=1e-12),))
    for sign in (1.0, -1.0):
        (m,) = segments(prog, run, "end_closed", sign)
        dp = sign * (run.p1[m] - run.p2[m])
        assert np.mean(dp[:100]) - np.mean(dp[-100:]) > 20 * cyl_a.sensors.pressure_noise


def test_the_slow_moves_cross_the_whole_stroke_both_ways_at_the_end_speed(cyl_a, nominal):
    prog, run = nominal
    L = cyl_a.geometry.stroke
    v = np.gradient(run.x, run.t)
    for sign in (1.0, -1.0):
        # to mid-stroke (where the valve closes for a hold), then on into the stop
        moves = [m for kind in ("slow", "end") for m in segments(prog, run, kind, sign)]
        assert len(moves) == 2
        moving = np.any(moves, axis=0) & (run.x > 0.2 * L) & (run.x < 0.8 * L)
        covered = np.histogram(run.x[moving], bins=6, range=(0.2 * L, 0.8 * L))[0]
        assert np.all(covered * prog.end_speed / 1000 > 0.5 * 0.1 * L)  # every sixth of the way, slowly
        steady = [m for kind in ("slow", "end") for m in segments(prog, run, kind, sign, settle=0.2)]
        steady = np.any(steady, axis=0) & (run.x > 0.2 * L) & (run.x < 0.8 * L)
        assert np.median(sign * v[steady]) == pytest.approx(prog.end_speed, rel=0.25)
        # landed in the stop before the hold with the valve open
        (hold,) = segments(prog, run, "end_hold", sign, settle=0.3)
        assert np.all(run.x[hold] > L - 5e-4) if sign > 0 else np.all(run.x[hold] < 5e-4)


def test_live_help_names_every_program(capsys):
    from combined_reality.cli import main
    from combined_reality.live import PROGRAMS

    assert main(["live", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert all(f"{name}: " in text for name in PROGRAMS) and "file:CMD.csv" in text
