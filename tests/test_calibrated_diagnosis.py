"""Calibration and diagnosis together (`diagnose --calibrate`): every candidate calibrated with
the file's quantities, the nominal calibration one candidate among them; the calibration's
other starts where the valve is multimodal; a calibration that stays above the noise says so.

The end-to-end case is the project's own plant with a departed file and a leak; the benchmark
benchmarks/gauntlet.py runs the independent plant."""
from __future__ import annotations

import contextlib
import io
import json
import math
from dataclasses import replace

import casadi as ca
import numpy as np
import pytest
from conftest import CONFIGS

from combined_reality.calibrate import misfit_note
from combined_reality.calibrate.dead_band import dead_band_in_overlap, overlap_as_dead_band
from combined_reality.cli import main
from combined_reality.diagnose.calibrated import Screen, choose, train_share
from combined_reality.files import cylinder_tag, write_run
from combined_reality.identify import IdentifyResult
from combined_reality.identify.shooting import warm_nodes
from combined_reality.live import run_program
from combined_reality.live.programs import make_program
from hw.virtual_rig import VirtualRig
from sim.cylinder import OPENING_GRID, load_cylinder
from sim.effects import make_effect
from sim.plant import plant_for, valve_conductance


def _result(sigma: float, cost: float = 100.0, effects=()) -> IdentifyResult:
    return IdentifyResult(params={}, fit={}, fit_per_run=[], solver={"residual_sigma": sigma, "cost": cost},
                          cylinder=None, effects=tuple(effects), drive="command")


def _screen(effect: str, share: float, gain: float = 0.1) -> Screen:
    return Screen(effect=effect, stage="valve and chambers", share=share, gain=gain, status="converged",
                  result=_result(1.0))


def test_the_screen_passes_the_clear_shares_of_both_stages_best_first():
    screens = [_screen("leakage", 0.95, 0.8), _screen("heat_transfer", 0.35, 0.05), _screen("supply_droop", 0.05),
               _screen("friction_asymmetry", 0.3, 0.2), _screen("friction_position", 0.08),
               _screen("friction_dynamics", 0.5, 0.004),  # under half a percent of its stage's cost
               Screen(effect="valve_delay", stage="valve and chambers", error="failed")]
    chosen = [s.effect for s in choose(screens, screen_min=0.2, screen_share=0.1, leaders=3)]
    assert chosen == ["leakage", "friction_asymmetry", "heat_transfer"]  # by the share of the stage's cost
    # a share under screen_share of the best one's is left out, however large on its own
    assert [s.effect for s in choose(screens, 0.2, 0.4, 3)] == ["leakage"]
    assert choose([_screen("leakage", 0.9, gain=0.0)], 0.2, 0.1, 3) == []  # no gain on the stage's cost


def test_leaders_of_one_stage_are_followed_by_the_other_stages_best():
    """Gains compare badly across stages: where the leaders all come from the force balance, the
    best screen of the valve and chambers is calibrated too, last (a hard dead zone's screen took
    all its stage's excess, 4.4 % of the cost, behind three friction screens)."""
    def mech(effect, share, gain):
        return replace(_screen(effect, share, gain), stage="force balance in the whole model")

    screens = [mech("friction_position", 0.46, 0.15), mech("friction_dynamics", 0.38, 0.12),
               mech("friction_asymmetry", 0.23, 0.07), mech("stiction", 0.21, 0.035),
               _screen("valve_deadzone", 1.0, 0.044), _screen("leakage", 1.0, 0.027)]
    chosen = [s.effect for s in choose(screens, screen_min=0.2, screen_share=0.1, leaders=3)]
    assert chosen == ["friction_position", "friction_dynamics", "friction_asymmetry", "valve_deadzone"]
    # leaders of both stages already: nothing added
    mixed = screens[:2] + screens[4:]
    assert [s.effect for s in choose(mixed, 0.2, 0.1, 3)] == ["friction_position", "friction_dynamics",
                                                              "valve_deadzone"]


def test_a_candidate_fit_left_unfinished_above_the_noise_is_fitted_again_from_the_nominal_calibration(monkeypatch):
    """A candidate's whole-model fit that ran out of iterations above the noise crawled in a wrong
    basin although it ended below the nominal calibration: once more from the nominal calibration
    with the effect neutral, the lower cost kept; a converged one or one at the noise is kept as it is."""
    from combined_reality.diagnose import calibrated

    nominal = replace(_result(1.48, cost=1000.0), cylinder="nominal cylinder", nodes=np.zeros((4, 3)))
    starts = []

    def whole_model(cyl, runs, opts, say, start, nodes, effects, give_up_above=math.inf):
        starts.append((start, [e.name for e in effects]))
        return replace(_result(1.04, cost=500.0), solver={"residual_sigma": 1.04, "cost": 500.0,
                                                            "status": "converged"}), []

    monkeypatch.setattr(calibrated, "whole_model", whole_model)
    neutral = (make_effect("friction_dynamics", {"share": 0.0}),)
    for status, sigma, again in (("max_iterations", 1.46, True), ("line_search_failed", 1.46, True),
                                 ("converged", 1.46, False), ("max_iterations", 1.1, False)):
        staged = calibrated.WholeFit(result=replace(_result(sigma, cost=970.0), solver={
            "residual_sigma": sigma, "cost": 970.0, "status": status}), start="staged")
        starts.clear()
        w = calibrated.nested(staged, None, [], nominal, neutral, 1)
        assert starts == ([("nominal cylinder", ["friction_dynamics"])] if again else [])
        assert (w.start, w.result.solver["cost"]) == (("nested", 500.0) if again else ("staged", 970.0))


def test_a_held_shape_is_screened_from_each_of_its_basins_and_the_lowest_cost_kept(monkeypatch):
    """Stiction's decay shapes are held until the rest converges, so its screen starts nested and
    from the break-aways twice each: with the exponential tail (0) and the rational one (1, an
    alternative start's); the lowest TRAIN cost is the screen. An effect without held shapes
    screens once."""
    from combined_reality.diagnose import calibrated

    seen = []

    def screen_fit(base, runs, drive, estimate, effect, start, workers):
        seen.append((start, getattr(effect, "tail", None), getattr(effect, "Fs_excess", None)))
        cost = 10.0 if getattr(effect, "tail", 0.0) == 1.0 else 50.0
        return Screen(effect=effect.name, stage="force balance in the whole model", start=start, status="converged",
                      iterations=5, result=replace(_result(1.0, cost=cost), solver={"cost": cost, "residual_sigma": 1.0,
                                                                                    "status": "converged"}))

    monkeypatch.setattr(calibrated, "_screen_fit", screen_fit)
    monkeypatch.setattr(calibrated, "_went_nowhere", lambda s: False)
    data = []

    def from_data(cyl, runs, start, opts, say, file_cyl):
        data.append((start.tail, start.Fs_excess))
        cost = 5.0 if start.tail == 1.0 else 20.0
        return replace(_result(1.0, cost=cost, effects=(start,)),
                       solver={"cost": cost, "residual_sigma": 1.0, "status": "converged", "iterations": 9})

    monkeypatch.setattr(calibrated, "DATA_STARTS", {"stiction": from_data})
    base = _result(3.0, cost=100.0)
    [best] = calibrated.screen_candidate(("stiction", base, [], 1, None))
    assert seen == [(0, 0.0, 0.0), ("0, tail=1", 1.0, 0.0)]
    assert data == [(0.0, 10.0), (1.0, 10.0)]  # the break-aways from the defaults, both tails
    assert best.start == "data, tail=1" and best.result.solver["cost"] == 5.0
    seen.clear()
    calibrated.screen_candidate(("friction_asymmetry", base, [], 1, None))
    assert [s[0] for s in seen] == [0]


def test_a_screened_out_candidate_that_trades_off_against_a_calibrated_quantity_is_said(cyl_a):
    """A Coulomb friction that differs by direction is a constant force while the piston slides:
    its screen's a_coulomb trades off against the external force, and the diagnosis says so even
    where the candidate is not calibrated as a whole; a pair is said once (the whole fit's first),
    and a screen without a gain says nothing."""
    from combined_reality.diagnose.calibrated import WholeFit, trade_offs

    names = ["Fc", "external_force", "friction_asymmetry.a_coulomb", "friction_asymmetry.a_viscous"]
    corr = np.eye(4)
    corr[1, 2] = corr[2, 1] = 0.976
    asym = make_effect("friction_asymmetry")
    res = replace(_result(1.2, effects=(asym,)), params=dict.fromkeys(names), correlation=corr)
    screen = Screen(effect="friction_asymmetry", stage="force balance in the whole model", gain=0.15, share=0.15,
                    result=res)
    want = [{"effect": "friction_asymmetry", "parameter": "a_coulomb", "quantity": "external_force", "r": 0.976}]
    assert trade_offs([], [screen]) == want
    assert trade_offs([WholeFit(result=None)], [replace(screen, gain=0.001)]) == []
    corr2 = corr.copy()
    corr2[1, 2] = corr2[2, 1] = -0.99
    whole = WholeFit(result=replace(res, correlation=corr2))
    assert [c["r"] for c in trade_offs([whole], [screen])] == [-0.99]


def test_a_calibration_above_the_noise_says_so_and_names_the_next_step():
    assert misfit_note(_result(1.2)) == ""
    text = misfit_note(_result(1.66))
    assert "1.66 x the sensor noise" in text and "diagnose --calibrate" in text and "effect" in text
    assert "with leakage still lacks" in misfit_note(_result(1.9, effects=(make_effect("leakage"),)))
    assert train_share(_result(3.0), _result(1.0)) == pytest.approx(1.0)
    assert train_share(_result(3.0), _result(math.sqrt(5.0))) == pytest.approx(0.5)


def _curve(valve, direction: str, a: np.ndarray) -> np.ndarray:
    rises = valve.flow_increments(direction)
    return np.array([float(valve_conductance(1.0, float(x), getattr(valve, f"overlap_{direction}"),
                                             [ca.DM(r) for r in rises])) for x in a])


def test_an_overlap_said_as_a_dead_band_is_the_same_valve_and_goes_back():
    cyl = load_cylinder(CONFIGS / "cyl_a_32x100.toml")
    grid = np.array(OPENING_GRID)
    start = replace(cyl, valve=replace(cyl.valve, overlap_retract=0.04, flow_retract=tuple(0.9 * grid ** 1.3)))
    zero = overlap_as_dead_band(start)
    assert set(zero) == {"retract"}  # the extend direction has no overlap
    after = start.with_values(zero["retract"])
    assert after.valve.overlap_retract == 0.0 and after.valve.flow_extend == start.valve.flow_extend
    a = np.linspace(0.0, 1.0, 41)
    # the same valve up to the interpolation between grid points (1 % of full opening)
    assert np.max(np.abs(_curve(after.valve, "retract", a) - _curve(start.valve, "retract", a))) < 0.01 * 0.9
    back = dead_band_in_overlap(after)["retract"]
    assert back["overlap_retract"] == pytest.approx(OPENING_GRID[1])  # the last closed grid point below 0.04


def test_the_screens_base_recovers_where_the_first_stage_left_the_motion_far_off(cyl_a):
    """The mechanical screens are measured against the force balance through the whole model,
    fitted to its end from stage 1's motion node states. Where stage 1 ends far off (a supply
    droop case: 406 x the noise), so did that base (940 x), and every friction candidate then
    "removed" 99.99 % of its cost and crowded the true effect out. Fitted to its end, it starts
    once more from node states afresh from the data and keeps the lower cost."""
    from combined_reality.calibrate import CalibrateOptions, first_stages, force_balance_in_model

    truth = cyl_a.with_values({"mass": 1.25 * cyl_a.mechanics.moving_mass})
    rig = VirtualRig(truth, rate=1000, seed=5)
    run = run_program(rig, make_program("calibration", cyl_a, 8.0, seed=5), 8000)
    opts = CalibrateOptions(threads=1, max_iter=20)
    mech, pneu = first_stages(cyl_a, [run], opts, lambda _m: None)
    lost = replace(mech, nodes=mech.nodes + np.array([[0.02], [0.0]]))  # stage 1's motion 20 mm off
    started = force_balance_in_model(cyl_a, [run], opts, lambda _m: None, lost, pneu, start_only=True)
    base = force_balance_in_model(cyl_a, [run], opts, lambda _m: None, lost, pneu, start_only=False)
    assert started.solver["residual_sigma"] > 3.0  # the nodes alone lead it astray ...
    assert base.solver["residual_sigma"] < 1.2  # ... the base recovers
    assert base.params["mass"].value == pytest.approx(truth.mechanics.moving_mass, rel=0.03)
    assert base.params["Fc"].value == pytest.approx(cyl_a.friction.Fc, rel=0.03)


def test_warm_nodes_of_the_chambers_drive_keep_an_added_state_from_the_data(cyl_a):
    """The chambers drive has no motion states: a pneumatic effect's state starts as the data
    gave it (this raised on the missing x state before)."""
    plant = plant_for(cyl_a, "chambers", (make_effect("valve_delay"),))
    S = np.vstack([np.full((2, 5), 3e5), np.arange(5.0)[None, :]])
    warm = np.vstack([np.full((2, 5), 4e5), np.zeros((1, 5))])
    out = warm_nodes(plant, cyl_a, S, warm)
    assert np.all(out[:2] == 4e5) and np.all(out[2] == S[2])


def test_a_force_balance_that_does_not_explain_the_run_hands_on_its_values_not_its_motion(cyl_a):
    """The pressure drive can end far above the noise with node states that describe the misfit
    (100 m/s on a reference-plant case at 223 x the noise): the command-driven model then starts
    from its values, the chambers' pressures and the measured motion (warm_nodes takes the data
    where a node state is NaN); within the noise its motion is handed on as before."""
    from combined_reality.calibrate import joint_start

    pneu = replace(_result(1.05), nodes=np.full((2, 5), 4e5), drive="chambers")
    motion = np.vstack([np.full(5, 0.05), np.full(5, 99.9)])
    for sigma, kept in ((2.1, True), (223.0, False)):
        mech = replace(_result(sigma), nodes=motion, drive="pressure")
        nodes = joint_start(cyl_a, mech, pneu)[1]
        assert np.all(nodes[:2] == 4e5)
        assert np.array_equal(nodes[2:], motion) if kept else np.all(np.isnan(nodes[2:]))
    plant = plant_for(cyl_a, "command")
    S = np.vstack([np.full((2, 5), 3e5), np.full((1, 5), 0.04), np.zeros((1, 5))])
    out = warm_nodes(plant, cyl_a, S, nodes)
    assert np.all(out[:2] == 4e5) and np.array_equal(out[2:4], S[2:4])


def _record(truth, file_cyl, seed: int, program: str, duration: float, effects=()):
    rig = VirtualRig(truth, effects, rate=1000, seed=seed)
    run = run_program(rig, make_program(program, file_cyl, duration, seed=seed), int(duration * 1000))
    return replace(run, comments=(cylinder_tag(file_cyl),))


@pytest.mark.slow
def test_a_leak_on_a_rig_whose_file_is_off_is_named_with_the_file_calibrated_beside_it(cyl_a, tmp_path):
    """The file's dead volume and mass are off and the piston seal leaks: the leak is named, the
    mis-set quantities are those of the calibration with the leak, and the model with the leak
    reproduces VALID. A calibration run and an ordinary run are calibrated together."""
    truth = cyl_a.with_values({"dead_volume_cap": 2.0 * cyl_a.geometry.dead_volume_cap,
                               "mass": 1.3 * cyl_a.mechanics.moving_mass, "critical_ratio": 0.4})
    leak = make_effect("leakage", {"conductance": 2e-3 * cyl_a.valve.sonic_conductance})
    paths = []
    for seed, program, duration in ((1, "calibration", 10.0), (2, "mixed", 4.0), (3, "mixed", 5.0)):
        paths.append(tmp_path / f"run{seed}.csv")
        run = _record(truth, cyl_a, seed, program, duration, (leak,))
        write_run(paths[-1], run, comments=list(run.comments))
    out = tmp_path / "d.json"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = main(["diagnose", str(paths[0]), str(paths[1]), "--validate", str(paths[2]), "--config",
                     str(CONFIGS / "cyl_a_32x100.toml"), "--candidates", "leakage,mass",
                     "--calibrate", "--json", str(out), "-q"])
    assert code == 0, printed.getvalue()
    d = json.loads(out.read_text())
    assert d["verdict"] == "leakage", printed.getvalue()
    cal = d["calibration"]
    assert cal["model"] == "leakage" and cal["residual_sigma"] < 1.3
    mis = {m["quantity"]: m for m in cal["mis_set"]}
    assert mis["dead_volume_cap"]["calibrated"] == pytest.approx(truth.geometry.dead_volume_cap, rel=0.1)
    assert mis["mass"]["calibrated"] == pytest.approx(truth.mechanics.moving_mass, rel=0.05)
    rows = {r["effect"]: r for r in d["ranking"]}
    assert rows["mass"]["status"] == "absorbed"
    assert rows["leakage"]["params"]["conductance"] == pytest.approx(leak.conductance, rel=0.3)
    assert rows["leakage"]["normalized_rms_validation"] < 2.0
    assert "mis-set in the cylinder file (calibrated on TRAIN with leakage): dead_volume_cap" in printed.getvalue()
    # without --calibrate, one TRAIN run only
    with contextlib.redirect_stderr(io.StringIO()) as err:
        assert main(["diagnose", str(paths[0]), str(paths[1]), "--validate", str(paths[2]), "-q"]) == 2
    assert "--calibrate" in err.getvalue()


def test_separability_names_what_a_run_lacks_to_tell_an_effect_from_calibrated_quantities(cyl_a):
    """A run that holds the valve closed at 2 bar for 2 s and jumps its command 12 times, but
    moves only one way and never opens the valve wide: leakage and valve_delay are separable,
    friction_asymmetry and supply_droop are not, and the report says what would separate them."""
    from combined_reality.calibrate import separability
    from combined_reality.files import Run

    n = 6000
    t = np.arange(n) * 1e-3
    u = np.zeros(n)
    u[2000:] = np.where((np.arange(n - 2000) // 150) % 2 == 0, 0.35, 0.2)  # 26 command jumps of 0.15
    x = np.where(t < 2.0, 0.02, 0.02 + 0.01 * (t - 2.0))  # at rest, then extending at 10 mm/s
    p1, p2 = np.full(n, 4e5), np.full(n, 2e5)
    rows = {e["effect"]: e for e in separability(cyl_a, [Run(t, u, x, p1, p2)])}
    assert "leakage" not in rows and "valve_delay" not in rows
    assert rows["friction_asymmetry"]["amount"] == 0.0 and "both directions" in rows["friction_asymmetry"]["needs"]
    assert rows["supply_droop"]["amount"] == 0.0


def test_a_gate_takes_over_the_overlap_the_calibration_gave_the_characteristic(cyl_a):
    """The hard dead zone the calibration cannot take starts from the nominal calibration with its
    overlap handed over: the gate's overlap at the larger calibrated overlap, the characteristic's
    overlaps lowered by as much; where the calibration holds no overlap, there is nothing to hand."""
    from combined_reality.diagnose.calibrated import handed_over

    cyl = cyl_a.with_values({"overlap_extend": 0.016, "overlap_retract": 0.014})
    nodes = np.ones((4, 3))
    nominal = replace(_result(1.44), cylinder=cyl, nodes=nodes)
    start, start_nodes, effects = handed_over("valve_deadzone", nominal)
    assert (start.value("overlap_extend"), start.value("overlap_retract")) == (0.0, 0.0)
    assert start.value("mass") == cyl.value("mass") and start_nodes is nodes
    (gate,) = effects
    assert (gate.name, gate.overlap, gate.gate) == ("valve_deadzone", 0.016, 1.0)
    closed = cyl_a.with_values({"overlap_extend": 0.0, "overlap_retract": 0.0})
    assert handed_over("valve_deadzone", replace(nominal, cylinder=closed)) is None
