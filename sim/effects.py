"""Unmodelled effects as composable extensions of the nominal plant.

An effect is an extension of the plant (sim.extension): a frozen dataclass whose fields are
its parameter values, hooking into named stages of the plant's signal flow (command,
supply, flows, friction terms, friction, piston, chambers; see sim.extension.Signals). The virtual rig uses effects as truth; the
identifier and the diagnosis use them as candidates. Names follow the docs/formats.md
vocabulary; docs/effects.md gives every equation, parameter and realistic strength.

Conventions shared by all effects:
- NEUTRAL holds parameter values at which the effect vanishes exactly: the plant then
  computes the nominal trajectory to rounding (states an effect adds stay at zero, or
  never feed back). A state that feeds back also relaxes to zero there: a fit's node states
  start it anywhere, and one that held its value would be a free input of every shooting
  interval (supply_droop's sag). heat_transfer's (h = 0) lies just below its identification
  bound (see there).
- Defaults are the identification start of a candidate: weak to medium values from which
  the fit converges both to a medium truth and to the neutral value.
- STRENGTH maps every drawn parameter to a realistic (weak, strong) range. Weak is "barely
  visible": on a 20 s closed-loop virtual-rig run (1 kHz, 5 um / 300 Pa noise), the
  nominal model re-identified (Fc, Fv, kp) leaves a residual sigma of about 1.1-1.5 x the
  sensor noise. Strong is a physically strong but realistic level. Parameters in SHAPE
  are not strengths but shapes (where, how wide, how fast): their range is the realistic
  span. Parameters in SIGNED may take either sign (the range is of the magnitude). Where
  a bound depends on the cylinder, SCALED names a reference (`reference`) that multiplies
  it: (weak reference, strong reference). `strength(cyl)` gives every range in the
  parameter's own unit for one cylinder; `random(rng, cyl)` and `typical(cyl, level)`
  draw from it. A parameter in UNDRAWN (leakage's laminar term) is fitted by a candidate but
  held at its neutral value by drawn truths; its strengths are those of the parameter named
  there.
- Effect states are dimensionless (the integrator's tolerance for them is absolute).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar, Mapping

import casadi as ca
import numpy as np

from .extension import Effect, ParamInfo, make_from, parse_spec, seal_friction_reference
from .flow import KAPPA, R_AIR, R_LAM, choked_flow, flow_function, mass_flow

__all__ = ["EFFECTS", "Effect", "ParamInfo", "make_effect", "parse_effect_spec", "seal_friction_reference",
           "FRICTION_CHANGES", "FrictionChange", "make_friction_change", "Stiction", "FrictionAsymmetry", "FrictionPosition", "FrictionDynamics", "Mass", "ValveDeadzone",
           "ValveDelay", "Leakage", "HeatTransfer", "SupplyDroop"]


# ================================================================ mechanical effects

@dataclass(frozen=True)
class Stiction(Effect):
    """Breakaway friction above the Coulomb level at low speed (Stribeck curve).

    Ff += (Fs_excess + pressure_excess * kp |p1 - p2|) * decay(z) * tanh(v / v_smooth)
    z = |v / v_stribeck|^exponent,   decay = (1 + tail z)^(-1/tail)   (tail 0: exp(-z))

    exponent 2 is the Gaussian decay (the default, and every drawn truth), 1 the exponential;
    the published seals lie between 0.5 and 2 (Armstrong-Helouvry's generalised Stribeck
    curve). tail 1 with exponent 2 is Hess and Soom's rational curve 1 / (1 + (v/v_stribeck)^2),
    whose excess lingers at speeds where the exponential one is gone. z is computed from
    (v / v_stribeck)^2 + 1e-12 so that its derivatives stay finite at rest for an exponent
    below 1; below t z = 1e-3 the decay's logarithm is its series. A pressure-energised seal
    breaks away harder the more it is pressed: pressure_excess is the static excess of the
    pressure friction kp|p1 - p2| (0: a constant excess, drawn truths; 0.4 with
    Fs_excess = 0.4 Fc: a static friction 1.4 times the seal level at every pressure).
    """

    name: ClassVar[str] = "stiction"
    subsystem: ClassVar[str] = "mechanical"
    FRICTION: ClassVar[str | None] = "reshapes"
    description: ClassVar[str] = "breakaway friction above the Coulomb level at low speed"
    REVISION: ClassVar[int] = 4
    PARAMS: ClassVar[dict[str, ParamInfo]] = {
        "Fs_excess": ParamInfo("N", 0.0, 1e4, "static minus Coulomb friction"),
        "v_stribeck": ParamInfo("m/s", 1e-4, 1.0, "Stribeck velocity"),
        "exponent": ParamInfo("1", 0.5, 2.5, "exponent of the Stribeck decay (2: Gaussian, 1: exponential)"),
        "pressure_excess": ParamInfo("1", 0.0, 10.0, "static minus sliding pressure friction, relative to "
                                                     "kp|p1-p2|"),
        "tail": ParamInfo("1", 0.0, 2.0, "heaviness of the decay's tail (0: exp(-z), 1: 1 / (1 + z))"),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"Fs_excess": 0.0, "pressure_excess": 0.0}
    # weak: 0.45 N; strong: static friction twice the seal level; truths are Gaussian with a
    # constant excess
    STRENGTH: ClassVar[dict[str, tuple[float, float]]] = {"Fs_excess": (0.45, 1.0), "v_stribeck": (0.003, 0.02),
                                                           "exponent": (2.0, 2.0), "tail": (0.0, 0.0)}
    UNDRAWN: ClassVar[dict[str, str]] = {"pressure_excess": "Fs_excess"}
    SHAPE: ClassVar[frozenset[str]] = frozenset({"v_stribeck", "exponent", "tail"})
    FREED_LAST: ClassVar[frozenset[str]] = frozenset({"exponent", "pressure_excess", "tail"})
    # pressure_excess (undrawn) at Fs_excess's strengths as a share of the pressure friction at
    # 2 bar: weak 0.45 N of it, strong as much again as it
    SCALED: ClassVar[dict[str, tuple[str | None, str | None]]] = {"Fs_excess": (None, "seal_friction"),
                                                                 "pressure_excess": ("per_pressure_friction", None)}
    # the rational curve (tail 1) is a basin of its own: from tail 0 a strong one (the
    # benchmark plant's, 32 mm) ended at 20 x the noise on TRAIN, tail 0 and exponent 2.5
    STARTS: ClassVar[tuple[dict[str, float], ...]] = ({"Fs_excess": 2.0, "v_stribeck": 0.004}, {"tail": 1.0})
    Fs_excess: float = 10.0
    v_stribeck: float = 0.01
    exponent: float = 2.0
    pressure_excess: float = 0.0
    tail: float = 0.0

    def on_friction(self, sig, q, s) -> None:
        v, t = sig.v, q["tail"]
        z = ((v / q["v_stribeck"]) ** 2 + 1e-12) ** (0.5 * q["exponent"])
        tz = t * z
        log_decay = ca.if_else(tz < 1e-3, z * (1 - tz / 2 + tz * tz / 3), ca.log1p(tz) / ca.fmax(t, 1e-12))
        decay = ca.exp(-log_decay)
        excess = q["Fs_excess"] + q["pressure_excess"] * sig.par["kp"] * ca.fabs(sig.p1 - sig.p2)
        sig.Ff = sig.Ff + excess * decay * ca.tanh(v / sig.par["v_smooth"])


@dataclass(frozen=True)
class FrictionAsymmetry(Effect):
    """Friction differs between extension and retraction.

    The seal level (Fc + kp|p1-p2|) and the viscous coefficient Fv become per direction,
    with Fc, kp, Fv the mean of the two directions; a lip seal pressed harder from one side
    also makes the pressure term depend on which chamber is pressurised (in most motion the
    cap side while extending, the rod side while retracting):

        Fseal += a_side * kp * (p1 - p2)                (cap side pressurised: kp (1 + a_side))
        Fseal *= 1 + a_coulomb * tanh(v / v_smooth)     (extension: 1 + a, retraction: 1 - a)
        Fvisc *= 1 + a_viscous * tanh(v / v_smooth)

    |a| <= 1 keeps every direction's friction non-negative, so friction still opposes motion.
    """

    name: ClassVar[str] = "friction_asymmetry"
    subsystem: ClassVar[str] = "mechanical"
    FRICTION: ClassVar[str | None] = "reshapes"
    description: ClassVar[str] = "friction differs between extension and retraction"
    PARAMS: ClassVar[dict[str, ParamInfo]] = {
        "a_coulomb": ParamInfo("1", -1.0, 1.0, "relative excess of the seal (Coulomb + pressure) friction "
                                               "when extending (negative: when retracting)"),
        "a_viscous": ParamInfo("1", -1.0, 1.0, "relative excess of the viscous coefficient when extending"),
        "a_side": ParamInfo("1", -1.0, 1.0, "relative excess of the pressure friction kp|p1-p2| with the "
                                            "cap side pressurised (negative: the rod side)"),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"a_coulomb": 0.0, "a_viscous": 0.0, "a_side": 0.0}
    # weak: a difference of 0.26 N in the seal friction, of 0.032 N in the viscous force at
    # 0.1 m/s, of 0.26 N in the pressure friction at 2 bar between the directions (sides);
    # strong: published industrial cylinders (0.6, 0.5), a lip seal's one-sided pressure
    # loading (0.5)
    STRENGTH: ClassVar[dict[str, tuple[float, float]]] = {
        "a_coulomb": (0.13, 0.6), "a_viscous": (0.016, 0.5), "a_side": (0.13, 0.5)}
    SIGNED: ClassVar[frozenset[str]] = frozenset({"a_coulomb", "a_viscous", "a_side"})
    SCALED: ClassVar[dict[str, tuple[str | None, str | None]]] = {
        "a_coulomb": ("per_seal_friction", None), "a_viscous": ("per_viscous_force", None),
        "a_side": ("per_pressure_friction", None)}
    a_coulomb: float = 0.2
    a_viscous: float = 0.1
    a_side: float = 0.0

    def on_friction_terms(self, sig, q, s) -> None:
        d = ca.tanh(sig.v / sig.par["v_smooth"])
        sig.Fseal = sig.Fseal + q["a_side"] * sig.par["kp"] * (sig.p1 - sig.p2)
        sig.Fseal = sig.Fseal * (1 + q["a_coulomb"] * d)
        sig.Fvisc = sig.Fvisc * (1 + q["a_viscous"] * d)


@dataclass(frozen=True)
class FrictionPosition(Effect):
    """Friction changes along the stroke: a slope (wear, misalignment) and a local tight
    (or loose) section, both relative to the seal level at mid-stroke:

        xi = x / L
        Fseal *= max(0, 1 + slope*(xi - 1/2) + bump*exp(-((xi - center)/width)^2))

    Fc and kp then mean the seal friction at mid-stroke away from the bump.
    """

    name: ClassVar[str] = "friction_position"
    subsystem: ClassVar[str] = "mechanical"
    FRICTION: ClassVar[str | None] = "reshapes"
    description: ClassVar[str] = "friction changes along the stroke"
    PARAMS: ClassVar[dict[str, ParamInfo]] = {
        "slope": ParamInfo("1", -1.9, 1.9, "relative change of the seal friction from x = 0 to x = L"),
        "bump": ParamInfo("1", -0.9, 10.0, "relative extra seal friction at the tight spot (negative: loose)"),
        "center": ParamInfo("1", 0.0, 1.0, "tight spot position as a fraction of the stroke"),
        "width": ParamInfo("1", 0.02, 1.0, "tight spot half-width (1/e) as a fraction of the stroke"),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"slope": 0.0, "bump": 0.0}
    # weak: 0.5 N change over the stroke, a 0.22 N tight spot; strong: +-40 % at the ends,
    # a spot with 2.5 times the friction
    STRENGTH: ClassVar[dict[str, tuple[float, float]]] = {
        "slope": (0.5, 0.8), "bump": (0.22, 1.5), "center": (0.25, 0.75), "width": (0.04, 0.15)}
    SHAPE: ClassVar[frozenset[str]] = frozenset({"center", "width"})
    SIGNED: ClassVar[frozenset[str]] = frozenset({"slope"})
    SCALED: ClassVar[dict[str, tuple[str | None, str | None]]] = {
        "slope": ("per_seal_friction", None), "bump": ("per_seal_friction", None)}
    # defaults are the identification start: a small bump; `center` is found only from a
    # start within about 0.1 of the stroke (try several centres for an unknown spot)
    STARTS: ClassVar[tuple[dict[str, float], ...]] = ({"center": 0.25}, {"center": 0.75})
    slope: float = 0.0
    bump: float = 0.1
    center: float = 0.5
    width: float = 0.1

    def on_friction_terms(self, sig, q, s) -> None:
        xi = sig.x / sig.par["stroke"]
        factor = 1 + q["slope"] * (xi - 0.5) + q["bump"] * ca.exp(-(((xi - q["center"]) / q["width"]) ** 2))
        sig.Fseal = sig.Fseal * ca.fmax(factor, 0.0)


@dataclass(frozen=True)
class FrictionDynamics(Effect):
    """Friction with memory (LuGre type): pre-sliding displacement and hysteresis.

    A share w of the seal friction is carried by bristles whose normalised deflection
    s in [-1, 1] follows  ds/dt = (v - |v| s) / x_pre : it saturates at sign(v) after a
    displacement of about x_pre (LuGre with sigma0 = Fseal / x_pre, z = x_pre * s), and
    the bristles are damped with sigma1 = sigma0 * t_damp. The state is q = w s (so it
    stays exactly zero when w = 0):

        dq/dt = (w v - |v| q) / x_pre
        Fseal * sgn  ->  Fseal * ((1 - w) tanh(v / v_smooth) + q + t_damp dq/dt)

    w = 0 is the nominal plant, w = 1 full LuGre (without Stribeck: that is `stiction`).
    Both added terms dissipate: w v - |v| q has the sign of v for |q| <= w.
    """

    name: ClassVar[str] = "friction_dynamics"
    subsystem: ClassVar[str] = "mechanical"
    FRICTION: ClassVar[str | None] = "reshapes"
    description: ClassVar[str] = "friction with memory: pre-sliding displacement, hysteresis (LuGre)"
    PARAMS: ClassVar[dict[str, ParamInfo]] = {
        "share": ParamInfo("1", 0.0, 1.0, "share of the seal friction with memory (bristles)"),
        "x_pre": ParamInfo("m", 1e-5, 5e-3, "pre-sliding displacement (bristle level / stiffness)"),
        "t_damp": ParamInfo("s", 0.0, 0.02, "bristle damping time sigma1 / sigma0"),
    }
    STATES: ClassVar[tuple[str, ...]] = ("q",)
    NEUTRAL: ClassVar[dict[str, float]] = {"share": 0.0}
    # weak: 0.85 N of the seal friction with memory; strong: all of it (full LuGre)
    STRENGTH: ClassVar[dict[str, tuple[float, float]]] = {
        "share": (0.85, 1.0), "x_pre": (3e-5, 5e-4), "t_damp": (5e-4, 4e-3)}
    SHAPE: ClassVar[frozenset[str]] = frozenset({"x_pre", "t_damp"})
    SCALED: ClassVar[dict[str, tuple[str | None, str | None]]] = {"share": ("per_seal_friction", None)}
    STARTS: ClassVar[tuple[dict[str, float], ...]] = ({"share": 0.95, "x_pre": 3e-4},)
    share: float = 0.5
    x_pre: float = 1e-4
    t_damp: float = 2e-3

    def initial_states(self, cyl, p1: float, p2: float, v0: float = 0.0) -> list[float]:
        # sliding: saturated bristles; at rest: relaxed
        vs = cyl.friction.v_smooth
        return [self.share * math.tanh(v0 / vs) if abs(v0) > 10 * vs else 0.0]

    def on_friction_terms(self, sig, q, s) -> None:
        v, z, w = sig.v, s["q"], q["share"]
        dz = (w * v - ca.fabs(v) * z) / q["x_pre"]
        sig.deriv[self.key("q")] = dz
        sig.sgn = sig.sgn * (1 - w) + z + q["t_damp"] * dz


@dataclass(frozen=True)
class Mass(Effect):
    """The moving mass differs from the configured one (payload): M -> M (1 + delta).
    The payload's weight counts too (inclined mounting)."""

    name: ClassVar[str] = "mass"
    subsystem: ClassVar[str] = "mechanical"
    description: ClassVar[str] = "the moving mass differs from the configured one"
    PARAMS: ClassVar[dict[str, ParamInfo]] = {
        "delta": ParamInfo("1", -0.8, 10.0, "relative change of the moving mass"),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"delta": 0.0}
    STRENGTH: ClassVar[dict[str, tuple[float, float]]] = {"delta": (0.0035, 1.0)}
    SIGNED: ClassVar[frozenset[str]] = frozenset({"delta"})
    LIGHTEST: ClassVar[float] = -0.5  # random(): a lighter load than configured, the piston and rod remain
    delta: float = 0.3

    @classmethod
    def random(cls, rng: np.random.Generator, cyl) -> "Mass":
        e = super().random(rng, cyl)
        return e if e.delta >= cls.LIGHTEST else cls(delta=cls.LIGHTEST)

    def on_piston(self, sig, q, s) -> None:
        sig.M = sig.M * (1 + q["delta"])


# ================================================================ pneumatic effects

@dataclass(frozen=True)
class ValveDeadzone(Effect):
    """The valve does not open until |u| passes the spool overlap d. Beyond it, a share
    1 - g of the opening grows linearly from zero to full opening at |u| = 1 (a shifted
    opening, rated conductance kept), a share g opens to the full command at once (a gate:
    a valve whose electronics suppress small commands, a hard dead zone):

        u_eff = (1 - g) (smax(u - d) - smax(-u - d)) / (1 - d) + g u (step(u - d) + step(-u - d))

    smax(z) = max(z, 0) with the corner rounded by a parabola over |z| < e, e = d/10
    (0 for z <= -e, (z + e)^2 / (4 e) between, z for z >= e), step(z) a step from 0 to 1 over
    the same width (the cubic 1/2 + 3/4 z/e - 1/4 (z/e)^3 between): exactly closed for
    |u| <= 0.9 d, continuously differentiable for Gauss-Newton, exactly u when d = 0.
    """

    name: ClassVar[str] = "valve_deadzone"
    subsystem: ClassVar[str] = "pneumatic"
    description: ClassVar[str] = "the valve does not open until the command passes a threshold"
    REVISION: ClassVar[int] = 3
    PARAMS: ClassVar[dict[str, ParamInfo]] = {
        "overlap": ParamInfo("1", 0.0, 0.3, "command at which the valve starts to open (spool overlap)"),
        "gate": ParamInfo("1", 0.0, 1.0, "share of the opening that jumps to the command beyond the overlap "
                                         "(0: the opening grows from zero; 1: a hard dead zone)"),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"overlap": 0.0}
    # truths are shifted openings (gate 0); gate lets a candidate reach a hard dead zone
    STRENGTH: ClassVar[dict[str, tuple[float, float]]] = {"overlap": (1.2e-5, 0.1), "gate": (0.0, 0.0)}
    SHAPE: ClassVar[frozenset[str]] = frozenset({"gate"})
    SMOOTH: ClassVar[float] = 0.1  # rounding half-width as a fraction of the overlap (bump REVISION with it)
    # the default is the identification start: from a start far above the truth (in effect
    # size) the multiple-shooting fit can stall in a local minimum of the first node state.
    # A hard dead zone lies in another basin: from the shifted opening the fit shrinks the
    # overlap towards zero, so a gate is started as one (a small overlap: a gate's overlap has a
    # gradient only from the commands within its rounded edge, d/10 either side). Starts at 0.015
    # and 0.04 as well gained nothing on a reference-plant gate of 0.02 that the calibrated
    # characteristic had taken, and no more on the cases beside it
    STARTS: ClassVar[tuple[dict[str, float], ...]] = ({"overlap": 0.03}, {"overlap": 0.005, "gate": 1.0})
    overlap: float = 1e-4
    gate: float = 0.0

    def on_command(self, sig, q, s) -> None:
        d, g = q["overlap"], q["gate"]
        e = self.SMOOTH * d
        e_safe = ca.fmax(e, 1e-300)

        def smax(z):
            return ca.if_else(z >= e, z, ca.if_else(z <= -e, 0.0, (z + e) ** 2 / (4 * e_safe)))

        def step(z):
            t = z / e_safe
            return ca.if_else(z >= e, 1.0, ca.if_else(z <= -e, 0.0, 0.5 + 0.75 * t - 0.25 * t ** 3))

        u = sig.u
        shifted = (smax(u - d) - smax(-u - d)) / (1 - d)
        sig.u = (1 - g) * shifted + g * u * (step(u - d) + step(-u - d))


@dataclass(frozen=True)
class ValveDelay(Effect):
    """The chambers see the command late: a lag of the effective opening, with a top speed.

    A share w of the opening lags with the time constant tau, its speed limited to about
    1 / t_slew (the spool's full travel from centre to an end takes t_slew at its top speed).
    The state is the lagged part y = w u_lag, so that it stays exactly zero at w = 0, the
    neutral value:

        r = (w u - y) / tau,    dy/dt = r (1 - exp(-t_slew |r|)) / (t_slew |r|),    u_valve = (1 - w) u + y

    w = 1 is a pure lag (the default), w < 1 a lead-lag, w = 2 the all-pass
    (1 - s tau) / (1 + s tau): the first-order Pade approximation of a dead time 2 tau (its
    gain is 1 at every frequency for w in [0, 2]; at low frequencies every w delays by w tau).
    t_slew = 0 is the linear lag; t_slew > 0 a rate-limited spool (with tau small: it moves at
    its top speed until it nearly reaches the command). The factor (1 - exp(-z)) / z of
    z = t_slew |r| is 1 - z / 2 near 0, so t_slew keeps a gradient at 0 and a fit can leave the
    linear lag; at large z the speed reaches 1 / t_slew exponentially (revision 5's
    1 / (1 + z) only as 1 / z, so its spool crept into the command).

    tau -> 0 would be singular, hence the lower bound 20 us: on a rate-limited spool the
    speed falls off within tau / t_slew of the command, so the corner sharpens as tau falls
    (at 0.1 ms, revision 6's bound, that band alone kept the model 7 x the noise away from an
    exact rate limit). Simulator and identifier share the one discretised step, which at
    20 us is what meets an exact rate limit; the step's own distance from the lag's ODE there
    is in docs/effects.md.
    """

    name: ClassVar[str] = "valve_delay"
    subsystem: ClassVar[str] = "pneumatic"
    description: ClassVar[str] = "the chambers see the valve command late"
    REVISION: ClassVar[int] = 7
    PARAMS: ClassVar[dict[str, ParamInfo]] = {
        "tau": ParamInfo("s", 2e-5, 0.2, "time constant of the valve opening"),
        "share": ParamInfo("1", 0.0, 2.0, "share of the opening that lags (1: a pure lag; 2: a dead time 2 tau)"),
        "t_slew": ParamInfo("s", 0.0, 0.05, "time the opening takes from centre to an end at its top speed "
                                            "(0: no speed limit)"),
    }
    STATES: ClassVar[tuple[str, ...]] = ("u_eff",)  # the lagged part w u_lag (u_lag at w = 1)
    NEUTRAL: ClassVar[dict[str, float]] = {"share": 0.0}
    # weak: 0.1 ms (already clearly visible); truths are pure lags (share 1, no speed limit);
    # share and t_slew let a candidate reach the nominal plant, a dead time and a rate-limited
    # spool
    STRENGTH: ClassVar[dict[str, tuple[float, float]]] = {"tau": (1e-4, 0.02), "share": (1.0, 1.0),
                                                           "t_slew": (0.0, 0.0)}
    SHAPE: ClassVar[frozenset[str]] = frozenset({"share", "t_slew"})
    # the identification start: from above the truth (e.g. 5 ms for 1.4 ms) the fit can end
    # in a lead-lag local minimum (share ~0.7); from 1 ms it converged for 0.1 to 20 ms and
    # to share = 0 on runs without a lag. A dead time and a rate-limited spool lie in other
    # basins: from the lag they end at a lead-lag (share ~0.2, tau 2-3 ms), from these starts
    # at the dead time (0.2-1 ms of tau for 0.68 ms) and at the speed limit
    STARTS: ClassVar[tuple[dict[str, float], ...]] = ({"tau": 3e-4, "share": 2.0}, {"tau": 1e-4, "t_slew": 3e-3})
    tau: float = 0.001
    share: float = 1.0
    t_slew: float = 0.0

    def on_command(self, sig, q, s) -> None:
        w, y = q["share"], s["u_eff"]
        r = (w * sig.u - y) / q["tau"]
        z = q["t_slew"] * ca.fabs(r)
        # (1 - exp(-z)) / z, its series below 1e-6 (where the quotient loses its digits)
        speed_share = ca.if_else(z < 1e-6, 1 - 0.5 * z, -ca.expm1(-z) / ca.fmax(z, 1e-6))
        sig.deriv[self.key("u_eff")] = r * speed_share
        sig.u = sig.u * (1 - w) + y


@dataclass(frozen=True)
class Leakage(Effect):
    """Air leaks across the piston seal between the chambers: through an orifice (a worn or
    damaged seal, ISO 6358 law with the valve's critical ratio) and through a fine gap (laminar:
    the volume flow at the chambers' mean density grows with the pressure difference); and out
    of a chamber to the atmosphere (the rod seal, a fitting, a port), through a fine gap and
    through an orifice:

        m = mass_flow(conductance, p1 -> p2) + laminar (p1^2 - p2^2) / (2 R T)
        m_out_i = vent_i (p_i^2 - pa^2) / (2 R T) + mass_flow(orifice_i, p_i -> pa)

    A seal's leak is one, the other or both; either alone imitates the other badly where the
    leak is strong (a capillary leak of 1.5e-4 m^3/s at supply against atmosphere, fitted by
    the orifice alone, left a calibrated model at 10.6 x the noise). A leak out of the rod
    chamber empties it towards the atmosphere instead of towards the other chamber: across
    the piston, a reference-plant rod-seal leak of 1e-4 m^3/s left a calibrated model at 68 x
    the noise on VALID; out of the chamber through the fine gap alone (revision 3), at 36.5 x
    (that leak's flow is linear in the gauge pressure, which neither law is; the two
    together: 1.76 x)."""

    name: ClassVar[str] = "leakage"
    subsystem: ClassVar[str] = "pneumatic"
    description: ClassVar[str] = "air leaks across the piston seal between the chambers, or out of a chamber"
    REVISION: ClassVar[int] = 4
    PARAMS: ClassVar[dict[str, ParamInfo]] = {
        "conductance": ParamInfo("m^3/(s Pa)", 0.0, 1e-7, "sonic conductance of the leak path (an orifice)"),
        "laminar": ParamInfo("m^3/(s Pa)", 0.0, 1e-7, "laminar conductance of the leak path (a fine gap): "
                                                       "volume flow at the mean density per Pa"),
        "vent_cap": ParamInfo("m^3/(s Pa)", 0.0, 1e-7, "laminar conductance from the cap-end chamber to the "
                                                        "atmosphere (a fitting, a port)"),
        "vent_rod": ParamInfo("m^3/(s Pa)", 0.0, 1e-7, "laminar conductance from the rod-end chamber to the "
                                                        "atmosphere (the rod seal, a fitting)"),
        "orifice_cap": ParamInfo("m^3/(s Pa)", 0.0, 1e-7, "sonic conductance from the cap-end chamber to the "
                                                           "atmosphere (a worn port seal, a loose fitting)"),
        "orifice_rod": ParamInfo("m^3/(s Pa)", 0.0, 1e-7, "sonic conductance from the rod-end chamber to the "
                                                           "atmosphere (a worn rod seal, a loose fitting)"),
    }
    NEUTRAL: ClassVar[dict[str, float]] = dict.fromkeys(PARAMS, 0.0)  # every path closed
    # relative to the valve: weak 7e-6 Cmax, strong 2 % of Cmax (a worn seal, litres per minute)
    STRENGTH: ClassVar[dict[str, tuple[float, float]]] = {"conductance": (7e-6, 0.02)}
    UNDRAWN: ClassVar[dict[str, str]] = {n: "conductance" for n in PARAMS if n != "conductance"}
    SCALED: ClassVar[dict[str, tuple[str | None, str | None]]] = dict.fromkeys(
        PARAMS, ("valve_conductance", "valve_conductance"))
    conductance: float = 2e-10
    # truths (random, typical) leak through an orifice; a candidate fits every path
    laminar: float = 0.0
    vent_cap: float = 0.0
    vent_rod: float = 0.0
    orifice_cap: float = 0.0
    orifice_rod: float = 0.0

    def on_flows(self, sig, q, s) -> None:
        rt2 = 2 * R_AIR * sig.T
        m = mass_flow(q["conductance"], sig.p1, sig.p2, sig.b, sig.T)
        m = m + q["laminar"] * (sig.p1 * sig.p1 - sig.p2 * sig.p2) / rt2
        pa2 = sig.pa * sig.pa
        sig.mdot1 = (sig.mdot1 - m - q["vent_cap"] * (sig.p1 * sig.p1 - pa2) / rt2
                     - mass_flow(q["orifice_cap"], sig.p1, sig.pa, sig.b, sig.T))
        sig.mdot2 = (sig.mdot2 + m - q["vent_rod"] * (sig.p2 * sig.p2 - pa2) / rt2
                     - mass_flow(q["orifice_rod"], sig.p2, sig.pa, sig.b, sig.T))


@dataclass(frozen=True)
class HeatTransfer(Effect):
    """Chamber air exchanges heat with the walls (at the supply temperature Ts).

    Chamber temperatures Ti = Ts (1 + theta_i) are states. Heat flow into chamber i
    Qi = h Awi (Ts - Ti), with Awi the wall area of a cylinder of the chamber's volume
    (cap: 2 A1 + pi D V1/A1; rod: 2 A2 + pi (D + d) V2/A2). The pressure equations get

        dpi/dt += (kappa - 1) / Vi * Qi

    and the temperatures follow the energy balance of the chamber air (inflow at Ts,
    outflow at Ti, compression work, wall heat):

        dTi/dt / Ti = R (max(mdot_i, 0) (kappa Ts - Ti) + (kappa - 1) Ti min(mdot_i, 0)) / (pi Vi)
                      - (kappa - 1) (dVi/dt) / Vi + (kappa - 1) Qi / (pi Vi)

    A polytropic exponent n scales the nominal pressure equations first (dpi/dt *= n / kappa):
    heat exchange too fast to resolve, or a chamber that is neither adiabatic nor isothermal
    in the way the wall law says, shows as an exponent between 1 and kappa.

    h = 0 and n = kappa are the nominal (adiabatic) plant exactly; h -> infinity makes the
    chambers isothermal at Ts. The energy balance takes Ti at least T_FLOOR Ts (a bound no air
    in a chamber comes near): near h = 0 the outputs barely see the temperatures, so a fit of
    node states may step them anywhere, and below 0 K the balance grows without bound. The
    pressure equations keep the nominal plant's convention (the outflow leaves with the
    enthalpy of Ts); the temperatures do not, or they would drift without bound over
    fill-exhaust cycles. With the valve closed the chamber mass
    pi Vi / (R Ti) stays exactly constant.
    """

    name: ClassVar[str] = "heat_transfer"
    subsystem: ClassVar[str] = "pneumatic"
    description: ClassVar[str] = "chamber air exchanges heat with the walls (not adiabatic)"
    REVISION: ClassVar[int] = 5
    PARAMS: ClassVar[dict[str, ParamInfo]] = {
        "h": ParamInfo("W/(m^2 K)", 0.01, 2000.0, "heat transfer coefficient between chamber air and wall"),
        "n": ParamInfo("1", 1.0, KAPPA, "polytropic exponent of the chamber pressure equations (kappa: adiabatic)"),
    }
    # h = 0 is the exact nominal plant but lies below the identification bound: there the
    # temperature states have no influence at all and the Gauss-Newton matrix is singular
    # (the fit then stalls at the bound); at 0.01 the effect is far below the noise.
    STATES: ClassVar[tuple[str, ...]] = ("theta1", "theta2")
    NEUTRAL: ClassVar[dict[str, float]] = {"h": 0.0, "n": KAPPA}
    # typical free/forced convection in cylinder chambers is 5-100 W/(m^2 K); below 5 the
    # effect is weak (barely visible at 0.8); truths exchange heat by the wall law (n = kappa),
    # n lets a candidate cover an effective exponent
    STRENGTH: ClassVar[dict[str, tuple[float, float]]] = {"h": (0.8, 100.0), "n": (KAPPA, KAPPA)}
    SHAPE: ClassVar[frozenset[str]] = frozenset({"n"})
    T_FLOOR: ClassVar[float] = 0.1  # the least chamber temperature the energy balance takes, x Ts
    h: float = 10.0
    n: float = KAPPA

    @staticmethod
    def wall_areas(sig):
        D, d = sig.par["bore"], sig.par["rod"]
        Aw1 = 2 * sig.A1 + math.pi * D * sig.V1 / sig.A1
        Aw2 = 2 * sig.A2 + math.pi * (D + d) * sig.V2 / sig.A2
        return Aw1, Aw2

    def on_chambers(self, sig, q, s) -> None:
        Ts, v = sig.T, sig.v
        sig.dp1 = sig.dp1 * (q["n"] / KAPPA)
        sig.dp2 = sig.dp2 * (q["n"] / KAPPA)
        for i, Aw, dV in zip((1, 2), self.wall_areas(sig), (sig.A1 * v, -sig.A2 * v)):
            r = ca.fmax(1 + s[f"theta{i}"], self.T_FLOOR)  # Ti / Ts
            p, V, mdot = getattr(sig, f"p{i}"), getattr(sig, f"V{i}"), getattr(sig, f"mdot{i}")
            Q = q["h"] * Aw * Ts * (1 - r)  # W into the chamber air
            setattr(sig, f"dp{i}", getattr(sig, f"dp{i}") + (KAPPA - 1) / V * Q)
            T = Ts * r
            flow = R_AIR * (ca.fmax(mdot, 0.0) * (KAPPA * Ts - T) + (KAPPA - 1) * T * ca.fmin(mdot, 0.0))
            sig.deriv[self.key(f"theta{i}")] = r * ((flow + (KAPPA - 1) * Q) / (p * V) - (KAPPA - 1) * dV / V)


@dataclass(frozen=True)
class SupplyDroop(Effect):
    """Supply pressure sags while air is drawn: the supply line is a restriction (ISO 6358
    law, with the valve's critical ratio) feeding the volume of hose and manifold, from which
    the valve draws. The relative sag s of the valve's supply pressure is a state:

        ps_valve = ps (1 - s)
        ds/dt = (droop mdot_supply / mdot_ref - (1 - droop) k phi(1 - s)) / tau,   k = droop / phi(1 - droop)
        mdot_ref = C ps rho0 sqrt(T0/Ts)

    (the line's flow is mdot_ref (1 - droop) phi(1 - s) / phi(1 - droop); phi is linear in its
    laminar end, so k is a constant for droop below 1 - R_LAM, droop = 0 included: there the sag
    relaxes to zero with tau, as it must, or a fit's node states would make it a free supply
    pressure of every shooting interval)

    droop is the relative sag at the valve's full-open choked draw, steady (s = droop there,
    tested); tau is the line's time constant (at the start of a full draw the sag grows at
    droop / tau per second). The restriction's law is what shapes the sag: its flow grows as
    the square root of the pressure drop and chokes below the critical ratio, so a small
    draw sags the supply much less, and a large one much more, than a linear resistance
    would. The linear resistance this replaces (revision 1) left a reference-plant supply line
    at 18.9 x the noise on VALID and a reservoir refilled through an orifice at 34.6 x (this
    law: 5.37 and 1.18).
    droop = 0 is the nominal plant exactly.
    """

    name: ClassVar[str] = "supply_droop"
    subsystem: ClassVar[str] = "pneumatic"
    description: ClassVar[str] = "supply pressure sags while air is drawn"
    REVISION: ClassVar[int] = 3
    PARAMS: ClassVar[dict[str, ParamInfo]] = {
        "droop": ParamInfo("1", 0.0, 0.8, "relative supply sag at the valve's full-open choked draw"),
        "tau": ParamInfo("s", 1e-3, 5.0, "time constant of the supply line and its volume"),
    }
    STATES: ClassVar[tuple[str, ...]] = ("sag",)
    NEUTRAL: ClassVar[dict[str, float]] = {"droop": 0.0}
    STRENGTH: ClassVar[dict[str, tuple[float, float]]] = {"droop": (0.003, 0.3), "tau": (0.01, 0.2)}
    SHAPE: ClassVar[frozenset[str]] = frozenset({"tau"})
    droop: float = 0.1
    tau: float = 0.05

    def on_supply(self, sig, q, s) -> None:
        sig.ps = sig.ps * (1 - s["sag"])

    def on_flows(self, sig, q, s) -> None:
        mdot_ref = choked_flow(sig.C, sig.par["supply_pressure"], sig.T)
        d = q["droop"]
        dk = ca.fmax(d, 1 - R_LAM)  # k is the same below the laminar end's droop
        k = dk / flow_function(1 - dk, sig.b)
        line = (1 - d) * k * flow_function(1 - s["sag"], sig.b)
        sig.deriv[self.key("sag")] = (d * sig.mdot_supply / mdot_ref - line) / q["tau"]


EFFECTS: dict[str, type[Effect]] = {cls.name: cls for cls in (
    Stiction, FrictionAsymmetry, FrictionPosition, FrictionDynamics, Mass,
    ValveDeadzone, ValveDelay, Leakage, HeatTransfer, SupplyDroop)}


# ================================================================ a rig that changes during a run

@dataclass(frozen=True)
class FrictionChange(Effect):
    """The rig's friction changes during a run (seals that warm up or wear, a payload or a
    seal exchanged): a step of Fc and Fv at t_step and a ramp from t_ramp on, both relative
    to the cylinder's values. A truth for the virtual rig, `simulate` and the benchmarks, not
    a word of the diagnosis vocabulary (the identifier's friction is constant by design):

        c(t) = step_Fc [t >= t_step] + ramp_Fc max(t - t_ramp, 0)
        f(t) = step_Fv [t >= t_step] + ramp_Fv max(t - t_ramp, 0)
        Fseal += Fc c(t),   Fvisc *= 1 + f(t)

    t is the time since the plant started (a run's t), held in the state `clock`
    (dclock/dt = 1, integrated exactly: its error estimate is zero). The step is a jump at
    t_step (the integrator refines the step that holds it); a ramp of +40 %/min is
    ramp = 0.4 / 60 = 0.00667 1/s.
    """

    name: ClassVar[str] = "friction_change"
    subsystem: ClassVar[str] = "mechanical"
    FRICTION: ClassVar[str | None] = "reshapes"
    description: ClassVar[str] = "the friction changes during the run (a step and a ramp of Fc and Fv)"
    PARAMS: ClassVar[dict[str, ParamInfo]] = {
        "t_step": ParamInfo("s", 0.0, 1e6, "time of the step"),
        "step_Fc": ParamInfo("1", -0.9, 10.0, "relative step of Fc at t_step"),
        "step_Fv": ParamInfo("1", -0.9, 10.0, "relative step of Fv at t_step"),
        "t_ramp": ParamInfo("s", 0.0, 1e6, "time the ramp starts"),
        "ramp_Fc": ParamInfo("1/s", -0.1, 0.1, "relative rate of change of Fc from t_ramp on"),
        "ramp_Fv": ParamInfo("1/s", -0.1, 0.1, "relative rate of change of Fv from t_ramp on"),
    }
    STATES: ClassVar[tuple[str, ...]] = ("clock",)
    NEUTRAL: ClassVar[dict[str, float]] = {"step_Fc": 0.0, "step_Fv": 0.0, "ramp_Fc": 0.0, "ramp_Fv": 0.0}
    t_step: float = 0.0
    step_Fc: float = 0.0
    step_Fv: float = 0.0
    t_ramp: float = 0.0
    ramp_Fc: float = 0.0
    ramp_Fv: float = 0.0

    def relative(self, t):
        """(c, f): the relative changes of Fc and Fv at time t (numbers or arrays)."""
        on = np.asarray(t, float) >= self.t_step
        ramp = np.maximum(np.asarray(t, float) - self.t_ramp, 0.0)
        return self.step_Fc * on + self.ramp_Fc * ramp, self.step_Fv * on + self.ramp_Fv * ramp

    def on_friction_terms(self, sig, q, s) -> None:
        t = s["clock"]
        sig.deriv[self.key("clock")] = ca.SX(1.0)
        on = ca.if_else(t >= q["t_step"], 1.0, 0.0)
        ramp = ca.fmax(t - q["t_ramp"], 0.0)
        sig.Fseal = sig.Fseal + sig.par["Fc"] * (q["step_Fc"] * on + q["ramp_Fc"] * ramp)
        sig.Fvisc = sig.Fvisc * (1 + q["step_Fv"] * on + q["ramp_Fv"] * ramp)


FRICTION_CHANGES: dict[str, type[Effect]] = {FrictionChange.name: FrictionChange}


def make_friction_change(values: Mapping[str, Any] | None = None) -> Effect:
    """A FrictionChange with parameter values (others default), checked against the bounds."""
    return make_from(FRICTION_CHANGES, "friction change", FrictionChange.name, values)


def make_effect(name: str, values: Mapping[str, Any] | None = None) -> Effect:
    """An effect by its vocabulary word, with parameter values (others default)."""
    return make_from(EFFECTS, "effect", name, values)


def parse_effect_spec(spec: str) -> Effect:
    """'stiction:Fs_excess=8,v_stribeck=0.01' -> Stiction(8, 0.01)."""
    return parse_spec(spec, make_effect)
