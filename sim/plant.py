"""The nominal servopneumatic plant of docs/model.md, written once, symbolically, in CasADi.

Everything that simulates or identifies builds on `build_plant`: the simulator and the
virtual rig (command drive, with effects as truth), the identifier (either drive, with
effects as candidates). Unmodelled effects (sim.effects) and friction models (sim.friction_models) are composable
extensions (sim.extension) that hook into named stages of the signal flow; the nominal
equations below never fork. The flow laws live in sim.flow.
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from typing import Sequence

import casadi as ca

from .cylinder import PARAMETERS, Cylinder
from .extension import Effect, Signals, check_combination
from .flow import G, KAPPA, R_AIR, mass_flow

NOMINAL_PARAMS: tuple[str, ...] = tuple(PARAMETERS)

DRIVES = ("command", "pressure")


@dataclass(frozen=True)
class Plant:
    """The plant's symbolic right-hand side for one drive.

    command drive: state (p1, p2, x, v, *effect states), input (u,)
    pressure drive: state (x, v, *mechanical effect states), input (p1, p2)
    Outputs are the measured states: (x, p1, p2) for the command drive, (x,) for the pressure drive.
    """

    drive: str
    effects: tuple[Effect, ...]
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    param_names: tuple[str, ...]
    rhs: ca.Function = field(repr=False)  # (state, input, params) -> dstate/dt
    friction: ca.Function = field(repr=False)  # (state, input, params) -> friction force

    @property
    def nx(self) -> int:
        return len(self.state_names)

    @property
    def structure_key(self) -> str:
        """Identifies the symbolic structure (not the values): the key of compiled-code caches."""
        desc = repr((self.drive, tuple(e.structure() for e in self.effects), self.param_names, MODEL_REVISION))
        return hashlib.sha256(desc.encode()).hexdigest()[:16]

    def parameter_vector(self, cyl: Cylinder) -> list[float]:
        vals = [cyl.value(n) for n in NOMINAL_PARAMS]
        for e in self.effects:
            vals.extend(e.values())
        return vals

    def initial_state(self, cyl: Cylinder, x0: float, p1: float, p2: float, v0: float = 0.0) -> list[float]:
        base = [p1, p2, x0, v0] if self.drive == "command" else [x0, v0]
        extra = [s0 for e in self.effects if _applies(e, self.drive) for s0 in e.initial_states(cyl, p1, p2, v0)]
        return base + extra


# Bump when the nominal equations change, so cached compiled code is rebuilt.
MODEL_REVISION = 1


def _applies(effect: Effect, drive: str) -> bool:
    return drive == "command" or effect.subsystem == "mechanical"


def build_plant(drive: str = "command", effects: Sequence[Effect] = ()) -> Plant:
    if drive not in DRIVES:
        raise ValueError(f"unknown drive {drive!r} (expected one of {DRIVES})")
    effects = tuple(effects)
    names = [e.name for e in effects]
    if len(set(names)) != len(names):
        raise ValueError(f"an effect is listed twice: {names}")
    check_combination(effects)
    active = [e for e in effects if _applies(e, drive)]

    param_names = list(NOMINAL_PARAMS)
    for e in effects:
        param_names.extend(e.key(n) for n in e.param_names())
    P = ca.SX.sym("P", len(param_names))
    par = dict(zip(param_names, ca.vertsplit(P)))

    D, d, L = par["bore"], par["rod"], par["stroke"]
    A1 = math.pi * D**2 / 4
    A2 = math.pi * (D**2 - d**2) / 4

    extra_states = [(e, s) for e in active for s in e.state_names()]
    if drive == "command":
        base_states = ["p1", "p2", "x", "v"]
        input_names = ["u"]
        output_names = ["x", "p1", "p2"]
    else:
        base_states = ["x", "v"]
        input_names = ["p1", "p2"]
        output_names = ["x"]
    state_names = base_states + [e.key(s) for e, s in extra_states]
    X = ca.SX.sym("X", len(state_names))
    U = ca.SX.sym("U", len(input_names))
    st = dict(zip(state_names, ca.vertsplit(X)))
    inp = dict(zip(input_names, ca.vertsplit(U)))

    p1 = st["p1"] if drive == "command" else inp["p1"]
    p2 = st["p2"] if drive == "command" else inp["p2"]
    sig = Signals(
        A1=A1, A2=A2, x=st["x"], v=st["v"], p1=p1, p2=p2, par=par,
        pa=par["atmosphere"], ps=par["supply_pressure"], T=par["temperature"],
        M=par["mass"], C=par["conductance"], b=par["critical_ratio"],
        V1=par["dead_volume_cap"] + A1 * st["x"],
        V2=par["dead_volume_rod"] + A2 * (L - st["x"]),
    )

    # each active effect's own parameter and state symbols, by their short names
    owned = {e.name: ({n: par[e.key(n)] for n in e.param_names()}, {n: st[e.key(n)] for n in e.state_names()})
             for e in active}

    def stage(hook: str) -> None:
        """Let every active effect act on the signals at one stage (see Signals), in order."""
        for e in active:
            getattr(e, hook)(sig, *owned[e.name])

    if drive == "command":
        sig.u = ca.fmin(ca.fmax(inp["u"], -1.0), 1.0)
        stage("on_command")
        stage("on_supply")
        c_pos = sig.C * ca.fmax(sig.u, 0.0)
        c_neg = sig.C * ca.fmax(-sig.u, 0.0)
        # supply -> chamber paths (drawn from the supply) and chamber <- exhaust paths
        sig.mdot_s1 = mass_flow(c_pos, sig.ps, p1, sig.b, sig.T)
        sig.mdot_s2 = mass_flow(c_neg, sig.ps, p2, sig.b, sig.T)
        sig.mdot1 = sig.mdot_s1 + mass_flow(c_neg, sig.pa, p1, sig.b, sig.T)
        sig.mdot2 = sig.mdot_s2 + mass_flow(c_pos, sig.pa, p2, sig.b, sig.T)
        sig.mdot_supply = sig.mdot_s1 + sig.mdot_s2  # net mass flow drawn from the supply
        stage("on_flows")

    # friction: every term opposes motion. Ff = Fseal * sgn + Fvisc, with the seal (Coulomb
    # plus pressure) level Fseal >= 0, the direction function sgn in [-1, 1] and the viscous
    # term Fvisc; on_friction_terms hooks reshape these before they are combined.
    v = sig.v
    sig.sgn = ca.tanh(v / par["v_smooth"])
    sig.Fseal = par["Fc"] + par["kp"] * ca.fabs(p1 - p2)
    sig.Fvisc = par["Fv"] * v
    stage("on_friction_terms")
    sig.Ff = sig.Fseal * sig.sgn + sig.Fvisc
    stage("on_friction")
    stage("on_piston")
    sig.dv = (p1 * A1 - p2 * A2 - sig.pa * (A1 - A2) - sig.Ff - sig.M * G * ca.sin(par["angle"])) / sig.M

    if drive == "command":
        sig.dp1 = KAPPA / sig.V1 * (R_AIR * sig.T * sig.mdot1 - p1 * A1 * v)
        sig.dp2 = KAPPA / sig.V2 * (R_AIR * sig.T * sig.mdot2 + p2 * A2 * v)
        stage("on_chambers")
        base_deriv = [sig.dp1, sig.dp2, v, sig.dv]
    else:
        base_deriv = [v, sig.dv]
    deriv = base_deriv + [sig.deriv[e.key(s)] for e, s in extra_states]

    return Plant(
        drive=drive,
        effects=effects,
        state_names=tuple(state_names),
        input_names=tuple(input_names),
        output_names=tuple(output_names),
        param_names=tuple(param_names),
        rhs=ca.Function("rhs", [X, U, P], [ca.vertcat(*deriv)], ["x", "u", "p"], ["xdot"]),
        friction=ca.Function("friction", [X, U, P], [sig.Ff], ["x", "u", "p"], ["Ff"]),
    )
