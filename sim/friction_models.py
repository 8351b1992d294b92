"""Friction models of the static-map literature, as replacements of the nominal friction.

One symbolic definition per model serves the simulation and identification (as an
`Effect` in the plant) and the static friction-velocity map (a numeric function built
from the same CasADi expression). Models (docs/friction.md) from the seed papers: seed 000
(Trentini et al., Karnopp friction identified by least squares in a servopneumatic axis),
seed 003 (Romeo et al., static friction models with load terms in a pneumatic gripper) and
seed 004 (friction of industrial pneumatic actuators: friction-velocity maps, Table 3):

    cv         Coulomb-viscous                         F = Fc s + B v
    karnopp    Karnopp stick band                      F = Fs s (|v| < dv),  Fc s + B v (|v| >= dv)
    threlfall  exponential approach to Coulomb         F = Fc min((1 - exp(-3|v|/ve)) / 0.95, 1) s + B v
    cvs        static-Coulomb-Stribeck-viscous         F = (Fc + (Fs - Fc) exp(-(|v|/vs)^delta)) s + B v
    lugre      LuGre (bristle state z)                 static: cvs with delta = 2
    cv_load    cv with normal-load terms (seed 003)    F = (Fc + mu Fn) s + (B + mu_v Fn) v
    cvs_load   cvs with normal-load terms (seed 003)   F = ((Fc + mu Fn)(1 - e) + (Fs + mu_s Fn) e) s + (B + mu_v Fn) v
    belforte   pressure-dependent (seed 004 Eq. 2)     F = (FA + (1 + K1 |v|^alpha)(K2 |p1 - p2| + K3 pc)) s
    cv_dp      the nominal law per direction           F = (Fc + kp |p1 - p2|) s + Fv v
    efficiency friction proportional to the pressure   F = kp |p1 - p2| s      (seed 004 Eq. 1)

Conventions:
- Every parameter exists once per direction: suffix `_pos` for extension (v > 0) and
  `_neg` for retraction (v < 0). Forces and velocities are magnitudes (>= 0) in both
  directions: seed 004's Table 3 prints the retraction values negative, here
  Fc_neg = 13.47 N means F = -13.47 N while retracting. Direction-independent parameters
  (LuGre's sigma0, sigma1; the load Fn) have no suffix.
- s is a direction function. In the plant s = tanh(v / v_smooth), like the nominal
  friction, so the right-hand side stays smooth; in the static map s = sign(v) (map points
  never have v = 0). A per-direction parameter P enters as
  P(s) = P_pos (1 + s)/2 + P_neg (1 - s)/2: exactly P_pos or P_neg when s = sign(v),
  a smooth blend over |v| ~ v_smooth in the plant.
- A friction model REPLACES the nominal friction: its `on_friction` hook overwrites
  sig.Ff, so the nominal Fc, Fv, kp no longer act (set them to 0, `without_nominal_friction`,
  and do not estimate them). Do not combine a friction model with another one or with the
  friction effects of sim.effects (`sim.extension.check_combination` says so).
- pc, the counter pressure, is the gauge pressure of the chamber the piston pushes
  against: p2 - pa while extending, p1 - pa while retracting (Belforte's P2).
- Fn, the normal load of seed 003, has no signal in the plant: there it is a constant
  parameter of the model; the static curve takes it per point (`load`).

The registry FRICTION_MODELS is kept apart from sim.effects.EFFECTS: friction models are
alternatives to the nominal friction, not words of the diagnosis vocabulary.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, fields
from typing import Any, Callable, ClassVar, Mapping, Sequence

import casadi as ca
import numpy as np

from .effects import EFFECTS, FRICTION_CHANGES, make_friction_change, parse_effect_spec
from .extension import Effect, ParamInfo, make_from, parse_spec

__all__ = ["FrictionModel", "CV", "Karnopp", "Threlfall", "CVS", "LuGre", "CVLoad", "CVSLoad", "Belforte",
           "CVPressure", "Efficiency", "FRICTION_MODELS", "DIRECTIONS", "make_friction_model", "parse_friction_spec",
           "parameter_unit", "without_nominal_friction"]

# direction name -> parameter suffix, sign of v
DIRECTIONS: dict[str, tuple[str, float]] = {"extension": ("pos", 1.0), "retraction": ("neg", -1.0)}

# Threlfall: 1 - exp(-3) = 0.9502, the plateau factor of seed 003 Eq. (7)
_THRELFALL_PLATEAU = 0.95
# below any physical speed: keeps |v|^x and its derivatives finite at v = 0 (x may be symbolic)
_TINY = 1e-150


def _directional(**base: ParamInfo) -> dict[str, ParamInfo]:
    """Each base parameter once per direction: NAME_pos (extension), NAME_neg (retraction)."""
    out = {}
    for name, info in base.items():
        for suffix, word in (("pos", "extension, v > 0"), ("neg", "retraction, v < 0")):
            out[f"{name}_{suffix}"] = ParamInfo(info.unit, info.lower, info.upper, f"{info.description} ({word})")
    return out


_FC = ParamInfo("N", 0.0, 1e4, "Coulomb friction (magnitude)")
_FS = ParamInfo("N", 0.0, 1e4, "static (breakaway) friction (magnitude)")
_B = ParamInfo("N s/m", 0.0, 1e5, "viscous coefficient")
_VS = ParamInfo("m/s", 1e-5, 1.0, "Stribeck velocity")
_DELTA = ParamInfo("1", 0.2, 5.0, "Stribeck exponent")
_FN = ParamInfo("N", 0.0, 1e6, "normal load on the seals and guides (constant in the plant)")


def _per(q: Mapping[str, Any], base: str, s):
    """A per-direction parameter at direction s (exact for s = +-1, blended in between)."""
    return q[f"{base}_pos"] * (1 + s) / 2 + q[f"{base}_neg"] * (1 - s) / 2


def _stribeck(v, vs, delta):
    """exp(-(|v| / vs)^delta), finite with finite derivatives at v = 0."""
    return ca.exp(-(ca.fmax(ca.fabs(v) / vs, _TINY) ** delta))


@dataclass(frozen=True)
class FrictionModel(Effect):
    """Base of the friction models: a static curve `curve` that replaces the plant's friction.

    Subclasses define BASE (per-direction parameter names, in PARAMS order), PARAMS, the
    fields (the parameter values), `curve`, and optionally CONDITIONS (operating inputs of
    the curve: "dp" = |p1 - p2| [Pa], "pc" = counter pressure [Pa gauge], "load" = normal
    load [N]), SHARED (direction-independent parameters), DYNAMIC (parameters the static
    curve does not contain) and SCALES (velocity scales of the curve: the identifiability
    check of a map compares them with the tested speeds).
    """

    subsystem: ClassVar[str] = "mechanical"
    FRICTION: ClassVar[str | None] = "replaces"
    # a friction model replaces the nominal friction: no value makes it vanish
    NEUTRAL: ClassVar[dict[str, float]] = {}
    BASE: ClassVar[tuple[str, ...]]
    SHARED: ClassVar[tuple[str, ...]] = ()
    CONDITIONS: ClassVar[tuple[str, ...]] = ()
    DYNAMIC: ClassVar[frozenset[str]] = frozenset()
    SCALES: ClassVar[frozenset[str]] = frozenset()

    # ------------------------------------------------------------ the one definition
    @classmethod
    def curve(cls, v, q: Mapping[str, Any], cond: Mapping[str, Any], direction: Callable[[Any], Any]):
        """The friction force (opposing motion) at velocity v: symbolic, with the direction
        function `direction` (tanh(./v_smooth) in the plant, sign in the static map)."""
        raise NotImplementedError

    # ------------------------------------------------------------ plant
    @staticmethod
    def _smooth_direction(sig) -> Callable[[Any], Any]:
        vsm = sig.par["v_smooth"]
        return lambda z: ca.tanh(z / vsm)

    @classmethod
    def _plant_conditions(cls, sig, q, direction) -> dict[str, Any]:
        s = direction(sig.v)
        return {"dp": ca.fabs(sig.p1 - sig.p2),
                "pc": (1 + s) / 2 * (sig.p2 - sig.pa) + (1 - s) / 2 * (sig.p1 - sig.pa),
                "load": q["Fn"] if "Fn" in q else 0.0}

    def on_friction(self, sig, q, s) -> None:
        direction = self._smooth_direction(sig)
        sig.Ff = self.curve(sig.v, q, self._plant_conditions(sig, q, direction), direction)

    # ------------------------------------------------------------ static map (numeric)
    @classmethod
    def static_force(cls, v, params: Sequence[float] | np.ndarray, dp=None, pc=None, load=None) -> np.ndarray:
        """The static curve F(v) (sign(v) as direction) for a full parameter vector in PARAMS
        order; v an array (or scalar), the conditions scalars or arrays like v."""
        f, _ = _static_functions(cls)
        return _evaluate(cls, f, v, params, dp, pc, load, 1)

    @classmethod
    def static_jacobian(cls, v, params: Sequence[float] | np.ndarray, dp=None, pc=None, load=None) -> np.ndarray:
        """dF/dparams of the static curve, shape (len(v), len(PARAMS))."""
        _, j = _static_functions(cls)
        return _evaluate(cls, j, v, params, dp, pc, load, len(cls.PARAMS))

    def static_curve(self, v, dp=None, pc=None, load=None) -> np.ndarray:
        """This model's static friction-velocity curve (its own parameter values); `load`
        defaults to the model's Fn."""
        if load is None and "Fn" in self.PARAMS:
            load = self.Fn  # type: ignore[attr-defined]
        return self.static_force(v, self.values(), dp, pc, load)

    @classmethod
    def param_index(cls, name: str) -> int:
        return list(cls.PARAMS).index(name)

    @classmethod
    def defaults(cls) -> dict[str, float]:
        return {f.name: float(f.default) for f in fields(cls)}  # type: ignore[arg-type]


def _static_functions_uncached(cls: type[FrictionModel]) -> tuple[ca.Function, ca.Function]:
    v = ca.SX.sym("v")
    P = ca.SX.sym("p", len(cls.PARAMS))
    dp, pc, load = ca.SX.sym("dp"), ca.SX.sym("pc"), ca.SX.sym("load")
    q = dict(zip(cls.PARAMS, ca.vertsplit(P)))
    F = cls.curve(v, q, {"dp": dp, "pc": pc, "load": load}, ca.sign)
    names = ["v", "p", "dp", "pc", "load"]
    f = ca.Function(f"{cls.name}_static", [v, P, dp, pc, load], [F], names, ["F"])
    j = ca.Function(f"{cls.name}_static_jac", [v, P, dp, pc, load], [ca.jacobian(F, P)], names, ["dF_dp"])
    return f, j


# a memo of pure functions of the (immutable) class, not state
_static_functions = functools.lru_cache(maxsize=None)(_static_functions_uncached)


def _evaluate(cls, fn: ca.Function, v, params, dp, pc, load, width: int) -> np.ndarray:
    shape = np.shape(v)
    vv = np.asarray(v, float).ravel()
    p = np.asarray(params, float).ravel()
    if p.size != len(cls.PARAMS):
        raise ValueError(f"{cls.name}: {p.size} parameter values given, the model has {len(cls.PARAMS)} "
                         f"({', '.join(cls.PARAMS)}).")
    cond = {}
    for key, val, what in (("dp", dp, "dp = |p1 - p2| in Pa"), ("pc", pc, "pc = counter pressure in Pa gauge"),
                           ("load", load, "load = normal force in N")):
        if val is None:
            if key in cls.CONDITIONS:
                raise ValueError(f"friction model {cls.name} needs {what} for its static curve.")
            val = 0.0
        cond[key] = np.broadcast_to(np.asarray(val, float), vv.shape).ravel()
    if vv.size == 0:
        return np.empty(shape + ((width,) if width > 1 else ()))
    out = np.asarray(fn(vv[None, :], p, cond["dp"][None, :], cond["pc"][None, :], cond["load"][None, :]))
    if width == 1:
        return out.reshape(shape)
    return out.reshape(vv.size, width).reshape(shape + (width,))


# ================================================================ the models

@dataclass(frozen=True)
class CV(FrictionModel):
    """Coulomb-viscous (seed 003 Eq. 5 without load terms; seed 000 Eqs. 4-5).

        F = Fc(s) s + B(s) v

    With Fc_pos = Fc_neg = Fc and B_pos = B_neg = Fv it is the nominal plant's friction
    with kp = 0, to rounding.
    """

    name: ClassVar[str] = "cv"
    description: ClassVar[str] = "Coulomb-viscous friction per direction"
    BASE: ClassVar[tuple[str, ...]] = ("Fc", "B")
    PARAMS: ClassVar[dict[str, ParamInfo]] = _directional(Fc=_FC, B=_B)
    Fc_pos: float = 20.0
    Fc_neg: float = 20.0
    B_pos: float = 50.0
    B_neg: float = 50.0

    @classmethod
    def curve(cls, v, q, cond, direction):
        s = direction(v)
        return _per(q, "Fc", s) * s + _per(q, "B", s) * v


@dataclass(frozen=True)
class Karnopp(FrictionModel):
    """Karnopp's stick band (seed 000 Fig. 2, seed 003 Eq. 6), with a viscous term.

    Static curve (the map):

        F = Fs(s) s                     |v| <  dv     (stuck: the static force holds)
        F = Fc(s) s + B(s) v            |v| >= dv     (sliding)

    written as F = Fs s (1 - H) + (Fc s + B v) H with H = (1 + s(|v| - dv)) / 2, s = sign.
    The true Karnopp model switches on the force balance (stuck while the applied force
    stays below Fs, friction then equals the applied force), which an ODE right-hand side
    cannot do without events. In the plant the same expression with s = tanh(./v_smooth)
    is its smooth stand-in: below dv the friction is Fs tanh(v / v_smooth), a steep damper
    that holds the piston (|v| of order v_smooth) as long as the applied force stays below
    Fs, and the step to the sliding branch at dv is smoothed over about v_smooth. Keep
    v_smooth well below dv. B = 0 is seed 003's form, Fs = Fc without band seed 000's.
    """

    name: ClassVar[str] = "karnopp"
    description: ClassVar[str] = "Karnopp stick band: static friction below dv, Coulomb-viscous above"
    BASE: ClassVar[tuple[str, ...]] = ("Fc", "Fs", "B", "dv")
    PARAMS: ClassVar[dict[str, ParamInfo]] = _directional(
        Fc=_FC, Fs=_FS, B=_B, dv=ParamInfo("m/s", 1e-5, 0.5, "stick band half-width (minimum sliding speed)"))
    SCALES: ClassVar[frozenset[str]] = frozenset({"dv"})
    Fc_pos: float = 20.0
    Fc_neg: float = 20.0
    Fs_pos: float = 25.0
    Fs_neg: float = 25.0
    B_pos: float = 50.0
    B_neg: float = 50.0
    dv_pos: float = 0.005
    dv_neg: float = 0.005

    @classmethod
    def curve(cls, v, q, cond, direction):
        s = direction(v)
        H = (1 + direction(ca.fabs(v) - _per(q, "dv", s))) / 2
        return _per(q, "Fs", s) * s * (1 - H) + (_per(q, "Fc", s) * s + _per(q, "B", s) * v) * H


@dataclass(frozen=True)
class Threlfall(FrictionModel):
    """Threlfall's exponential approach to Coulomb friction (seed 003 Eq. 7), with a
    viscous term:

        F = Fc(s) min((1 - exp(-3 |v| / ve(s))) / 0.95, 1) s + B(s) v

    Fc is the sliding (plateau) level, seed 003's 0.95 mu_d: the exponential reaches 0.95
    at |v| = ve ln(20)/3 = 0.9986 ve, so this continuous form equals Eq. (7) to 0.02 % of Fc.
    B = 0 is seed 003's form (added because cylinders are strongly viscous, seed 004).
    """

    name: ClassVar[str] = "threlfall"
    description: ClassVar[str] = "Threlfall: friction rises exponentially to the Coulomb level within ve"
    BASE: ClassVar[tuple[str, ...]] = ("Fc", "ve", "B")
    PARAMS: ClassVar[dict[str, ParamInfo]] = _directional(
        Fc=_FC, ve=ParamInfo("m/s", 1e-5, 1.0, "velocity at which Coulomb friction is reached"), B=_B)
    SCALES: ClassVar[frozenset[str]] = frozenset({"ve"})
    Fc_pos: float = 20.0
    Fc_neg: float = 20.0
    ve_pos: float = 0.005
    ve_neg: float = 0.005
    B_pos: float = 50.0
    B_neg: float = 50.0

    @classmethod
    def curve(cls, v, q, cond, direction):
        s = direction(v)
        rise = ca.fmin((1 - ca.exp(-3 * ca.fabs(v) / _per(q, "ve", s))) / _THRELFALL_PLATEAU, 1.0)
        return _per(q, "Fc", s) * rise * s + _per(q, "B", s) * v


@dataclass(frozen=True)
class CVS(FrictionModel):
    """Static-Coulomb-Stribeck-viscous (seed 004 Eq. 3, seed 000 Eqs. 1-2, seed 003 Eq. 8):

        F = (Fc(s) + (Fs(s) - Fc(s)) exp(-(|v| / vs(s))^delta(s))) s + B(s) v

    delta = 2 is the usual choice (seed 004, Dupont); the map fits it fixed (`cvs`) or free.
    """

    name: ClassVar[str] = "cvs"
    description: ClassVar[str] = "static-Coulomb-Stribeck-viscous friction per direction"
    BASE: ClassVar[tuple[str, ...]] = ("Fc", "Fs", "vs", "B", "delta")
    PARAMS: ClassVar[dict[str, ParamInfo]] = _directional(Fc=_FC, Fs=_FS, vs=_VS, B=_B, delta=_DELTA)
    SCALES: ClassVar[frozenset[str]] = frozenset({"vs"})
    Fc_pos: float = 20.0
    Fc_neg: float = 20.0
    Fs_pos: float = 25.0
    Fs_neg: float = 25.0
    vs_pos: float = 0.01
    vs_neg: float = 0.01
    B_pos: float = 50.0
    B_neg: float = 50.0
    delta_pos: float = 2.0
    delta_neg: float = 2.0

    @classmethod
    def curve(cls, v, q, cond, direction):
        s = direction(v)
        Fc = _per(q, "Fc", s)
        e = _stribeck(v, _per(q, "vs", s), _per(q, "delta", s))
        return (Fc + (_per(q, "Fs", s) - Fc) * e) * s + _per(q, "B", s) * v


@dataclass(frozen=True)
class LuGre(FrictionModel):
    """LuGre (seed 004 Eq. 4; Canudas de Wit et al. 1995) with per-direction Stribeck curve:

        g(v)  = Fc(s) + (Fs(s) - Fc(s)) exp(-(v / vs(s))^2)
        dz/dt = v - sigma0 |v| z / g(v)
        F     = sigma0 z + sigma1 dz/dt + B(s) v

    At steady speed z = sign(v) g / sigma0 and dz/dt = 0, so the static curve is the cvs
    curve with delta = 2: F = g(v) s + B v. sigma0 (bristle stiffness; Fs / sigma0 is the
    pre-sliding displacement) and sigma1 (bristle damping) are dynamic: a static map does
    not determine them. The plant state is the dimensionless zeta = sigma0 z / Fr with
    Fr = (Fs_pos + Fs_neg)/2 (|zeta| about 1 when sliding):

        dzeta/dt = sigma0 / Fr (v - |v| zeta Fr / g),    F = Fr zeta + sigma1 dz/dt + B v
    """

    name: ClassVar[str] = "lugre"
    description: ClassVar[str] = "LuGre dynamic friction (bristle state) with a per-direction Stribeck curve"
    BASE: ClassVar[tuple[str, ...]] = ("Fc", "Fs", "vs", "B")
    SHARED: ClassVar[tuple[str, ...]] = ("sigma0", "sigma1")
    PARAMS: ClassVar[dict[str, ParamInfo]] = {
        **_directional(Fc=ParamInfo("N", 1e-3, 1e4, _FC.description), Fs=ParamInfo("N", 1e-3, 1e4, _FS.description),
                       vs=_VS, B=_B),
        "sigma0": ParamInfo("N/m", 1e2, 1e9, "bristle stiffness"),
        "sigma1": ParamInfo("N s/m", 0.0, 1e5, "bristle damping"),
    }
    STATES: ClassVar[tuple[str, ...]] = ("zeta",)
    DYNAMIC: ClassVar[frozenset[str]] = frozenset({"sigma0", "sigma1"})
    SCALES: ClassVar[frozenset[str]] = frozenset({"vs"})
    Fc_pos: float = 20.0
    Fc_neg: float = 20.0
    Fs_pos: float = 25.0
    Fs_neg: float = 25.0
    vs_pos: float = 0.01
    vs_neg: float = 0.01
    B_pos: float = 50.0
    B_neg: float = 50.0
    sigma0: float = 1e5  # 0.25 mm pre-sliding at 25 N
    sigma1: float = 200.0  # bristles about half-critically damped with 0.7 kg

    @staticmethod
    def _g(v, q, s):
        Fc = _per(q, "Fc", s)
        return Fc + (_per(q, "Fs", s) - Fc) * _stribeck(v, _per(q, "vs", s), 2.0)

    @classmethod
    def curve(cls, v, q, cond, direction):
        s = direction(v)
        return cls._g(v, q, s) * s + _per(q, "B", s) * v

    def on_friction(self, sig, q, s) -> None:
        v, zeta = sig.v, s["zeta"]
        d = self._smooth_direction(sig)(v)
        Fr = (q["Fs_pos"] + q["Fs_neg"]) / 2
        dz = v - ca.fabs(v) * zeta * Fr / self._g(v, q, d)
        sig.deriv[self.key("zeta")] = q["sigma0"] / Fr * dz
        sig.Ff = Fr * zeta + q["sigma1"] * dz + _per(q, "B", d) * v

    def initial_states(self, cyl, p1: float, p2: float, v0: float = 0.0) -> list[float]:
        # sliding: bristles at their steady deflection; at rest: relaxed
        if abs(v0) <= 10 * cyl.friction.v_smooth:
            return [0.0]
        B = self.B_pos if v0 > 0 else self.B_neg
        g_signed = float(self.static_curve(v0)) - B * v0
        return [g_signed / ((self.Fs_pos + self.Fs_neg) / 2)]


@dataclass(frozen=True)
class CVLoad(FrictionModel):
    """Coulomb-viscous growing with the normal load Fn (seed 003 Eq. 5):

        F = (Fc(s) + mu(s) Fn) s + (B(s) + mu_v(s) Fn) v

    seed 003's mu_d1 = Fc, mu_d = mu, mu_f = B, mu_f1 = mu_v. Fn is a per-point input of the
    static curve (`load`); in the plant, which has no load signal, the constant parameter Fn.
    """

    name: ClassVar[str] = "cv_load"
    description: ClassVar[str] = "Coulomb-viscous friction with terms proportional to the normal load"
    BASE: ClassVar[tuple[str, ...]] = ("Fc", "mu", "B", "mu_v")
    SHARED: ClassVar[tuple[str, ...]] = ("Fn",)
    CONDITIONS: ClassVar[tuple[str, ...]] = ("load",)
    PARAMS: ClassVar[dict[str, ParamInfo]] = {
        **_directional(Fc=_FC, mu=ParamInfo("1", 0.0, 10.0, "Coulomb friction per newton of normal load"),
                       B=_B, mu_v=ParamInfo("s/m", 0.0, 1e4, "viscous coefficient per newton of normal load")),
        "Fn": _FN,
    }
    Fc_pos: float = 20.0
    Fc_neg: float = 20.0
    mu_pos: float = 0.1
    mu_neg: float = 0.1
    B_pos: float = 50.0
    B_neg: float = 50.0
    mu_v_pos: float = 0.0
    mu_v_neg: float = 0.0
    Fn: float = 0.0

    @classmethod
    def curve(cls, v, q, cond, direction):
        s = direction(v)
        Fn = cond["load"]
        return (_per(q, "Fc", s) + _per(q, "mu", s) * Fn) * s + (_per(q, "B", s) + _per(q, "mu_v", s) * Fn) * v


@dataclass(frozen=True)
class CVSLoad(FrictionModel):
    """Static-Coulomb-Stribeck-viscous growing with the normal load Fn (seed 003 Eq. 8):

        e = exp(-(|v| / vs(s))^2)
        F = ((Fc + mu Fn)(1 - e) + (Fs + mu_s Fn) e) s + (B + mu_v Fn) v     (all per direction)

    seed 003's mu_d1 = Fc, mu_d = mu, mu_s1 = Fs, mu_s = mu_s, mu_f = B, mu_f1 = mu_v.
    """

    name: ClassVar[str] = "cvs_load"
    description: ClassVar[str] = "Stribeck friction with terms proportional to the normal load"
    BASE: ClassVar[tuple[str, ...]] = ("Fc", "mu", "Fs", "mu_s", "vs", "B", "mu_v")
    SHARED: ClassVar[tuple[str, ...]] = ("Fn",)
    CONDITIONS: ClassVar[tuple[str, ...]] = ("load",)
    PARAMS: ClassVar[dict[str, ParamInfo]] = {
        **_directional(Fc=_FC, mu=ParamInfo("1", 0.0, 10.0, "Coulomb friction per newton of normal load"),
                       Fs=_FS, mu_s=ParamInfo("1", 0.0, 10.0, "static friction per newton of normal load"),
                       vs=_VS, B=_B, mu_v=ParamInfo("s/m", 0.0, 1e4, "viscous coefficient per newton of normal load")),
        "Fn": _FN,
    }
    SCALES: ClassVar[frozenset[str]] = frozenset({"vs"})
    Fc_pos: float = 20.0
    Fc_neg: float = 20.0
    mu_pos: float = 0.1
    mu_neg: float = 0.1
    Fs_pos: float = 25.0
    Fs_neg: float = 25.0
    mu_s_pos: float = 0.15
    mu_s_neg: float = 0.15
    vs_pos: float = 0.01
    vs_neg: float = 0.01
    B_pos: float = 50.0
    B_neg: float = 50.0
    mu_v_pos: float = 0.0
    mu_v_neg: float = 0.0
    Fn: float = 0.0

    @classmethod
    def curve(cls, v, q, cond, direction):
        s = direction(v)
        Fn = cond["load"]
        e = _stribeck(v, _per(q, "vs", s), 2.0)
        coulomb = _per(q, "Fc", s) + _per(q, "mu", s) * Fn
        static = _per(q, "Fs", s) + _per(q, "mu_s", s) * Fn
        return (coulomb * (1 - e) + static * e) * s + (_per(q, "B", s) + _per(q, "mu_v", s) * Fn) * v


@dataclass(frozen=True)
class Belforte(FrictionModel):
    """Pressure-dependent friction of Belforte et al. (1989), seed 004 Eq. (2):

        F = (FA(s) + (1 + K1(s) |v|^alpha(s)) (K2(s) |p1 - p2| + K3(s) pc)) s

    FA the friction without pressure, K2 the seal term growing with the pressure difference
    across the piston (as kp in the nominal model), K3 the term growing with the counter
    pressure pc (Belforte's P2: the gauge pressure of the chamber the piston pushes against,
    p2 - pa extending, p1 - pa retracting), K1 and alpha the speed dependence of the
    pressure terms. K1 is in (s/m)^alpha.
    """

    name: ClassVar[str] = "belforte"
    description: ClassVar[str] = "Belforte: friction growing with the pressure difference and the counter pressure"
    BASE: ClassVar[tuple[str, ...]] = ("FA", "K1", "alpha", "K2", "K3")
    CONDITIONS: ClassVar[tuple[str, ...]] = ("dp", "pc")
    PARAMS: ClassVar[dict[str, ParamInfo]] = _directional(
        FA=ParamInfo("N", 0.0, 1e4, "friction without pressure"),
        K1=ParamInfo("(s/m)^alpha", 0.0, 1e6, "speed factor of the pressure terms"),
        alpha=ParamInfo("1", 0.1, 3.0, "speed exponent of the pressure terms"),
        K2=ParamInfo("N/Pa", 0.0, 1e-2, "friction per pascal of |p1 - p2|"),
        K3=ParamInfo("N/Pa", 0.0, 1e-2, "friction per pascal of counter pressure (gauge)"))
    FA_pos: float = 10.0
    FA_neg: float = 10.0
    K1_pos: float = 1.0
    K1_neg: float = 1.0
    alpha_pos: float = 1.0
    alpha_neg: float = 1.0
    K2_pos: float = 1e-5
    K2_neg: float = 1e-5
    K3_pos: float = 1e-5
    K3_neg: float = 1e-5

    @classmethod
    def curve(cls, v, q, cond, direction):
        s = direction(v)
        speed = 1 + _per(q, "K1", s) * ca.fmax(ca.fabs(v), _TINY) ** _per(q, "alpha", s)
        return (_per(q, "FA", s) + speed * (_per(q, "K2", s) * cond["dp"] + _per(q, "K3", s) * cond["pc"])) * s


_KP = ParamInfo("N/Pa", 0.0, 1e-2, "friction per pascal of |p1 - p2| (seal pressure)")


@dataclass(frozen=True)
class CVPressure(FrictionModel):
    """The product's own friction law (docs/model.md) with every parameter per direction:

        F = (Fc(s) + kp(s) |p1 - p2|) s + Fv(s) v

    With Fc_pos = Fc_neg = Fc, kp_pos = kp_neg = kp and Fv_pos = Fv_neg = Fv it is the nominal
    plant's friction, to rounding. Fv is the viscous coefficient (B in the other models).
    """

    name: ClassVar[str] = "cv_dp"
    description: ClassVar[str] = "the nominal law per direction: Coulomb plus seal-pressure term, plus viscous"
    BASE: ClassVar[tuple[str, ...]] = ("Fc", "kp", "Fv")
    CONDITIONS: ClassVar[tuple[str, ...]] = ("dp",)
    PARAMS: ClassVar[dict[str, ParamInfo]] = _directional(Fc=_FC, kp=_KP, Fv=_B)
    Fc_pos: float = 20.0
    Fc_neg: float = 20.0
    kp_pos: float = 1e-5
    kp_neg: float = 1e-5
    Fv_pos: float = 50.0
    Fv_neg: float = 50.0

    @classmethod
    def curve(cls, v, q, cond, direction):
        s = direction(v)
        return (_per(q, "Fc", s) + _per(q, "kp", s) * cond["dp"]) * s + _per(q, "Fv", s) * v


@dataclass(frozen=True)
class Efficiency(FrictionModel):
    """Friction proportional to the pressure force, as catalogues give it (seed 004 Eq. 1,
    F = m P A with the efficiency factor m): with P the pressure difference across the piston,

        F = kp(s) |p1 - p2| s,        kp = m A1 (N/Pa)

    The simplest pressure-dependent form; cv_dp contains it (Fc = Fv = 0).
    """

    name: ClassVar[str] = "efficiency"
    description: ClassVar[str] = "friction proportional to the pressure difference (the catalogues' efficiency factor)"
    BASE: ClassVar[tuple[str, ...]] = ("kp",)
    CONDITIONS: ClassVar[tuple[str, ...]] = ("dp",)
    PARAMS: ClassVar[dict[str, ParamInfo]] = _directional(kp=_KP)
    kp_pos: float = 5e-5
    kp_neg: float = 5e-5

    @classmethod
    def curve(cls, v, q, cond, direction):
        s = direction(v)
        return _per(q, "kp", s) * cond["dp"] * s


FRICTION_MODELS: dict[str, type[FrictionModel]] = {cls.name: cls for cls in (
    CV, Karnopp, Threlfall, CVS, LuGre, CVLoad, CVSLoad, Belforte, CVPressure, Efficiency)}


# ================================================================ helpers

def make_friction_model(name: str, values: Mapping[str, Any] | None = None) -> FrictionModel:
    """A friction model by name, with parameter values (others default), checked against
    the bounds."""
    return make_from(FRICTION_MODELS, "friction model", name, values)


def parse_friction_spec(spec: str) -> FrictionModel:
    """'cvs:Fc_pos=16.9,Fc_neg=13.5' -> CVS(...) (command-line form)."""
    return parse_spec(spec, make_friction_model, "friction model")


def parse_truth_spec(spec: str) -> Effect:
    """'name:k=v,...' naming a word of the effect vocabulary, a friction model of the family or
    friction_change (a friction that changes during the run): what the virtual rig can be
    given as truth."""
    name = spec.partition(":")[0].strip()
    if name in FRICTION_MODELS and name not in EFFECTS:
        return parse_friction_spec(spec)
    if name in FRICTION_CHANGES:
        return parse_spec(spec, lambda _, values: make_friction_change(values), "friction change")
    if name not in EFFECTS:
        raise ValueError(f"unknown effect or friction model '{name}' (effects: {', '.join(EFFECTS)}; "
                         f"friction models: {', '.join(FRICTION_MODELS)}; friction_change)")
    return parse_effect_spec(spec)


def parameter_unit(family: str, base: str) -> str:
    """The unit of a parameter of the model `family` ('Fc' for Fc_pos and Fc_neg, or a shared
    one), '' when dimensionless."""
    params = FRICTION_MODELS[family].PARAMS
    info = params.get(f"{base}_pos") or params.get(base)
    return "" if info is None or info.unit == "1" else info.unit


def without_nominal_friction(cyl):
    """The cylinder with the nominal friction (Fc, Fv, kp) set to 0, as a friction model
    expects (it replaces that friction; v_smooth is kept: the model's direction function)."""
    return cyl.with_values({"Fc": 0.0, "Fv": 0.0, "kp": 0.0})
