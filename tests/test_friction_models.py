"""The friction-model family: one CasADi definition for the plant and the static map.

Each model is an Effect that replaces the nominal friction; in the plant at steady speed
its friction is its static curve; cv reproduces the nominal friction; the static curves
follow the published equations (independent numpy transcriptions here); LuGre's bristle
ODE settles on its static curve; Karnopp's smooth stand-in holds the piston below Fs.
"""
import dataclasses
import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.optimize import brentq

from sim.effects import EFFECTS, Effect, Stiction
from sim.extension import check_combination
from sim.friction_models import (CV, CVS, DIRECTIONS, FRICTION_MODELS, Belforte, CVLoad, CVPressure, CVSLoad,
                                 Efficiency, Karnopp, LuGre, Threlfall, make_friction_model, parse_friction_spec,
                                 without_nominal_friction)
from sim.plant import build_plant

# seed 004 (friction of industrial pneumatic actuators) Table 3, actuator 2 (Norgren 32 x 100), SI, magnitudes
TABLE3_N2 = dict(Fc_pos=16.87, Fc_neg=13.47, Fs_pos=22.0, Fs_neg=20.0, vs_pos=0.00342, vs_neg=0.00616,
                 B_pos=178.85, B_neg=165.59)

# asymmetric, non-default values for every model (both directions differ)
EXAMPLES = {
    "cv": CV(Fc_pos=16.9, Fc_neg=13.5, B_pos=179.0, B_neg=166.0),
    "karnopp": Karnopp(Fc_pos=16.9, Fc_neg=13.5, Fs_pos=22.0, Fs_neg=20.0, B_pos=179.0, B_neg=166.0,
                       dv_pos=0.005, dv_neg=0.008),
    "threlfall": Threlfall(Fc_pos=16.9, Fc_neg=13.5, ve_pos=0.004, ve_neg=0.007, B_pos=179.0, B_neg=166.0),
    "cvs": CVS(**TABLE3_N2, delta_pos=2.0, delta_neg=1.5),
    "lugre": LuGre(**TABLE3_N2, sigma0=2e5, sigma1=300.0),
    "cv_load": CVLoad(Fc_pos=10.0, Fc_neg=8.0, mu_pos=0.2, mu_neg=0.3, B_pos=150.0, B_neg=120.0,
                      mu_v_pos=0.5, mu_v_neg=0.8, Fn=40.0),
    "cvs_load": CVSLoad(Fc_pos=10.0, Fc_neg=8.0, mu_pos=0.2, mu_neg=0.3, Fs_pos=14.0, Fs_neg=12.0, mu_s_pos=0.3,
                        mu_s_neg=0.35, vs_pos=0.004, vs_neg=0.006, B_pos=150.0, B_neg=120.0, mu_v_pos=0.5,
                        mu_v_neg=0.8, Fn=40.0),
    "belforte": Belforte(FA_pos=8.0, FA_neg=6.0, K1_pos=3.0, K1_neg=2.0, alpha_pos=0.8, alpha_neg=1.2,
                         K2_pos=2e-5, K2_neg=1.5e-5, K3_pos=1e-5, K3_neg=2e-5),
    "cv_dp": CVPressure(Fc_pos=16.9, Fc_neg=13.5, kp_pos=2e-5, kp_neg=3e-5, Fv_pos=179.0, Fv_neg=166.0),
    "efficiency": Efficiency(kp_pos=4e-5, kp_neg=5e-5),
}


def _state(plant, cyl, model, p1, p2, v, x=0.05):
    """A plant state at speed v (LuGre's bristles at their steady deflection)."""
    return plant.initial_state(cyl, x, p1, p2, v)


# ------------------------------------------------------------------ the family as effects

def test_registry_is_separate_and_complete():
    assert set(FRICTION_MODELS) == set(EXAMPLES)
    assert not set(FRICTION_MODELS) & set(EFFECTS)  # not words of the diagnosis vocabulary
    assert all(not issubclass(c, tuple(FRICTION_MODELS.values())) for c in EFFECTS.values())


@pytest.mark.parametrize("name", sorted(FRICTION_MODELS))
def test_model_is_a_well_formed_effect(name):
    cls = FRICTION_MODELS[name]
    assert issubclass(cls, Effect) and cls.name == name and cls.subsystem == "mechanical"
    assert cls.description and cls.__doc__ and "F" in cls.__doc__
    assert [f.name for f in dataclasses.fields(cls)] == list(cls.PARAMS)  # fields are the parameters
    expected = [f"{b}_{s}" for b in cls.BASE for s in ("pos", "neg")] + list(cls.SHARED)
    assert list(cls.PARAMS) == expected
    for k, v in cls().as_dict().items():  # defaults inside the bounds
        info = cls.PARAMS[k]
        assert info.lower <= v <= info.upper, k
        assert info.lower < info.upper and info.unit
    with pytest.raises(dataclasses.FrozenInstanceError):
        cls().__setattr__(cls.BASE[0] + "_pos", 1.0)


@pytest.mark.parametrize("name", sorted(FRICTION_MODELS))
def test_plant_builds_with_a_friction_model(name, cyl_a):
    model = EXAMPLES[name]
    for drive in ("command", "pressure"):
        plant = build_plant(drive, [model])
        assert plant.param_names[-len(model.PARAMS):] == tuple(f"{name}.{n}" for n in model.PARAMS)
        assert plant.state_names[-len(model.STATES) or len(plant.state_names):] == \
            tuple(f"{name}.{s}" for s in model.STATES) or not model.STATES
        p = plant.parameter_vector(without_nominal_friction(cyl_a))
        state = plant.initial_state(cyl_a, 0.05, 4e5, 3e5, 0.0)
        u = [0.2] if drive == "command" else [4e5, 3e5]
        assert np.all(np.isfinite(np.asarray(plant.rhs(state, u, p))))


@pytest.mark.parametrize("name", sorted(FRICTION_MODELS))
def test_plant_friction_is_the_static_curve_at_steady_speed(name, cyl_a):
    """plant.friction (tanh direction, per-direction blend) = static curve (sign) once |v| >> v_smooth."""
    model = EXAMPLES[name]
    cyl = without_nominal_friction(cyl_a)
    pa = cyl.supply.atmosphere
    rng = np.random.default_rng(1)
    for drive in ("command", "pressure"):
        plant = build_plant(drive, [model])
        p = plant.parameter_vector(cyl)
        for _ in range(20):
            v = rng.choice([-1, 1]) * 10 ** rng.uniform(-1.7, -0.3)  # 20 mm/s .. 0.5 m/s
            p1, p2 = rng.uniform(1.5e5, 7e5), rng.uniform(1.5e5, 7e5)
            state = _state(plant, cyl, model, p1, p2, v)
            u = [0.3] if drive == "command" else [p1, p2]
            Ff = float(plant.friction(state, u, p))
            pc = (p2 if v > 0 else p1) - pa
            static = float(model.static_curve(v, dp=abs(p1 - p2), pc=pc))
            assert Ff == pytest.approx(static, rel=1e-9, abs=1e-9)
            assert np.sign(Ff) == np.sign(v)  # opposes motion


def test_cv_reproduces_the_nominal_friction_with_kp_zero(cyl_a):
    """CV(Fc, Fc, Fv, Fv) on a cylinder with Fc = Fv = kp = 0 is the nominal plant with kp = 0."""
    f = cyl_a.friction
    nominal_cyl = cyl_a.with_values({"kp": 0.0})
    model = CV(Fc_pos=f.Fc, Fc_neg=f.Fc, B_pos=f.Fv, B_neg=f.Fv)
    rng = np.random.default_rng(0)
    for drive in ("command", "pressure"):
        nominal, with_model = build_plant(drive), build_plant(drive, [model])
        pn, pm = nominal.parameter_vector(nominal_cyl), with_model.parameter_vector(without_nominal_friction(cyl_a))
        for _ in range(300):
            p1, p2 = rng.uniform(1e5, 7e5), rng.uniform(1e5, 7e5)
            v = rng.choice([-1, 1]) * 10 ** rng.uniform(-6, 0)  # through the smoothing band too
            base = [p1, p2, rng.uniform(0, 0.1), v] if drive == "command" else [rng.uniform(0, 0.1), v]
            u = [rng.uniform(-1, 1)] if drive == "command" else [p1, p2]
            np.testing.assert_allclose(float(with_model.friction(base, u, pm)), float(nominal.friction(base, u, pn)),
                                       rtol=1e-13, atol=1e-12)
            np.testing.assert_allclose(np.asarray(with_model.rhs(base, u, pm)), np.asarray(nominal.rhs(base, u, pn)),
                                       rtol=1e-12, atol=1e-9)


# ------------------------------------------------------------------ static curves against the papers

def _sgn_select(v, pos, neg):
    return np.where(v > 0, pos, neg)


def test_static_curves_follow_the_published_equations():
    """Independent numpy transcriptions of seed 000/003/004's equations, both directions."""
    v = np.concatenate([np.geomspace(1e-4, 0.5, 40), -np.geomspace(1e-4, 0.5, 40)])
    s, a = np.sign(v), np.abs(v)
    m = EXAMPLES["cvs"]  # seed 004 Eq. 3
    Fc, Fs = _sgn_select(v, m.Fc_pos, m.Fc_neg), _sgn_select(v, m.Fs_pos, m.Fs_neg)
    vs, B, d = _sgn_select(v, m.vs_pos, m.vs_neg), _sgn_select(v, m.B_pos, m.B_neg), _sgn_select(v, 2.0, 1.5)
    np.testing.assert_allclose(m.static_curve(v), s * (Fc + (Fs - Fc) * np.exp(-(a / vs) ** d)) + B * v, rtol=1e-12)
    # LuGre's static curve is the cvs curve with exponent 2
    lg = EXAMPLES["lugre"]
    np.testing.assert_allclose(lg.static_curve(v), CVS(**TABLE3_N2).static_curve(v), rtol=1e-13)
    # Karnopp: Fs inside the band, Coulomb-viscous outside (seed 003 Eq. 6 with B, seed 000 Fig. 2)
    k = EXAMPLES["karnopp"]
    dv = _sgn_select(v, k.dv_pos, k.dv_neg)
    Fs, Fc, B = _sgn_select(v, k.Fs_pos, k.Fs_neg), _sgn_select(v, k.Fc_pos, k.Fc_neg), _sgn_select(v, k.B_pos, k.B_neg)
    np.testing.assert_allclose(k.static_curve(v), np.where(a < dv, s * Fs, s * Fc + B * v), rtol=1e-12)
    # Threlfall (seed 003 Eq. 7): mu_d (1 - exp(-3|v|/ve)) inside ve, 0.95 mu_d outside, with Fc = 0.95 mu_d
    th = EXAMPLES["threlfall"]
    ve, mu_d = _sgn_select(v, th.ve_pos, th.ve_neg), _sgn_select(v, th.Fc_pos, th.Fc_neg) / 0.95
    eq7 = np.where(a <= ve, mu_d * (1 - np.exp(-3 * a / ve)), 0.95 * mu_d) * s
    B = _sgn_select(v, th.B_pos, th.B_neg)
    np.testing.assert_allclose(th.static_curve(v) - B * v, eq7, rtol=0, atol=2.2e-4 * mu_d.max())
    # Belforte (seed 004 Eq. 2) with dp = |p1 - p2| and the counter pressure pc
    b = EXAMPLES["belforte"]
    dp, pc = np.linspace(0.5e5, 5e5, v.size), np.linspace(0.1e5, 2e5, v.size)
    g = {n: _sgn_select(v, getattr(b, f"{n}_pos"), getattr(b, f"{n}_neg")) for n in b.BASE}
    expected = s * (g["FA"] + (1 + g["K1"] * a ** g["alpha"]) * (g["K2"] * dp + g["K3"] * pc))
    np.testing.assert_allclose(b.static_curve(v, dp=dp, pc=pc), expected, rtol=1e-12)
    # seed 003 Eqs. 5 and 8: load terms; with no load they are cv and cvs
    cl, csl = EXAMPLES["cv_load"], EXAMPLES["cvs_load"]
    L = np.linspace(0, 80, v.size)
    g = {n: _sgn_select(v, getattr(cl, f"{n}_pos"), getattr(cl, f"{n}_neg")) for n in cl.BASE}
    np.testing.assert_allclose(cl.static_curve(v, load=L), (g["Fc"] + g["mu"] * L) * s + (g["B"] + g["mu_v"] * L) * v,
                               rtol=1e-12)
    np.testing.assert_allclose(cl.static_curve(v), cl.static_curve(v, load=cl.Fn), rtol=0)  # load defaults to Fn
    no_load = CVSLoad(**{k: (0.0 if k.startswith("mu") else getattr(csl, k)) for k in csl.PARAMS})
    ref = CVS(**{k: getattr(csl, k) for k in CVS.PARAMS if hasattr(csl, k)})
    np.testing.assert_allclose(no_load.static_curve(v, load=50.0), ref.static_curve(v), rtol=1e-12)


def test_retraction_values_are_magnitudes():
    m = EXAMPLES["cvs"]
    assert float(m.static_curve(-1e-6)) == pytest.approx(-m.Fs_neg, rel=1e-4)
    assert float(m.static_curve(1e-6)) == pytest.approx(m.Fs_pos, rel=1e-4)
    assert float(m.static_curve(-0.5)) == pytest.approx(-(m.Fc_neg + m.B_neg * 0.5), rel=1e-12)
    assert set(DIRECTIONS) == {"extension", "retraction"}


@pytest.mark.parametrize("name", sorted(FRICTION_MODELS))
def test_static_jacobian_matches_finite_differences(name):
    model = EXAMPLES[name]
    cls = type(model)
    v = np.array([-0.3, -0.02, -0.004, 0.003, 0.015, 0.25])
    kw = {"dp": np.linspace(1e5, 4e5, 6), "pc": np.linspace(0.2e5, 1e5, 6), "load": np.linspace(10, 60, 6)}
    p = np.array(model.values())
    J = cls.static_jacobian(v, p, **kw)
    assert J.shape == (6, len(p))
    for j in range(len(p)):
        h = 1e-6 * max(abs(p[j]), 1e-6)
        up, dn = p.copy(), p.copy()
        up[j] += h
        dn[j] -= h
        fd = (cls.static_force(v, up, **kw) - cls.static_force(v, dn, **kw)) / (2 * h)
        np.testing.assert_allclose(J[:, j], fd, rtol=1e-5, atol=1e-7 * max(1.0, np.abs(fd).max()))


def test_static_curve_shapes_and_missing_conditions():
    m = EXAMPLES["cvs"]
    assert np.shape(m.static_curve(0.01)) == ()
    assert m.static_curve(np.zeros((2, 3)) + 0.01).shape == (2, 3)
    assert m.static_curve(np.empty(0)).shape == (0,)
    with pytest.raises(ValueError, match="dp"):
        EXAMPLES["belforte"].static_curve(0.1)
    with pytest.raises(ValueError, match="parameter values"):
        CVS.static_force([0.1], [1.0, 2.0])


# ------------------------------------------------------------------ dynamics in the plant

def test_lugre_bristles_settle_on_the_static_curve(cyl_a):
    """At constant speed the bristle ODE of the plant converges to the Stribeck curve."""
    model = EXAMPLES["lugre"]
    cyl = without_nominal_friction(cyl_a)
    plant = build_plant("pressure", [model])
    p = plant.parameter_vector(cyl)
    iz = plant.state_names.index("lugre.zeta")
    for v in (0.01, -0.015, 0.05, -0.2):  # |v| >> v_smooth: the per-direction blend is exact
        def rhs(_, z):
            return [float(plant.rhs([0.05, v, z[0]], [4e5, 3e5], p)[iz])]

        sol = solve_ivp(rhs, (0, 0.5), [0.0], method="LSODA", rtol=1e-10, atol=1e-12)
        z_end = sol.y[0, -1]
        F = float(plant.friction([0.05, v, z_end], [4e5, 3e5], p))
        assert F == pytest.approx(float(model.static_curve(v)), rel=1e-6)


def test_karnopp_stand_in_holds_below_the_static_force(cyl_a):
    """The smooth Karnopp holds an applied force below Fs at a creep speed of order v_smooth,
    and an applied force above it slides on the Coulomb-viscous branch beyond dv."""
    model = EXAMPLES["karnopp"]
    cyl = without_nominal_friction(cyl_a)
    plant = build_plant("pressure", [model])
    p = plant.parameter_vector(cyl)
    vsm = cyl.friction.v_smooth

    def friction(v):
        return float(plant.friction([0.05, v], [4e5, 3e5], p))

    held = brentq(lambda v: friction(v) - 0.9 * model.Fs_pos, 0.0, model.dv_pos)
    assert held < 2 * vsm  # stuck within the smoothing band
    applied = model.Fc_pos + model.B_pos * 0.05  # steady sliding at 50 mm/s
    assert applied > model.Fs_pos
    sliding = brentq(lambda v: friction(v) - applied, model.dv_pos + 5 * vsm, 1.0)
    assert sliding == pytest.approx(0.05, rel=1e-9)


# ------------------------------------------------------------------ helpers

def test_make_and_parse_friction_models():
    m = parse_friction_spec("cvs:Fc_pos=16.87,Fc_neg=13.47,vs_pos=0.00342")
    assert isinstance(m, CVS) and m.Fc_neg == 13.47 and m.vs_pos == 0.00342 and m.Fs_pos == CVS().Fs_pos
    assert make_friction_model("karnopp", {"dv_neg": 0.01}).dv_neg == 0.01
    with pytest.raises(ValueError, match="unknown friction model 'stribeck'"):
        make_friction_model("stribeck")
    with pytest.raises(ValueError, match="no parameter Fc"):
        make_friction_model("cvs", {"Fc": 3.0})
    with pytest.raises(ValueError, match="outside"):
        make_friction_model("cvs", {"Fc_pos": -1.0})
    with pytest.raises(ValueError, match="not a number"):
        parse_friction_spec("cv:Fc_pos=abc")


def test_combinations_that_would_silently_override_are_refused():
    check_combination([CVS()])
    with pytest.raises(ValueError, match="only one friction model"):
        check_combination([CVS(), CV()])
    with pytest.raises(ValueError, match="stiction"):
        check_combination([Stiction(), CVS()])


def test_without_nominal_friction(cyl_a):
    c = without_nominal_friction(cyl_a)
    assert (c.friction.Fc, c.friction.Fv, c.friction.kp) == (0.0, 0.0, 0.0)
    assert c.friction.v_smooth == cyl_a.friction.v_smooth
    assert math.isclose(c.geometry.bore, cyl_a.geometry.bore)
