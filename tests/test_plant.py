"""The CasADi plant against docs/model.md: an independent transcription, physics invariants."""
import math

import numpy as np
import pytest

from model_reference import ReferenceModel
from sim.compiled import shooting_functions
from sim.effects import Leakage, Stiction, ValveDelay, make_effect, parse_effect_spec
from sim.flow import flow_function, mass_flow
from sim.plant import build_plant, plant_for


def test_rhs_matches_independent_transcription(cyl_a):
    plant = build_plant("command")
    p = plant.parameter_vector(cyl_a)
    ref = ReferenceModel(cyl_a)
    f = cyl_a.friction
    rng = np.random.default_rng(0)
    L = cyl_a.geometry.stroke
    for _ in range(300):
        state = [rng.uniform(1.0e5, 7.0e5), rng.uniform(1.0e5, 7.0e5), rng.uniform(0, L), rng.normal(0, 0.3)]
        u = rng.uniform(-1.3, 1.3)
        ours = np.asarray(plant.rhs(state, u, p)).ravel()
        expected = ref.rhs(0.0, state, u, f.Fc, f.Fv, f.kp)
        np.testing.assert_allclose(ours, expected, rtol=1e-10, atol=1e-9)


def test_linear_valve_plant_is_the_special_case_of_the_curve(cyl_a):
    """A cylinder without a flow characteristic gets the cheaper linear valve law, with the
    same right-hand side; a characteristic (in the file or to be estimated) brings the curve,
    and a linear plant refuses a cylinder that has one rather than simulate it wrongly."""
    linear, curve = plant_for(cyl_a), build_plant("command")
    assert not linear.valve_curve and curve.valve_curve
    assert linear.structure_key != curve.structure_key
    assert plant_for(cyl_a, "command", (), ("Fc", "overlap_extend")).valve_curve
    p = linear.parameter_vector(cyl_a)
    rng = np.random.default_rng(1)
    for _ in range(200):
        state = [rng.uniform(1.0e5, 7.0e5), rng.uniform(1.0e5, 7.0e5), rng.uniform(0, 0.1), rng.normal(0, 0.3)]
        u = rng.uniform(-1.2, 1.2)
        np.testing.assert_allclose(np.asarray(linear.rhs(state, u, p)).ravel(),
                                   np.asarray(curve.rhs(state, u, p)).ravel(), rtol=1e-12, atol=1e-9)
    overlapped = cyl_a.with_values({"overlap_extend": 0.05})
    assert plant_for(overlapped).valve_curve
    with pytest.raises(ValueError, match="flow characteristic"):
        linear.parameter_vector(overlapped)


def test_flow_function_shape():
    b = 0.3
    vals = {r: float(flow_function(r, b)) for r in (0.0, 0.3, 0.5, 0.995, 1.0)}
    assert vals[0.0] == 1.0 and vals[0.3] == 1.0  # choked
    assert vals[1.0] == 0.0  # no pressure drop, no flow
    # continuous where the laminar end starts
    assert abs(float(flow_function(0.995 - 1e-12, b)) - float(flow_function(0.995 + 1e-12, b))) < 1e-9


def test_mass_flow_matches_independent_transcription(cyl_a):
    """Every regime (choked, subsonic, laminar end, no drop) in both directions."""
    ref = ReferenceModel(cyl_a)
    C, b, T = 1e-8, cyl_a.valve.critical_ratio, cyl_a.supply.temperature
    for p_low, p_high in ((1.0e5, 7.0e5), (3.0e5, 5.0e5), (4.99e5, 5.0e5), (5.0e5, 5.0e5)):
        for p_from, p_to in ((p_high, p_low), (p_low, p_high)):
            ours = float(mass_flow(C, p_from, p_to, b, T))
            assert ours == pytest.approx(ref.mdot(C, p_from, p_to), rel=1e-12, abs=1e-20), (p_from, p_to)
            assert ours * (p_from - p_to) >= 0  # from high to low pressure


def test_closed_valve_keeps_p_V_kappa_constant(cyl_a):
    """Valve centred: no air enters or leaves, so each chamber follows p V^kappa = const."""
    plant = build_plant("command")
    sf = shooting_functions(plant, 1)
    p = np.array(plant.parameter_vector(cyl_a))
    g = cyl_a.geometry
    A1, A2 = g.area_cap, g.area_rod
    s = np.array([5.5e5, 2.0e5, 0.03, 0.0])  # unbalanced: the piston oscillates on the air springs
    inv = []
    for _ in range(2000):
        p1, p2, x, _v = s
        V1, V2 = g.dead_volume_cap + A1 * x, g.dead_volume_rod + A2 * (g.stroke - x)
        inv.append((p1 * V1 ** 1.4, p2 * V2 ** 1.4))
        s = np.asarray(sf.step(s, 0.0, 0.0, p, 1e-3)).ravel()
    inv = np.array(inv)
    assert np.ptp(inv[:, 0]) / inv[0, 0] < 1e-5  # about 5 Pa over 2 s: integration error, no leak
    assert np.ptp(inv[:, 1]) / inv[0, 1] < 1e-5
    assert abs(s[2] - 0.03) > 1e-3  # it did move


def test_friction_opposes_motion(cyl_a):
    plant = build_plant("command")
    p = plant.parameter_vector(cyl_a)
    for v in (-0.5, -1e-3, 1e-3, 0.5):
        Ff = float(plant.friction([4e5, 3e5, 0.05, v], 0.0, p))
        assert np.sign(Ff) == np.sign(v)


def test_effects_extend_without_forking(cyl_a):
    base = build_plant("command")
    full = build_plant("command", [Stiction(), ValveDelay(), Leakage()])
    assert full.state_names == base.state_names + ("valve_delay.u_eff",)
    assert full.param_names[: len(base.param_names)] == base.param_names
    assert "leakage.conductance" in full.param_names
    # the pressure drive takes only the mechanical effects
    pd = build_plant("pressure", [Stiction(), ValveDelay()])
    assert pd.state_names == ("x", "v") and pd.input_names == ("p1", "p2")
    # structure keys differ by structure, not by parameter values
    assert build_plant("command", [Stiction(5.0)]).structure_key == build_plant("command", [Stiction(9.0)]).structure_key
    assert full.structure_key != base.structure_key


def test_one_symbolic_build_serves_every_value_of_a_structure(cyl_a):
    """Effect values are parameters: plants of one structure share their equations, and each
    carries (and feeds the parameter vector from) its own effects' values."""
    weak, strong = build_plant("command", [Stiction(5.0)]), build_plant("command", [Stiction(9.0)])
    assert weak.rhs is strong.rhs and weak.effects != strong.effects
    i = weak.param_names.index("stiction.Fs_excess")
    assert weak.parameter_vector(cyl_a)[i] == 5.0 and strong.parameter_vector(cyl_a)[i] == 9.0
    # another structure (drive, effects, their order, the valve law) builds its own
    assert build_plant("pressure", [Stiction(5.0)]).rhs is not weak.rhs
    assert build_plant("command", [Stiction(5.0), Leakage()]).rhs is not \
        build_plant("command", [Leakage(), Stiction(5.0)]).rhs
    assert build_plant("command", [Stiction(5.0)], valve_curve=False).rhs is not weak.rhs


def test_stiction_adds_breakaway_force(cyl_a):
    plant = build_plant("command", [Stiction(Fs_excess=8.0, v_stribeck=0.01)])
    base = build_plant("command")
    pe, pb = plant.parameter_vector(cyl_a), base.parameter_vector(cyl_a)
    st = [4e5, 4e5, 0.05, 0.005]
    extra = float(plant.friction(st, 0.0, pe)) - float(base.friction(st, 0.0, pb))
    assert extra == pytest.approx(8.0 * math.exp(-0.25) * math.tanh(5.0), rel=1e-9)


def test_effect_spec_parsing():
    e = parse_effect_spec("valve_delay:tau=0.01")
    assert isinstance(e, ValveDelay) and e.tau == 0.01
    with pytest.raises(ValueError, match="unknown effect 'nope'"):
        parse_effect_spec("nope")
    with pytest.raises(ValueError, match="no parameter"):
        make_effect("stiction", {"bogus": 1.0})
    with pytest.raises(ValueError, match="outside"):
        make_effect("valve_delay", {"tau": -1.0})
