"""The shipped cylinder files in configs/ against the seed papers they come from.

Seed 002 (combined-reality friction identification): Table 1 (bore, stroke), Table 2 (Fc, Fv, kp).
Seed 004 (friction of industrial actuators): Table 1 (bore, stroke), Table 2 (valve), Table 3
(friction per direction). The reference values below are typed from the papers, not read from the
files, so a wrong file fails here.
"""
from __future__ import annotations

import math
import tomllib
from pathlib import Path

import pytest

from sim.cylinder import load_cylinder

CONFIGS = Path(__file__).resolve().parent.parent / "configs"

SEED002 = {  # file: (bore m, stroke m, Fc N, Fv N s/m, kp N/Pa); Table 2 kp 2.89 / 0.79 "N/Pa" is N/bar
    "cyl_a_32x100.toml": (0.032, 0.1, 24.8, 13.45, 2.89e-5),
    "cyl_b_16x40.toml": (0.016, 0.04, 5.2, 2.24, 7.9e-6),
}

SEED004_T1 = {  # actuator number: (file, bore m, stroke m) -- Table 1 (mm there)
    1: ("ind1_rexroth_25x500.toml", 0.025, 0.500),
    2: ("ind2_norgren_32x100.toml", 0.032, 0.100),
    3: ("ind3_norgren_40x250.toml", 0.040, 0.250),
    4: ("ind4_norgren_50x400.toml", 0.050, 0.400),
    5: ("ind5_festo_32x100.toml", 0.032, 0.100),
    6: ("ind6_proar_32x100.toml", 0.032, 0.100),
    7: ("ind7_proar_40x250.toml", 0.040, 0.250),
    8: ("ind8_dover_40x30.toml", 0.040, 0.030),
}

# Seed 004 Table 3 as printed: Fs(v>0), Fs(v<0), Fc(v>0), Fc(v<0) [N], B(v>0), B(v<0) [N s/m],
# Stribeck velocity (v>0), (v<0) [mm/s].
SEED004_T3 = {
    1: (24, -31, 23.10, -30.63, 46.53, 37.61, 10.0, -10.0),
    2: (22, -20, 16.87, -13.47, 178.85, 165.59, 3.42, -6.16),
    3: (5.5, -10, 1.08, -6.63, 201.35, 247.59, 10.4, -23.2),
    4: (6, -11, 1.59, -6.10, 203.71, 259.13, 8.5, -8.9),
    5: (10, -5, 8.82, -3.71, 43.89, 40.13, 10.0, -13.0),
    6: (8, -6, 6.42, -4.00, 10.40, 30.39, 26.0, -25.9),
    7: (10, -10, 1.84, -3.99, 74.69, 78.04, 26.0, -26.0),
    8: (35, -32, 20.36, -20.30, 492.77, 666.67, 10.0, -10.0),
}

EXPECTED = set(SEED002) | {f for f, _, _ in SEED004_T1.values()}

SUPPLY = 7.013e5  # 6.0 bar gauge + 1.013e5 Pa


def _conductance(qn_l_per_min: float, b: float = 0.3) -> float:
    """ISO 6358 C from a nominal flow at 6 bar gauge inlet and 1 bar drop."""
    p_in = SUPPLY
    r = (p_in - 1.0e5) / p_in
    phi = math.sqrt(1.0 - ((r - b) / (1.0 - b)) ** 2)
    return qn_l_per_min * 1e-3 / 60.0 / (p_in * phi)


def test_exactly_the_ten_files():
    assert {p.name for p in CONFIGS.glob("*.toml")} == EXPECTED
    assert len(EXPECTED) == 10


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_loads_and_is_sane(name):
    cyl = load_cylinder(CONFIGS / name)
    g = cyl.geometry
    assert 0.0 <= g.rod < g.bore
    assert g.dead_volume_cap > 0 and g.dead_volume_rod > 0
    assert g.dead_volume_cap < g.area_cap * g.stroke
    assert g.dead_volume_rod < g.area_rod * g.stroke
    assert cyl.supply.pressure == pytest.approx(SUPPLY)
    assert cyl.supply.atmosphere == pytest.approx(1.013e5)
    assert cyl.supply.temperature == pytest.approx(293.15)
    assert cyl.valve.critical_ratio == pytest.approx(0.3)
    assert cyl.friction.v_smooth == pytest.approx(1e-3)
    assert cyl.mechanics.angle == 0.0
    assert 0.3 <= cyl.mechanics.moving_mass <= 3.0
    # every file says where it comes from
    head = (CONFIGS / name).read_text(encoding="utf-8").splitlines()[0]
    assert head.startswith("#") and "seed 00" in head


@pytest.mark.parametrize("name", sorted(SEED002))
def test_seed002_table1_and_table2(name):
    bore, stroke, fc, fv, kp = SEED002[name]
    cyl = load_cylinder(CONFIGS / name)
    assert cyl.geometry.bore == pytest.approx(bore)
    assert cyl.geometry.stroke == pytest.approx(stroke)
    assert cyl.friction.Fc == pytest.approx(fc)
    assert cyl.friction.Fv == pytest.approx(fv)
    assert cyl.friction.kp == pytest.approx(kp)
    # MPYE-5-1/8-LF, 350 l/min (assumed: seed 002 names no valve)
    assert cyl.valve.sonic_conductance == pytest.approx(_conductance(350.0), rel=1e-3)


def test_seed002_kp_is_table2_per_bar():
    for name, table2 in (("cyl_a_32x100.toml", 2.89), ("cyl_b_16x40.toml", 0.79)):
        assert load_cylinder(CONFIGS / name).friction.kp == pytest.approx(table2 / 1e5)


@pytest.mark.parametrize("n", sorted(SEED004_T1))
def test_seed004_tables(n):
    name, bore, stroke = SEED004_T1[n]
    fs_p, fs_n, fc_p, fc_n, b_p, b_n, vs_p, vs_n = SEED004_T3[n]
    cyl = load_cylinder(CONFIGS / name)
    assert cyl.geometry.bore == pytest.approx(bore)
    assert cyl.geometry.stroke == pytest.approx(stroke)
    assert cyl.friction.Fc == pytest.approx((abs(fc_p) + abs(fc_n)) / 2)
    assert cyl.friction.Fv == pytest.approx((b_p + b_n) / 2)
    assert cyl.friction.kp == pytest.approx(1.0e-5 * (bore / 0.032) ** 2, rel=1e-3)
    # MPYE-5-1/8 of seed 004 Table 2, 700 l/min
    assert cyl.valve.sonic_conductance == pytest.approx(_conductance(700.0), rel=1e-3)
    if n == 1:
        assert cyl.geometry.rod == 0.0  # rodless actuator
    else:
        assert cyl.geometry.rod > 0.0


@pytest.mark.parametrize("n", sorted(SEED004_T1))
def test_seed004_per_direction_comment_block(n):
    """The commented Table 3 row (SI) parses as TOML once un-commented and matches the paper."""
    name = SEED004_T1[n][0]
    lines = (CONFIGS / name).read_text(encoding="utf-8").splitlines()
    start = next(i for i, s in enumerate(lines) if "BEGIN friction_per_direction" in s)
    end = next(i for i, s in enumerate(lines) if "END friction_per_direction" in s)
    block = tomllib.loads("\n".join(s.removeprefix("#") for s in lines[start + 1:end]))
    fs_p, fs_n, fc_p, fc_n, b_p, b_n, vs_p, vs_n = SEED004_T3[n]
    expected = {"Fs_ext": fs_p, "Fs_ret": fs_n, "Fc_ext": fc_p, "Fc_ret": fc_n,
                "B_ext": b_p, "B_ret": b_n, "vs_ext": vs_p * 1e-3, "vs_ret": vs_n * 1e-3}
    assert block.keys() == expected.keys()
    for key, value in expected.items():
        assert block[key] == pytest.approx(value), key


def test_seed004_supply_and_valve_shared():
    cyls = [load_cylinder(CONFIGS / f) for f, _, _ in SEED004_T1.values()]
    assert {c.supply.pressure for c in cyls} == {SUPPLY}
    assert len({c.valve.sonic_conductance for c in cyls}) == 1
