"""The nominal servopneumatic plant of docs/model.md, written once, symbolically, in CasADi.

Everything that simulates or identifies builds on `build_plant`: the simulator and the
virtual rig (command drive, with effects as truth), the identifier (either drive, with
effects as candidates). Unmodelled effects (sim.effects) and friction models (sim.friction_models) are composable
extensions (sim.extension) that hook into named stages of the signal flow; the nominal
equations below never fork. The flow laws live in sim.flow.
"""
from __future__ import annotations

import functools
import hashlib
import math
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import casadi as ca
import numpy as np

from .cylinder import FLOW_CHARACTERISTIC, OPENING_GRID, PARAMETERS, VALVE_DIRECTIONS, Cylinder
from .extension import Effect, Signals, check_combination
from .flow import G, KAPPA, R_AIR, flow_characteristic, mass_flow

NOMINAL_PARAMS: tuple[str, ...] = tuple(PARAMETERS)

# command: the whole plant driven by the valve command; pressure: the piston alone, driven by
# the measured pressures; chambers: the valve and both chambers alone, driven by the command
# and the measured motion (position and its velocity)
DRIVES = ("command", "pressure", "chambers")
_BASE = {"command": (("p1", "p2", "x", "v"), ("u",), ("x", "p1", "p2")),
         "pressure": (("x", "v"), ("p1", "p2"), ("x",)),
         "chambers": (("p1", "p2"), ("u", "x", "v"), ("p1", "p2"))}


@dataclass(frozen=True)
class Plant:
    """The plant's symbolic right-hand side for one drive.

    command drive: state (p1, p2, x, v, *effect states), input (u,)
    pressure drive: state (x, v, *mechanical effect states), input (p1, p2)
    chambers drive: state (p1, p2, *pneumatic effect states), input (u, x, v)
    Outputs are the measured states: (x, p1, p2), (x,) and (p1, p2) respectively. Pressures,
    as states and as inputs, are what the sensors read (true pressure + the sensor's offset).
    """

    drive: str
    effects: tuple[Effect, ...]
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    param_names: tuple[str, ...]
    rhs: ca.Function = field(repr=False)  # (state, input, params) -> dstate/dt
    friction: ca.Function = field(repr=False)  # (state, input, params) -> friction force
    # the valve's flow characteristic in the equations; False: the linear law of the model
    # contract (C * command), its special case, at under half the cost of a step
    valve_curve: bool = True

    @property
    def nx(self) -> int:
        return len(self.state_names)

    @property
    def structure_key(self) -> str:
        """Identifies the symbolic structure (not the values): the key of compiled-code caches."""
        desc = repr((self.drive, tuple(e.structure() for e in self.effects), self.param_names, MODEL_REVISION,
                     OPENING_GRID if self.valve_curve else "linear valve"))
        return hashlib.sha256(desc.encode()).hexdigest()[:16]

    def parameter_vector(self, cyl: Cylinder) -> list[float]:
        if not self.valve_curve and not cyl.valve.is_linear:
            raise ValueError(f"{cyl.name}: its valve has a flow characteristic (overlap or curve), but this plant "
                             "was built for the linear valve law; build it with plant_for(cyl, ...)")
        vals = [cyl.value(n) for n in NOMINAL_PARAMS]
        for e in self.effects:
            vals.extend(e.values())
        return vals

    def possible_states(self, cyl: Cylinder) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper): per state, a range no state of this cylinder can leave, with a wide
        margin (pressures between minus and ten times the supply, the piston within a stroke of
        its travel, slower than 100 m/s; effect states unbounded). A solver's trial point outside
        it is one whose simulation diverges, and rejected without one."""
        ps, L = cyl.value("supply_pressure"), cyl.value("stroke")
        wide = {"p1": (-ps, 10 * ps), "p2": (-ps, 10 * ps), "x": (-L, 2 * L), "v": (-100.0, 100.0)}
        lo, hi = zip(*(wide.get(n, (-np.inf, np.inf)) for n in self.state_names))
        return np.array(lo), np.array(hi)

    def initial_state(self, cyl: Cylinder, x0: float, p1: float, p2: float, v0: float = 0.0) -> list[float]:
        """The state at a measured (x, v, p1, p2): pressures as the sensors read them."""
        known = {"p1": p1, "p2": p2, "x": x0, "v": v0}
        base = [known[n] for n in _BASE[self.drive][0]]
        extra = [s0 for e in self.effects if _applies(e, self.drive) for s0 in e.initial_states(cyl, p1, p2, v0)]
        return base + extra


# Bump when the nominal equations change, so cached compiled code is rebuilt.
MODEL_REVISION = 2


def _applies(effect: Effect, drive: str) -> bool:
    return drive == "command" or (effect.subsystem == "mechanical") == (drive == "pressure")


def valve_conductance(C, a, overlap, rises):
    """Sonic conductance of a path at the command magnitude a in [0, 1]: closed up to the
    overlap, then C times the flow characteristic of the opening s beyond it: the monotone
    piecewise-cubic (PCHIP) curve through (0, 0) and the levels its `rises` reach at the
    OPENING_GRID openings (sim.flow.flow_characteristic). Smooth and monotone; the defaults
    (rises the segment widths) give C * a exactly, since the interpolant of a straight line is
    that line."""
    s = ca.fmax(a - overlap, 0.0) / (1.0 - overlap)
    return C * flow_characteristic(s, rises, OPENING_GRID)


def end_stop_force(x, v, stroke, stiffness, damping):
    """The end stops: a stiff, damped contact beyond x = 0 and x = stroke, nothing between."""
    below = -stiffness * x - damping * v
    above = -stiffness * (x - stroke) - damping * v
    return ca.if_else(x < 0, below, ca.if_else(x > stroke, above, 0.0))


def plant_for(cyl: Cylinder, drive: str = "command", effects: Sequence[Effect] = (),
              estimate: Sequence[str] = ()) -> Plant:
    """The plant for `cyl`: the valve's flow characteristic in the equations only where the
    cylinder has one or it is to be estimated (the linear law is its cheaper special case)."""
    curve = not cyl.valve.is_linear or any(n in FLOW_CHARACTERISTIC for n in estimate)
    return build_plant(drive, effects, valve_curve=curve)


def build_plant(drive: str = "command", effects: Sequence[Effect] = (), valve_curve: bool = True) -> Plant:
    """The plant for one drive with `effects`; `valve_curve` False builds the linear valve law
    (conductance C * command) instead of the flow characteristic, for cylinders without one."""
    if drive not in DRIVES:
        raise ValueError(f"unknown drive {drive!r} (expected one of {DRIVES})")
    effects = tuple(effects)
    names = [e.name for e in effects]
    if len(set(names)) != len(names):
        raise ValueError(f"an effect is listed twice: {names}")
    check_combination(effects)
    # effect values are parameters (inputs), never part of the equations: one symbolic build
    # serves every value. A validation fits 20-60 segments of one model, and rebuilding took a
    # fifth of its time
    built = _symbolic_plant(_Structure(drive, tuple((type(e), e.structure()) for e in effects), valve_curve, effects))
    return replace(built, effects=effects)


@dataclass(frozen=True)
class _Structure:
    """What a plant's equations depend on; `effects` (any values) only build them."""

    drive: str
    key: tuple
    valve_curve: bool
    effects: tuple[Effect, ...] = field(compare=False, hash=False)


@functools.lru_cache(maxsize=128)
def _symbolic_plant(structure: _Structure) -> Plant:
    drive, effects, valve_curve = structure.drive, structure.effects, structure.valve_curve
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
    base_states, input_names, output_names = _BASE[drive]
    state_names = [*base_states, *(e.key(s) for e, s in extra_states)]
    X = ca.SX.sym("X", len(state_names))
    U = ca.SX.sym("U", len(input_names))
    known = {**dict(zip(input_names, ca.vertsplit(U))), **dict(zip(state_names, ca.vertsplit(X)))}
    st = {n: known[n] for n in state_names}

    # the pressures the plant works with are the true ones: a sensor reads true + offset
    p1 = known["p1"] - par["offset_p1"]
    p2 = known["p2"] - par["offset_p2"]
    x, v = known["x"], known["v"]
    sig = Signals(
        A1=A1, A2=A2, x=x, v=v, p1=p1, p2=p2, par=par,
        pa=par["atmosphere"], ps=par["supply_pressure"], T=par["temperature"],
        M=par["mass"], C=par["conductance"], b=par["critical_ratio"],
        V1=par["dead_volume_cap"] + A1 * x,
        V2=par["dead_volume_rod"] + A2 * (L - x),
    )

    # each active effect's own parameter and state symbols, by their short names
    owned = {e.name: ({n: par[e.key(n)] for n in e.param_names()}, {n: st[e.key(n)] for n in e.state_names()})
             for e in active}

    def stage(hook: str) -> None:
        """Let every active effect act on the signals at one stage (see Signals), in order."""
        for e in active:
            getattr(e, hook)(sig, *owned[e.name])

    pneumatic = drive != "pressure"
    mechanical = drive != "chambers"
    if pneumatic:
        _valve_flows(sig, known["u"], valve_curve, stage)
    sig.Ff = 0.0
    if mechanical:
        _piston_acceleration(sig, L, stage)

    derivs = {"x": v}
    if mechanical:
        derivs["v"] = sig.dv
    if pneumatic:
        sig.dp1 = KAPPA / sig.V1 * (R_AIR * sig.T * sig.mdot1 - p1 * A1 * v)
        sig.dp2 = KAPPA / sig.V2 * (R_AIR * sig.T * sig.mdot2 + p2 * A2 * v)
        stage("on_chambers")
        derivs.update(p1=sig.dp1, p2=sig.dp2)
    deriv = [derivs[n] for n in base_states] + [sig.deriv[e.key(s)] for e, s in extra_states]

    return Plant(
        drive=drive,
        effects=effects,
        state_names=tuple(state_names),
        input_names=tuple(input_names),
        output_names=tuple(output_names),
        param_names=tuple(param_names),
        rhs=ca.Function("rhs", [X, U, P], [ca.vertcat(*deriv)], ["x", "u", "p"], ["xdot"]),
        friction=ca.Function("friction", [X, U, P], [ca.SX(sig.Ff)], ["x", "u", "p"], ["Ff"]),
        valve_curve=valve_curve,
    )


def _valve_flows(sig: Signals, u, valve_curve: bool, stage: Callable[[str], None]) -> None:
    """The valve's mass flows into the chambers (sig.mdot1, mdot2) and from the supply, from
    the command bounded to [-1, 1]; effects act on the command, the supply and the flows."""
    par, p1, p2 = sig.par, sig.p1, sig.p2
    sig.u = ca.fmin(ca.fmax(u, -1.0), 1.0)
    stage("on_command")
    stage("on_supply")
    openings = (ca.fmax(sig.u, 0.0), ca.fmax(-sig.u, 0.0))
    if valve_curve:
        c_pos, c_neg = (valve_conductance(sig.C, a, par[f"overlap_{d}"],
                                          [par[f"flow_{d}_{k + 1}"] for k in range(len(OPENING_GRID))])
                        for d, a in zip(VALVE_DIRECTIONS, openings))
    else:
        c_pos, c_neg = (sig.C * a for a in openings)
    # supply -> chamber paths (drawn from the supply) and chamber <- exhaust paths
    sig.mdot_s1 = mass_flow(c_pos, sig.ps, p1, sig.b, sig.T)
    sig.mdot_s2 = mass_flow(c_neg, sig.ps, p2, sig.b, sig.T)
    sig.mdot1 = sig.mdot_s1 + mass_flow(c_neg, sig.pa, p1, sig.b, sig.T)
    sig.mdot2 = sig.mdot_s2 + mass_flow(c_pos, sig.pa, p2, sig.b, sig.T)
    sig.mdot_supply = sig.mdot_s1 + sig.mdot_s2  # net mass flow drawn from the supply
    stage("on_flows")


def _piston_acceleration(sig: Signals, stroke, stage: Callable[[str], None]) -> None:
    """The friction (sig.Ff) and the piston's acceleration (sig.dv); effects act on the
    friction's terms, the friction and the piston's forces.

    Every friction term opposes motion: Ff = Fseal * sgn + Fvisc, with the seal (Coulomb plus
    pressure) level Fseal >= 0, the direction function sgn in [-1, 1] and the viscous term
    Fvisc; on_friction_terms hooks reshape these before they are combined."""
    par, x, v, p1, p2, A1, A2 = sig.par, sig.x, sig.v, sig.p1, sig.p2, sig.A1, sig.A2
    sig.sgn = ca.tanh(v / par["v_smooth"])
    sig.Fseal = par["Fc"] + par["kp"] * ca.fabs(p1 - p2)
    sig.Fvisc = par["Fv"] * v
    stage("on_friction_terms")
    sig.Ff = sig.Fseal * sig.sgn + sig.Fvisc
    stage("on_friction")
    sig.F_ext = par["external_force"]
    sig.F_end = end_stop_force(x, v, stroke, par["end_stiffness"], par["end_damping"])
    stage("on_piston")
    sig.dv = (p1 * A1 - p2 * A2 - sig.pa * (A1 - A2) - sig.Ff - sig.M * G * ca.sin(par["angle"])
              + sig.F_ext + sig.F_end) / sig.M
