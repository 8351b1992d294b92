"""sim/cylinder.py: the cylinder TOML of docs/formats.md, its defaults, round trip and refusals."""
from __future__ import annotations

import math
import tomllib
from pathlib import Path

import pytest

from sim.cylinder import (
    EARLIER_OPENING_GRIDS,
    ESTIMABLE,
    FLOW_CHARACTERISTIC,
    OPENING_GRID,
    PARAMETERS,
    ConfigError,
    Cylinder,
    cylinder_to_toml,
    load_cylinder,
    parse_cylinder,
)

# The example of docs/formats.md, verbatim apart from the angle (non-zero so the conversion shows).
EXAMPLE = """\
name = "A"                      # free text

[geometry]
bore = 0.032                    # m
rod = 0.012                     # m
stroke = 0.200                  # m
dead_volume_cap = 1.5e-5        # m^3, V01
dead_volume_rod = 1.5e-5        # m^3, V02

[mechanics]
moving_mass = 0.8               # kg, piston + rod + payload
angle = 30.0                    # deg, positive when extension lifts the load

[supply]
pressure = 7.0e5                # Pa absolute
atmosphere = 1.013e5            # Pa absolute
temperature = 293.15            # K

[valve]
sonic_conductance = 6.0e-9      # m^3/(s Pa) per path at full opening
critical_ratio = 0.3

[friction]                      # starting values; identified ones are replaced
Fc = 10.0                       # N
Fv = 50.0                       # N s/m
kp = 1.0e-6                     # N/Pa
v_smooth = 1.0e-3               # m/s
"""

# Only the required keys: everything else must come from the defaults.
MINIMAL = """\
[geometry]
bore = 0.05
rod = 0.02
stroke = 0.3
dead_volume_cap = 2e-5
dead_volume_rod = 3e-5

[mechanics]
moving_mass = 1.2

[supply]
pressure = 6e5

[valve]
sonic_conductance = 5e-9

[friction]
Fc = 12
Fv = 40
kp = 0
"""


def write(tmp_path: Path, text: str, name: str = "cyl.toml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def edit(text: str, old: str, new: str) -> str:
    assert old in text, old  # guards the tests themselves against a typo in `old`
    return text.replace(old, new, 1)


def refused(tmp_path: Path, text: str, *fragments: str) -> str:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_cylinder(path)
    msg = str(info.value)
    assert str(path) in msg
    for frag in fragments:
        assert frag in msg, (frag, msg)
    assert "\n" not in msg and msg.endswith(".")
    return msg


# --------------------------------------------------------------------------- valid files


def test_formats_example_loads(tmp_path: Path) -> None:
    path = write(tmp_path, EXAMPLE)
    cyl = load_cylinder(path)
    assert cyl.name == "A"
    assert cyl.source == path
    g = cyl.geometry
    assert (g.bore, g.rod, g.stroke) == (0.032, 0.012, 0.200)
    assert (g.dead_volume_cap, g.dead_volume_rod) == (1.5e-5, 1.5e-5)
    assert cyl.mechanics.moving_mass == 0.8
    assert (cyl.supply.pressure, cyl.supply.atmosphere, cyl.supply.temperature) == (7.0e5, 1.013e5, 293.15)
    assert (cyl.valve.sonic_conductance, cyl.valve.critical_ratio) == (6.0e-9, 0.3)
    f = cyl.friction
    assert (f.Fc, f.Fv, f.kp, f.v_smooth) == (10.0, 50.0, 1.0e-6, 1.0e-3)
    assert g.area_cap == pytest.approx(804.25e-6, rel=1e-5)  # 32 mm bore: 256 pi mm^2
    assert g.area_rod == pytest.approx(691.15e-6, rel=1e-5)  # minus the 12 mm rod: 220 pi mm^2


def test_angle_is_converted_from_degrees_to_radians(tmp_path: Path) -> None:
    cyl = load_cylinder(write(tmp_path, EXAMPLE))
    assert cyl.mechanics.angle == pytest.approx(math.pi / 6)
    assert cyl.value("angle") == pytest.approx(math.pi / 6)


def test_defaults_are_applied(tmp_path: Path) -> None:
    path = write(tmp_path, MINIMAL, name="rig_b.toml")
    cyl = load_cylinder(path)
    assert cyl.name == "rig_b"  # no name: the file's stem
    assert cyl.mechanics.angle == 0.0
    assert cyl.supply.atmosphere == 1.013e5
    assert cyl.supply.temperature == 293.15
    assert cyl.valve.critical_ratio == 0.3
    assert cyl.friction.v_smooth == 1.0e-3
    assert cyl.sensors.position_noise == 5.0e-6
    assert cyl.sensors.pressure_noise == 300.0
    assert cyl.identify.estimate == ("Fc", "Fv", "kp")
    assert cyl.identify.drive == "command"
    # integers in the file are numbers like any other
    assert isinstance(cyl.friction.Fc, float) and cyl.friction.Fc == 12.0


def test_optional_tables_are_read(tmp_path: Path) -> None:
    text = MINIMAL + '\n[sensors]\nposition_noise = 1e-5\n\n[identify]\nestimate = ["Fc", "mass"]\ndrive = "pressure"\n'
    cyl = load_cylinder(write(tmp_path, text))
    assert cyl.sensors.position_noise == 1e-5
    assert cyl.sensors.pressure_noise == 300.0
    assert cyl.identify.estimate == ("Fc", "mass")
    assert cyl.identify.drive == "pressure"


@pytest.mark.parametrize("angle", ["0.0", "30.0", "57.0", "-12.5", "-89.3", "45", "90"])
def test_round_trip_through_toml(tmp_path: Path, angle: str) -> None:
    # 57.0 and -89.3 are among the angles whose degrees->radians->degrees is not exact
    text = EXAMPLE.replace("angle = 30.0", f"angle = {angle}")
    text += '\n[sensors]\npressure_noise = 250.0\n\n[identify]\nestimate = ["Fc", "Fv", "kp", "mass"]\n'
    cyl = load_cylinder(write(tmp_path, text))
    again = load_cylinder(write(tmp_path, cylinder_to_toml(cyl), name="again.toml"))
    assert again == cyl
    assert again.mechanics.angle == cyl.mechanics.angle  # exactly, not approximately


def test_round_trip_keeps_identified_values_and_awkward_names(tmp_path: Path) -> None:
    cyl = load_cylinder(write(tmp_path, EXAMPLE))
    cyl = cyl.with_values({"Fc": 20.123456789012345, "Fv": 1 / 3, "kp": 5.1e-6, "angle": math.radians(57.0)})
    from dataclasses import replace
    cyl = replace(cyl, name='Rig "A"\\2\nline two\ttab')
    again = load_cylinder(write(tmp_path, cylinder_to_toml(cyl), name="again.toml"))
    assert again == cyl


def test_parse_cylinder_from_a_mapping() -> None:
    import tomllib

    cyl = parse_cylinder(tomllib.loads(EXAMPLE))
    assert cyl.source is None and cyl.name == "A"
    with pytest.raises(ConfigError, match="<cylinder>"):
        parse_cylinder({"name": "x"})


def test_value_and_with_values(tmp_path: Path) -> None:
    cyl = load_cylinder(write(tmp_path, EXAMPLE))
    assert cyl.value("Fc") == 10.0
    assert cyl.value("mass") == 0.8  # canonical name differs from the attribute
    assert cyl.value("conductance") == 6.0e-9
    assert cyl.value("supply_pressure") == 7.0e5

    new = cyl.with_values({"Fc": 20, "Fv": 60.0, "mass": 1.5, "critical_ratio": 0.4})
    assert isinstance(new, Cylinder)
    assert (new.friction.Fc, new.friction.Fv, new.friction.kp) == (20.0, 60.0, 1.0e-6)
    assert isinstance(new.friction.Fc, float)
    assert new.mechanics.moving_mass == 1.5 and new.value("mass") == 1.5
    assert new.valve.critical_ratio == 0.4
    assert new.geometry == cyl.geometry
    # the original is untouched (frozen) and compares unequal
    assert cyl.friction.Fc == 10.0 and cyl.mechanics.moving_mass == 0.8
    assert new != cyl
    assert cyl.with_values({}) == cyl
    with pytest.raises(KeyError):
        cyl.value("nonsense")


def test_every_parameter_is_reachable(tmp_path: Path) -> None:
    cyl = load_cylinder(write(tmp_path, EXAMPLE))
    for name, spec in PARAMETERS.items():
        inside = spec.lower + 0.3 * (spec.upper - spec.lower)  # differs from every value of the example
        assert cyl.value(name) != inside and cyl.with_values({name: inside}).value(name) == pytest.approx(inside, rel=1e-12)
    assert set(ESTIMABLE) <= set(PARAMETERS)


# --------------------------------------------------------------------------- refusals


def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nope.toml"
    with pytest.raises(ConfigError) as info:
        load_cylinder(path)
    assert str(path) in str(info.value) and "not found" in str(info.value)


def test_invalid_toml(tmp_path: Path) -> None:
    refused(tmp_path, EXAMPLE.replace("bore = 0.032", "bore = = 0.032"), "not valid TOML")


def test_unknown_top_level_key(tmp_path: Path) -> None:
    refused(tmp_path, "colour = 'red'\n" + EXAMPLE, "'colour'")


def test_unknown_top_level_table(tmp_path: Path) -> None:
    refused(tmp_path, EXAMPLE + "\n[extras]\na = 1\n", "'extras'")


@pytest.mark.parametrize("section, line", [
    ("geometry", "bore = 0.032", ),
    ("friction", "Fc = 10.0"),
    ("supply", "pressure = 7.0e5"),
])
def test_unknown_key_in_table(tmp_path: Path, section: str, line: str) -> None:
    text = edit(EXAMPLE, line, f"{line}\nbroe = 1.0")
    refused(tmp_path, text, f"'{section}.broe'")


def test_unknown_key_in_optional_table(tmp_path: Path) -> None:
    refused(tmp_path, EXAMPLE + "\n[sensors]\nvelocity_noise = 1.0\n", "'sensors.velocity_noise'")


def test_missing_table_and_missing_key(tmp_path: Path) -> None:
    text = EXAMPLE[:EXAMPLE.index("[friction]")]
    refused(tmp_path, text, "[friction]")
    refused(tmp_path, edit(EXAMPLE, "Fv = 50.0", ""), "'friction.Fv'")


@pytest.mark.parametrize("old, new, key", [
    ("bore = 0.032", 'bore = "0.032"', "geometry.bore"),         # string where a number belongs
    ("moving_mass = 0.8", "moving_mass = true", "mechanics.moving_mass"),  # bool is not a number
    ("Fc = 10.0", "Fc = [10.0]", "friction.Fc"),
    ("pressure = 7.0e5", "pressure = nan", "supply.pressure"),
])
def test_wrong_type(tmp_path: Path, old: str, new: str, key: str) -> None:
    refused(tmp_path, edit(EXAMPLE, old, new), f"'{key}'")


def test_name_must_be_a_string(tmp_path: Path) -> None:
    refused(tmp_path, edit(EXAMPLE, 'name = "A"', "name = 3"), "'name'")


def test_table_given_as_a_value(tmp_path: Path) -> None:
    refused(tmp_path, "sensors = 3\n" + EXAMPLE, "'sensors'")


def test_negative_bore(tmp_path: Path) -> None:
    refused(tmp_path, edit(EXAMPLE, "bore = 0.032", "bore = -0.032"), "'geometry.bore'")


@pytest.mark.parametrize("rod", ["0.032", "0.04"])
def test_rod_not_smaller_than_bore(tmp_path: Path, rod: str) -> None:
    refused(tmp_path, edit(EXAMPLE, "rod = 0.012", f"rod = {rod}"), "'geometry.rod'")


def test_bore_in_mm(tmp_path: Path) -> None:
    msg = refused(tmp_path, edit(EXAMPLE, "bore = 0.032", "bore = 32"), "geometry.bore")
    assert "mm" in msg


def test_supply_pressure_in_bar(tmp_path: Path) -> None:
    msg = refused(tmp_path, edit(EXAMPLE, "pressure = 7.0e5", "pressure = 7.0"), "'supply.pressure'")
    assert "bar" in msg


def test_unknown_parameter_to_estimate(tmp_path: Path) -> None:
    text = EXAMPLE + '\n[identify]\nestimate = ["Fc", "stiction"]\n'
    refused(tmp_path, text, "'identify.estimate'", "'stiction'")


def test_measured_parameter_is_not_estimable(tmp_path: Path) -> None:
    refused(tmp_path, EXAMPLE + '\n[identify]\nestimate = ["bore"]\n', "'identify.estimate'", "'bore'")


def test_parameter_estimated_twice(tmp_path: Path) -> None:
    refused(tmp_path, EXAMPLE + '\n[identify]\nestimate = ["Fc", "Fv", "Fc"]\n', "'identify.estimate'")


def test_a_parameter_list_is_judged_by_one_rule_in_the_file_and_on_the_command_line(tmp_path: Path) -> None:
    """identify.estimate in a cylinder file and --estimate on the command line: the same words
    after the key's or the option's name (sim.cylinder.parameter_list_problem)."""
    from combined_reality import options

    for names, after in ((["Fc", "Fv", "Fc"], "names Fc more than once; give each once."),
                         (["Fc", "bore"], "names unknown parameter 'bore' (estimable: ")):
        msg = refused(tmp_path, EXAMPLE + f'\n[identify]\nestimate = {names!r}\n'.replace("'", '"'))
        assert f"key 'identify.estimate' {after}" in msg, msg
        with pytest.raises(options.OptionError) as e:
            options.check_estimable(options.parameter_names(",".join(names)), ESTIMABLE)
        assert str(e.value).startswith(f"--estimate {after}"), str(e.value)


def test_bad_drive(tmp_path: Path) -> None:
    refused(tmp_path, EXAMPLE + '\n[identify]\ndrive = "voltage"\n', "'identify.drive'")


@pytest.mark.parametrize("old, new, key", [
    ("angle = 30.0", "angle = 120.0", "mechanics.angle"),
    ("atmosphere = 1.013e5", "atmosphere = 1.013", "supply.atmosphere"),
    ("critical_ratio = 0.3", "critical_ratio = 1.5", "valve.critical_ratio"),
    ("Fc = 10.0", "Fc = -1.0", "friction.Fc"),
    ("moving_mass = 0.8", "moving_mass = 0", "mechanics.moving_mass"),
])
def test_implausible_values(tmp_path: Path, old: str, new: str, key: str) -> None:
    refused(tmp_path, edit(EXAMPLE, old, new), f"'{key}'")


@pytest.mark.parametrize("name", [n for n in PARAMETERS if n not in FLOW_CHARACTERISTIC])
def test_loader_refuses_what_the_identifier_bounds_exclude(name: str) -> None:
    """A file loads only if every model parameter starts inside the bounds the identifier keeps."""
    spec = PARAMETERS[name]
    scale = 180.0 / math.pi if name == "angle" else 1.0  # the file gives degrees
    span = spec.upper - spec.lower
    for v in (spec.upper + 0.01 * span, spec.lower - 0.01 * span):
        data = tomllib.loads(EXAMPLE)
        data.setdefault(spec.section, {})[spec.attr] = v * scale
        with pytest.raises(ConfigError, match=rf"'{spec.section}\.{spec.attr}' must (be positive and )?lie in \[.*\]"):
            parse_cylinder(data, "cyl.toml")


# --------------------------------------------------------------------------- the valve's flow characteristic

EXTEND = tuple(round(1.1 * g ** 1.3, 6) for g in OPENING_GRID)  # a valve that opens progressively, 10 % strong
RETRACT = tuple(round(0.9 * g, 6) for g in OPENING_GRID)
CHARACTERISTIC = f"""\
overlap_extend = 0.04
flow_extend = {list(EXTEND)}
flow_retract = {list(RETRACT)}
"""
N = len(OPENING_GRID)


def with_valve(lines: str) -> str:
    return edit(EXAMPLE, "critical_ratio = 0.3\n", "critical_ratio = 0.3\n" + lines)


def test_flow_characteristic_loads_and_round_trips(tmp_path: Path) -> None:
    cyl = load_cylinder(write(tmp_path, with_valve(CHARACTERISTIC)))
    v = cyl.valve
    assert v.overlap_extend == 0.04 and v.overlap_retract == 0.0 and not v.is_linear
    assert v.flow_extend == EXTEND
    # the plant's parameters are the rises over the grid segments; setting one moves the levels above it
    assert cyl.value("flow_extend_2") == pytest.approx(EXTEND[1] - EXTEND[0])
    moved = cyl.with_values({"flow_extend_2": EXTEND[1] - EXTEND[0] + 0.1})
    assert moved.valve.flow_extend == pytest.approx(EXTEND[:1] + tuple(x + 0.1 for x in EXTEND[1:]))
    again = load_cylinder(write(tmp_path, cylinder_to_toml(cyl), name="again.toml"))
    assert again == cyl
    assert load_cylinder(write(tmp_path, EXAMPLE, name="plain.toml")).valve.is_linear


def test_a_file_on_the_earlier_grid_is_read_as_the_same_curve(tmp_path: Path) -> None:
    """A file written on the 11 openings of earlier versions: the same monotone cubic, evaluated
    at today's openings; exact for a straight characteristic, close for a curved one."""
    old = EARLIER_OPENING_GRIDS[0]
    assert len(old) != N
    straight = load_cylinder(write(tmp_path, with_valve(f"flow_extend = {list(old)}\n")))
    assert straight.valve.flow_extend == OPENING_GRID and straight.valve.is_linear  # the nominal law, exactly
    curved = tuple(1.2 * g ** 1.6 for g in old)
    v = load_cylinder(write(tmp_path, with_valve(f"flow_extend = {list(curved)}\n"), name="curved.toml")).valve
    assert len(v.flow_extend) == N and v.flow_extend[-1] == curved[-1]
    assert all(b >= a for a, b in zip(v.flow_extend, v.flow_extend[1:]))
    assert v.flow_extend == pytest.approx(tuple(1.2 * g ** 1.6 for g in OPENING_GRID), rel=0.03, abs=2e-4)


@pytest.mark.parametrize("lines, fragment", [
    (f"flow_extend = {[0.1, 0.05] + list(OPENING_GRID[2:])}\n",
     "'valve.flow_extend' must be non-negative and non-decreasing"),
    ("flow_extend = [0.1, 0.3]\n", f"'valve.flow_extend' must be a list of {N} numbers"),
    ("overlap_retract = 0.7\n", "'valve.overlap_retract' must lie in [0, 0.5]"),
    (f"flow_extend = {[0] * N}\n", "'valve.flow_extend' must end (full opening) between 0 and 5"),
    ("flow_retract = 1.0\n", f"'valve.flow_retract' must be a list of {N} numbers"),
])
def test_flow_characteristic_refusals(tmp_path: Path, lines: str, fragment: str) -> None:
    refused(tmp_path, with_valve(lines), fragment)
