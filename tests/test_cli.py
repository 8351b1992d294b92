"""The command line per docs/formats.md: bad input refused with exit 2 and one clear sentence."""
import json
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import assert_refused

from combined_reality.cli import main

ROOT = Path(__file__).resolve().parents[1]
CFG = ROOT / "configs" / "cyl_a_32x100.toml"
GOOD_ROWS = ["0.000,0.1,0.0500,4.0e5,3.0e5", "0.001,0.1,0.0501,4.0e5,3.0e5", "0.002,0.1,0.0502,4.0e5,3.0e5"]


def _csv(tmp_path, lines, name="run.csv"):
    p = tmp_path / name
    p.write_text("\n".join(lines) + "\n")
    return p


def _run(argv, capsys):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.mark.parametrize("lines, fragments", [
    (["t,u,x,p1", *[r.rsplit(",", 1)[0] for r in GOOD_ROWS]], ["'p2'"]),  # missing column
    (["t,u,x,p1,p2", GOOD_ROWS[0], "0.001,0.1,abc,4.0e5,3.0e5", GOOD_ROWS[2]], ["line 3", "'x'", "abc"]),
    (["t,u,x,p1,p2", GOOD_ROWS[0], "0.001,0.1,0.05,nan,3.0e5", GOOD_ROWS[2]], ["line 3", "'p1'"]),
    (["t,u,x,p1,p2", GOOD_ROWS[0], GOOD_ROWS[2], GOOD_ROWS[1]], ["line 4", "'t'"]),  # time backwards
    (["t,u,x,p1,p2", "0.000,0.1,0.05,4.0,3.0", "0.001,0.1,0.05,4.0,3.0", "0.002,0.1,0.05,4.0,3.0"],
     ["bar or gauge"]),
    (["t,u,x,p1,p2", "0.000,0.1,0.05,3.0e5,2.0e3", "0.001,0.1,0.05,3.0e5,2.0e3", "0.002,0.1,0.05,3.0e5,2.0e3"],
     ["bar or gauge", "'p2'"]),
    ([], ["empty"]),
])
def test_bad_run_files_are_refused(tmp_path, capsys, lines, fragments):
    run = _csv(tmp_path, lines)
    code, _, err = _run(["identify", "--config", CFG, run, "--json", tmp_path / "o.json"], capsys)
    assert_refused(code, err, "run.csv", *fragments)
    assert not (tmp_path / "o.json").exists()  # nothing half-written


def test_missing_run_file(tmp_path, capsys):
    code, _, err = _run(["identify", "--config", CFG, tmp_path / "nope.csv"], capsys)
    assert_refused(code, err, "nope.csv", "not found")


def test_position_in_mm_against_the_stroke(tmp_path, capsys):
    run = _csv(tmp_path, ["t,u,x,p1,p2", "0.000,0.1,0.50,4.0e5,3.0e5", "0.001,0.1,0.501,4.0e5,3.0e5",
                          "0.002,0.1,0.502,4.0e5,3.0e5"])
    code, _, err = _run(["identify", "--config", CFG, run], capsys)
    assert_refused(code, err, "run.csv", "stroke")


@pytest.mark.parametrize("edit, fragments", [
    (lambda t: t.replace("[geometry]", "[geometry]\ncolour = 3"), ["geometry.colour"]),  # unknown key
    (lambda t: t + "\n[extras]\nx = 1\n", ["'extras'"]),  # unknown table
    (lambda t: _set(t, "stroke", '"long"'), ["geometry.stroke", "number"]),  # wrong type
    (lambda t: _set(t, "bore", "-0.032"), ["geometry.bore", "positive"]),  # negative bore
    (lambda t: _set(t, "pressure", "7.0"), ["supply.pressure"]),  # bar
    (lambda t: t.replace("[friction]", "[friction"), ["TOML"]),  # syntax
])
def test_bad_cylinder_files_are_refused(tmp_path, capsys, edit, fragments):
    cfg = tmp_path / "cyl.toml"
    cfg.write_text(edit(CFG.read_text()))
    run = _csv(tmp_path, ["t,u,x,p1,p2", *GOOD_ROWS])
    code, _, err = _run(["identify", "--config", cfg, run], capsys)
    assert_refused(code, err, "cyl.toml", *fragments)


def _set(text, key, value):
    out = []
    for line in text.splitlines():
        if line.split("=")[0].strip() == key:
            line = f"{key} = {value}"
        out.append(line)
    return "\n".join(out) + "\n"


def test_missing_config(tmp_path, capsys):
    run = _csv(tmp_path, ["t,u,x,p1,p2", *GOOD_ROWS])
    code, _, err = _run(["identify", "--config", tmp_path / "none.toml", run], capsys)
    assert_refused(code, err, "none.toml", "not found")


def test_bad_options(tmp_path, capsys):
    run = _csv(tmp_path, ["t,u,x,p1,p2", *GOOD_ROWS])
    code, _, err = _run(["identify", "--config", CFG, run, "--estimate", "Fc,colour"], capsys)
    assert_refused(code, err, "colour")
    code, _, err = _run(["simulate", "--config", CFG, "-o", tmp_path / "r.csv", "--effect", "sticktion"], capsys)
    assert_refused(code, err, "sticktion")
    code, _, err = _run(["simulate", "--config", CFG, "-o", tmp_path / "r.csv", "--duration", "-3"], capsys)
    assert_refused(code, err, "--duration")


def test_simulate_then_identify_end_to_end(tmp_path):
    """As a user runs it: the installed console entry point, two processes, JSON per FORMATS."""
    exe = str(Path(sys.executable).parent / "combined-reality")
    run = tmp_path / "run.csv"
    out = tmp_path / "id.json"
    sim = subprocess.run([exe, "simulate", "--config", str(CFG),
                          "--duration", "6", "--seed", "4", "-o", str(run),
                          "--effect", "valve_delay:tau=0.004"], capture_output=True, text=True)
    assert sim.returncode == 0, sim.stderr
    text = run.read_text()
    assert text.startswith("# cylinder: ") and "# combined-reality virtual rig" in text and "valve_delay(tau=0.004" in text
    ident = subprocess.run([exe, "identify", "--config", str(CFG), str(run),
                            "--json", str(out), "--effect", "valve_delay", "--estimate", "Fc,Fv,kp,valve_delay.tau",
                            "--write-config", str(tmp_path / "identified.toml")],
                           capture_output=True, text=True)
    assert ident.returncode == 0, ident.stderr
    res = json.loads(out.read_text())
    assert res["solver"]["status"] == "converged"
    assert abs(res["params"]["valve_delay.tau"]["value"] - 0.004) < 0.0004
    assert abs(res["params"]["Fc"]["value"] - 24.8) / 24.8 < 0.03
    assert "Fc" in ident.stdout and "N s/m" in ident.stdout  # the readable table
    from sim.cylinder import load_cylinder

    written = load_cylinder(tmp_path / "identified.toml")
    assert written.friction.Fc == res["params"]["Fc"]["value"]


def test_version(capsys):
    from importlib.metadata import version

    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"combined-reality {version('combined-reality')}"


def test_rerun_without_the_sdk_says_how_to_install_it(monkeypatch, capsys):
    import importlib.util

    from combined_reality.cli.common import UsageError, rerun_mode

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "rerun" else real(name, *a))
    assert rerun_mode(["off"]) == ("off", None)  # off needs nothing
    with pytest.raises(UsageError, match=r"--rerun spawn needs the Rerun SDK .* pip install rerun-sdk\."):
        rerun_mode(["spawn"])


def test_live_help_lists_every_program(capsys):
    from combined_reality.live.programs import PROGRAMS

    assert main(["live", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    for name in [*PROGRAMS, "file:CMD.csv"]:
        assert name in text, name


def test_identify_in_the_chambers_drive_prints_the_pressures_fit(tmp_path, capsys):
    """The chambers drive has no position output: its fit is told in pressures (it once ended
    in 'internal error: rmse_x' after writing its JSON)."""
    from combined_reality.files import write_run
    from combined_reality.simulation import simulate_run
    from sim.cylinder import load_cylinder

    run = tmp_path / "run.csv"
    write_run(run, simulate_run(load_cylinder(CFG), 4.0, seed=2))
    code, out, err = _run(["identify", "--config", CFG, run, "--drive", "chambers", "--estimate", "dead_volume_cap",
                           "--json", tmp_path / "o.json"], capsys)
    assert code == 0, err
    assert "fit: rmse_p1" in out and "rmse_x" not in out and "chambers drive" in out
    assert json.loads((tmp_path / "o.json").read_text())["params"]["dead_volume_cap"]["std"] > 0
