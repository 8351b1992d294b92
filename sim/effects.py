"""Unmodelled effects as composable extensions of the nominal plant.

An effect is a frozen dataclass whose fields are its parameter values. It hooks into
named stages of the plant's signal flow (command, supply, flows, friction, piston,
chambers), may add states of its own, and declares bounds for identification. The
virtual rig uses effects as truth; the identifier and the diagnosis use them as
candidates. Names follow the FORMATS.md vocabulary.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any, ClassVar, Mapping

import casadi as ca

from .plant import mass_flow


@dataclass(frozen=True)
class ParamInfo:
    unit: str
    lower: float
    upper: float
    description: str


@dataclass(frozen=True)
class Effect:
    name: ClassVar[str]
    subsystem: ClassVar[str]  # "mechanical" effects also apply to the pressure drive
    description: ClassVar[str]
    PARAMS: ClassVar[dict[str, ParamInfo]]
    STATES: ClassVar[tuple[str, ...]] = ()

    def param_names(self) -> tuple[str, ...]:
        return tuple(self.PARAMS)

    def values(self) -> list[float]:
        return [float(getattr(self, n)) for n in self.PARAMS]

    def state_names(self) -> tuple[str, ...]:
        return self.STATES

    def structure(self) -> tuple:
        """What changes the symbolic form (options, not parameter values)."""
        return (self.name,) + tuple((f.name, getattr(self, f.name)) for f in fields(self) if f.name not in self.PARAMS)

    def initial_states(self, cyl, p1: float, p2: float) -> list[float]:
        return [0.0] * len(self.STATES)

    def key(self, state: str) -> str:
        return f"{self.name}.{state}"

    # hooks: (signals, own parameter symbols, own state symbols); default: no change
    def on_command(self, sig, q, s) -> None: ...
    def on_supply(self, sig, q, s) -> None: ...
    def on_flows(self, sig, q, s) -> None: ...
    def on_friction(self, sig, q, s) -> None: ...
    def on_piston(self, sig, q, s) -> None: ...
    def on_chambers(self, sig, q, s) -> None: ...


@dataclass(frozen=True)
class Stiction(Effect):
    """Breakaway friction above the Coulomb level at low speed (Stribeck curve).

    Ff += Fs_excess * exp(-(v / v_stribeck)^2) * tanh(v / v_smooth)
    """

    name: ClassVar[str] = "stiction"
    subsystem: ClassVar[str] = "mechanical"
    description: ClassVar[str] = "breakaway friction above the Coulomb level at low speed"
    PARAMS: ClassVar[dict[str, ParamInfo]] = {
        "Fs_excess": ParamInfo("N", 0.0, 1e4, "static minus Coulomb friction"),
        "v_stribeck": ParamInfo("m/s", 1e-4, 1.0, "Stribeck velocity"),
    }
    Fs_excess: float = 10.0
    v_stribeck: float = 0.01

    def on_friction(self, sig, q, s) -> None:
        v = sig.v
        sig.Ff = sig.Ff + q["Fs_excess"] * ca.exp(-((v / q["v_stribeck"]) ** 2)) * ca.tanh(v / sig.par["v_smooth"])


@dataclass(frozen=True)
class ValveDelay(Effect):
    """The chambers see the command late: a first-order lag of the effective opening."""

    name: ClassVar[str] = "valve_delay"
    subsystem: ClassVar[str] = "pneumatic"
    description: ClassVar[str] = "the chambers see the valve command late"
    PARAMS: ClassVar[dict[str, ParamInfo]] = {"tau": ParamInfo("s", 1e-4, 0.2, "time constant of the valve opening")}
    STATES: ClassVar[tuple[str, ...]] = ("u_eff",)
    tau: float = 0.005

    def on_command(self, sig, q, s) -> None:
        sig.deriv[self.key("u_eff")] = (sig.u - s["u_eff"]) / q["tau"]
        sig.u = s["u_eff"]


@dataclass(frozen=True)
class Leakage(Effect):
    """Air leaks across the piston seal between the chambers (an orifice, ISO 6358 law)."""

    name: ClassVar[str] = "leakage"
    subsystem: ClassVar[str] = "pneumatic"
    description: ClassVar[str] = "air leaks across the piston seal between the chambers"
    PARAMS: ClassVar[dict[str, ParamInfo]] = {
        "conductance": ParamInfo("m^3/(s Pa)", 0.0, 1e-7, "sonic conductance of the leak path"),
    }
    conductance: float = 2e-10

    def on_flows(self, sig, q, s) -> None:
        m = mass_flow(q["conductance"], sig.p1, sig.p2, sig.b, sig.T)
        sig.mdot1 = sig.mdot1 - m
        sig.mdot2 = sig.mdot2 + m


EFFECTS: dict[str, type[Effect]] = {cls.name: cls for cls in (Stiction, ValveDelay, Leakage)}


def make_effect(name: str, values: Mapping[str, Any] | None = None) -> Effect:
    """An effect by its vocabulary word, with parameter values (others default)."""
    try:
        cls = EFFECTS[name]
    except KeyError:
        raise ValueError(f"unknown effect '{name}' (available: {', '.join(EFFECTS)})") from None
    values = dict(values or {})
    unknown = set(values) - set(cls.PARAMS)
    if unknown:
        raise ValueError(f"effect '{name}' has no parameter {', '.join(sorted(unknown))} "
                         f"(parameters: {', '.join(cls.PARAMS)})")
    for k, v in values.items():
        info = cls.PARAMS[k]
        if not (isinstance(v, (int, float)) and math.isfinite(v) and info.lower <= v <= info.upper):
            raise ValueError(f"effect parameter {name}.{k} = {v!r} is outside [{info.lower:g}, {info.upper:g}] {info.unit}")
    return cls(**{k: float(v) for k, v in values.items()})


def parse_effect_spec(spec: str) -> Effect:
    """'stiction:Fs_excess=8,v_stribeck=0.01' -> Stiction(8, 0.01) (command-line form)."""
    name, _, rest = spec.partition(":")
    values: dict[str, float] = {}
    for item in filter(None, rest.split(",")):
        k, eq, v = item.partition("=")
        if not eq:
            raise ValueError(f"effect parameter '{item}' must be written name=value")
        try:
            values[k.strip()] = float(v)
        except ValueError:
            raise ValueError(f"effect parameter {k.strip()} = '{v}' is not a number") from None
    return make_effect(name.strip(), values)
