"""A cylinder as typed, frozen, SI parameters, loaded from the cylinder TOML (docs/formats.md).

Units are SI everywhere inside; the only conversion at this edge is the mounting
angle, which the file gives in degrees and the model uses in radians.

Beyond the nominal model's values, a cylinder file may state what a real rig needs
calibrated (`combined-reality calibrate` writes them): the valve's flow characteristic
per direction, the pressure sensors' offsets, a constant external force, and the end
stops' stiffness and damping. A file that leaves them out describes the nominal model.
"""
from __future__ import annotations

import itertools
import math
import tomllib
from dataclasses import MISSING, dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Mapping, Sequence

from .errors import InputError
from .inputs import TOML_MAX_BYTES, decode_text, parse_toml, read_checked, shorten


class ConfigError(InputError):
    """A cylinder file that cannot be used; the message is one sentence naming file and key (exit
    status 2)."""


@dataclass(frozen=True)
class Geometry:
    bore: float  # m
    rod: float  # m (0 for a rodless / through-rod-free design: A2 = A1)
    stroke: float  # m
    dead_volume_cap: float  # m^3, V01
    dead_volume_rod: float  # m^3, V02

    @property
    def area_cap(self) -> float:
        return math.pi * self.bore**2 / 4.0

    @property
    def area_rod(self) -> float:
        return math.pi * (self.bore**2 - self.rod**2) / 4.0


@dataclass(frozen=True)
class Mechanics:
    moving_mass: float  # kg
    angle: float = 0.0  # rad (file: deg), positive when extension lifts the load
    external_force: float = 0.0  # N, a constant force on the piston, positive towards extension
    end_stiffness: float = 1.0e6  # N/m, of the end stops at x = 0 and x = stroke
    end_damping: float = 2.0e3  # N s/m, of the end stops (while in contact)


@dataclass(frozen=True)
class Supply:
    pressure: float  # Pa absolute
    atmosphere: float = 1.013e5  # Pa absolute
    temperature: float = 293.15  # K


# The valve's flow characteristic is given at these openings, as fractions of the command range
# beyond the overlap (the last is full opening); between them it is the monotone cubic through
# them (PCHIP). Denser at small openings, where closed-loop position control spends most of its
# time: a real valve's curve there (a power of the opening, an S-shape) decides how the piston
# creeps. On the calibration benchmark's Norgren rigs, the earlier grid of 11 openings could not
# follow such curves closely enough: the whole model fitted their calibration runs to 1.25-1.67 x
# the sensor noise, and predicted another run to 3.1-16 x in 4 of 6; on these 15 it fits to
# 1.00-1.11 x and predicts to 1.0-1.8 x.
OPENING_GRID: tuple[float, ...] = (0.01, 0.03, 0.06, 0.1, 0.14, 0.18, 0.23, 0.28, 0.34, 0.4, 0.5, 0.6, 0.7, 0.85, 1.0)
# Grids of earlier versions: a cylinder file with as many levels is read on its own grid and
# resampled onto OPENING_GRID (the same monotone cubic, evaluated there).
EARLIER_OPENING_GRIDS: tuple[tuple[float, ...], ...] = (
    (0.02, 0.05, 0.1, 0.175, 0.25, 0.325, 0.4, 0.5, 0.6, 0.8, 1.0),
)
VALVE_DIRECTIONS: tuple[str, ...] = ("extend", "retract")  # u > 0, u < 0


@dataclass(frozen=True)
class Valve:
    """A 5/3 proportional valve. In direction D (extend: u > 0, retract: u < 0) each path has
    the sonic conductance C = sonic_conductance * flow_D(s) at the opening s = (|u| - overlap_D)
    / (1 - overlap_D) (closed for |u| <= overlap_D); flow_D is the monotone piecewise-cubic
    (PCHIP) curve through (0, 0) and (OPENING_GRID[k], flow_D[k]), non-decreasing. The defaults
    are the linear law C = sonic_conductance * |u| of the nominal model."""

    sonic_conductance: float  # m^3/(s Pa) per path at full opening
    critical_ratio: float = 0.3
    overlap_extend: float = 0.0
    overlap_retract: float = 0.0
    flow_extend: tuple[float, ...] = OPENING_GRID
    flow_retract: tuple[float, ...] = OPENING_GRID

    def flow_increments(self, direction: str) -> tuple[float, ...]:
        """The rise of the flow characteristic over each grid segment (what the plant takes)."""
        levels = getattr(self, f"flow_{direction}")
        return tuple(b - a for a, b in zip((0.0, *levels[:-1]), levels))

    @property
    def is_linear(self) -> bool:
        return (self.overlap_extend == 0.0 and self.overlap_retract == 0.0
                and self.flow_extend == OPENING_GRID and self.flow_retract == OPENING_GRID)


@dataclass(frozen=True)
class Friction:
    Fc: float  # N
    Fv: float  # N s/m
    kp: float  # N/Pa
    v_smooth: float = 1.0e-3  # m/s


@dataclass(frozen=True)
class Sensors:
    """White sensor noise (standard deviations: identification weights and virtual-rig noise)
    and the pressure sensors' offsets (what a sensor reads minus the true pressure)."""

    position_noise: float = 5.0e-6  # m
    pressure_noise: float = 300.0  # Pa
    offset_p1: float = 0.0  # Pa
    offset_p2: float = 0.0  # Pa


@dataclass(frozen=True)
class IdentifySettings:
    estimate: tuple[str, ...] = ("Fc", "Fv", "kp")
    drive: str = "command"  # "command", "pressure" or "chambers" (see sim.plant.DRIVES)


@dataclass(frozen=True)
class Cylinder:
    name: str
    geometry: Geometry
    mechanics: Mechanics
    supply: Supply
    valve: Valve
    friction: Friction
    sensors: Sensors = field(default_factory=Sensors)
    identify: IdentifySettings = field(default_factory=IdentifySettings)
    source: Path | None = field(default=None, compare=False)

    def value(self, name: str) -> float:
        spec = PARAMETERS[name]
        section = getattr(self, spec.section)
        if spec.segment is None:
            return float(getattr(section, spec.attr))
        return float(section.flow_increments(spec.attr.removeprefix("flow_"))[spec.segment])

    def with_values(self, values: Mapping[str, float]) -> "Cylinder":
        """A copy with the named model parameters (PARAMETERS keys) replaced."""
        sections: dict[str, dict[str, object]] = {}
        rises: dict[str, list[float]] = {}
        for name, v in values.items():
            spec = PARAMETERS[name]
            if spec.segment is None:
                sections.setdefault(spec.section, {})[spec.attr] = float(v)
                continue
            direction = spec.attr.removeprefix("flow_")
            rise = rises.setdefault(spec.attr, list(self.valve.flow_increments(direction)))
            rise[spec.segment] = float(v)
        for attr, rise in rises.items():  # a flow characteristic is the running sum of its rises
            sections.setdefault("valve", {})[attr] = tuple(float(x) for x in itertools.accumulate(rise))
        return replace(self, **{s: replace(getattr(self, s), **kw) for s, kw in sections.items()})


@dataclass(frozen=True)
class ParameterSpec:
    section: str
    attr: str
    unit: str
    lower: float  # bounds used by the identifier
    upper: float
    description: str
    segment: int | None = None  # a flow characteristic's rise over this grid segment (attr: flow_D)


def _flow_parameters() -> dict[str, ParameterSpec]:
    """The valve's flow characteristic as parameters: per direction the overlap and the rise of
    C / sonic_conductance over every grid segment (rises >= 0 keep the curve non-decreasing)."""
    out = {}
    for d, sign in zip(VALVE_DIRECTIONS, ("u > 0", "u < 0")):
        out[f"overlap_{d}"] = ParameterSpec("valve", f"overlap_{d}", "1", 0.0, 0.5,
                                            f"valve overlap, {d} ({sign}): closed below this |u|")
        lo = 0.0
        for k, hi in enumerate(OPENING_GRID):
            out[f"flow_{d}_{k + 1}"] = ParameterSpec(
                "valve", f"flow_{d}", "1", 0.0, 5.0,
                f"rise of C/Cmax, {d} ({sign}), from {lo:.0%} to {hi:.0%} of the opening", segment=k)
            lo = hi
    return out


# Every physical parameter of the nominal model under its canonical (command-line, JSON) name.
# Order matters: it is the order of the model's parameter vector.
PARAMETERS: dict[str, ParameterSpec] = {
    "bore": ParameterSpec("geometry", "bore", "m", 1e-3, 1.0, "bore diameter D"),
    "rod": ParameterSpec("geometry", "rod", "m", 0.0, 1.0, "rod diameter d"),
    "stroke": ParameterSpec("geometry", "stroke", "m", 1e-3, 10.0, "stroke L"),
    "dead_volume_cap": ParameterSpec("geometry", "dead_volume_cap", "m^3", 1e-8, 1e-2, "cap-side dead volume V01"),
    "dead_volume_rod": ParameterSpec("geometry", "dead_volume_rod", "m^3", 1e-8, 1e-2, "rod-side dead volume V02"),
    "mass": ParameterSpec("mechanics", "moving_mass", "kg", 1e-3, 1e4, "moving mass M"),
    "angle": ParameterSpec("mechanics", "angle", "rad", -math.pi / 2, math.pi / 2, "mounting angle"),
    "supply_pressure": ParameterSpec("supply", "pressure", "Pa", 1e5, 5e6, "supply pressure ps"),
    "atmosphere": ParameterSpec("supply", "atmosphere", "Pa", 5e4, 2e5, "atmospheric pressure pa"),
    "temperature": ParameterSpec("supply", "temperature", "K", 200.0, 400.0, "supply temperature T"),
    "conductance": ParameterSpec("valve", "sonic_conductance", "m^3/(s Pa)", 1e-12, 1e-5, "valve sonic conductance Cmax"),
    "critical_ratio": ParameterSpec("valve", "critical_ratio", "1", 0.01, 0.9, "valve critical pressure ratio b"),
    "Fc": ParameterSpec("friction", "Fc", "N", 0.0, 1e4, "Coulomb friction"),
    "Fv": ParameterSpec("friction", "Fv", "N s/m", 0.0, 1e5, "viscous friction coefficient"),
    "kp": ParameterSpec("friction", "kp", "N/Pa", 0.0, 1e-2, "seal-pressure friction coefficient"),
    "v_smooth": ParameterSpec("friction", "v_smooth", "m/s", 1e-6, 1.0, "friction smoothing velocity"),
    "external_force": ParameterSpec("mechanics", "external_force", "N", -1e5, 1e5,
                                    "constant external force, positive towards extension"),
    "end_stiffness": ParameterSpec("mechanics", "end_stiffness", "N/m", 1e3, 1e10, "stiffness of the end stops"),
    "end_damping": ParameterSpec("mechanics", "end_damping", "N s/m", 0.0, 1e7, "damping of the end stops"),
    "offset_p1": ParameterSpec("sensors", "offset_p1", "Pa", -5e4, 5e4, "offset of the p1 sensor (reads p1 + offset)"),
    "offset_p2": ParameterSpec("sensors", "offset_p2", "Pa", -5e4, 5e4, "offset of the p2 sensor (reads p2 + offset)"),
    **_flow_parameters(),
}

# The valve's flow characteristic, every parameter of it (overlaps, then rises per direction).
FLOW_CHARACTERISTIC = tuple(n for n in PARAMETERS if n.startswith(("overlap_", "flow_")))

# The parameters a user may ask the identifier to estimate (geometry and supply are measured, not fitted).
ESTIMABLE = ("Fc", "Fv", "kp", "mass", "conductance", "critical_ratio",
             "dead_volume_cap", "dead_volume_rod", "angle", "external_force", "offset_p1", "offset_p2",
             *FLOW_CHARACTERISTIC)


# --------------------------------------------------------------------------- loading

# the file's tables and their keys are the sections of Cylinder and their fields (a field's
# default, if any, is the key's; the angle's 0.0 is the same in degrees and radians)
_SECTIONS = {"geometry": Geometry, "mechanics": Mechanics, "supply": Supply, "valve": Valve,
             "friction": Friction, "sensors": Sensors, "identify": IdentifySettings}
_SCHEMA: dict[str, dict[str, Any]] = {
    section: {f.name: f.default for f in fields(cls)}  # MISSING: required
    for section, cls in _SECTIONS.items()}
_FLOWS = {f"flow_{d}" for d in VALVE_DIRECTIONS}  # lists: the flow characteristic
_OPTIONAL_SECTIONS = {"sensors", "identify"}
# why a value above (+1) or below (-1) the parameter's bounds is most likely wrong
_HINTS = {("geometry.bore", 1): "lengths are in metres, not mm",
          ("geometry.stroke", 1): "lengths are in metres, not mm",
          ("supply.pressure", -1): "an absolute pressure in Pa (bar or gauge?)",
          ("supply.atmosphere", -1): "an absolute pressure in Pa (about 1.013e5)",
          ("supply.atmosphere", 1): "an absolute pressure in Pa (about 1.013e5)"}


def load_cylinder(path: str | Path) -> Cylinder:
    path = Path(path)
    text = decode_text(read_checked(path, "a cylinder file", ConfigError, TOML_MAX_BYTES),
                       lambda line, _: ConfigError(f"{path}, line {line}: not UTF-8 text (a cylinder file is TOML, "
                                                   "which is UTF-8; save it as UTF-8)."))
    try:
        data = parse_toml(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: not valid TOML ({e}).") from None
    return parse_cylinder(data, path)


def parse_cylinder(data: Mapping[str, Any], source: str | Path | None = None) -> Cylinder:
    where = str(source) if source is not None else "<cylinder>"

    def fail(msg: str) -> ConfigError:
        return ConfigError(f"{where}: {msg}")

    for key in data:
        if key != "name" and key not in _SCHEMA:
            raise fail(f"unknown key '{shorten(key)}' (expected name, {', '.join(_SCHEMA)}).")
    name = data.get("name", Path(where).stem)
    if not isinstance(name, str):
        raise fail("key 'name' must be a string.")

    values: dict[str, dict[str, Any]] = {}
    for section, keys in _SCHEMA.items():
        table = data.get(section)
        if table is None:
            if section not in _OPTIONAL_SECTIONS:
                raise fail(f"missing table [{section}].")
            table = {}
        if not isinstance(table, dict):
            raise fail(f"key '{section}' must be a table [{section}].")
        for key in table:
            if key not in keys:
                raise fail(f"unknown key '{section}.{shorten(key)}' (expected one of {', '.join(keys)}).")
        vals: dict[str, Any] = {}
        for key, default in keys.items():
            full = f"{section}.{key}"
            if key not in table:
                if default is MISSING:
                    raise fail(f"missing key '{full}'.")
                vals[key] = default
                continue
            v = table[key]
            if section == "identify":
                vals[key] = _check_identify(key, v, fail)
                continue
            if key in _FLOWS:
                vals[key] = _flow_levels(v, full, fail)
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise fail(f"key '{full}' must be a number, not {type(v).__name__} {shorten(repr(v))}.")
            v = float(v)
            if not math.isfinite(v):
                raise fail(f"key '{full}' must be finite, not {v}.")
            vals[key] = v
        values[section] = vals

    _check_physics(values, fail)
    values["mechanics"]["angle"] = math.radians(values["mechanics"]["angle"])
    return Cylinder(name=name, source=Path(source) if source is not None else None,
                    **{section: cls(**values[section]) for section, cls in _SECTIONS.items()})


def _flow_levels(v: Any, full: str, fail) -> tuple[float, ...]:
    """valve.flow_extend / flow_retract: C / sonic_conductance at OPENING_GRID (or at an earlier
    version's grid, then resampled), non-decreasing."""
    grid = ", ".join(f"{g:g}" for g in OPENING_GRID)
    earlier = {len(g): g for g in EARLIER_OPENING_GRIDS}
    if (not isinstance(v, list) or len(v) not in (len(OPENING_GRID), *earlier)
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)):
        raise fail(f"key '{full}' must be a list of {len(OPENING_GRID)} numbers: C / sonic_conductance at "
                   f"{grid} of the opening beyond the overlap (or {' or '.join(map(str, earlier))} numbers, on "
                   "the grid of earlier versions).")
    levels = tuple(float(x) for x in v)
    if levels[0] < 0 or any(b < a for a, b in zip(levels, levels[1:])):
        raise fail(f"key '{full}' must be non-negative and non-decreasing (a valve opens further as the "
                   f"command grows), not {list(levels)}.")
    if not 0 < levels[-1] <= 5.0:
        raise fail(f"key '{full}' must end (full opening) between 0 and 5 times sonic_conductance, "
                   f"not {levels[-1]:g}.")
    if len(levels) != len(OPENING_GRID):
        levels = resampled_levels(earlier[len(levels)], levels)
    return levels


def resampled_levels(grid: tuple[float, ...], levels: tuple[float, ...]) -> tuple[float, ...]:
    """A flow characteristic given at `grid`, at OPENING_GRID (flow_levels_at). A straight
    characteristic stays exactly straight (the linear law is a cheaper plant)."""
    full = levels[-1]
    if all(abs(level - full * g) <= 1e-12 * full for level, g in zip(levels, grid)):
        return tuple(full * g for g in OPENING_GRID)
    return flow_levels_at(grid, levels, OPENING_GRID)


def flow_levels_at(grid: tuple[float, ...], levels: tuple[float, ...], openings) -> tuple[float, ...]:
    """The flow characteristic whose `levels` are given at the openings `grid` (ending at full
    opening, 1), at other `openings` in [0, 1]: the plant's own monotone cubic through (0, 0)
    and them (sim.flow.flow_characteristic), non-decreasing, full opening's level kept exactly."""
    import casadi as ca  # here: reading a cylinder file needs no numerics otherwise

    from .flow import flow_characteristic

    a = [float(x) for x in openings]
    rises = [ca.DM(b - c) for c, b in zip((0.0, *levels), levels)]
    y = ca.DM(flow_characteristic(ca.DM(a), rises, grid)).elements()
    out = [levels[-1] if math.isclose(x, 1.0) else max(float(v), 0.0) for x, v in zip(a, y)]
    return tuple(itertools.accumulate(out, max))


def _check_identify(key: str, v: Any, fail) -> Any:
    if key == "drive":
        if v not in ("command", "pressure", "chambers"):
            raise fail(f"key 'identify.drive' must be \"command\", \"pressure\" or \"chambers\", "
                       f"not {shorten(repr(v))}.")
        return v
    if not isinstance(v, list) or not v or not all(isinstance(s, str) for s in v):
        raise fail("key 'identify.estimate' must be a non-empty list of parameter names.")
    problem = parameter_list_problem(v, ESTIMABLE)
    if problem:
        raise fail(f"key 'identify.estimate' {problem}.")
    return tuple(v)


def parameter_list_problem(names: Sequence[str], known: Sequence[str] | None = None) -> str | None:
    """What is wrong with a list of parameter names, to follow the option's or key's name: one
    named more than once, or (with `known`) one not among them; None if nothing is. The one
    rule of a cylinder file's identify.estimate and of the command line's lists."""
    twice = sorted({n for n in names if list(names).count(n) > 1})
    if twice:
        return f"names {', '.join(shorten(n) for n in twice)} more than once; give each once"
    unknown = [n for n in names if known is not None and n not in known]
    if unknown:
        return f"names unknown parameter '{shorten(unknown[0])}' (estimable: {', '.join(known)})"
    return None


def _check_physics(v: dict[str, dict[str, Any]], fail) -> None:
    """Every model parameter within the identifier's bounds (PARAMETERS), then what relates keys."""
    for spec in PARAMETERS.values():
        if spec.segment is not None:
            continue  # the flow characteristic: checked as a whole where it is read
        full, x = f"{spec.section}.{spec.attr}", v[spec.section][spec.attr]
        lo, hi, unit = spec.lower, spec.upper, spec.unit
        if full == "mechanics.angle":  # the file gives degrees
            lo, hi, unit = math.degrees(lo), math.degrees(hi), "degrees"
        if not lo <= x <= hi:
            hint = _HINTS.get((full, 1 if x > hi else -1))
            hint = f"; {hint}" if hint else ""
            unit = "" if unit == "1" else f" {unit}"
            positive = "be positive and " if x <= 0 < lo else ""
            raise fail(f"key '{full}' must {positive}lie in [{lo:g}, {hi:g}]{unit} ({spec.description}), "
                       f"not {x:g}{hint}.")
    g, s = v["geometry"], v["supply"]
    if not g["rod"] < g["bore"]:
        raise fail(f"key 'geometry.rod' must be smaller than the bore, not {g['rod']:g} m.")
    if s["pressure"] <= s["atmosphere"]:
        raise fail(f"key 'supply.pressure' must be an absolute pressure in Pa above atmosphere, not {s['pressure']:g} "
                   "(bar or gauge?).")
    for key, unit in (("position_noise", "m"), ("pressure_noise", "Pa")):
        if v["sensors"][key] <= 0:
            raise fail(f"key 'sensors.{key}' must be positive ({unit}), not {v['sensors'][key]:g}.")


def cylinder_to_toml(cyl: Cylinder) -> str:
    """The cylinder in the cylinder-file layout (round-trips through load_cylinder)."""
    lines = [f"name = {_toml_str(cyl.name)}", ""]
    for section in ("geometry", "mechanics", "supply", "valve", "friction", "sensors"):
        obj = getattr(cyl, section)
        lines.append(f"[{section}]")
        for f in fields(obj):
            val = getattr(obj, f.name)
            if section == "mechanics" and f.name == "angle":
                val = _angle_to_deg(val)
            if isinstance(val, tuple):
                val = list(val)
            lines.append(f"{f.name} = {val!r}")
        lines.append("")
    lines.append("[identify]")
    lines.append("estimate = [" + ", ".join(_toml_str(s) for s in cyl.identify.estimate) + "]")
    lines.append(f"drive = {_toml_str(cyl.identify.drive)}")
    return "\n".join(lines) + "\n"


def _angle_to_deg(rad: float) -> float:
    """Degrees that load_cylinder turns back into exactly ``rad``.

    math.degrees alone does not round-trip (radians(degrees(radians(57.0))) != radians(57.0)),
    so look for the shortest decimal, then the neighbouring doubles, that convert back exactly.
    """
    deg = math.degrees(rad)
    for candidate in (round(deg, digits) for digits in range(16)):
        if math.radians(candidate) == rad:
            return candidate
    lo = hi = deg
    for _ in range(4):
        lo, hi = math.nextafter(lo, -math.inf), math.nextafter(hi, math.inf)
        for candidate in (lo, hi):
            if math.radians(candidate) == rad:
                return candidate
    return deg  # not every double is radians(some double); nearest is the best there is


def _toml_str(s: str) -> str:
    s = s.replace("\\", "\\\\").replace('"', '\\"')
    # TOML basic strings may not hold raw control characters (a newline in a name would end it).
    return '"' + "".join(f"\\u{ord(c):04X}" if (ord(c) < 0x20 and c != "\t") or c == "\x7f" else c
                         for c in s) + '"'
