"""Plausibility (issue 17): runs in the wrong unit or range, and runs that cannot determine the
chosen parameters, are refused with a named cause and exit status 2, never "converged"."""
from __future__ import annotations


import numpy as np
import pytest
from conftest import CONFIGS, assert_refused

from combined_reality.cli import main
from combined_reality.cli.identify import format_table
from combined_reality.files import Run, RunFormatError, check_run_against_cylinder, write_run
from combined_reality.identify import Estimate, IdentifyResult, check_determinable
from sim.cylinder import ConfigError

CFG = CONFIGS / "cyl_a_32x100.toml"
PA = 1.013e5


def call(argv, capsys):
    code = main([str(a) for a in argv])
    return code, capsys.readouterr().err


def synthetic(speeds_mm_s, dp_of=None, duration_each=0.4, rate=1000.0, name="run.csv", back=True) -> Run:
    """Moves at the given speeds (each for duration_each, and the same back unless not `back`),
    with |p1 - p2| from dp_of(speed) (default: varying independently of the speed)."""
    dt = 1.0 / rate
    n = int(duration_each / dt)
    v = np.concatenate([np.r_[np.full(n, s), np.full(n if back else 0, -s)] * 1e-3 for s in speeds_mm_s])
    x = 0.02 + np.cumsum(v) * dt
    t = np.arange(v.size) * dt
    rng = np.random.default_rng(0)
    dp = dp_of(np.abs(v)) if dp_of else 1e5 + 1.5e5 * rng.uniform(size=v.size)
    p2 = np.full(v.size, 3e5)
    p1 = p2 + np.sign(v) * dp
    return Run(t=t, u=np.sign(v) * 0.3, x=x, p1=p1, p2=p2, source=name)


# ------------------------------------------------------------------ against the cylinder file


@pytest.fixture(scope="module")
def stroke_run(cyl_a):
    """Full strokes with the valve open, resting 1 s at each end: the filled chamber at the supply, the other
    at the atmosphere (a position-controlled run may do neither; then gauge readings cannot be told from
    absolute ones)."""
    rng = np.random.default_rng(2)
    ps, L = cyl_a.supply.pressure, cyl_a.geometry.stroke
    n_move, n_rest = 400, 1000
    x = np.r_[np.linspace(0, L, n_move), np.full(n_rest, L), np.linspace(L, 0, n_move), np.zeros(n_rest)]
    u = np.r_[np.full(n_move + n_rest, 0.5), np.full(n_move + n_rest, -0.5)]
    rise = np.r_[np.linspace(3e5, ps, n_move), np.full(n_rest, ps)]
    fall = np.r_[np.linspace(2.5e5, PA, n_move), np.full(n_rest, PA)]
    p1, p2 = np.r_[rise, fall], np.r_[fall, rise]
    noise = lambda: rng.normal(0, 300.0, x.size)  # noqa: E731
    return Run(t=np.arange(x.size) * 1e-3, u=u, x=x + rng.normal(0, 5e-6, x.size), p1=p1 + noise(),
               p2=p2 + noise(), source="strokes.csv")


def test_pressures_in_gauge_pa_are_refused(cyl_a, stroke_run):
    run = stroke_run
    check_run_against_cylinder(run, cyl_a)  # absolute: fine
    gauge = Run(t=run.t, u=run.u, x=run.x, p1=run.p1 - PA, p2=run.p2 - PA, source="gauge.csv")
    assert (gauge.p1 > 2e4).mean() > 0.5  # most cells pass the reader's per-cell check ...
    with pytest.raises(RunFormatError, match=r"gauge.csv, column 'p\d' at t = .* look like gauge pressures"):
        check_run_against_cylinder(gauge, cyl_a)  # ... but not the run as a whole


def test_a_supply_pressure_in_gauge_is_refused_naming_the_key(cyl_a, stroke_run):
    gauge_supply = cyl_a.with_values({"supply_pressure": cyl_a.supply.pressure - PA})
    with pytest.raises(ConfigError, match=r"key 'supply.pressure' = 600000 Pa looks like gauge: .* holds 7.0"):
        check_run_against_cylinder(stroke_run, gauge_supply)


def test_gauge_supply_through_the_command_line(tmp_path, capsys, stroke_run):
    run = tmp_path / "run.csv"
    write_run(run, stroke_run)
    cfg = tmp_path / "cyl.toml"
    cfg.write_text(CFG.read_text().replace("pressure = 7.013e5", "pressure = 6.0e5"))
    assert "6.0e5" in cfg.read_text()
    code, err = call(["identify", "--config", cfg, run, "-q"], capsys)
    assert_refused(code, err, "cyl.toml", "supply.pressure", "gauge")


# ------------------------------------------------------------------ runs that cannot determine a parameter


def test_a_run_without_motion_is_refused_not_converged(tmp_path, capsys):
    n = 3000
    still = Run(t=np.arange(n) * 1e-3, u=np.zeros(n), x=np.full(n, 0.05) + 1e-6 * np.sin(np.arange(n)),
                p1=np.full(n, 3e5), p2=np.full(n, 3e5))
    path = tmp_path / "still.csv"
    write_run(path, still)
    code, err = call(["identify", "--config", CFG, path, "--json", tmp_path / "o.json"], capsys)  # progress on
    assert_refused(code, err, "still.csv: this run cannot determine Fc, Fv, kp: the piston does not move")
    assert not (tmp_path / "o.json").exists()


def test_one_direction_cannot_determine_fc(cyl_a):
    one_way = synthetic([20, 40, 80], back=False)
    with pytest.raises(RunFormatError, match="cannot determine Fc: the piston moves only while extending"):
        check_determinable(cyl_a, [one_way], ("Fc", "Fv", "kp"))
    check_determinable(cyl_a, [one_way], ("Fv", "kp"))  # without Fc: fine


def test_one_speed_cannot_determine_fv(cyl_a):
    with pytest.raises(RunFormatError, match="cannot determine Fv: the piston moves at nearly one speed"):
        check_determinable(cyl_a, [synthetic([50, 50, 50])], ("Fc", "Fv", "kp"))
    check_determinable(cyl_a, [synthetic([20, 50, 120])], ("Fc", "Fv", "kp"))


def test_one_pressure_difference_cannot_determine_kp(cyl_a):
    run = synthetic([20, 50, 120], dp_of=lambda s: np.full(s.size, 2e5))
    with pytest.raises(RunFormatError, match=r"cannot determine kp: while the piston moves, \|p1 - p2\| stays"):
        check_determinable(cyl_a, [run], ("Fc", "Fv", "kp"))


def test_speed_and_pressure_changing_together_cannot_separate_kp_and_fv(cyl_a):
    run = synthetic([20, 50, 120], dp_of=lambda s: 5e4 + 2e6 * s)
    with pytest.raises(RunFormatError, match="cannot determine kp and Fv apart: speed and .* changed together"):
        check_determinable(cyl_a, [run], ("Fc", "Fv", "kp"))
    check_determinable(cyl_a, [run], ("Fc", "kp"))  # one of them: fine


def test_too_short_to_move_in_both_directions(cyl_a, run_a):
    with pytest.raises(RunFormatError, match="cannot determine"):
        check_determinable(cyl_a, [run_a.slice(0, 60)], ("Fc", "Fv", "kp"))
    check_determinable(cyl_a, [run_a], ("Fc", "Fv", "kp"))  # the whole virtual-rig run: fine


def test_a_parameter_whose_std_is_as_large_as_its_value_is_not_determined_and_not_converged(cyl_a):
    est = lambda n, v, s: Estimate(n, v, s, "N/Pa", v)  # noqa: E731
    result = IdentifyResult(params={"Fc": est("Fc", 24.8, 0.1), "kp": est("kp", 2e-7, 3e-7),
                                    "Fv": est("Fv", 13.0, float("nan"))},
                            fit={"rmse_x": 5e-6, "r2_x": 0.99}, fit_per_run=[], cylinder=cyl_a, effects=(),
                            drive="command", solver={"status": "converged", "iterations": 8, "wall_s": 1.0,
                                                     "n_samples": 100, "residual_sigma": 1.0})
    assert result.not_determined == ["kp", "Fv"]
    # the document identify --json writes, made by the result itself (also for batch and library callers)
    doc = result.document(inputs=["run.csv"])
    assert {n: e["determined"] for n, e in doc["params"].items()} == {"Fc": True, "kp": False, "Fv": False}
    assert doc["solver"]["status"] == "not_determined" and result.to_json()["solver"]["status"] == "converged"
    assert result.status == "not_determined"
    assert doc["config"] == str(cyl_a.source) and doc["inputs"] == ["run.csv"]
    table = format_table(result)
    assert "not determined" in table and "solver: converged" not in table
    assert "do not determine Fv, kp" in table
