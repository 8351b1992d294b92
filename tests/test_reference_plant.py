"""The independent reference plant (benchmarks/reference_plant.py): it agrees with the project's
plant on the nominal physics, its integration is converged, every effect form vanishes at its
neutral value and is visible at its strong one, air is conserved in closed chambers, the end
stops hold, and the truth travels with the run.

Most checks share 0.5 s simulations of the default cylinder in closed loop (seed 5, which moves
fast enough for the supply effects to matter): the nominal plant alone and every effect form at
its neutral and at its strong value, simulated together in one call (see plant_runs). Every strong form changes the
position by at least twice the test's threshold within that half second (the weakest,
supply_droop:line, by 108 um; in 2 s runs, which cost four times as much, it shows less: 81 um).
"""
from __future__ import annotations

import ast
import importlib.util
import json
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from combined_reality.files import cylinder_identity, cylinder_tag, read_run, recorded_cylinder
from sim.cylinder import load_cylinder

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_CYLINDER = ROOT / "combined_reality" / "data" / "cyl_a_32x100.toml"
SEED, DURATION = 5, 0.5


def _load_module():
    spec = importlib.util.spec_from_file_location("reference_plant", ROOT / "benchmarks" / "reference_plant.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["reference_plant"] = mod  # dataclasses look their module up by name
    spec.loader.exec_module(mod)
    return mod


rp = _load_module()
FORMS = list(rp.EFFECT_FORMS.values())


def _rms(a, b):
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


@pytest.fixture(scope="module")
def cyl():
    return load_cylinder(DEFAULT_CYLINDER)


HALVED = (rp.DelayTransport, rp.DeadzoneHard, rp.DynamicsDahl)  # forms that switch within a step or carry a state


@pytest.fixture(scope="module")
def plant_runs(cyl):
    """Every run the module's effect checks share, as one call: the nominal plant (no effect form,
    noise off), every form at its neutral and at its strong value, and the nominal run and the
    forms of HALVED again at half the nominal step ("fine", ...). A batch costs about the same
    per step whatever it holds, so the cases at the nominal step run as one batch (the neutral
    values among all the others) and every other case at one finer step: the strong forms that
    ask for more than the nominal step (their visibility does not depend on it) and the halved
    runs."""
    nominal = rp.Case(cyl, DURATION, SEED, noise=False)
    n0 = rp.substeps_for(nominal)
    keys, cases = ["nominal"], [nominal]
    for cls in FORMS:
        for level, eff in (("neutral", cls.neutral()), ("strong", cls.typical(cyl, 1.0))):
            cases.append(rp.Case(cyl, DURATION, SEED, noise=False, effects=(eff,)))
            keys.append((cls, level))
    auto = [rp.substeps_for(c) for c in cases]
    fine = max([2 * n0] + auto)
    steps = [n if n == n0 else fine for n in auto]
    for cls in (None,) + HALVED:
        keys.append(("fine", cls))
        cases.append(nominal if cls is None else cases[keys.index((cls, "strong"))])
        steps.append(2 * n0)
    return dict(zip(keys, rp.simulate_detailed(cases, substeps=steps)))


@pytest.fixture(scope="module")
def nominal(plant_runs):
    return plant_runs["nominal"]


@pytest.fixture(scope="module")
def effect_runs(plant_runs):
    """{(form, level): Result}"""
    return {k: v for k, v in plant_runs.items() if k != "nominal" and k[0] != "fine"}


# ---------------------------------------------------------------- independence


def test_the_reference_plant_shares_no_physics_code_with_the_project():
    tree = ast.parse((ROOT / "benchmarks" / "reference_plant.py").read_text(encoding="utf-8"))
    imported = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            imported.add(node.module)
            imported.update(f"{node.module}.{a.name}" for a in node.names)
        elif isinstance(node, ast.Import):
            imported.update(a.name for a in node.names)
    forbidden = ("sim.plant", "sim.flow", "sim.effects", "sim.friction_models", "sim.integrator", "sim.compiled",
                 "sim.extension", "hw")
    bad = sorted(m for m in imported if any(m == f or m.startswith(f + ".") for f in forbidden))
    assert not bad, bad
    assert "sim.cylinder" in imported  # it does read cylinder files


# ---------------------------------------------------------------- nominal physics


@pytest.mark.slow
def test_nominal_plant_agrees_with_the_projects_virtual_rig(cyl, nominal):
    """Same cylinder, seed and controller, noise off: the two plants close the same loop and
    give the same run to far below the sensor noise (5 um, 300 Pa)."""
    from combined_reality.simulation import simulate_run

    theirs = simulate_run(cyl, DURATION, SEED, noise=False)
    ours = nominal.run
    np.testing.assert_allclose(ours.t, theirs.t, rtol=0, atol=1e-12)
    assert np.all((ours.x > 0) & (ours.x < cyl.geometry.stroke))  # the end stops play no part
    assert np.ptp(ours.x) > 0.3 * cyl.geometry.stroke  # and the piston did move
    dx, dp1, dp2 = _rms(ours.x, theirs.x), _rms(ours.p1, theirs.p1), _rms(ours.p2, theirs.p2)
    print(f"\nreference vs project plant, {DURATION:g} s closed loop: RMS x {dx * 1e6:.4f} um, "
          f"p1 {dp1:.3f} Pa, p2 {dp2:.3f} Pa, u {_rms(ours.u, theirs.u):.2e}")
    assert dx < 0.05 * cyl.sensors.position_noise
    assert max(dp1, dp2) < 0.05 * cyl.sensors.pressure_noise


def test_each_run_starts_at_rest_in_force_balance(cyl):
    """The run starts at rest: chamber 2 at half the supply span, chamber 1 balancing it."""
    g, s = cyl.geometry, cyl.supply
    p2 = 0.5 * (s.pressure + s.atmosphere)
    p1 = (p2 * g.area_rod + s.atmosphere * (g.area_cap - g.area_rod)) / g.area_cap
    res = rp.simulate_detailed([rp.Case(cyl, 0.002, SEED, noise=False, commands=np.zeros(2))])[0]
    assert res.states["p2"][0] == pytest.approx(p2, abs=1e-3)
    assert res.states["p1"][0] == pytest.approx(p1, abs=1e-3)
    assert abs(res.states["x"][0] - 0.5 * g.stroke) < 1e-12


@pytest.mark.slow
def test_halving_the_step_changes_nothing_visible(cyl, nominal, effect_runs, plant_runs):
    """The nominal run and the forms that switch within a step (a dead time, a hard dead zone)
    or carry a state with a sign switch (Dahl), rerun with half the automatic step."""
    forms = HALVED
    coarse = [nominal] + [effect_runs[(cls, "strong")] for cls in forms]
    assert {r.substeps for r in coarse} == {nominal.substeps}
    fine = [plant_runs[("fine", cls)] for cls in (None,) + forms]
    assert {r.substeps for r in fine} == {2 * nominal.substeps}
    dx = [_rms(c.run.x, f.run.x) for c, f in zip(coarse, fine)]
    dp = [max(_rms(c.run.p1, f.run.p1), _rms(c.run.p2, f.run.p2)) for c, f in zip(coarse, fine)]
    print(f"\nRK4 {nominal.substeps} -> {2 * nominal.substeps} substeps per sample, {DURATION:g} s: RMS change of x "
          + ", ".join(f"{n} {d * 1e9:.3f} nm" for n, d in zip(["nominal"] + [c.FORM for c in forms], dx))
          + f"; of p at most {max(dp):.4f} Pa")
    assert max(dx) < 0.01 * cyl.sensors.position_noise
    assert max(dp) < 0.01 * cyl.sensors.pressure_noise


def test_closed_chambers_conserve_their_air(cyl):
    """After a pulse the valve closes (u = 0, or u inside a hard dead zone) while the piston is
    still moving: each chamber's air mass, p V / (R T) with the adiabatic T ~ p^((k-1)/k), that
    is p V^kappa, stays constant (also with stiction and a payload acting on the piston)."""
    n, pulse = 150, 10
    closed = np.r_[np.full(pulse, 0.5), np.zeros(n - pulse)]
    inside = np.r_[np.full(pulse, 0.5), np.full(n - pulse, 0.05)]
    cases = [rp.Case(cyl, n / 1000, SEED, noise=False, commands=closed),
             rp.Case(cyl, n / 1000, SEED, noise=False, commands=inside, effects=(rp.DeadzoneHard(d=0.1),)),
             rp.Case(cyl, n / 1000, SEED, noise=False, commands=closed,
                     effects=(rp.StictionExp(Fs_excess=20.0), rp.MassPayload(m_p=0.5)))]
    g = cyl.geometry
    for res in rp.simulate_detailed(cases):
        st = res.states
        first_closed = pulse  # row `pulse` is the first whose held command closes the valve
        x = st["x"][first_closed:]
        assert np.ptp(x) > 5e-3 and x.max() < g.stroke  # it moves several mm on its air springs meanwhile
        for p, V in ((st["p1"], g.dead_volume_cap + g.area_cap * st["x"]),
                     (st["p2"], g.dead_volume_rod + g.area_rod * (g.stroke - st["x"]))):
            inv = (p * V ** rp.KAPPA)[first_closed:]
            assert np.ptp(inv) / inv.mean() < 1e-9
            before = (p * V ** rp.KAPPA)[:first_closed]
            assert np.ptp(before) / before.mean() > 1e-2  # and it did change while the valve was open


def test_end_stops_hold_the_piston_within_force_over_stiffness(cyl):
    """Driven hard into each end, the piston stops beyond it by the stop's deflection under the
    full pressure force (k_end = 1e6 N/m) and never further than a little dynamic overshoot."""
    g, s = cyl.geometry, cyl.supply
    n = 600
    cmd = np.r_[np.full(n // 2, 0.8), np.full(n // 2, -0.8)]
    res = rp.simulate_detailed([rp.Case(cyl, n / 1000, SEED, noise=False, commands=cmd)])[0]
    x = res.states["x"]
    f_out = g.area_cap * (s.pressure - s.atmosphere)  # p1 = ps, p2 = pa
    f_in = g.area_rod * (s.pressure - s.atmosphere)  # p2 = ps, p1 = pa
    out, back = x[: n // 2], x[n // 2:]
    assert out.max() > g.stroke  # it did reach the end
    assert out.max() - g.stroke < 1.5 * f_out / rp.K_END
    assert out[-1] - g.stroke == pytest.approx(f_out / rp.K_END, rel=0.02)  # settled: F / k_end
    assert back.min() < 0
    assert -back.min() < 1.5 * f_in / rp.K_END
    assert -back[-1] == pytest.approx(f_in / rp.K_END, rel=0.02)
    print(f"\nend stops: overshoot {(out.max() - g.stroke) * 1e3:.3f} mm, settled {(out[-1] - g.stroke) * 1e3:.3f} mm "
          f"(F/k {f_out / rp.K_END * 1e3:.3f} mm); retracted {-back.min() * 1e3:.3f} / {-back[-1] * 1e3:.3f} mm")


# ---------------------------------------------------------------- effects


@pytest.mark.parametrize("cls", FORMS, ids=lambda c: f"{c.WORD}:{c.FORM}")
def test_every_form_vanishes_at_its_neutral_value(cls, nominal, effect_runs):
    """Even in a batch that holds every form, the neutral value gives the nominal run exactly."""
    res = effect_runs[(cls, "neutral")]
    run = res.run
    assert cls.neutral().is_neutral() and res.substeps == nominal.substeps and len(run.x) == len(nominal.run.x)
    np.testing.assert_array_equal(run.x, nominal.run.x)
    np.testing.assert_array_equal(run.p1, nominal.run.p1)
    np.testing.assert_array_equal(run.p2, nominal.run.p2)
    np.testing.assert_array_equal(run.u, nominal.run.u)


@pytest.mark.parametrize("cls", FORMS, ids=lambda c: f"{c.WORD}:{c.FORM}")
def test_every_form_is_visible_at_its_strong_value(cls, cyl, nominal, effect_runs):
    run = effect_runs[(cls, "strong")].run
    assert len(run.x) == len(nominal.run.x)
    dx = _rms(run.x, nominal.run.x)
    print(f"\n{cls.WORD}:{cls.FORM} strong {cls.typical(cyl, 1.0).values()}: RMS x change {dx * 1e6:.1f} um")
    assert dx > 10 * cyl.sensors.position_noise


def test_every_word_of_the_vocabulary_has_at_least_two_forms():
    for word in rp.WORDS:
        assert len(rp.forms_of(word)) >= 2, word
    assert {c.WORD for c in FORMS} == set(rp.WORDS)


@pytest.mark.parametrize("cls", FORMS, ids=lambda c: f"{c.WORD}:{c.FORM}")
def test_random_strengths_lie_in_the_documented_ranges(cls, cyl):
    rng = np.random.default_rng(7)
    ranges = cls.ranges(cyl)
    for _ in range(50):
        e = cls.random(rng, cyl)
        e.check(cyl)
        assert not e.is_neutral()
        for k, v in e.values().items():
            lo, hi = sorted(ranges[k])
            assert lo * (1 - 1e-12) <= abs(v) if cls.PARAMS[k].kind != "shape" else lo <= v, (k, v, lo)
            assert abs(v) <= hi * (1 + 1e-12), (k, v, hi)


def test_random_cases_on_small_and_large_cylinders_simulate_stably():
    """Every word at a random strength with random calibration and sensor departures, on the
    16 mm and the 50 mm cylinder: finite, and the piston stays in its stroke."""
    rng = np.random.default_rng(11)
    cases = []
    for name in ("cyl_b_16x40.toml", "ind4_norgren_50x400.toml"):
        c = load_cylinder(ROOT / "configs" / name)
        for word in rp.WORDS:
            cases.append(rp.Case(c, 0.1, int(rng.integers(1000)), effects=(rp.random_effect(rng, c, word),),
                                 calibration=rp.Calibration.random(rng, c),
                                 sensors=rp.SensorDepartures.random(rng)))
    # one batch at the finest step any of them asks for (the automatic choice would split them)
    for res in rp.simulate_detailed(cases, substeps=max(rp.substeps_for(c) for c in cases)):
        L = res.case.cyl.geometry.stroke
        assert all(np.all(np.isfinite(v)) for v in res.states.values())
        assert np.all((res.states["x"] > -1e-3) & (res.states["x"] < L + 1e-3))


def test_a_dead_time_of_whole_samples_equals_shifting_the_commands(cyl):
    rng = np.random.default_rng(3)
    cmd = np.repeat(rng.uniform(-0.3, 0.3, 30), 10)
    shifted = np.r_[np.zeros(3), cmd[:-3]]
    a, b = rp.simulate_detailed([
        rp.Case(cyl, 0.3, SEED, noise=False, commands=cmd, effects=(rp.DelayTransport(tau=0.003),)),
        rp.Case(cyl, 0.3, SEED, noise=False, commands=shifted)])
    np.testing.assert_array_equal(a.states["x"], b.states["x"])
    np.testing.assert_array_equal(a.states["p1"], b.states["p1"])
    assert np.ptp(a.states["x"]) > 1e-3


# ---------------------------------------------------------------- calibration departures and sensors


@pytest.mark.parametrize("name", sorted(rp.SHAPES))
def test_valve_shapes_are_monotone_from_zero_to_one_and_closed_in_the_overlap(name):
    rng = np.random.default_rng(1)
    a = np.linspace(0, 1, 2001)
    for _ in range(20):
        shape = rp.random_shape(rng) if name != "linear" else rp.Linear(overlap=0.05)
        if shape.SHAPE != name and name != "linear":
            continue
        f = shape(a)
        assert f[0] == 0.0 and f[-1] == pytest.approx(1.0, abs=1e-12)
        assert np.all(np.diff(f) >= -1e-15)
        assert np.all(f[a <= shape.overlap] == 0.0)
        assert rp.make_shape(shape.to_dict()) == shape
    if name != "linear":  # not the nominal straight line
        s = rp.make_shape({"shape": name, "overlap": 0.0})
        assert np.max(np.abs(s(a) - a)) > 0.03


def test_characteristics_act_per_direction_and_the_identity_is_nominal(cyl):
    cmd = np.r_[np.full(100, 0.4), np.full(100, -0.4)]
    cases = [rp.Case(cyl, 0.2, SEED, noise=False, commands=cmd),
             rp.Case(cyl, 0.2, SEED, noise=False, commands=cmd, calibration=rp.Calibration(
                 characteristic_pos=rp.PowerLaw(exponent=1.0), characteristic_neg=lambda a: a)),
             rp.Case(cyl, 0.2, SEED, noise=False, commands=cmd, calibration=rp.Calibration(
                 characteristic_pos=rp.PowerLaw(exponent=2.0))),
             rp.Case(cyl, 0.2, SEED, noise=False, commands=cmd, calibration=rp.Calibration(conductance_pos=0.0)),
             rp.Case(cyl, 0.2, SEED, noise=False, commands=cmd, calibration=rp.Calibration(conductance_neg=0.0))]
    nom, ident, power, no_pos, no_neg = [r.states for r in rp.simulate_detailed(cases)]
    np.testing.assert_allclose(ident["x"], nom["x"], rtol=0, atol=1e-12)
    np.testing.assert_allclose(ident["p1"], nom["p1"], rtol=1e-12)
    # a slower opening: the same direction, less travel in the first half, identical before the first command
    assert 0 < power["x"][99] - power["x"][0] < 0.8 * (nom["x"][99] - nom["x"][0])
    # u > 0 paths shut: a positive command moves nothing; u < 0 paths shut: only the second half stands still
    assert np.ptp(no_pos["x"][:100]) < 1e-9 and np.ptp(no_pos["x"][100:]) > 1e-3
    assert np.ptp(no_neg["x"][:100]) > 1e-3 and np.ptp(no_neg["x"][101:]) < 2e-3


def test_invalid_characteristics_are_refused(cyl):
    with pytest.raises(ValueError, match="monotone"):
        rp.simulate([rp.Case(cyl, 0.01, 1, calibration=rp.Calibration(characteristic_pos=lambda a: np.sin(3 * a)
                                                                       / np.sin(3.0)))])
    with pytest.raises(ValueError, match="f\\(1\\) = 1"):
        rp.simulate([rp.Case(cyl, 0.01, 1, calibration=rp.Calibration(characteristic_neg=lambda a: 0.5 * a))])
    with pytest.raises(TypeError, match="cannot be serialised"):
        rp.Case(cyl, 0.01, 1, calibration=rp.Calibration(characteristic_neg=lambda a: a)).to_json()


def test_every_calibration_departure_changes_the_run(cyl):
    cmd = np.repeat(np.random.default_rng(2).uniform(-0.5, 0.5, 20), 10)
    g, m = cyl.geometry, cyl.mechanics
    departures = {"conductance_pos": 0.7, "conductance_neg": 1.3, "critical_ratio": 0.45,
                  "characteristic_pos": rp.Smoothstep(weight=0.8), "characteristic_neg": rp.Progressive(overlap=0.05),
                  "dead_volume_cap": 2 * g.dead_volume_cap, "dead_volume_rod": 0.5 * g.dead_volume_rod,
                  "moving_mass": 1.5 * m.moving_mass, "offset_p1": 2000.0, "offset_p2": -1500.0,
                  "external_force": 20.0}
    cases = [rp.Case(cyl, 0.2, SEED, noise=False, commands=cmd)]
    cases += [rp.Case(cyl, 0.2, SEED, noise=False, commands=cmd, calibration=rp.Calibration(**{k: v}))
              for k, v in departures.items()]
    runs = rp.simulate(cases)
    for (k, _), run in zip(departures.items(), runs[1:]):
        change = max(_rms(run.x, runs[0].x) / cyl.sensors.position_noise,
                     _rms(run.p1, runs[0].p1) / cyl.sensors.pressure_noise,
                     _rms(run.p2, runs[0].p2) / cyl.sensors.pressure_noise)
        assert change > 3, k
    offset = runs[list(departures).index("offset_p1") + 1]
    np.testing.assert_allclose(offset.p1 - runs[0].p1, 2000.0, rtol=0, atol=1e-6)


def test_sensor_noise_gain_lag_and_offsets(cyl):
    cmd = np.r_[np.zeros(20), np.full(80, 0.5)]
    sen = rp.SensorDepartures(position_gain=0.02, pressure_lag=0.004, pressure_gain_p2=-0.01)
    cal = rp.Calibration(offset_p1=1000.0)
    quiet, noisy = rp.simulate_detailed([
        rp.Case(cyl, 0.1, 9, noise=False, commands=cmd, sensors=sen, calibration=cal),
        rp.Case(cyl, 0.1, 9, noise=True, commands=cmd, sensors=sen, calibration=cal)])
    st, run, pa = quiet.states, quiet.run, cyl.supply.atmosphere
    np.testing.assert_allclose(run.x, 1.02 * st["x"], rtol=1e-15)
    np.testing.assert_allclose(run.p1, st["p1_lag"] + 1000.0, rtol=1e-15)
    np.testing.assert_allclose(run.p2, pa + 0.99 * (st["p2_lag"] - pa), rtol=1e-15)
    # the lag state follows dp_lag/dt = (p - p_lag) / tau
    dlag = np.gradient(st["p1_lag"], 1e-3)[30:-1]
    np.testing.assert_allclose(dlag, ((st["p1"] - st["p1_lag"]) / 0.004)[30:-1], rtol=0.05,
                               atol=0.02 * np.abs(dlag).max())
    assert np.max(np.abs(st["p1"] - st["p1_lag"])) > 5e3  # a visible lag during the step
    # white noise drawn like the project's virtual rig: x, p1, p2 per sample from default_rng(seed)
    draws = np.random.default_rng(9).standard_normal((100, 3))
    sn = cyl.sensors
    np.testing.assert_allclose(noisy.run.x - run.x, sn.position_noise * draws[:, 0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(noisy.run.p1 - run.p1, sn.pressure_noise * draws[:, 1], rtol=0, atol=1e-8)
    np.testing.assert_allclose(noisy.run.p2 - run.p2, sn.pressure_noise * draws[:, 2], rtol=0, atol=1e-8)


# ---------------------------------------------------------------- the truth travels with the run


def test_runs_carry_the_cylinder_tag_and_the_truth(cyl):
    case = rp.Case(cyl, 0.05, 4, effects=(rp.LeakRod(q_ref=1e-4), rp.StictionExp.neutral()),
                   calibration=rp.Calibration(conductance_neg=0.8))
    run = rp.simulate([case])[0]
    assert run.comments[0] == cylinder_tag(cyl)
    assert recorded_cylinder(run) == cylinder_identity(cyl)
    truth = json.loads(next(c for c in run.comments if c.startswith("truth: "))[len("truth: "):])
    assert truth == json.loads(json.dumps(case.truth()))
    assert truth["verdict"] == "leakage"  # the neutral stiction is no part of the truth
    assert truth["calibration"]["conductance_neg"] == pytest.approx(0.8 * cyl.valve.sonic_conductance)


def test_cases_round_trip_through_json_and_rebuild_the_same_run(cyl):
    case = rp.Case(cyl, 0.05, 4, effects=(rp.DynamicsMaxwell(), rp.DelaySpool()),
                   calibration=rp.Calibration(characteristic_pos=rp.Logistic(overlap=0.02), moving_mass=1.0),
                   sensors=rp.SensorDepartures(pressure_lag=0.002))
    again = rp.Case.from_json(json.loads(json.dumps(case.to_json())))
    assert again.key() == case.key()
    assert again.truth() == case.truth()
    a, b = rp.simulate([case, again])
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.p2, b.p2)
    assert rp.Case(cyl, 0.05, 5).key() != rp.Case(cyl, 0.05, 4).key()
    # the same cylinder read from another checkout: the same runs
    elsewhere = replace(cyl, source=Path("/elsewhere") / cyl.source.name)
    assert rp.Case(elsewhere, 0.05, 4).key() == rp.Case(cyl, 0.05, 4).key()
    assert rp.Case(cyl.with_values({"Fc": 30.0}), 0.05, 4).key() != rp.Case(cyl, 0.05, 4).key()


def test_a_stretch_replayed_from_its_true_state_is_the_same_stretch(cyl):
    """A closed-loop run's stretch, simulated again open loop with its commands from the true
    state before it (an effect's own states too), is that stretch exactly: what the gauntlet's
    replays of VALID without the effect stand on. A state the batch lacks is refused."""
    case = rp.Case(cyl, 0.6, SEED, effects=(rp.DynamicsDahl(),), noise=False)
    run = rp.simulate_detailed([case])[0]
    a, b = 250, 520
    start = {name: v[a - 1] for name, v in run.states.items()}
    assert "friction_dynamics.dahl.s" in start
    part = rp.Case(cyl, (b - a) / case.rate, 0, effects=case.effects, noise=False, commands=run.run.u[a:b],
                   start=start, command_before=run.run.u[a - 1])
    again = rp.Case.from_json(json.loads(json.dumps(part.to_json())))
    assert again.key() == part.key() != rp.Case(cyl, part.duration, 0, effects=case.effects, noise=False,
                                                commands=run.run.u[a:b]).key()
    replay = rp.simulate_detailed([again])[0]
    for name in ("x", "v", "p1", "p2", "friction_dynamics.dahl.s"):
        np.testing.assert_array_equal(replay.states[name], run.states[name][a:b])
    with pytest.raises(ValueError, match="no state 'heat_transfer.wall.T1'"):
        rp.simulate([replace(part, start={**start, "heat_transfer.wall.T1": 300.0})])
    with pytest.raises(ValueError, match="command_before"):
        rp.Case(cyl, 1.0, 1, command_before=1.5)


def test_command_line_writes_a_run_the_project_reads(tmp_path, capsys):
    out, truth = tmp_path / "run.csv", tmp_path / "case.json"
    code = rp.main(["--config", str(DEFAULT_CYLINDER), "--duration", "0.05", "--seed", "2",
                    "--effect", "valve_delay:transport:tau=0.004", "--departure", "conductance_pos=0.9",
                    "--departure", "characteristic_neg=power,exponent=1.5,overlap=0.05",
                    "--sensor", "position_gain=0.01", "-o", str(out), "--truth", str(truth)])
    assert code == 0
    run = read_run(out)
    assert len(run.t) == 50 and run.t[0] == pytest.approx(1e-3)
    assert recorded_cylinder(run) == cylinder_identity(load_cylinder(DEFAULT_CYLINDER))
    case = rp.Case.from_json(json.loads(truth.read_text()))
    assert case.effects[0].tau == 0.004 and case.calibration.characteristic_neg.exponent == 1.5
    assert rp.main(["--config", str(DEFAULT_CYLINDER), "--effect", "valve_delay:nope", "-o", str(out)]) == 2
    assert "unknown effect form" in capsys.readouterr().err
    assert math.isclose(case.sensors.position_gain, 0.01)


def test_cases_refuse_what_makes_no_physical_sense(cyl):
    with pytest.raises(ValueError, match="one form per effect word"):
        rp.Case(cyl, 1.0, 1, effects=(rp.StictionExp(), rp.StictionRational()))
    with pytest.raises(ValueError, match="q_ref must be >= 0"):
        rp.Case(cyl, 1.0, 1, effects=(rp.LeakRod(q_ref=-1e-5),))
    with pytest.raises(ValueError, match="x_d must be > 0"):
        rp.Case(cyl, 1.0, 1, effects=(rp.DynamicsDahl(x_d=0.0),))
    with pytest.raises(ValueError, match="n must lie in"):
        rp.Case(cyl, 1.0, 1, effects=(rp.HeatPolytropic(n=1.6),))
    with pytest.raises(ValueError, match="commands"):
        rp.Case(cyl, 1.0, 1, commands=np.zeros(10))
    with pytest.raises(ValueError, match="non-negative integer"):
        rp.Case(cyl, 1.0, 1.5)
    assert rp.Case(cyl, 1.0, np.int64(3)).seed == 3


def test_cached_runs_are_simulated_once_and_read_back_as_simulated(cyl, tmp_path, monkeypatch):
    """The benchmarks keep the reference plant's runs (minutes per case) by the case's content
    hash: a second call reads them back, to the run file's precision, without simulating."""
    cases = [rp.Case(cyl, 0.1, SEED), rp.Case(cyl, 0.1, SEED + 1)]
    first = rp.cached_runs(cases, tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(f"{c.key()}{ext}" for c in cases
                                                                 for ext in (".csv", ".states.npz"))
    truth = rp.simulate_detailed(cases)

    def no_simulation(*_a, **_k):
        raise AssertionError("simulated again")

    monkeypatch.setattr(rp, "simulate_detailed", no_simulation)
    again = rp.cached_runs(cases, tmp_path)
    for a, b in zip(first, again):
        for ch in ("t", "u", "x", "p1", "p2"):
            np.testing.assert_allclose(getattr(b, ch), getattr(a, ch), rtol=1e-9, atol=1e-12)
    for res, states in zip(truth, rp.cached_states(cases, tmp_path)):  # the true states kept beside, exactly
        assert set(states) == set(res.states)
        for name, values in res.states.items():
            np.testing.assert_array_equal(states[name], values)
    assert first[0].x[-1] != first[1].x[-1] or first[0].p1[-1] != first[1].p1[-1]  # two cases, two runs
