"""An independent reference plant: a servopneumatic cylinder written from the physics in plain numpy.

The project's plant (CasADi, sim/) generates the truth of most benchmarks, so those only show
that the tool works in its own world. This module is the deliberate exception: a second
implementation of the same nominal physics, sharing no code with the project's plant, plus
what real rigs add on top of it, in mathematical forms that differ from the project's own
effect library. Later benchmarks use it as "the rig".

Nominal physics (SI units throughout; chamber 1 = cap side, chamber 2 = rod side):

    A1 = pi D^2 / 4,   A2 = pi (D^2 - d^2) / 4
    V1 = V01 + A1 x,   V2 = V02 + A2 (L - x)
    valve (5/3, closed centre): u > 0 opens supply -> 1 and 2 -> exhaust with C = Cmax f(u),
        u < 0 opens supply -> 2 and 1 -> exhaust with C = Cmax f(|u|); f(a) = a nominally
    ISO 6358 mass flow from pu to pd (back-flow negative), r = pd / pu:
        phi = 1 (r <= b),  sqrt(1 - ((r - b) / (1 - b))^2) (b < r <= 0.995),
              phi(0.995) (1 - r) / 0.005 (laminar end),   mdot = C pu rho0 sqrt(T0 / T) phi
    chambers (adiabatic):  dp1/dt = kappa / V1 (R T mdot1 - p1 A1 v)
                           dp2/dt = kappa / V2 (R T mdot2 + p2 A2 v)
    piston:  M dv/dt = p1 A1 - p2 A2 - pa (A1 - A2) - Ff - M g sin(angle) + F_end
             Ff = (Fc + kp |p1 - p2|) tanh(v / v_s) + Fv v
             F_end = -k_end (x - L) - c_end v beyond L, -k_end x - c_end v below 0, else 0

Integration: classical fixed-step RK4 with N substeps per sample period; N follows from an
upper bound of the plant's fastest rate (the friction band v_s, the laminar end of the valve,
end stops, effect states) so that every case of a batch is integrated stably and accurately.
A batch of independent cases is one set of numpy arrays (one value per case), so the Python
overhead is paid once per substep for the whole batch; the controller runs per case per sample.

Sampling follows the rig convention: the command latched at a tick is held until the next
tick (zero-order hold), and the command computed from a sample reaches the valve at the next
tick. Row k of a run (t = (k + 1) / rate) holds the sensors at t and the command held over
[t, t + 1 / rate).

    python benchmarks/reference_plant.py --config CYL.toml --duration 20 --seed 1 \\
        --effect stiction:exp:Fs_excess=10 --departure conductance_pos=0.8 -o run.csv
    python benchmarks/reference_plant.py --list          # every effect form and its parameters
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
import time
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Callable, ClassVar, Mapping, Sequence

import numpy as np
from scipy.linalg import expm

if __name__ == "__main__":  # run as a script: make the project's packages importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from combined_reality.files import Run, cylinder_tag, read_run, write_run  # noqa: E402
from sim.cylinder import Cylinder, cylinder_to_toml, load_cylinder, parse_cylinder  # noqa: E402

__all__ = ["Case", "Calibration", "SensorDepartures", "Effect", "Param", "EFFECT_FORMS", "TIME_FORMS", "WORDS",
           "FrictionSchedule", "make_effect",
           "forms_of", "parse_effect", "random_effect", "ValveShape", "Linear", "PowerLaw", "Smoothstep", "Logistic",
           "Progressive", "SHAPES", "make_shape", "random_shape", "Result", "simulate", "simulate_detailed",
           "sensor_noise", "cached_runs", "cached_states",
           "substeps_for", "main"]

# ------------------------------------------------------------------ constants of the physics

RHO0 = 1.185  # kg/m^3, ISO 6358 reference density
T_REF = 293.15  # K, ISO 6358 reference temperature
R_LAM = 0.995  # pressure ratio where the flow function turns laminar (finite slope at r = 1)
KAPPA = 1.4  # ratio of specific heats of air
R_GAS = 287.0  # J/(kg K)
GRAVITY = 9.81  # m/s^2
K_END = 1.0e6  # N/m, end stop stiffness
C_END = 2.0e3  # N s/m, end stop damping

# RK4 is stable up to |lambda h| ~ 2.8 on the negative real axis; the bound of lambda is
# taken at the largest possible pressure difference, so 2.0 keeps a margin (tests show the
# trajectory is then converged to nanometres: halving the step changes nothing visible).
SAFETY = 2.0
TABLE_POINTS = 4097  # valve characteristics are tabulated on this many points of |u| in [0, 1]
# where RK4's stages lie within a substep, as fractions of it (positions (k, i, j) of the right-
# hand side index this): strictly inside, so a held or delayed command is looked up in the
# sample interval the stage belongs to
STAGES = (1e-6, 0.5, 1.0 - 1e-6)


# ------------------------------------------------------------------ valve characteristics


@dataclass(frozen=True)
class ValveShape:
    """A valve flow characteristic f(a), a = |u| in [0, 1]: the fraction of full conductance.

    f(a) = 0 up to the spool overlap o, then g((a - o) / (1 - o)) with g(0) = 0, g(1) = 1,
    g monotone: so f(0) = 0, f(1) = 1 and f is monotone for every subclass.
    """

    SHAPE: ClassVar[str] = ""
    overlap: float = 0.0  # 1, command below which the path stays closed

    def g(self, z: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def __call__(self, a):
        a = np.clip(np.asarray(a, float), 0.0, 1.0)
        o = self.overlap
        z = np.clip((a - o) / (1.0 - o), 0.0, 1.0)
        return self.g(z)

    def to_dict(self) -> dict[str, Any]:
        return {"shape": self.SHAPE, **{f.name: getattr(self, f.name) for f in fields(self)}}

    def __post_init__(self) -> None:
        if not 0.0 <= self.overlap < 0.5:
            raise ValueError(f"valve shape {self.SHAPE}: overlap must lie in [0, 0.5), not {self.overlap:g}.")


@dataclass(frozen=True)
class Linear(ValveShape):
    """g(z) = z: the nominal characteristic (with an overlap: a linear valve with a dead band)."""

    SHAPE: ClassVar[str] = "linear"

    def g(self, z):
        return z


@dataclass(frozen=True)
class PowerLaw(ValveShape):
    """g(z) = z^gamma: gamma > 1 opens slowly near centre (progressive), gamma < 1 quickly."""

    SHAPE: ClassVar[str] = "power"
    exponent: float = 1.5

    def g(self, z):
        return z ** self.exponent


@dataclass(frozen=True)
class Smoothstep(ValveShape):
    """g(z) = (1 - w) z + w (3 z^2 - 2 z^3): an S-shape, flat near closed and near full opening
    (w in [0, 1]; g' = 1 - w + 6 w z (1 - z) >= 0)."""

    SHAPE: ClassVar[str] = "smoothstep"
    weight: float = 0.6

    def g(self, z):
        w = self.weight
        return (1.0 - w) * z + w * z * z * (3.0 - 2.0 * z)


@dataclass(frozen=True)
class Logistic(ValveShape):
    """g(z) = (s(k (z - c)) - s(-k c)) / (s(k (1 - c)) - s(-k c)), s the logistic function:
    an S-shape steepest at z = c (steepness k)."""

    SHAPE: ClassVar[str] = "logistic"
    steepness: float = 8.0
    centre: float = 0.5

    def g(self, z):
        k, c = self.steepness, self.centre

        def s(y):
            return 1.0 / (1.0 + np.exp(-y))

        lo, hi = s(-k * c), s(k * (1.0 - c))
        return (s(k * (z - c)) - lo) / (hi - lo)


@dataclass(frozen=True)
class Progressive(ValveShape):
    """Two slopes with a smooth knee: h(z) = z + (q - 1) w softplus((z - z_k) / w),
    g = (h(z) - h(0)) / (h(1) - h(0)); the slope above the knee z_k is q times the slope
    below it (q > 1 progressive, q < 1 degressive), the knee rounded over about w."""

    SHAPE: ClassVar[str] = "progressive"
    knee: float = 0.4
    ratio: float = 2.5
    width: float = 0.05

    def g(self, z):
        def h(y):
            return y + (self.ratio - 1.0) * self.width * np.logaddexp(0.0, (y - self.knee) / self.width)

        h0, h1 = h(0.0), h(1.0)
        return (h(z) - h0) / (h1 - h0)


SHAPES: dict[str, type[ValveShape]] = {c.SHAPE: c for c in (Linear, PowerLaw, Smoothstep, Logistic, Progressive)}
# realistic spans of the shape parameters for random draws
_SHAPE_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "power": {"exponent": (0.6, 2.0)},
    "smoothstep": {"weight": (0.2, 1.0)},
    "logistic": {"steepness": (4.0, 12.0), "centre": (0.3, 0.7)},
    "progressive": {"knee": (0.2, 0.7), "ratio": (0.3, 3.0)},
}


def make_shape(spec: Mapping[str, Any] | str) -> ValveShape:
    """A valve shape from its dict ({"shape": "power", "exponent": 1.5, "overlap": 0.05}) or from
    'power,exponent=1.5,overlap=0.05'."""
    if isinstance(spec, str):
        name, _, rest = spec.partition(",")
        d: dict[str, Any] = {"shape": name.strip()}
        d.update(_parse_kv(rest))
        spec = d
    spec = dict(spec)
    name = spec.pop("shape", None)
    if name not in SHAPES:
        raise ValueError(f"unknown valve shape {name!r} (known: {', '.join(SHAPES)}).")
    return SHAPES[name](**{k: float(v) for k, v in spec.items()})


def random_shape(rng: np.random.Generator, max_overlap: float = 0.1) -> ValveShape:
    """A random non-linear characteristic; half of them with an overlap up to `max_overlap`."""
    name = ("power", "smoothstep", "logistic", "progressive")[rng.integers(4)]
    params = {k: float(rng.uniform(lo, hi)) for k, (lo, hi) in _SHAPE_RANGES[name].items()}
    overlap = float(rng.uniform(0.0, max_overlap)) if rng.random() < 0.5 else 0.0
    return SHAPES[name](overlap=overlap, **params)


def _tabulate(f: Callable | None) -> np.ndarray:
    """The characteristic on the table grid, checked: f(0) = 0, f(1) = 1, monotone, finite."""
    a = np.linspace(0.0, 1.0, TABLE_POINTS)
    if f is None:
        return a
    y = np.asarray(f(a), float)
    if y.shape != a.shape:  # a scalar callable: call it point by point
        y = np.array([float(f(float(ai))) for ai in a])
    if not np.all(np.isfinite(y)):
        raise ValueError("valve characteristic: not finite on [0, 1].")
    if abs(y[0]) > 1e-9 or abs(y[-1] - 1.0) > 1e-9:
        raise ValueError(f"valve characteristic: needs f(0) = 0 and f(1) = 1, got {y[0]:g} and {y[-1]:g}.")
    if np.any(np.diff(y) < -1e-12):
        raise ValueError("valve characteristic: not monotone on [0, 1].")
    y[0], y[-1] = 0.0, 1.0
    return y


def _shape_to_json(f: Callable | None) -> dict[str, Any] | None:
    if f is None:
        return None
    if isinstance(f, ValveShape):
        return f.to_dict()
    raise TypeError(f"valve characteristic {f!r} is an arbitrary callable and cannot be serialised "
                    "(use a named shape: " + ", ".join(SHAPES) + ").")


def _shape_to_table(f: Callable | None) -> Any:
    """For truth tables: the shape's dict, 'linear', or the callable's repr."""
    if f is None:
        return "linear"
    return f.to_dict() if isinstance(f, ValveShape) else repr(f)


# ------------------------------------------------------------------ calibration and sensor departures


@dataclass(frozen=True)
class Calibration:
    """What a cylinder file only guesses; None or neutral values keep the file's value.

    The valve's conductance of the paths opened by u > 0 is Cmax * conductance_pos *
    characteristic_pos(u) (likewise for u < 0); characteristics are callables f(|u|) with
    f(0) = 0, f(1) = 1, monotone (named ValveShape objects serialise, arbitrary callables do not).
    Pressure sensors read true + offset. external_force is a constant force on the piston,
    positive in the extension direction. In the simulation a characteristic is tabulated on
    TABLE_POINTS points of |u| and interpolated linearly between them.
    """

    conductance_pos: float = 1.0  # 1, multiplier of the file's Cmax for u > 0
    conductance_neg: float = 1.0  # 1, multiplier of the file's Cmax for u < 0
    critical_ratio: float | None = None  # 1
    characteristic_pos: Callable | None = None
    characteristic_neg: Callable | None = None
    dead_volume_cap: float | None = None  # m^3
    dead_volume_rod: float | None = None  # m^3
    moving_mass: float | None = None  # kg
    offset_p1: float = 0.0  # Pa
    offset_p2: float = 0.0  # Pa
    external_force: float = 0.0  # N

    def resolved(self, cyl: Cylinder) -> dict[str, Any]:
        """Every value in SI, the file's where this calibration keeps it (for truth tables)."""
        g = cyl.geometry
        return {
            "conductance_pos": cyl.valve.sonic_conductance * self.conductance_pos,
            "conductance_neg": cyl.valve.sonic_conductance * self.conductance_neg,
            "conductance_scale_pos": self.conductance_pos, "conductance_scale_neg": self.conductance_neg,
            "critical_ratio": self.b(cyl),
            "characteristic_pos": _shape_to_table(self.characteristic_pos),
            "characteristic_neg": _shape_to_table(self.characteristic_neg),
            "dead_volume_cap": _or(self.dead_volume_cap, g.dead_volume_cap),
            "dead_volume_rod": _or(self.dead_volume_rod, g.dead_volume_rod),
            "moving_mass": _or(self.moving_mass, cyl.mechanics.moving_mass),
            "offset_p1": self.offset_p1, "offset_p2": self.offset_p2, "external_force": self.external_force,
        }

    def b(self, cyl: Cylinder) -> float:
        return _or(self.critical_ratio, cyl.valve.critical_ratio)

    def to_json(self) -> dict[str, Any]:
        d: dict[str, Any] = {f.name: getattr(self, f.name) for f in fields(self)}
        d["characteristic_pos"] = _shape_to_json(self.characteristic_pos)
        d["characteristic_neg"] = _shape_to_json(self.characteristic_neg)
        return d

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> "Calibration":
        d = dict(d)
        for k in ("characteristic_pos", "characteristic_neg"):
            if d.get(k) is not None:
                d[k] = make_shape(d[k])
        _check_keys(cls, d, "calibration")
        return cls(**d)

    @classmethod
    def random(cls, rng: np.random.Generator, cyl: Cylinder, which: Sequence[str] | None = None) -> "Calibration":
        """Realistic departures of a real rig from its file: conductance scales 0.6-1.4 per
        direction, b in 0.2-0.5, random non-linear characteristics (half with an overlap up to
        0.1), dead volumes 0.5-2x, mass 0.8-1.5x, sensor offsets up to 3 kPa, an external force
        up to 3 % of the piston's full force. `which` limits the draw to some fields."""
        g, m = cyl.geometry, cyl.mechanics
        force = g.area_cap * (cyl.supply.pressure - cyl.supply.atmosphere)
        draws = {
            "conductance_pos": lambda: float(rng.uniform(0.6, 1.4)),
            "conductance_neg": lambda: float(rng.uniform(0.6, 1.4)),
            "critical_ratio": lambda: float(rng.uniform(0.2, 0.5)),
            "characteristic_pos": lambda: random_shape(rng),
            "characteristic_neg": lambda: random_shape(rng),
            "dead_volume_cap": lambda: g.dead_volume_cap * float(np.exp(rng.uniform(np.log(0.5), np.log(2.0)))),
            "dead_volume_rod": lambda: g.dead_volume_rod * float(np.exp(rng.uniform(np.log(0.5), np.log(2.0)))),
            "moving_mass": lambda: m.moving_mass * float(rng.uniform(0.8, 1.5)),
            "offset_p1": lambda: float(rng.uniform(-3e3, 3e3)),
            "offset_p2": lambda: float(rng.uniform(-3e3, 3e3)),
            "external_force": lambda: float(rng.uniform(-0.03, 0.03)) * force,
        }
        which = list(draws) if which is None else list(which)
        unknown = [w for w in which if w not in draws]
        if unknown:
            raise ValueError(f"unknown calibration field(s) {unknown} (known: {', '.join(draws)}).")
        return cls(**{k: draws[k]() for k in which})


@dataclass(frozen=True)
class SensorDepartures:
    """Sensor errors outside the tool's vocabulary (the diagnosis should call them unexplained).

    x_meas = (1 + position_gain) x
    p_meas = pa + (1 + pressure_gain_i) (p_lag_i - pa) + offset_i,  dp_lag/dt = (p - p_lag) / pressure_lag
    (a gauge transducer's gain error; pressure_lag = 0: no lag)."""

    position_gain: float = 0.0  # 1
    pressure_lag: float = 0.0  # s
    pressure_gain_p1: float = 0.0  # 1
    pressure_gain_p2: float = 0.0  # 1

    def to_json(self) -> dict[str, float]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> "SensorDepartures":
        _check_keys(cls, d, "sensors")
        return cls(**d)

    @classmethod
    def random(cls, rng: np.random.Generator) -> "SensorDepartures":
        """Position gain error 0.5-3 %, a pressure sensor lag of 1-8 ms, gain errors up to 2 %."""
        return cls(position_gain=float(rng.choice([-1, 1]) * rng.uniform(0.005, 0.03)),
                   pressure_lag=float(rng.uniform(1e-3, 8e-3)),
                   pressure_gain_p1=float(rng.uniform(-0.02, 0.02)),
                   pressure_gain_p2=float(rng.uniform(-0.02, 0.02)))


def _or(value: float | None, default: float) -> float:
    return float(default if value is None else value)


def _check_keys(cls, d: Mapping[str, Any], what: str) -> None:
    names = {f.name for f in fields(cls)}
    unknown = [k for k in d if k not in names]
    if unknown:
        raise ValueError(f"unknown {what} field(s) {unknown} (known: {', '.join(sorted(names))}).")


# ------------------------------------------------------------------ effects


@dataclass(frozen=True)
class Param:
    """One effect parameter: unit, meaning and realistic range.

    kind "strength": (low, high) = (weak, strong), drawn log-uniformly; "signed": a strength
    of either sign; "shape": where, how wide, how fast; (low, high) is its realistic span,
    drawn uniformly. `scale` names a reference quantity of the cylinder that multiplies low
    and high (see _reference).

    Weak is "barely visible": on a 20 s closed-loop run of the default 32 x 100 cylinder
    (seed 5, 5 um / 300 Pa noise), the nominal model with (Fc, Fv, kp) re-identified by the
    project's identifier leaves a residual of about 1.3 (1.1 to 1.5) times the sensor noise
    (RMS of x, p1, p2 in units of their noise; 1.0 without the effect). Strong is a physically
    strong but realistic level. For the valve delays the weak end is faster than any real
    valve: every real spool is plainly visible."""

    unit: str
    description: str
    low: float
    high: float
    kind: str = "strength"
    scale: str | None = None
    positive: bool = True  # a shape that must be > 0 (strengths must be >= 0, signed ones any)


def _reference(cyl: Cylinder, what: str | None) -> float:
    """Cylinder quantities that set the size of an effect."""
    if what is None:
        return 1.0
    fr, s = cyl.friction, cyl.supply
    refs = {
        "seal": fr.Fc + fr.kp * 0.5 * (s.pressure - s.atmosphere),  # N, seal friction at half supply
        "coulomb": fr.Fc,  # N
        "viscous": max(fr.Fv, 1e-6),  # N s/m (a rig without viscous friction: a negligible span)
        "mass": cyl.mechanics.moving_mass,  # kg
        "stroke": cyl.geometry.stroke,  # m
        "valve_flow": cyl.valve.sonic_conductance * s.pressure,  # m^3/s (ANR) at full choked opening
        # N/Pa: the seal friction spread over half the supply span (so k * half span is relative to it)
        "seal_per_pressure": (fr.Fc / (0.5 * (s.pressure - s.atmosphere)) + fr.kp),
    }
    return refs[what]


class _Sig:
    """The signals of one evaluation of the right-hand side (arrays of one value per case)."""


@dataclass(frozen=True)
class Effect:
    """One unmodelled effect in one mathematical form. Fields are the parameter values (SI).

    Class attributes: WORD (the vocabulary word), FORM (the form's name), PARAMS, NEUTRAL (the
    values at which the effect vanishes exactly), STATES (extra state variables).

    Vectorised hooks are classmethods on P, a dict of parameter arrays (one value per case of a
    batch; cases without this form carry its neutral values), Y / dY (this form's rows of the
    state and its derivative) and s (the signals); a "sample" hook runs once per sample tick on
    P and the batch. Every hook is the identity at the neutral values, so forms compose and mix
    freely within one batch.
    """

    WORD: ClassVar[str] = ""
    FORM: ClassVar[str] = ""
    PARAMS: ClassVar[dict[str, Param]] = {}
    NEUTRAL: ClassVar[dict[str, float]] = {}
    STATES: ClassVar[tuple[str, ...]] = ()
    HOOKS: ClassVar[tuple[str, ...]] = ()

    # ---- description
    def values(self) -> dict[str, float]:
        return {f.name: float(getattr(self, f.name)) for f in fields(self)}

    def to_json(self) -> dict[str, Any]:
        return {"effect": self.WORD, "form": self.FORM, "params": self.values()}

    def is_neutral(self) -> bool:
        v = self.values()
        return all(v[k] == x for k, x in self.NEUTRAL.items())

    def check(self, cyl: Cylinder) -> None:
        """Raise ValueError for values that make no physical sense on this cylinder."""
        for k, x in self.values().items():
            p = self.PARAMS[k]
            if not math.isfinite(x):
                raise ValueError(f"{self.WORD}:{self.FORM}: parameter {k} must be finite, not {x}.")
            if p.kind == "strength" and x < 0 or p.kind == "shape" and p.positive and x <= 0:
                sign = ">=" if p.kind == "strength" else ">"
                raise ValueError(f"{self.WORD}:{self.FORM}: parameter {k} must be {sign} 0 ({p.description}), "
                                 f"not {x:g}.")

    @classmethod
    def neutral(cls) -> "Effect":
        return cls(**cls.NEUTRAL)

    @classmethod
    def ranges(cls, cyl: Cylinder) -> dict[str, tuple[float, float]]:
        """(low, high) of every parameter in SI for this cylinder (strengths: weak, strong)."""
        return {k: (p.low * _reference(cyl, p.scale), p.high * _reference(cyl, p.scale)) for k, p in cls.PARAMS.items()}

    @classmethod
    def typical(cls, cyl: Cylinder, level: float = 0.5) -> "Effect":
        """Strengths at `level` between weak (0) and strong (1), geometrically; shapes at mid-span."""
        vals = {}
        for k, (lo, hi) in cls.ranges(cyl).items():
            kind = cls.PARAMS[k].kind
            vals[k] = 0.5 * (lo + hi) if kind == "shape" else lo * (hi / lo) ** level
        return cls._constrained(vals, cyl)

    @classmethod
    def random(cls, rng: np.random.Generator, cyl: Cylinder) -> "Effect":
        """Realistic random values: strengths log-uniform from weak to strong (signed ones with a
        random sign), shapes uniform over their span."""
        vals = {}
        for k, (lo, hi) in cls.ranges(cyl).items():
            kind = cls.PARAMS[k].kind
            if kind == "shape":
                vals[k] = float(rng.uniform(lo, hi))
            else:
                vals[k] = float(np.exp(rng.uniform(math.log(lo), math.log(hi))))
                if kind == "signed" and rng.random() < 0.5:
                    vals[k] = -vals[k]
        return cls._constrained(vals, cyl)

    @classmethod
    def _constrained(cls, vals: dict[str, float], cyl: Cylinder) -> "Effect":
        """Bring random or typical values within the form's physical limits (override per form)."""
        return cls(**vals)

    # ---- vectorised physics (defaults: no states, no hooks)
    @classmethod
    def prepare(cls, P: dict[str, np.ndarray], c) -> None:
        """Derived arrays of the batch (stored in P under names starting with '_')."""

    @classmethod
    def prepare_step(cls, P: dict[str, np.ndarray], c) -> None:
        """Derived arrays that need the integration step (c.N, c.h)."""

    @classmethod
    def init_states(cls, P, s) -> np.ndarray:
        return np.zeros((len(cls.STATES), s.c.n))

    @classmethod
    def rate(cls, P, c) -> np.ndarray:
        """An upper bound of this form's fastest rate (1/s) per case, for the integration step."""
        return np.zeros(c.n)

    @classmethod
    def friction_level(cls, P, c) -> np.ndarray:
        """Friction (N) this form adds within the smoothing band |v| < v_s, for the step."""
        return np.zeros(c.n)


# ---- stiction


@dataclass(frozen=True)
class StictionExp(Effect):
    """Breakaway friction with an exponential (exponent 1) Stribeck decay, an absolute level:

        Ff += Fs_excess exp(-|v| / v_stribeck) tanh(v / v_s)
    """

    WORD: ClassVar[str] = "stiction"
    FORM: ClassVar[str] = "exp"
    PARAMS: ClassVar[dict[str, Param]] = {
        "Fs_excess": Param("N", "static minus Coulomb friction", 0.015, 1.0, scale="seal"),
        "v_stribeck": Param("m/s", "Stribeck velocity (1/e decay)", 0.002, 0.02, "shape"),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"Fs_excess": 0.0}
    HOOKS: ClassVar[tuple[str, ...]] = ("friction",)
    Fs_excess: float = 10.0
    v_stribeck: float = 0.005

    @classmethod
    def friction(cls, P, Y, dY, s):
        s.Ff = s.Ff + P["Fs_excess"] * np.exp(-np.abs(s.v) / P["v_stribeck"]) * s.sgn

    @classmethod
    def friction_level(cls, P, c):
        return np.abs(P["Fs_excess"])


@dataclass(frozen=True)
class StictionRational(Effect):
    """Breakaway friction proportional to the seal level (so it grows with the pressure
    difference), with a rational (Lorentzian) Stribeck decay:

        Ff += ratio (Fc + kp |p1 - p2|) tanh(v / v_s) / (1 + (v / v_stribeck)^2)
    """

    WORD: ClassVar[str] = "stiction"
    FORM: ClassVar[str] = "rational"
    PARAMS: ClassVar[dict[str, Param]] = {
        "ratio": Param("1", "static friction excess relative to the seal friction", 0.015, 1.0),
        "v_stribeck": Param("m/s", "Stribeck velocity (half decay)", 0.002, 0.02, "shape"),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"ratio": 0.0}
    HOOKS: ClassVar[tuple[str, ...]] = ("friction",)
    ratio: float = 0.4
    v_stribeck: float = 0.005

    @classmethod
    def friction(cls, P, Y, dY, s):
        q = s.v / P["v_stribeck"]
        s.Ff = s.Ff + P["ratio"] * s.Fseal * s.sgn / (1.0 + q * q)

    @classmethod
    def friction_level(cls, P, c):
        return np.abs(P["ratio"]) * (c.Fc + c.kp * (c.ps - c.pa))


# ---- friction asymmetry


@dataclass(frozen=True)
class AsymmetryLevels(Effect):
    """Separate Coulomb and viscous levels per direction (absolute; extension gets +, retraction -):

        Fc -> Fc + dFc sgn,  Fv -> Fv + dFv sign(v)
        Ff += dFc tanh(v / v_s)^2 + dFv |v|
    """

    WORD: ClassVar[str] = "friction_asymmetry"
    FORM: ClassVar[str] = "levels"
    PARAMS: ClassVar[dict[str, Param]] = {
        "dFc": Param("N", "Coulomb friction of extension minus the mean", 0.005, 0.5, "signed", "coulomb"),
        "dFv": Param("N s/m", "viscous coefficient of extension minus the mean", 0.005, 0.7, "signed", "viscous"),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"dFc": 0.0, "dFv": 0.0}
    HOOKS: ClassVar[tuple[str, ...]] = ("friction",)
    dFc: float = 5.0
    dFv: float = 5.0

    @classmethod
    def _constrained(cls, vals, cyl):
        # no direction may get a negative level
        vals["dFc"] = float(np.clip(vals["dFc"], -0.9 * cyl.friction.Fc, 0.9 * cyl.friction.Fc))
        vals["dFv"] = float(np.clip(vals["dFv"], -0.9 * cyl.friction.Fv, 0.9 * cyl.friction.Fv))
        return cls(**vals)

    @classmethod
    def friction(cls, P, Y, dY, s):
        s.Ff = s.Ff + P["dFc"] * s.sgn * s.sgn + P["dFv"] * np.abs(s.v)

    @classmethod
    def friction_level(cls, P, c):
        return np.abs(P["dFc"])


@dataclass(frozen=True)
class AsymmetryPressureSide(Effect):
    """The seal's pressure coefficient depends on which side is pressurised (a lip seal is
    pressed harder from one side): kp -> kp + k_side sign(p1 - p2), i.e.

        Ff += k_side (p1 - p2) tanh(v / v_s)

    While extending p1 > p2 mostly, while retracting p2 > p1: friction differs by direction.
    """

    WORD: ClassVar[str] = "friction_asymmetry"
    FORM: ClassVar[str] = "pressure_side"
    PARAMS: ClassVar[dict[str, Param]] = {
        "k_side": Param("N/Pa", "extra seal-pressure coefficient with the cap side pressurised",
                        0.07, 0.6, "signed", "seal_per_pressure"),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"k_side": 0.0}
    HOOKS: ClassVar[tuple[str, ...]] = ("friction",)
    k_side: float = 1e-5

    @classmethod
    def _constrained(cls, vals, cyl):
        # the seal level Fc + (kp +- k_side)|dp| must stay >= 0 over the supply span
        lim = 0.9 * (cyl.friction.kp + cyl.friction.Fc / (cyl.supply.pressure - cyl.supply.atmosphere))
        return cls(k_side=float(np.clip(vals["k_side"], -lim, lim)))

    @classmethod
    def friction(cls, P, Y, dY, s):
        s.Ff = s.Ff + P["k_side"] * (s.p1 - s.p2) * s.sgn

    @classmethod
    def friction_level(cls, P, c):
        return np.abs(P["k_side"]) * (c.ps - c.pa)


# ---- friction along the stroke


@dataclass(frozen=True)
class PositionTight(Effect):
    """A tight section between x_from and x_to with soft (tanh) edges of width `edge`:

        Ff += dF / 2 (tanh((x - x_from) / edge) - tanh((x - x_to) / edge)) tanh(v / v_s)
    """

    WORD: ClassVar[str] = "friction_position"
    FORM: ClassVar[str] = "tight"
    PARAMS: ClassVar[dict[str, Param]] = {
        "dF": Param("N", "extra friction inside the tight section", 0.008, 1.0, scale="seal"),
        "x_from": Param("m", "start of the section", 0.15, 0.55, "shape", "stroke", positive=False),
        "x_to": Param("m", "end of the section", 0.45, 0.85, "shape", "stroke", positive=False),
        "edge": Param("m", "width of the section's edges", 0.005, 0.05, "shape", "stroke"),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"dF": 0.0}
    HOOKS: ClassVar[tuple[str, ...]] = ("friction",)
    dF: float = 10.0
    x_from: float = 0.03
    x_to: float = 0.06
    edge: float = 0.002

    @classmethod
    def _constrained(cls, vals, cyl):
        lo, hi = sorted((vals["x_from"], vals["x_to"]))
        if hi - lo < 0.1 * cyl.geometry.stroke:  # a section at least a tenth of the stroke long
            mid = 0.5 * (lo + hi)
            lo, hi = mid - 0.05 * cyl.geometry.stroke, mid + 0.05 * cyl.geometry.stroke
        return cls(dF=vals["dF"], x_from=lo, x_to=hi, edge=vals["edge"])

    @classmethod
    def friction(cls, P, Y, dY, s):
        e = P["edge"]
        bump = 0.5 * P["dF"] * (np.tanh((s.x - P["x_from"]) / e) - np.tanh((s.x - P["x_to"]) / e))
        s.Ff = s.Ff + bump * s.sgn

    @classmethod
    def friction_level(cls, P, c):
        return np.abs(P["dF"])


@dataclass(frozen=True)
class PositionWave(Effect):
    """A sinusoidal wear profile of the whole seal level along the stroke:

        Ff += a (Fc + kp |p1 - p2|) sin(2 pi x / wavelength + phase) tanh(v / v_s),   |a| < 1
    """

    WORD: ClassVar[str] = "friction_position"
    FORM: ClassVar[str] = "wave"
    PARAMS: ClassVar[dict[str, Param]] = {
        "a": Param("1", "relative amplitude of the seal friction's variation", 0.008, 0.8),
        "wavelength": Param("m", "wavelength of the profile", 0.4, 2.0, "shape", "stroke"),
        "phase": Param("rad", "phase at x = 0", 0.0, 2 * math.pi, "shape", positive=False),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"a": 0.0}
    HOOKS: ClassVar[tuple[str, ...]] = ("friction",)
    a: float = 0.3
    wavelength: float = 0.1
    phase: float = 0.0

    @classmethod
    def friction(cls, P, Y, dY, s):
        w = np.sin(2 * math.pi * s.x / P["wavelength"] + P["phase"])
        s.Ff = s.Ff + P["a"] * s.Fseal * w * s.sgn

    @classmethod
    def friction_level(cls, P, c):
        return np.abs(P["a"]) * (c.Fc + c.kp * (c.ps - c.pa))


# ---- friction with memory


@dataclass(frozen=True)
class DynamicsDahl(Effect):
    """A Dahl element carries F_d of the Coulomb friction (absolute, F_d <= Fc): its normalised
    force s follows the Dahl law with exponent alpha,

        ds/dt = v / x_d (1 - s sign(v))^alpha,       Ff += F_d (s - tanh(v / v_s))

    so after a reversal the friction builds up over a pre-sliding displacement ~x_d and holds
    static forces up to F_d without moving (hysteresis, pre-sliding)."""

    WORD: ClassVar[str] = "friction_dynamics"
    FORM: ClassVar[str] = "dahl"
    PARAMS: ClassVar[dict[str, Param]] = {
        "F_d": Param("N", "friction carried by the Dahl element", 0.015, 1.0, scale="coulomb"),
        "x_d": Param("m", "pre-sliding displacement", 1e-4, 5e-4, "shape"),
        "alpha": Param("1", "Dahl exponent (shape of the build-up)", 1.0, 1.5, "shape"),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"F_d": 0.0}
    STATES: ClassVar[tuple[str, ...]] = ("s",)
    HOOKS: ClassVar[tuple[str, ...]] = ("friction",)
    F_d: float = 10.0
    x_d: float = 2e-4
    alpha: float = 1.0

    @classmethod
    def _constrained(cls, vals, cyl):
        vals["F_d"] = min(vals["F_d"], cyl.friction.Fc)
        return cls(**vals)

    @classmethod
    def friction(cls, P, Y, dY, s):
        z = Y[0]
        base = np.maximum(1.0 - z * np.sign(s.v), 0.0)
        dY[0] = P["_active"] * s.v / P["x_d"] * base ** P["alpha"]
        s.Ff = s.Ff + P["F_d"] * (z - s.sgn)

    @classmethod
    def rate(cls, P, c):
        return P["alpha"] * 2.0 ** (P["alpha"] - 1.0) * c.v_bound / P["x_d"]


@dataclass(frozen=True)
class DynamicsMaxwell(Effect):
    """Maxwell-slip elements: four elasto-plastic elements share F_h of the Coulomb friction
    equally; element i has break-away displacement x_i = x_min spread^(i/3), i = 0..3. Each
    normalised force s_i is elastic after a reversal and saturates quadratically at +-1:

        ds_i/dt = v / x_i (1 - max(s_i sign(v), 0)^2),    Ff += F_h (mean_i s_i - tanh(v / v_s))
    """

    WORD: ClassVar[str] = "friction_dynamics"
    FORM: ClassVar[str] = "maxwell"
    PARAMS: ClassVar[dict[str, Param]] = {
        "F_h": Param("N", "friction carried by the slip elements", 0.012, 1.0, scale="coulomb"),
        "x_min": Param("m", "break-away displacement of the stiffest element", 1e-4, 3e-4, "shape"),
        "spread": Param("1", "ratio of the largest to the smallest break-away displacement", 3.0, 20.0, "shape"),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"F_h": 0.0}
    STATES: ClassVar[tuple[str, ...]] = ("s0", "s1", "s2", "s3")
    HOOKS: ClassVar[tuple[str, ...]] = ("friction",)
    F_h: float = 10.0
    x_min: float = 1e-4
    spread: float = 10.0

    @classmethod
    def _constrained(cls, vals, cyl):
        vals["F_h"] = min(vals["F_h"], cyl.friction.Fc)
        return cls(**vals)

    @classmethod
    def prepare(cls, P, c):
        i = np.arange(4)[:, None] / 3.0
        P["_inv_x"] = P["_active"] / (P["x_min"][None, :] * P["spread"][None, :] ** i)  # (4, n)

    @classmethod
    def friction(cls, P, Y, dY, s):
        sv = np.sign(s.v)
        sat = np.maximum(Y * sv, 0.0)
        dY[:] = s.v * P["_inv_x"] * (1.0 - sat * sat)
        s.Ff = s.Ff + P["F_h"] * (0.25 * Y.sum(axis=0) - s.sgn)

    @classmethod
    def rate(cls, P, c):
        return 2.0 * c.v_bound / P["x_min"]


# ---- mass


@dataclass(frozen=True)
class MassAdded(Effect):
    """A rigidly attached extra mass dm (negative: lighter than configured), its weight included:

        M -> M + dm   (in the inertia and in M g sin(angle))
    """

    WORD: ClassVar[str] = "mass"
    FORM: ClassVar[str] = "added"
    PARAMS: ClassVar[dict[str, Param]] = {
        "dm": Param("kg", "extra moving mass", 0.005, 1.0, "signed", "mass"),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"dm": 0.0}
    HOOKS: ClassVar[tuple[str, ...]] = ("piston",)
    dm: float = 0.3

    @classmethod
    def _constrained(cls, vals, cyl):
        return cls(dm=max(vals["dm"], -0.5 * cyl.mechanics.moving_mass))

    def check(self, cyl):
        super().check(cyl)
        if self.dm <= -0.9 * cyl.mechanics.moving_mass:
            raise ValueError(f"mass:added: dm = {self.dm:g} kg leaves almost no moving mass.")

    @classmethod
    def piston(cls, P, Y, dY, s):
        s.M = s.M + P["dm"]


@dataclass(frozen=True)
class MassPayload(Effect):
    """A payload m_p coupled to the rod through a stiff, damped mount (natural frequency f_n,
    damping ratio zeta). With the payload's deflection d = y - x (y its position):

        d'' = -w^2 d - 2 zeta w d' - g sin(angle) - x'',    w = 2 pi f_n
        piston: F += m_p (w^2 d + 2 zeta w d')

    At rest the mount carries the payload's weight (d = -g sin(angle) / w^2)."""

    WORD: ClassVar[str] = "mass"
    FORM: ClassVar[str] = "payload"
    PARAMS: ClassVar[dict[str, Param]] = {
        "m_p": Param("kg", "payload mass", 0.005, 1.0, scale="mass"),
        "f_n": Param("Hz", "natural frequency of the payload on its mount", 25.0, 120.0, "shape"),
        "zeta": Param("1", "damping ratio of the mount", 0.05, 0.3, "shape"),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"m_p": 0.0}
    STATES: ClassVar[tuple[str, ...]] = ("d", "d_dot")
    HOOKS: ClassVar[tuple[str, ...]] = ("piston", "after_piston")
    m_p: float = 0.3
    f_n: float = 60.0
    zeta: float = 0.1

    @classmethod
    def prepare(cls, P, c):
        P["_w"] = 2 * math.pi * P["f_n"]

    @classmethod
    def init_states(cls, P, s):
        return np.vstack([-GRAVITY * s.c.sin_a / P["_w"] ** 2, np.zeros(s.c.n)])

    @classmethod
    def piston(cls, P, Y, dY, s):
        w = P["_w"]
        s.mount = w * w * Y[0] + 2 * P["zeta"] * w * Y[1]  # mount force per payload mass
        s.F = s.F + P["m_p"] * s.mount

    @classmethod
    def after_piston(cls, P, Y, dY, s):
        dY[0] = Y[1]
        dY[1] = -s.mount - GRAVITY * s.c.sin_a - s.a

    @classmethod
    def rate(cls, P, c):
        w = P["_w"]
        return w * np.sqrt(1.0 + P["m_p"] / c.M) * (1.0 + 2 * P["zeta"])


# ---- valve dead zone


@dataclass(frozen=True)
class DeadzoneHard(Effect):
    """A hard dead zone without shift: the valve stays closed for |u| <= d and opens to the full
    commanded value at once beyond (u_valve = 0 inside, u outside)."""

    WORD: ClassVar[str] = "valve_deadzone"
    FORM: ClassVar[str] = "hard"
    PARAMS: ClassVar[dict[str, Param]] = {
        "d": Param("1", "command below which the valve stays closed", 1.3e-3, 0.08),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"d": 0.0}
    HOOKS: ClassVar[tuple[str, ...]] = ("overlap",)
    d: float = 0.03

    @classmethod
    def overlap(cls, P, Y, dY, s):
        s.u = s.u * (np.abs(s.u) > P["d"])


@dataclass(frozen=True)
class DeadzoneSoft(Effect):
    """A smooth overlap: the opening rises as |u|^3 / (3 d^2) near centre and approaches u - d
    sign(u) beyond the overlap d:

        u_valve = u - d tanh(u / d)
    """

    WORD: ClassVar[str] = "valve_deadzone"
    FORM: ClassVar[str] = "soft"
    PARAMS: ClassVar[dict[str, Param]] = {
        "d": Param("1", "spool overlap (shift of the opening beyond it)", 4e-5, 0.08),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"d": 0.0}
    HOOKS: ClassVar[tuple[str, ...]] = ("overlap",)
    d: float = 0.03

    @classmethod
    def prepare(cls, P, c):
        on = P["d"] > 0
        P["_d"] = np.where(on, P["d"], 1.0)
        P["_dd"] = P["d"] * on  # zero where neutral: the subtracted term vanishes exactly

    @classmethod
    def overlap(cls, P, Y, dY, s):
        s.u = s.u - P["_dd"] * np.tanh(s.u / P["_d"])


# ---- valve delay


@dataclass(frozen=True)
class DelayTransport(Effect):
    """A pure dead time: the valve sees the command tau late (u_valve(t) = u(t - tau)),
    exact for the held command (no approximation of the delay)."""

    WORD: ClassVar[str] = "valve_delay"
    FORM: ClassVar[str] = "transport"
    PARAMS: ClassVar[dict[str, Param]] = {
        "tau": Param("s", "dead time", 6e-5, 8e-3),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"tau": 0.0}
    HOOKS: ClassVar[tuple[str, ...]] = ("spool",)
    tau: float = 3e-3

    def check(self, cyl):
        super().check(cyl)
        if not 0.0 <= self.tau <= 0.5:
            raise ValueError(f"valve_delay:transport: tau must lie in [0, 0.5] s, not {self.tau:g}.")

    @classmethod
    def spool(cls, P, Y, dY, s):
        # the delayed instant in units of substeps: exact integers for the held intervals
        b = s.c
        k, i, stage = s.pos
        j = np.floor(((k * b.N + i + STAGES[stage]) - P["tau"] / b.h) / b.N).astype(np.intp)
        s.u = b.U[b.U_off + j, b.cols]


@dataclass(frozen=True)
class DelaySpool(Effect):
    """Second-order spool dynamics (natural angular frequency w_n = 1 / t_n, damping zeta); the
    valve opening stops at the spool's ends:

        y'' = w_n^2 (u - y) - 2 zeta w_n y',    u_valve = clip(y, -1, 1)

    The command is held over a sample, so the spool's motion within it is applied exactly (the
    matrix exponential of the linear system, at every integration stage): however fast the
    spool, it costs no integration step."""

    WORD: ClassVar[str] = "valve_delay"
    FORM: ClassVar[str] = "spool"
    PARAMS: ClassVar[dict[str, Param]] = {
        "t_n": Param("s", "1 / natural angular frequency of the spool", 1e-5, 4e-3),
        "zeta": Param("1", "damping ratio of the spool", 0.5, 1.0, "shape"),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"t_n": 0.0}
    HOOKS: ClassVar[tuple[str, ...]] = ("sample", "spool")
    t_n: float = 1.5e-3
    zeta: float = 0.7

    @classmethod
    def prepare(cls, P, c):
        on = P["t_n"] > 0
        P["_on"] = on.astype(float)
        P["_w"] = 1.0 / np.where(on, P["t_n"], 1.0)
        P["_y"] = np.zeros((2, c.n))  # spool position and speed at the start of the current sample
        P["_u_last"] = np.zeros(c.n)  # the command held over the previous sample

    @classmethod
    def prepare_step(cls, P, c):
        # exp(A theta) of e = (y - u, y') with A = [[0, 1], [-w^2, -2 zeta w]] at every stage time
        # of a sample and over a whole sample
        w, z = P["_w"], P["zeta"]
        A = np.zeros((c.n, 2, 2))
        A[:, 0, 1] = 1.0
        A[:, 1, 0] = -w * w
        A[:, 1, 1] = -2 * z * w
        theta = (np.arange(c.N)[:, None] + np.array(STAGES)[None, :]) * c.h  # (N, stages)
        E = expm(A[None, None] * theta[:, :, None, None, None])  # (N, stages, n, 2, 2)
        P["_E0"], P["_E1"] = E[..., 0, 0], E[..., 0, 1]
        P["_E_dt"] = expm(A * c.dt)

    @classmethod
    def sample(cls, P, c):
        """At a tick: move the spool over the sample just ended, remember the new command."""
        u = P["_u_last"]
        e = P["_y"] - np.stack([u, np.zeros(c.n)])
        e = np.einsum("nij,jn->in", P["_E_dt"], e)
        P["_y"] = e + np.stack([u, np.zeros(c.n)])
        P["_u_last"] = c.u_held.copy()

    @classmethod
    def spool(cls, P, Y, dY, s):
        _, i, j = s.pos
        y = s.u + P["_E0"][i, j] * (P["_y"][0] - s.u) + P["_E1"][i, j] * P["_y"][1]
        s.u = s.u + P["_on"] * (np.minimum(np.maximum(y, -1.0), 1.0) - s.u)  # the command where neutral


@dataclass(frozen=True)
class DelaySlew(Effect):
    """A rate-limited spool: it moves towards the command at its top speed, 1 / t_slew (a full
    travel from centre to an end takes t_slew), and stops there. With the command held over a
    sample the motion is known in closed form, so it is applied exactly (no stiff state):

        y(t_k + s) = y_k + clip(u_k - y_k, -s / t_slew, s / t_slew),    u_valve = y
    """

    WORD: ClassVar[str] = "valve_delay"
    FORM: ClassVar[str] = "slew"
    PARAMS: ClassVar[dict[str, Param]] = {
        "t_slew": Param("s", "time for the spool to travel from centre to an end", 1.2e-4, 2e-2),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"t_slew": 0.0}
    HOOKS: ClassVar[tuple[str, ...]] = ("sample", "spool")
    t_slew: float = 5e-3

    @classmethod
    def prepare(cls, P, c):
        on = P["t_slew"] > 0
        P["_on"] = on.astype(float)
        P["_speed"] = 1.0 / np.where(on, P["t_slew"], 1.0)
        P["_y0"] = np.zeros(c.n)  # spool position at the start of the current sample
        P["_u_last"] = np.zeros(c.n)  # the command held over the previous sample

    @classmethod
    def sample(cls, P, c):
        """At a tick: move the spool over the sample just ended, remember the new command."""
        travel = P["_speed"] * c.dt
        P["_y0"] = P["_y0"] + np.minimum(np.maximum(P["_u_last"] - P["_y0"], -travel), travel)
        P["_u_last"] = c.u_held.copy()

    @classmethod
    def spool(cls, P, Y, dY, s):
        c = s.c
        _, i, j = s.pos
        travel = P["_speed"] * ((i + STAGES[j]) * c.h)
        y = P["_y0"] + np.minimum(np.maximum(s.u - P["_y0"], -travel), travel)
        s.u = s.u + P["_on"] * (y - s.u)  # the command where neutral


# ---- leakage


@dataclass(frozen=True)
class LeakPiston(Effect):
    """A compressible laminar leak across the piston seal (capillary law, mass flow ~ p1^2 - p2^2),
    sized by its ANR volume flow q_ref from supply to atmosphere pressure:

        mdot = rho0 q_ref (p1^2 - p2^2) / (ps^2 - pa^2)   from chamber 1 to chamber 2
    """

    WORD: ClassVar[str] = "leakage"
    FORM: ClassVar[str] = "piston"
    PARAMS: ClassVar[dict[str, Param]] = {
        "q_ref": Param("m^3/s", "ANR leak flow at supply against atmosphere", 3e-5, 0.02, scale="valve_flow"),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"q_ref": 0.0}
    HOOKS: ClassVar[tuple[str, ...]] = ("flows",)
    q_ref: float = 3e-5

    @classmethod
    def prepare(cls, P, c):
        P["_k"] = RHO0 * P["q_ref"] / (c.ps ** 2 - c.pa ** 2)

    @classmethod
    def flows(cls, P, Y, dY, s):
        m = P["_k"] * (s.p1 * s.p1 - s.p2 * s.p2)
        s.m1 = s.m1 - m
        s.m2 = s.m2 + m


@dataclass(frozen=True)
class LeakRod(Effect):
    """The rod seal leaks from chamber 2 to the atmosphere, linear in the gauge pressure,
    sized by its ANR volume flow q_ref at supply pressure:

        mdot_out2 = rho0 q_ref (p2 - pa) / (ps - pa)
    """

    WORD: ClassVar[str] = "leakage"
    FORM: ClassVar[str] = "rod"
    PARAMS: ClassVar[dict[str, Param]] = {
        "q_ref": Param("m^3/s", "ANR leak flow at supply pressure", 1.2e-5, 0.02, scale="valve_flow"),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"q_ref": 0.0}
    HOOKS: ClassVar[tuple[str, ...]] = ("flows",)
    q_ref: float = 3e-5

    @classmethod
    def prepare(cls, P, c):
        P["_g"] = RHO0 * P["q_ref"] / (c.ps - c.pa)

    @classmethod
    def flows(cls, P, Y, dY, s):
        s.m2 = s.m2 - P["_g"] * (s.p2 - s.pa)


# ---- heat transfer


@dataclass(frozen=True)
class HeatPolytropic(Effect):
    """Partial heat exchange as a polytropic exponent n (kappa = 1.4 adiabatic, 1 isothermal)
    in both chamber equations: dp_i/dt = n / V_i (R T mdot_i -+ p_i A_i v)."""

    WORD: ClassVar[str] = "heat_transfer"
    FORM: ClassVar[str] = "polytropic"
    PARAMS: ClassVar[dict[str, Param]] = {
        "n": Param("1", "polytropic exponent", KAPPA - 0.0065, KAPPA - 0.2),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"n": KAPPA}
    HOOKS: ClassVar[tuple[str, ...]] = ("chambers",)
    n: float = 1.3

    @classmethod
    def typical(cls, cyl, level=0.5):
        return cls(n=KAPPA - 0.0065 * (0.2 / 0.0065) ** level)

    @classmethod
    def random(cls, rng, cyl):
        return cls(n=KAPPA - float(np.exp(rng.uniform(math.log(0.0065), math.log(0.2)))))

    def check(self, cyl):
        super().check(cyl)
        if not 1.0 <= self.n <= KAPPA:
            raise ValueError(f"heat_transfer:polytropic: n must lie in [1, {KAPPA}], not {self.n:g}.")

    @classmethod
    def chambers(cls, P, Y, dY, s):
        s.kap1 = P["n"]
        s.kap2 = P["n"]


@dataclass(frozen=True)
class HeatWall(Effect):
    """Heat exchange with the barrel wall: constant areas A_i (each chamber's wall at mid-stroke),
    a wall temperature state Tw with heat capacity C_w and a conductance G_a to the ambient (at
    the supply temperature Ts), and the chamber air temperatures T_i as states that follow the
    energy balance of the chamber air (inflow enters at Ts, outflow leaves at T_i):

        Q_i = h A_i (Tw - T_i),     dp_i/dt += (kappa - 1) Q_i / V_i
        dT_i/dt = R T_i / (p_i V_i) (max(mdot_i, 0) (kappa Ts - T_i) + (kappa - 1) T_i min(mdot_i, 0))
                  + (kappa - 1) T_i / (p_i V_i) (Q_i - p_i dV_i/dt)
        C_w dTw/dt = -(Q1 + Q2) + G_a (Ts - Tw)

    The pressures keep the nominal chambers' convention (every flow at Ts), so h = 0 is the
    nominal plant exactly; the temperatures are those of real air, which stay bounded over
    fill and exhaust cycles."""

    WORD: ClassVar[str] = "heat_transfer"
    FORM: ClassVar[str] = "wall"
    PARAMS: ClassVar[dict[str, Param]] = {
        "h": Param("W/(m^2 K)", "heat transfer coefficient air-wall", 1.7, 100.0),
        "C_w": Param("J/K", "heat capacity of the wall's inner layer", 5.0, 100.0, "shape"),
        "G_a": Param("W/K", "conductance wall-ambient", 0.1, 2.0, "shape"),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"h": 0.0}
    STATES: ClassVar[tuple[str, ...]] = ("T1", "T2", "Tw")
    HOOKS: ClassVar[tuple[str, ...]] = ("chambers",)
    h: float = 20.0
    C_w: float = 20.0
    G_a: float = 0.5

    @classmethod
    def prepare(cls, P, c):
        half = 0.5 * c.L
        Aw1 = 2 * c.A1 + c.perim * (c.V01 / c.A1 + half)
        Aw2 = 2 * c.A2 + c.perim * (c.V02 / np.maximum(c.A2, 1e-12) + half)
        P["_hA1"], P["_hA2"] = P["h"] * Aw1, P["h"] * Aw2

    @classmethod
    def init_states(cls, P, s):
        T = s.c.T
        return np.vstack([T, T, T])

    @staticmethod
    def air_temperature_rate(T, p, V, dV, mdot, Q, Ts):
        """dT/dt of a chamber's air: inflow at Ts mixes in, outflow leaves at T, compression, heat."""
        k1 = KAPPA - 1.0
        flows = R_GAS * (np.maximum(mdot, 0.0) * (KAPPA * Ts - T) + k1 * T * np.minimum(mdot, 0.0))
        return T / (p * V) * (flows + k1 * (Q - p * dV))

    @classmethod
    def chambers(cls, P, Y, dY, s):
        c = s.c
        T1, T2, Tw = Y[0], Y[1], Y[2]
        Q1, Q2 = P["_hA1"] * (Tw - T1), P["_hA2"] * (Tw - T2)
        dY[0] = cls.air_temperature_rate(T1, s.p1, s.V1, c.A1 * s.v, s.m1, Q1, c.T)
        dY[1] = cls.air_temperature_rate(T2, s.p2, s.V2, -c.A2 * s.v, s.m2, Q2, c.T)
        dY[2] = (P["G_a"] * (c.T - Tw) - Q1 - Q2) / P["C_w"]
        s.Q1 = Q1 if s.Q1 is None else s.Q1 + Q1
        s.Q2 = Q2 if s.Q2 is None else s.Q2 + Q2

    @classmethod
    def rate(cls, P, c):
        # air: h A / (m cv) in the smallest, emptiest chamber, and the mixing of a full choked
        # inflow into it; wall: (h A + G_a) / C_w
        cv = R_GAS / (KAPPA - 1)
        pV = c.pa * np.minimum(c.V01, c.V02)
        hA = np.maximum(P["_hA1"], P["_hA2"])
        mix = KAPPA * c.RT * np.maximum(c.C_pos_rho, c.C_neg_rho) * c.ps / pV
        return hA * c.RT / (pV * cv) + mix + (2 * hA + P["G_a"]) / P["C_w"]


# ---- supply droop


@dataclass(frozen=True)
class SupplyReservoir(Effect):
    """The valve draws from a reservoir (volume V_r, isothermal) refilled from the regulated
    supply ps through an orifice (ISO 6358 law) whose conductance is Cmax / ratio:

        dp_r/dt = R T / V_r (mdot_iso(Cmax / ratio, ps -> p_r) - mdot_drawn),  valve supply = p_r
    """

    WORD: ClassVar[str] = "supply_droop"
    FORM: ClassVar[str] = "reservoir"
    PARAMS: ClassVar[dict[str, Param]] = {
        "ratio": Param("1", "valve conductance over the refill orifice's conductance", 0.1, 2.0),
        "V_r": Param("m^3", "reservoir volume (tubing, manifold, tank)", 5e-5, 3e-4, "shape"),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"ratio": 0.0}
    STATES: ClassVar[tuple[str, ...]] = ("p_r",)
    HOOKS: ClassVar[tuple[str, ...]] = ("supply", "flows")
    ratio: float = 0.5
    V_r: float = 1e-4

    @classmethod
    def prepare(cls, P, c):
        P["_on"] = (P["ratio"] > 0).astype(float)
        P["_Cf"] = np.where(P["ratio"] > 0, c.Cmax / np.where(P["ratio"] > 0, P["ratio"], 1.0), 0.0)

    @classmethod
    def init_states(cls, P, s):
        return s.c.ps.copy()[None, :]

    @classmethod
    def supply(cls, P, Y, dY, s):
        s.ps_valve = s.ps_valve - (s.c.ps - Y[0])

    @classmethod
    def flows(cls, P, Y, dY, s):
        c = s.c
        feed = _iso_flow(P["_Cf"] * c.rho, c.ps, Y[0], c.b, c.lamk, c.inv1mb)
        dY[0] = P["_on"] * c.RT / P["V_r"] * (feed - s.m_supply)

    @classmethod
    def rate(cls, P, c):
        return c.RT / P["V_r"] * P["_Cf"] * c.rho * c.lamk * 1.5


@dataclass(frozen=True)
class SupplyLine(Effect):
    """A long supply line: a quadratic (turbulent) resistance into the line's volume V_l
    (isothermal), regularised below a small pressure drop dp0 = droop ps / 10:

        mdot_line = k (ps - p_l) / sqrt(|ps - p_l| + dp0)
        dp_l/dt = R T / V_l (mdot_line - mdot_drawn),   valve supply = p_l

    k is such that a steady draw of the valve's full-open choked flow at ps, Cmax rho ps, drops
    the pressure by droop * ps."""

    WORD: ClassVar[str] = "supply_droop"
    FORM: ClassVar[str] = "line"
    PARAMS: ClassVar[dict[str, Param]] = {
        "droop": Param("1", "relative pressure drop of the line at the valve's full choked draw", 0.01, 0.4),
        "V_l": Param("m^3", "volume of the line", 5e-5, 3e-4, "shape"),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"droop": 0.0}
    STATES: ClassVar[tuple[str, ...]] = ("p_l",)
    HOOKS: ClassVar[tuple[str, ...]] = ("supply", "flows")
    droop: float = 0.1
    V_l: float = 1e-4

    @classmethod
    def prepare(cls, P, c):
        on = P["droop"] > 0
        P["_on"] = on.astype(float)
        drop = np.where(on, P["droop"], 1.0) * c.ps
        P["_dp0"] = 0.1 * drop
        P["_k"] = np.where(on, c.Cmax * c.rho * c.ps * np.sqrt(drop + P["_dp0"]) / drop, 0.0)

    @classmethod
    def init_states(cls, P, s):
        return s.c.ps.copy()[None, :]

    @classmethod
    def supply(cls, P, Y, dY, s):
        s.ps_valve = s.ps_valve - (s.c.ps - Y[0])

    @classmethod
    def flows(cls, P, Y, dY, s):
        c = s.c
        dp = c.ps - Y[0]
        line = P["_k"] * dp / np.sqrt(np.abs(dp) + P["_dp0"])
        dY[0] = P["_on"] * c.RT / P["V_l"] * (line - s.m_supply)

    @classmethod
    def rate(cls, P, c):
        return c.RT / P["V_l"] * P["_k"] / np.sqrt(P["_dp0"])


# ---- a rig that changes during the run (a truth for the online estimator's benchmarks, not a
# word of the diagnosis vocabulary: kept out of EFFECT_FORMS and WORDS)


@dataclass(frozen=True)
class FrictionSchedule(Effect):
    """Coulomb and viscous friction that change with time t (the run's time column): a jump by
    the fractions step_Fc, step_Fv at t_step, and from t_ramp on a linear rise by ramp_Fc,
    ramp_Fv per second (fractions of the cylinder's Fc, Fv):

        Fc(t) = Fc (1 + step_Fc H(t - t_step) + ramp_Fc (t - t_ramp)+)
        Fv(t) = Fv (1 + step_Fv H(t - t_step) + ramp_Fv (t - t_ramp)+)
    """

    WORD: ClassVar[str] = "friction_change"
    FORM: ClassVar[str] = "schedule"
    PARAMS: ClassVar[dict[str, Param]] = {
        "t_step": Param("s", "time of the jump", 0.0, 60.0, "shape", positive=False),
        "step_Fc": Param("1", "jump of Fc, fraction of Fc", 0.05, 0.5, "signed"),
        "step_Fv": Param("1", "jump of Fv, fraction of Fv", 0.05, 0.5, "signed"),
        "t_ramp": Param("s", "time the rise begins", 0.0, 60.0, "shape", positive=False),
        "ramp_Fc": Param("1/s", "rise of Fc per second, fraction of Fc", 1e-3, 1e-2, "signed"),
        "ramp_Fv": Param("1/s", "rise of Fv per second, fraction of Fv", 1e-3, 1e-2, "signed"),
    }
    NEUTRAL: ClassVar[dict[str, float]] = {"step_Fc": 0.0, "step_Fv": 0.0, "ramp_Fc": 0.0, "ramp_Fv": 0.0}
    HOOKS: ClassVar[tuple[str, ...]] = ("friction",)
    t_step: float = 0.0
    step_Fc: float = 0.0
    step_Fv: float = 0.0
    t_ramp: float = 0.0
    ramp_Fc: float = 0.0
    ramp_Fv: float = 0.0

    @staticmethod
    def _fractions(P, t):
        jump = (t >= P["t_step"]).astype(float)
        rise = np.maximum(t - P["t_ramp"], 0.0)
        return P["step_Fc"] * jump + P["ramp_Fc"] * rise, P["step_Fv"] * jump + P["ramp_Fv"] * rise

    @classmethod
    def friction(cls, P, Y, dY, s):
        k, i, j = s.pos
        c = s.c
        t = (k + (i + STAGES[j]) / c.N) * c.dt
        dc, dv = cls._fractions(P, t)
        s.Ff = s.Ff + c.Fc * dc * s.sgn + c.Fv * dv * s.v

    @classmethod
    def friction_level(cls, P, c):
        dc, _ = cls._fractions(P, np.full(c.n, c.t_end))
        return c.Fc * np.maximum(np.abs(dc), np.abs(P["step_Fc"]))


# The order of this list is the order in which forms act within one evaluation.
EFFECT_FORMS: dict[tuple[str, str], type[Effect]] = {(c.WORD, c.FORM): c for c in (
    DelayTransport, DelaySpool, DelaySlew, DeadzoneHard, DeadzoneSoft,
    SupplyReservoir, SupplyLine, LeakPiston, LeakRod,
    StictionExp, StictionRational, AsymmetryLevels, AsymmetryPressureSide, PositionTight, PositionWave,
    DynamicsDahl, DynamicsMaxwell, MassAdded, MassPayload, HeatPolytropic, HeatWall)}
WORDS: tuple[str, ...] = ("stiction", "friction_asymmetry", "friction_position", "friction_dynamics", "mass",
                          "valve_deadzone", "valve_delay", "leakage", "heat_transfer", "supply_droop")
# forms a Case may hold besides the vocabulary's: a friction that changes during the run
TIME_FORMS: dict[tuple[str, str], type[Effect]] = {(FrictionSchedule.WORD, FrictionSchedule.FORM): FrictionSchedule}
_ALL_FORMS = {**EFFECT_FORMS, **TIME_FORMS}
_ORDER = {cls: i for i, cls in enumerate(_ALL_FORMS.values())}


def forms_of(word: str) -> list[type[Effect]]:
    return [cls for (w, _), cls in EFFECT_FORMS.items() if w == word]


def make_effect(word: str, form: str, values: Mapping[str, float] | None = None, cyl: Cylinder | None = None) -> Effect:
    """An effect form by word and form name. Parameters not given keep the class defaults (sized
    for the default 32 x 100 cylinder), or with `cyl` the mid-range values for that cylinder."""
    cls = _ALL_FORMS.get((word, form))
    if cls is None:
        known = ", ".join(f"{w}:{f}" for w, f in _ALL_FORMS)
        raise ValueError(f"unknown effect form {word}:{form} (known: {known}).")
    values = dict(values or {})
    unknown = [k for k in values if k not in cls.PARAMS]
    if unknown:
        raise ValueError(f"{word}:{form} has no parameter(s) {unknown} (parameters: {', '.join(cls.PARAMS)}).")
    base = cls.typical(cyl, 0.5).values() if cyl is not None else {}
    return cls(**{**base, **{k: float(v) for k, v in values.items()}})


def parse_effect(spec: str, cyl: Cylinder | None = None) -> Effect:
    """'stiction:exp:Fs_excess=10,v_stribeck=0.005' -> StictionExp(10, 0.005) (see make_effect)."""
    parts = spec.split(":", 2)
    if len(parts) < 2:
        raise ValueError(f"effect {spec!r}: expected WORD:FORM[:k=v,...].")
    return make_effect(parts[0], parts[1], _parse_kv(parts[2] if len(parts) > 2 else ""), cyl)


def random_effect(rng: np.random.Generator, cyl: Cylinder, word: str, form: str | None = None) -> Effect:
    """A random realistic effect for `word` (a random form unless `form` is given)."""
    classes = forms_of(word) if form is None else [c for c in forms_of(word) if c.FORM == form]
    if not classes:
        known = ", ".join(f"{w}:{f}" for w, f in EFFECT_FORMS)
        raise ValueError(f"unknown effect {word!r}{f' form {form!r}' if form else ''} (known: {known}).")
    return classes[rng.integers(len(classes))].random(rng, cyl)


def _effect_from_json(d: Mapping[str, Any]) -> Effect:
    return make_effect(d["effect"], d["form"], d.get("params", {}))


def _parse_kv(text: str) -> dict[str, float]:
    out: dict[str, float] = {}
    for item in filter(None, (p.strip() for p in text.split(","))):
        k, eq, v = item.partition("=")
        if not eq:
            raise ValueError(f"expected key=value, not {item!r}.")
        out[k.strip()] = float(v)
    return out


# ------------------------------------------------------------------ cases


@dataclass(frozen=True, eq=False)
class Case:
    """One simulated run: a cylinder, the excitation and noise seed, and the truth.

    commands: None for a closed-loop experiment program of the project (`program`: mixed,
    steps, ramps, sines, calibration, ...; seeded, designed from the cylinder file), or the
    command held after each sample (open loop, one per sample). x0: start position (default mid-stroke); the piston starts at rest with
    chamber 2 at half the supply span and chamber 1 balancing it. start: the state at the start
    instead, by the names of Result.states (those not given as at rest), and command_before the
    command held over the first sample period (with `commands` and `start`: a stretch of another
    run replayed from that run's true state).
    """

    cyl: Cylinder
    duration: float = 20.0  # s
    seed: int = 0
    rate: float = 1000.0  # Hz
    calibration: Calibration = field(default_factory=Calibration)
    effects: tuple[Effect, ...] = ()
    sensors: SensorDepartures = field(default_factory=SensorDepartures)
    noise: bool = True
    commands: np.ndarray | None = None
    program: str = "mixed"  # closed loop (commands None): the experiment program by its name
    x0: float | None = None  # m
    end_stiffness: float = K_END  # N/m
    end_damping: float = C_END  # N s/m
    start: Mapping[str, float] | None = None  # state name -> value at the start (default: at rest)
    command_before: float = 0.0  # the command held over the first sample period and before it

    def __post_init__(self) -> None:
        object.__setattr__(self, "effects", tuple(self.effects))
        if self.start is not None:
            object.__setattr__(self, "start", {str(k): float(v) for k, v in self.start.items()})
            if not all(math.isfinite(v) for v in self.start.values()):
                raise ValueError(f"start: finite values needed, not {self.start}.")
        if not (math.isfinite(self.command_before) and abs(self.command_before) <= 1.0):
            raise ValueError(f"command_before must lie in [-1, 1], not {self.command_before!r}.")
        words = [e.WORD for e in self.effects]
        if len(set(words)) != len(words):
            raise ValueError(f"one form per effect word, not {words}.")
        for e in self.effects:
            e.check(self.cyl)
        if isinstance(self.seed, np.integer):
            object.__setattr__(self, "seed", int(self.seed))
        if not isinstance(self.seed, int) or isinstance(self.seed, bool) or self.seed < 0:
            raise ValueError(f"seed must be a non-negative integer, not {self.seed!r}.")
        if not (self.duration > 0 and self.rate > 0 and self.n_samples >= 1):
            raise ValueError(f"duration and rate must give at least one sample, not {self.duration!r} s "
                             f"at {self.rate!r} Hz.")
        if self.commands is not None:
            cmd = np.asarray(self.commands, float).ravel()
            if len(cmd) != self.n_samples or not np.all(np.isfinite(cmd)):
                raise ValueError(f"commands: {self.n_samples} finite values needed, got {len(cmd)}.")
            object.__setattr__(self, "commands", cmd)

    @property
    def n_samples(self) -> int:
        return int(round(self.duration * self.rate))

    def active_effects(self) -> list[Effect]:
        return [e for e in self.effects if not e.is_neutral()]

    def truth(self) -> dict[str, Any]:
        """The truth as a plain dict for benchmark tables (SI values, resolved for the cylinder)."""
        active = self.active_effects()
        return {
            "cylinder": self.cyl.name, "seed": self.seed, "duration": self.duration, "rate": self.rate,
            "verdict": "+".join(sorted(e.WORD for e in active)) or "none",
            "effects": {e.WORD: {"form": e.FORM, **e.values()} for e in self.effects},
            "calibration": self.calibration.resolved(self.cyl),
            "sensors": self.sensors.to_json(),
        }

    def to_json(self) -> dict[str, Any]:
        """Everything needed to rebuild the case (and its run) exactly; json.dumps-able."""
        return {
            "cylinder_toml": cylinder_to_toml(self.cyl),
            "cylinder_source": str(self.cyl.source) if self.cyl.source is not None else None,
            "duration": self.duration, "seed": self.seed, "rate": self.rate, "noise": self.noise,
            "calibration": self.calibration.to_json(),
            "effects": [e.to_json() for e in self.effects],
            "sensors": self.sensors.to_json(),
            "commands": None if self.commands is None else self.commands.tolist(),
            "program": self.program, "x0": self.x0, "end_stiffness": self.end_stiffness, "end_damping": self.end_damping,
            # only where set: the keys of the cached runs made before these existed stay as they were
            **({"start": dict(self.start)} if self.start is not None else {}),
            **({"command_before": self.command_before} if self.command_before else {}),
        }

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> "Case":
        cyl = parse_cylinder(tomllib.loads(d["cylinder_toml"]), d.get("cylinder_source"))
        cmd = d.get("commands")
        return cls(cyl=cyl, duration=float(d["duration"]), seed=int(d["seed"]), rate=float(d["rate"]),
                   noise=bool(d["noise"]), calibration=Calibration.from_json(d["calibration"]),
                   effects=tuple(_effect_from_json(e) for e in d["effects"]),
                   sensors=SensorDepartures.from_json(d["sensors"]),
                   commands=None if cmd is None else np.asarray(cmd, float), program=d.get("program", "mixed"),
                   x0=d.get("x0"),
                   end_stiffness=float(d.get("end_stiffness", K_END)), end_damping=float(d.get("end_damping", C_END)),
                   start=d.get("start"), command_before=float(d.get("command_before", 0.0)))

    def key(self) -> str:
        """A content hash of the case (and of this module's physics revision, and of the closed-loop
        program's revision where it changed) for on-disk caches; not of where the cylinder file
        lies, so that two checkouts share the runs."""
        case = {k: v for k, v in self.to_json().items() if k != "cylinder_source"}
        if self.commands is None:  # a closed-loop program whose commands changed: not the runs stored before
            from combined_reality.live.catalogue import program_revision

            if program_revision(self.program) != 1:
                case["program_revision"] = program_revision(self.program)
        text = json.dumps({"case": case, "revision": REVISION}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:20]


REVISION = 1  # bump when the physics of this module changes (invalidates cached runs)


@dataclass(frozen=True, eq=False)
class Result:
    """A simulated run and the true (noise-free) states at its samples."""

    case: Case
    run: Run
    states: dict[str, np.ndarray]  # "p1", "p2", "x", "v", then "<word>.<form>.<state>"
    substeps: int  # RK4 substeps per sample period
    wall_s: float  # wall time of the whole batch


# ------------------------------------------------------------------ the vectorised plant


def _iso_flow(C_rho, p_from, p_to, b, lamk, inv1mb):
    """ISO 6358 mass flow p_from -> p_to (negative when p_to > p_from), laminar end at R_LAM.

    C_rho = C rho0 sqrt(T0 / T), lamk = phi(R_LAM) / (1 - R_LAM), inv1mb = 1 / (1 - b)."""
    d = p_from - p_to
    pu = np.maximum(p_from, p_to)
    r = (pu - np.abs(d)) / pu
    z = np.maximum(r - b, 0.0) * inv1mb
    # the turbulent branch is concave in r and the laminar line is its chord from R_LAM to 1,
    # so the piecewise definition is exactly the smaller of the two
    phi = np.minimum(np.sqrt(1.0 - z * z), lamk * (1.0 - r))
    return C_rho * pu * phi * np.sign(d)


class _Batch:
    """Per-case constants as arrays and the right-hand side of every case at once."""

    def __init__(self, cases: Sequence[Case], substeps: int | None):
        n = len(cases)
        rate = cases[0].rate
        self.n, self.dt = n, 1.0 / rate
        self.t_end = max(c.duration for c in cases)
        self.cols = np.arange(n)

        def arr(fn):
            return np.array([float(fn(c)) for c in cases])

        cal = [c.calibration for c in cases]
        self.A1 = arr(lambda c: c.cyl.geometry.area_cap)
        self.A2 = arr(lambda c: c.cyl.geometry.area_rod)
        self.dA = self.A1 - self.A2
        self.perim = arr(lambda c: math.pi * c.cyl.geometry.bore)
        self.L = arr(lambda c: c.cyl.geometry.stroke)
        self.V01 = np.array([_or(k.dead_volume_cap, c.cyl.geometry.dead_volume_cap) for k, c in zip(cal, cases)])
        self.V02 = np.array([_or(k.dead_volume_rod, c.cyl.geometry.dead_volume_rod) for k, c in zip(cal, cases)])
        self.M = np.array([_or(k.moving_mass, c.cyl.mechanics.moving_mass) for k, c in zip(cal, cases)])
        self.sin_a = arr(lambda c: math.sin(c.cyl.mechanics.angle))
        self.ps = arr(lambda c: c.cyl.supply.pressure)
        self.pa = arr(lambda c: c.cyl.supply.atmosphere)
        self.T = arr(lambda c: c.cyl.supply.temperature)
        self.RT = R_GAS * self.T
        self.rho = RHO0 * np.sqrt(T_REF / self.T)
        self.Cmax = arr(lambda c: c.cyl.valve.sonic_conductance)
        self.C_pos = self.Cmax * np.array([k.conductance_pos for k in cal])
        self.C_neg = self.Cmax * np.array([k.conductance_neg for k in cal])
        self.b = np.array([k.b(c.cyl) for k, c in zip(cal, cases)])
        self.inv1mb = 1.0 / (1.0 - self.b)
        self.lamk = np.sqrt(1.0 - ((R_LAM - self.b) * self.inv1mb) ** 2) / (1.0 - R_LAM)
        self.Fc = arr(lambda c: c.cyl.friction.Fc)
        self.Fv = arr(lambda c: c.cyl.friction.Fv)
        self.kp = arr(lambda c: c.cyl.friction.kp)
        self.vs = arr(lambda c: c.cyl.friction.v_smooth)
        self.k_end = arr(lambda c: c.end_stiffness)
        self.c_end = arr(lambda c: c.end_damping)
        self.F_ext = np.array([k.external_force for k in cal])
        # upstream pressures of the four valve paths (supply, exhaust, supply, exhaust)
        self.frm_rows = np.vstack([self.ps, self.pa, self.ps, self.pa])
        self.C_pos_rho, self.C_neg_rho = self.C_pos * self.rho, self.C_neg * self.rho
        self.pa_dA = self.pa * self.dA
        self.g_sin = GRAVITY * self.sin_a
        self.C_rows: np.ndarray | None = None
        self.ends = True
        # an upper bound of the piston speed: the valve's full choked inflow into the smaller area
        self.v_bound = np.maximum(self.C_pos, self.C_neg) * self.rho * self.RT / np.minimum(
            self.A1, np.maximum(self.A2, 1e-12))

        # valve characteristics (tabulated only when some case has a non-linear one)
        chars = [(k.characteristic_pos, k.characteristic_neg) for k in cal]
        if any(f is not None for pair in chars for f in pair):
            self.table = np.concatenate([np.stack([_tabulate(p) for p, _ in chars]),
                                         np.stack([_tabulate(q) for _, q in chars])]).ravel()  # (2n * points)
            self.row_base = (np.arange(2 * n) * TABLE_POINTS).reshape(2, n)
        else:
            self.table = None

        # sensors
        sen = [c.sensors for c in cases]
        self.gain_x = 1.0 + np.array([s.position_gain for s in sen])
        self.gain_p = 1.0 + np.array([[s.pressure_gain_p1 for s in sen], [s.pressure_gain_p2 for s in sen]])
        self.offset_p = np.array([[k.offset_p1 for k in cal], [k.offset_p2 for k in cal]])
        tau_p = np.array([s.pressure_lag for s in sen])
        self.lag_on = tau_p > 0
        self.inv_lag = np.where(self.lag_on, 1.0 / np.where(self.lag_on, tau_p, 1.0), 0.0)

        # forms present anywhere in the batch; cases without a form carry its neutral values
        present = sorted({type(e) for c in cases for e in c.effects}, key=_ORDER.__getitem__)
        self.forms: list[tuple[type[Effect], dict[str, np.ndarray], slice]] = []
        row = 4
        for cls in present:
            insts = [next((e for e in c.effects if type(e) is cls), None) or cls.neutral() for c in cases]
            P = {k: np.array([getattr(e, k) for e in insts], float) for k in cls.PARAMS}
            # 1 where the case really has this form: the states of the others are frozen, so a
            # form's fast states never constrain the step of a case without it
            P["_active"] = np.array([0.0 if e.is_neutral() else 1.0 for e in insts])
            sl = slice(row, row + len(cls.STATES))
            row += len(cls.STATES)
            self.forms.append((cls, P, sl))
        self.lag_rows = slice(row, row + 2) if self.lag_on.any() else None
        self.nstate = row + (2 if self.lag_rows else 0)
        self.state_names = ["p1", "p2", "x", "v"] + [f"{cls.WORD}.{cls.FORM}.{s}" for cls, _, _ in self.forms
                                                      for s in cls.STATES] + (["p1_lag", "p2_lag"]
                                                                              if self.lag_rows else [])

        for cls, P, _ in self.forms:
            cls.prepare(P, self)
        self.N = int(substeps) if substeps else _ladder(self.dt * float(np.max(self.fastest_rate())) / SAFETY)
        # a generous bound of the piston's acceleration (for the end stop look-ahead)
        M_low = self.M + sum((np.minimum(P["dm"], 0.0) for cls, P, _ in self.forms if cls is MassAdded), 0.0)
        self.a_bound = 4.0 * ((self.A1 + self.A2) * self.ps + np.abs(self.F_ext) + self.Fc + self.kp * self.ps
                              + 3.0 * self.M) / M_low + 2 * GRAVITY
        self.h = self.dt / self.N
        for cls, P, _ in self.forms:
            cls.prepare_step(P, self)
        self.hooks = {name: [(getattr(cls, name), P, sl) for cls, P, sl in self.forms if name in cls.HOOKS]
                      for name in ("sample", "spool", "overlap", "supply", "flows", "friction", "piston",
                                   "after_piston", "chambers")}
        self.U: np.ndarray | None = None  # held commands by interval (set by the simulation)
        self.U_off = 0

    def fastest_rate(self) -> np.ndarray:
        """An upper bound of the fastest rate (1/s) of every case, from the plant's stiff parts."""
        M_low = self.M.copy()
        level = self.Fc + self.kp * (self.ps - self.pa)
        rates = []
        for cls, P, _ in self.forms:
            on = P["_active"] > 0
            level = level + np.where(on, cls.friction_level(P, self), 0.0)
            if cls is MassAdded:
                M_low = M_low + np.minimum(P["dm"], 0.0)
            rates.append(np.where(on, cls.rate(P, self), 0.0))
        # the velocity's own rate: the friction band's slope plus viscous and end stop damping
        fric = (level / self.vs + self.Fv + self.c_end) / M_low
        ends = np.sqrt(self.k_end / M_low)
        # laminar end of the valve into the smallest chamber volume
        valve = KAPPA * self.RT / np.minimum(self.V01, self.V02) * np.maximum(self.C_pos, self.C_neg) \
            * self.rho * self.lamk
        out = np.maximum.reduce([fric, ends, valve, self.inv_lag] + [np.broadcast_to(r, (self.n,)) for r in rates])
        return out

    def initial_state(self, cases: Sequence[Case]) -> np.ndarray:
        """At rest, valve centred: p2 at half the supply span, p1 so that the piston holds still.
        The piston's acceleration is affine in p1 at rest, so two evaluations find p1."""
        Y = np.zeros((self.nstate, self.n))
        Y[1] = 0.5 * (self.ps + self.pa)
        Y[2] = np.array([0.5 * c.cyl.geometry.stroke if c.x0 is None else c.x0 for c in cases])
        self.u_held = np.zeros(self.n)  # at rest before the start (a dead time looks back into U's zero rows)

        def accel(p1):
            Y[0] = p1
            self._init_form_states(Y)
            return self.rhs(Y, (0, 0, 1))[3]

        a0 = accel(Y[1].copy())
        a1 = accel(Y[1] + 1e4)
        Y[0] = Y[1] - a0 * 1e4 / (a1 - a0)
        self._init_form_states(Y)
        if self.lag_rows is not None:
            Y[self.lag_rows] = Y[0:2]
        for j, c in enumerate(cases):
            for name, value in (c.start or {}).items():
                if name not in self.state_names:
                    raise ValueError(f"start: no state {name!r} in this batch (states: {', '.join(self.state_names)}).")
                Y[self.state_names.index(name), j] = value
        return Y

    def _init_form_states(self, Y):
        s = _Sig()
        s.c = self
        s.p1, s.p2, s.x = Y[0], Y[1], Y[2]
        s.V1 = self.V01 + self.A1 * s.x
        s.V2 = self.V02 + self.A2 * (self.L - s.x)
        for cls, P, sl in self.forms:
            if cls.STATES:
                Y[sl] = cls.init_states(P, s)

    def valve_opening(self, u):
        """Fraction of full conductance of the u > 0 and u < 0 paths."""
        a_pos, a_neg = np.maximum(u, 0.0), np.maximum(-u, 0.0)
        if self.table is None:
            return a_pos, a_neg
        a = np.stack([a_pos, a_neg]) * (TABLE_POINTS - 1)
        i = np.minimum(a.astype(np.intp), TABLE_POINTS - 2)
        w = a - i
        idx = self.row_base + i
        lo = self.table[idx]
        f = lo + w * (self.table[idx + 1] - lo)
        return f[0], f[1]

    def begin_sample(self, Y: np.ndarray) -> None:
        """Work done once per sample: the forms' tick hooks, the valve's conductances when the held command maps to
        the opening statically (no spool dynamics or dead time in the batch), and whether any
        case can touch an end stop during the sample (if none can, the stop force is skipped:
        it is exactly zero then)."""
        for f, P, sl in self.hooks["sample"]:
            f(P, self)
        if not self.hooks["spool"]:
            s = _Sig()
            s.c, s.u = self, self.u_held
            for f, P, sl in self.hooks["overlap"]:
                f(P, None, None, s)
            self.C_rows = self.conductances(s.u)
        else:
            self.C_rows = None
        reach = np.abs(Y[3]) * self.dt + self.a_bound * self.dt ** 2
        self.ends = bool(np.any(Y[2] < reach) or np.any(Y[2] > self.L - reach))

    def conductances(self, u: np.ndarray) -> np.ndarray:
        """C rho of the four valve paths (rows: supply -> 1, exhaust -> 1, supply -> 2, exhaust -> 2)."""
        a_pos, a_neg = self.valve_opening(u)
        C = np.empty((4, self.n))
        C[0::3] = self.C_pos_rho * a_pos
        C[1:3] = self.C_neg_rho * a_neg
        return C

    def rhs(self, Y: np.ndarray, pos: tuple[int, int, int]) -> np.ndarray:
        """dY/dt of every case; pos = (sample, substep, stage) locates the time (see STAGES)."""
        hooks = self.hooks
        dY = np.empty_like(Y)
        s = _Sig()
        s.c, s.pos = self, pos
        s.p1, s.p2, s.x, s.v = p1, p2, x, v = Y[0], Y[1], Y[2], Y[3]
        s.pa = self.pa

        # ---- valve: command -> spool position -> opening of each direction's paths
        C = self.C_rows
        if C is None:
            s.u = self.u_held
            for f, P, sl in hooks["spool"]:
                f(P, Y[sl], dY[sl], s)
            for f, P, sl in hooks["overlap"]:
                f(P, Y[sl], dY[sl], s)
            C = self.conductances(s.u)

        # ---- mass flows into the chambers through the four paths, in one numpy call
        frm = self.frm_rows
        if hooks["supply"]:
            s.ps_valve = self.ps
            for f, P, sl in hooks["supply"]:
                f(P, Y[sl], dY[sl], s)
            frm = frm.copy()
            frm[0::2] = s.ps_valve
        to = np.empty_like(frm)
        to[0:2], to[2:4] = p1, p2
        m = _iso_flow(C, frm, to, self.b, self.lamk, self.inv1mb)
        s.m1, s.m2, s.m_supply = m[0] + m[1], m[2] + m[3], m[0] + m[2]
        for f, P, sl in hooks["flows"]:
            f(P, Y[sl], dY[sl], s)

        # ---- piston
        s.sgn = np.tanh(v / self.vs)
        s.Fseal = self.Fc + self.kp * np.abs(p1 - p2)
        s.Ff = s.Fseal * s.sgn + self.Fv * v
        for f, P, sl in hooks["friction"]:
            f(P, Y[sl], dY[sl], s)
        s.F = self.F_ext
        if self.ends:
            beyond = np.maximum(x - self.L, 0.0) + np.minimum(x, 0.0)  # penetration into an end stop
            s.F = s.F - self.k_end * beyond - self.c_end * v * (beyond != 0.0)
        s.M = self.M
        for f, P, sl in hooks["piston"]:
            f(P, Y[sl], dY[sl], s)
        pA1, pA2 = p1 * self.A1, p2 * self.A2
        s.a = (pA1 - pA2 - self.pa_dA - s.Ff + s.F) / s.M - self.g_sin
        for f, P, sl in hooks["after_piston"]:
            f(P, Y[sl], dY[sl], s)

        # ---- chambers
        V1 = self.V01 + self.A1 * x
        V2 = self.V02 + self.A2 * (self.L - x)
        if hooks["chambers"]:
            s.V1, s.V2 = V1, V2
            s.kap1 = s.kap2 = KAPPA
            s.Q1 = s.Q2 = None
            for f, P, sl in hooks["chambers"]:
                f(P, Y[sl], dY[sl], s)
            dY[0] = s.kap1 / V1 * (self.RT * s.m1 - pA1 * v)
            dY[1] = s.kap2 / V2 * (self.RT * s.m2 + pA2 * v)
            if s.Q1 is not None:
                dY[0] += (KAPPA - 1.0) * s.Q1 / V1
                dY[1] += (KAPPA - 1.0) * s.Q2 / V2
        else:
            dY[0] = KAPPA / V1 * (self.RT * s.m1 - pA1 * v)
            dY[1] = KAPPA / V2 * (self.RT * s.m2 + pA2 * v)
        dY[2] = v
        dY[3] = s.a
        if self.lag_rows is not None:
            dY[self.lag_rows] = (Y[0:2] - Y[self.lag_rows]) * self.inv_lag
        return dY

    def advance(self, Y: np.ndarray, k: int) -> np.ndarray:
        """Integrate over sample interval k (classical RK4, N substeps)."""
        h = self.h
        h2, h6 = 0.5 * h, h / 6.0
        rhs = self.rhs
        self.begin_sample(Y)
        for i in range(self.N):
            k1 = rhs(Y, (k, i, 0))
            k2 = rhs(Y + h2 * k1, (k, i, 1))
            k3 = rhs(Y + h2 * k2, (k, i, 1))
            k4 = rhs(Y + h * k3, (k, i, 2))
            Y = Y + h6 * (k1 + k4 + 2.0 * (k2 + k3))
        return Y


def _ladder(n: float) -> int:
    """The smallest of 8, 10, 12, 16, 20, 24, 32, ... (steps of at most 4/3) that is >= n."""
    e = 3
    while True:
        for m in (8, 10, 12):
            if m << (e - 3) >= n:
                return m << (e - 3)
        e += 1


def substeps_for(case: Case) -> int:
    """RK4 substeps per sample period the automatic choice takes for `case`: |lambda_max| h <=
    SAFETY for an upper bound lambda_max of the case's fastest rate, rounded up to a ladder
    value. It depends on the case alone, so a case's run does not depend on its batch."""
    return _Batch([case], None).N


def simulate_detailed(cases: Sequence[Case], substeps: int | Sequence[int | None] | None = None,
                      progress: Callable[[str], None] | None = None) -> list[Result]:
    """Simulate cases, returning runs and true states. Cases with the same sample rate and the
    same number of substeps run as one vectorised batch.

    substeps: RK4 substeps per sample period for every case, or one per case (None: the case's
    own choice, substeps_for(case), so that a case's run does not depend on the other cases; this
    is the default). A batch costs about the same per step whatever number of cases it holds, so
    cases with different forms and steps run faster together at the finest step any of them
    needs, substeps=max(substeps_for(c) for c in cases); their runs then differ from the default
    ones by nanometres."""
    cases = list(cases)
    per_case = list(substeps) if isinstance(substeps, Sequence) else [substeps] * len(cases)
    if len(per_case) != len(cases):
        raise ValueError(f"substeps: {len(per_case)} values for {len(cases)} cases")
    results: list[Result | None] = [None] * len(cases)
    groups: dict[tuple[float, int], list[int]] = {}
    for i, (c, n) in enumerate(zip(cases, per_case)):
        groups.setdefault((float(c.rate), int(n) if n else substeps_for(c)), []).append(i)
    for (_, N), idx in groups.items():
        for i, r in zip(idx, _simulate_batch([cases[i] for i in idx], N, progress)):
            results[i] = r
    return [r for r in results if r is not None]


def simulate(cases: Sequence[Case], substeps: int | Sequence[int | None] | None = None,
             progress: Callable[[str], None] | None = None) -> list[Run]:
    """The runs of `cases` (see Case), each with comment lines that describe the truth."""
    return [r.run for r in simulate_detailed(cases, substeps, progress)]


def sensor_noise(case: Case) -> np.ndarray:
    """The noise the sensors add to the case's run: (samples, 3) for x, p1, p2, drawn from its seed
    (zeros without noise)."""
    if not case.noise:
        return np.zeros((case.n_samples, 3))
    sen = case.cyl.sensors
    draw = np.random.default_rng(case.seed).standard_normal((case.n_samples, 3))
    return draw * np.array([sen.position_noise, sen.pressure_noise, sen.pressure_noise])


def cached_runs(cases: Sequence[Case], cache: Path | None) -> list[Run]:
    """The runs of `cases`, each simulated once and kept in `cache` as a run file named by the
    case's content hash (Case.key), with its true states beside it (cached_states): a benchmark
    rerun on changed code skips the simulation (minutes per case). Without a cache, simulated."""
    if cache is None:
        return simulate(cases)
    _simulate_into(cache, [c for c in cases if not (cache / f"{c.key()}.csv").exists()])
    return [read_run(cache / f"{c.key()}.csv") for c in cases]


def cached_states(cases: Sequence[Case], cache: Path) -> list[dict[str, np.ndarray]]:
    """The true states of the runs of `cases` (Result.states), kept in `cache` beside the runs;
    a run stored without them is simulated again."""
    _simulate_into(cache, [c for c in cases if not (cache / f"{c.key()}.states.npz").exists()])
    out = []
    for c in cases:
        with np.load(cache / f"{c.key()}.states.npz") as z:
            out.append({k: z[k] for k in z.files})
    return out


def _simulate_into(cache: Path, cases: list[Case]) -> None:
    """Simulate `cases` and store each run and its true states in `cache`, each file written whole
    (write_run is atomic; the states go to a temporary file renamed) so that an interrupted
    benchmark leaves no half-written one."""
    if not cases:
        return
    cache.mkdir(parents=True, exist_ok=True)
    print(f"simulating {len(cases)} runs on the reference plant ...", file=sys.stderr, flush=True)
    for res in simulate_detailed(cases, progress=lambda line: print(line, file=sys.stderr, flush=True)):
        key = res.case.key()
        tmp = cache / f"{key}.states.tmp.npz"
        np.savez(tmp, **res.states)
        tmp.replace(cache / f"{key}.states.npz")
        write_run(cache / f"{key}.csv", res.run, comments=list(res.run.comments))


def _simulate_batch(cases: list[Case], substeps: int | None, progress) -> list[Result]:
    t_start = time.perf_counter()
    batch = _Batch(cases, substeps)
    n = batch.n
    lengths = np.array([c.n_samples for c in cases])
    n_max = int(lengths.max())
    # held command of every interval (row U_off + j: interval j, [j dt, (j + 1) dt]); rows
    # before U_off are the rest before the start (a dead time looks back into them)
    max_delay = max([e.tau for c in cases for e in c.effects if isinstance(e, DelayTransport)] + [0.0])
    batch.U_off = int(math.ceil(max_delay / batch.dt)) + 2
    batch.U = np.zeros((batch.U_off + n_max + 2, n))
    batch.U[:batch.U_off + 1] = [c.command_before for c in cases]
    Y = batch.initial_state(cases)
    programs = [None if c.commands is not None else _program(c) for c in cases]
    is_open = np.array([p is None for p in programs])
    open_loop = np.zeros((n_max, n))
    for j, c in enumerate(cases):
        if c.commands is not None:
            open_loop[:lengths[j], j] = np.clip(c.commands, -1.0, 1.0)
    noise = np.zeros((n_max, 3, n))
    for j, c in enumerate(cases):
        noise[:lengths[j], :, j] = sensor_noise(c)

    states = np.empty((n_max, batch.nstate, n))
    meas = np.empty((n_max, 3, n))
    u_rows = np.zeros((n_max, n))
    sent = np.zeros(n)  # the last command computed, latched at the next tick
    every = max(1, n_max // 20)
    for k in range(n_max):
        batch.u_held = batch.U[batch.U_off + k]
        Y = batch.advance(Y, k)
        if not np.all(np.isfinite(Y)):
            bad = [cases[j].seed for j in np.flatnonzero(~np.all(np.isfinite(Y), axis=0))]
            raise FloatingPointError(f"reference plant diverged at t = {(k + 1) * batch.dt:.4f} s (seeds {bad}).")
        states[k] = Y
        x_m = batch.gain_x * Y[2] + noise[k, 0]
        p_src = Y[batch.lag_rows] if batch.lag_rows is not None else Y[0:2]
        if batch.lag_rows is not None:
            p_src = np.where(batch.lag_on, p_src, Y[0:2])
        p_m = batch.pa + batch.gain_p * (p_src - batch.pa) + batch.offset_p + noise[k, 1:3]
        meas[k, 0], meas[k, 1:3] = x_m, p_m
        # latch: closed loop the command computed at the previous sample, open loop the given one
        latched = np.where(is_open, open_loop[k], sent)
        batch.U[batch.U_off + k + 1] = latched
        u_rows[k] = latched
        t_k = (k + 1) * batch.dt
        for j, prog in enumerate(programs):
            if prog is not None and k < lengths[j]:
                sent[j] = _bounded(prog.command(t_k, float(x_m[j])))
        if progress and k % every == 0 and k:
            progress(f"  reference plant: {t_k:6.2f} / {n_max * batch.dt:g} s ({n} cases, {batch.N} substeps)")
    wall = time.perf_counter() - t_start

    out = []
    names = batch.state_names
    for j, c in enumerate(cases):
        m = lengths[j]
        t = (np.arange(m) + 1) * batch.dt
        comments = _comments(c, batch.N)
        run = Run(t=t, u=u_rows[:m, j].copy(), x=meas[:m, 0, j].copy(), p1=meas[:m, 1, j].copy(),
                  p2=meas[:m, 2, j].copy(), comments=tuple(comments))
        st = {name: states[:m, i, j].copy() for i, name in enumerate(names)}
        out.append(Result(case=c, run=run, states=st, substeps=batch.N, wall_s=wall))
    return out


def _bounded(u: float) -> float:
    return 0.0 if u != u else max(-1.0, min(1.0, float(u)))


def _program(case: Case):
    # imported here: the project's live package pulls in its own plant, which only the
    # closed-loop excitation needs (the controller itself is plain Python)
    from combined_reality.live.programs import make_program

    return make_program(case.program, case.cyl, case.duration, seed=case.seed)


def _comments(case: Case, substeps: int) -> list[str]:
    return [cylinder_tag(case.cyl),
            f"reference plant (benchmarks/reference_plant.py, revision {REVISION}): RK4, {substeps} substeps per "
            f"sample; {f'closed loop ({case.program})' if case.commands is None else 'open loop'}, seed {case.seed}, "
            f"noise {'on' if case.noise else 'off'}",
            "truth: " + json.dumps(case.truth(), sort_keys=True, default=str)]


# ------------------------------------------------------------------ command line


def _parse_departure(spec: str) -> tuple[str, Any]:
    key, eq, value = spec.partition("=")
    key = key.strip()
    if not eq:
        raise ValueError(f"departure {spec!r}: expected KEY=VALUE.")
    if key.startswith("characteristic_"):
        return key, make_shape(value)
    return key, float(value)


def _listing() -> str:
    lines = []
    for (word, form), cls in _ALL_FORMS.items():
        doc = " ".join((cls.__doc__ or "").strip().split("\n\n")[0].split())  # the first paragraph
        lines.append(f"{word}:{form}  {doc}")
        for k, p in cls.PARAMS.items():
            neutral = f", neutral {cls.NEUTRAL[k]:g}" if k in cls.NEUTRAL else ""
            scale = f" x {p.scale}" if p.scale else ""
            lines.append(f"    {k} [{p.unit}] {p.description}; {p.kind} {p.low:g}..{p.high:g}{scale}; "
                         f"default {getattr(cls(), k):g}{neutral}")
    lines.append("departures: " + ", ".join(f.name for f in fields(Calibration))
                 + "  (characteristic_pos/neg=SHAPE,k=v,...; shapes: " + ", ".join(SHAPES) + ")")
    lines.append("sensors: " + ", ".join(f.name for f in fields(SensorDepartures)))
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Simulate a run on the independent reference plant (numpy, RK4) "
                                             "and write it as a run CSV whose comments describe the truth.")
    ap.add_argument("--config", help="cylinder file (TOML)")
    ap.add_argument("--case", help="a case JSON written by --truth (replaces the other case options)")
    ap.add_argument("--duration", type=float, default=20.0, help="run length in s (default 20)")
    ap.add_argument("--seed", type=int, default=1, help="excitation and noise seed (default 1)")
    ap.add_argument("--rate", type=float, default=1000.0, help="sample rate in Hz (default 1000)")
    ap.add_argument("--effect", action="append", default=[], metavar="WORD:FORM[:k=v,...]",
                    help="an unmodelled effect (repeatable); see --list")
    ap.add_argument("--random-effect", action="append", default=[], metavar="WORD[:FORM]",
                    help="an unmodelled effect at a random realistic strength drawn with --seed (repeatable)")
    ap.add_argument("--random-departures", action="store_true",
                    help="random realistic calibration departures drawn with --seed (--departure overrides)")
    ap.add_argument("--departure", action="append", default=[], metavar="KEY=VALUE",
                    help="a calibration departure, e.g. conductance_pos=0.8 or "
                         "characteristic_neg=power,exponent=1.5,overlap=0.05 (repeatable)")
    ap.add_argument("--sensor", action="append", default=[], metavar="KEY=VALUE",
                    help="a sensor departure, e.g. pressure_lag=0.004 (repeatable)")
    ap.add_argument("--no-noise", action="store_true", help="noise-free sensors")
    ap.add_argument("--substeps", type=int, help="RK4 substeps per sample (default: automatic)")
    ap.add_argument("-o", "--output", help="run CSV to write")
    ap.add_argument("--truth", help="also write the case (truth included) as JSON here")
    ap.add_argument("--list", action="store_true", help="list effect forms, departures and sensor errors")
    args = ap.parse_args(argv)
    if args.list:
        print(_listing())
        return 0
    try:
        if args.case:
            case = Case.from_json(json.loads(Path(args.case).read_text(encoding="utf-8")))
        else:
            if not args.config:
                raise ValueError("--config (or --case) is required.")
            cyl = load_cylinder(args.config)
            rng = np.random.default_rng([args.seed, 20240])  # a stream apart from the noise's
            cal = Calibration.random(rng, cyl) if args.random_departures else Calibration()
            cal = Calibration(**{**{f.name: getattr(cal, f.name) for f in fields(cal)},
                                 **dict(_parse_departure(d) for d in args.departure)})
            sen = SensorDepartures(**{k: v for k, v in (_parse_departure(d) for d in args.sensor)})
            effects = [parse_effect(e, cyl) for e in args.effect]
            for spec in args.random_effect:
                word, _, form = spec.partition(":")
                effects.append(random_effect(rng, cyl, word, form or None))
            case = Case(cyl=cyl, duration=args.duration, seed=args.seed, rate=args.rate, calibration=cal,
                        effects=tuple(effects), sensors=sen, noise=not args.no_noise)
        if not args.output:
            raise ValueError("-o/--output is required.")
    except (ValueError, TypeError, OSError) as e:
        print(f"reference_plant: {e}", file=sys.stderr)
        return 2
    res = simulate_detailed([case], substeps=args.substeps)[0]
    write_run(args.output, res.run, res.run.comments)
    if args.truth:
        Path(args.truth).write_text(json.dumps(case.to_json(), indent=1) + "\n", encoding="utf-8")
    print(f"{args.output}: {len(res.run.t)} samples, {res.substeps} substeps, {res.wall_s:.1f} s wall; "
          f"truth {case.truth()['verdict']}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
