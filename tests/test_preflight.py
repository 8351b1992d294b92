"""The preflight (issue 42): the usual mistakes are refused before any fit, in one sentence that
names the likely cause and the fix (exit status 2), and runs that are right are never refused,
nor noted, on any cylinder of configs/.

The mistakes are made from runs of the virtual rig: a position-controlled run (mid-stroke) and
a run of the calibration program, which exhausts both chambers and holds against an end stop
with the valve open (only such a run shows gauge chambers and a gauge supply for sure)."""
from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import CONFIGS, ROOT, assert_refused

from combined_reality.cli import main
from combined_reality.files import Run, RunFormatError, cylinder_tag, read_run, write_run
from combined_reality.identify import preflight
from sim.cylinder import load_cylinder

CFG_A = CONFIGS / "cyl_a_32x100.toml"
CFG_40 = CONFIGS / "ind3_norgren_40x250.toml"
PA = 1.013e5


def call(argv, capsys):
    code = main([str(a) for a in argv])
    return code, capsys.readouterr().err


def program_run(cyl, program: str, duration: float, seed: int = 3, effects=()) -> Run:
    from combined_reality.live.experiment import run_program
    from combined_reality.live.programs import make_program
    from hw.virtual_rig import VirtualRig

    rig = VirtualRig(cyl, list(effects), rate=1000.0, seed=seed)
    return run_program(rig, make_program(program, cyl, duration, seed=seed), int(duration * 1000))


@pytest.fixture(scope="module")
def cal_run(cyl_a):
    """The calibration program up to its first hold at the end stop (chamber 2 at the supply,
    chamber 1 at the atmosphere)."""
    return program_run(cyl_a, "calibration", 10.0)


@pytest.fixture(scope="module")
def files(tmp_path_factory, cyl_a, run_a, cal_run):
    """The runs as files written by the tool (with their cylinder tag)."""
    d = tmp_path_factory.mktemp("preflight")
    write_run(d / "mixed.csv", run_a.slice(0, 8000), comments=[cylinder_tag(cyl_a)])
    write_run(d / "cal.csv", cal_run, comments=[cylinder_tag(cyl_a)])
    return d


def mistake(files: Path, name: str, run: Run, **changes) -> Path:
    """A copy of a run with one mistake, written as a file (its tag kept)."""
    path = files / name
    write_run(path, replace(run, **changes), comments=list(read_run(files / "mixed.csv").comments))
    return path


# ------------------------------------------------------------------ one test per mistake


def test_swapped_chambers_are_named(files, run_a, capsys):
    r = run_a.slice(0, 8000)
    code, err = call(["identify", "--config", CFG_A, mistake(files, "swapped.csv", r, p1=r.p2, p2=r.p1), "-q"],
                     capsys)
    assert_refused(code, err, "swapped.csv: p1 and p2 look swapped", "pushes the piston against its motion",
                   "swap the columns p1 and p2")


def test_an_inverted_valve_sign_is_named(files, run_a, capsys):
    r = run_a.slice(0, 8000)
    code, err = call(["identify", "--config", CFG_A, mistake(files, "inverted.csv", r, u=-r.u), "-q"], capsys)
    assert_refused(code, err, "inverted.csv: the command's sign looks inverted", "invert the command (u -> -u")


def test_a_reversed_position_is_named(cyl_a, run_a):
    r = run_a.slice(0, 8000)
    with pytest.raises(RunFormatError, match="the position looks reversed: .* use the stroke minus the position"):
        preflight(cyl_a, [replace(r, x=cyl_a.geometry.stroke - r.x)])


def test_positions_in_millimetres(files, run_a, cyl_a, capsys):
    r = run_a.slice(0, 8000)
    # the reader already: beyond 10 m
    code, err = call(["identify", "--config", CFG_A, mistake(files, "mm.csv", r, x=r.x * 1e3), "-q"], capsys)
    assert_refused(code, err, "mm.csv", "column 'x'", "looks like millimetres", "divide by 1000")
    # a stroke short enough that millimetres stay below 10 m: the preflight, against the stroke
    short = cyl_a.with_values({"stroke": 0.008})
    with pytest.raises(RunFormatError, match=r"stroke of 0.008 m: the positions look like millimetres; give them "
                                             r"in metres \(divide by 1000"):
        preflight(short, [replace(r, x=r.x * 0.08 * 1e3)])  # the same motion on an 8 mm stroke, in mm


def test_positions_from_another_origin(cyl_a, run_a):
    r = run_a.slice(0, 8000)
    with pytest.raises(RunFormatError, match="measured from another origin; add 0.0"):
        preflight(cyl_a, [replace(r, x=r.x - 0.05)])


def test_gauge_chamber_pressures(files, cal_run, capsys):
    r = cal_run
    # as written by a DAQ: the exhausted chamber reads about 0
    code, err = call(["identify", "--config", CFG_A, mistake(files, "gauge.csv", r, p1=r.p1 - PA, p2=r.p2 - PA),
                      "-q"], capsys)
    assert_refused(code, err, "gauge.csv", "looks like bar or gauge pressure", "plus the atmosphere")
    # a sensor that reads a little above the true gauge value passes the reader: the preflight sees
    # a chamber below half the atmosphere for a good part of the run
    lifted = mistake(files, "gauge_lifted.csv", r, p1=r.p1 - PA + 3e4, p2=r.p2 - PA + 3e4)
    code, err = call(["identify", "--config", CFG_A, lifted, "-q"], capsys)
    assert_refused(code, err, "gauge_lifted.csv, column 'p", "look like gauge pressures",
                   "add the atmosphere to them (or set gauge = true for them in the import map)")


def test_gauge_pressures_in_the_import_map(tmp_path, cal_run, capsys):
    """A DAQ's bar gauge readings imported without `gauge = true`: refused, naming the key."""
    lines = ["t_ms;u_V;x_mm;pA_bar;pB_bar"] + [
        f"{t * 1e3:.3f};{u * 5 + 5:.6f};{x * 1e3:.5f};{(p1 - PA) / 1e5:.6f};{(p2 - PA) / 1e5:.6f}"
        for t, u, x, p1, p2 in zip(cal_run.t, cal_run.u, cal_run.x, cal_run.p1, cal_run.p2)]
    raw = tmp_path / "daq.csv"
    raw.write_text("\n".join(lines) + "\n")
    mapping = ('[source]\ndelimiter = ";"\n[columns]\nt = { from = "t_ms", unit = "ms" }\n'
               'u = { from = "u_V", unit = "V", zero = 5.0, span = 5.0 }\nx = { from = "x_mm", unit = "mm" }\n'
               'p1 = { from = "pA_bar", unit = "bar"%s }\np2 = { from = "pB_bar", unit = "bar"%s }\n'
               '[atmosphere]\npressure = 101300.0\n')
    (tmp_path / "map.toml").write_text(mapping % ("", ""))
    code, err = call(["import", raw, "--map", tmp_path / "map.toml", "-o", tmp_path / "run.csv"], capsys)
    assert_refused(code, err, "daq.csv", "looks like bar or gauge pressure", "check unit and gauge of columns.p")
    assert not (tmp_path / "run.csv").exists()
    (tmp_path / "map.toml").write_text(mapping % (", gauge = true", ", gauge = true"))
    assert call(["import", raw, "--map", tmp_path / "map.toml", "-o", tmp_path / "run.csv", "-q"], capsys)[0] == 0
    assert preflight(load_cylinder(CFG_A), [read_run(tmp_path / "run.csv")]).notes == ()


def test_a_gauge_supply_in_the_cylinder_file(files, tmp_path, capsys):
    cfg = tmp_path / "cyl.toml"
    cfg.write_text(CFG_A.read_text().replace("pressure = 7.013e5", "pressure = 6.0e5"))
    code, err = call(["identify", "--config", cfg, files / "cal.csv", "-q"], capsys)
    assert_refused(code, err, "cyl.toml: key 'supply.pressure' = 600000 Pa looks like gauge",
                   "give it absolute (gauge + 101300 Pa)")


# ------------------------------------------------------------------ another cylinder, and the same one renamed


@pytest.fixture(scope="module")
def run32(files):
    return files / "mixed.csv"


@pytest.mark.parametrize("argv", [
    ["identify", "--config", CFG_40, "{run}"],
    ["calibrate", "--config", CFG_40, "{run}"],
    ["replay", "{run}", "--config", CFG_40, "--speed", "max"],
    ["friction-map", "{run}", "--config", CFG_40, "--json", "{dir}/map.json"],
    ["diagnose", "{run}", "--validate", "{run}", "--config", CFG_40],
    ["friction-compare", "--config", CFG_40, "{run}", "--validate", "{run}"],
], ids=lambda a: a[0])
def test_a_32_mm_run_with_the_40_mm_file_is_refused_naming_the_bore(argv, run32, capsys):
    code, err = call([str(a).format(run=run32, dir=run32.parent) for a in argv], capsys)
    assert_refused(code, err, "mixed.csv was recorded on a cylinder of another bore, rod and stroke: bore 32 mm",
                   "bore 40 mm", "ind3_norgren_40x250.toml", "its header names")
    assert not (run32.parent / "map.json").exists()


def test_batch_refuses_the_32_mm_run_with_the_40_mm_file_naming_the_bore(run32, tmp_path, capsys):
    manifest = tmp_path / "m.toml"
    manifest.write_text(f'[[cylinder]]\nname = "wrong"\nconfig = "{CFG_40}"\nruns = ["{run32}"]\n')
    assert main([str(a) for a in ("batch", manifest, "--out", tmp_path / "out", "--workers", "1", "--no-report",
                                         "--allow-outside")]) == 1
    out, err = capsys.readouterr()
    assert "wrong: " in err and "recorded on a cylinder of another bore" in err and "bore 32 mm" in err
    table = out.splitlines()  # the batch's table: the row FAILED, its reason wrapped within 100 columns
    assert table[0].split() == ["cylinder", "model", "status", "rmse_x", "verdict"]
    assert table[1].split() == ["wrong", "nominal", "FAILED"] and "another bore" in " ".join(table[2:])
    assert max(map(len, table)) <= 100


def test_the_same_cylinder_under_another_name_is_accepted_with_a_note(run32, tmp_path, capsys):
    cfg = tmp_path / "renamed.toml"
    cfg.write_text(CFG_A.read_text().replace('name = "seed 002 cylinder A (32 x 100)"', 'name = "press 3, cyl 2"'))
    found = preflight(load_cylinder(cfg), [read_run(run32)])
    assert found.notes == (f"{run32} names the cylinder 'seed 002 cylinder A (32 x 100)', {cfg} 'press 3, cyl 2': "
                           "the same bore, rod and stroke, so taken as the same cylinder",)
    # another file of the same geometry (seed 004's Norgren 32 x 100) is not refused either
    assert load_cylinder(CONFIGS / "ind2_norgren_32x100.toml").geometry.bore == 0.032
    preflight(load_cylinder(CONFIGS / "ind2_norgren_32x100.toml"), [read_run(run32)])


def test_without_config_the_cylinder_file_the_header_names_is_used(files, tmp_path, capsys, cyl_a):
    cfg = tmp_path / "mine.toml"
    shutil.copy(CFG_40, cfg)
    cyl = load_cylinder(cfg)
    from combined_reality.simulation import simulate_run

    run = tmp_path / "r40.csv"
    write_run(run, simulate_run(cyl, 3.0, seed=1), comments=[cylinder_tag(cyl)])
    code, err = call(["friction-map", run, "--json", tmp_path / "m.json"], capsys)
    assert err.splitlines()[0] == f"no --config: the cylinder file {cfg} that {run} names is used"
    assert code in (0, 2) and "another bore" not in err  # (a 3 s run may hold no constant-speed stretch)
    # a file named in the header that is not here: the built-in cylinder A, whose geometry it is not
    cfg.unlink()
    code, err = call(["friction-map", run, "--json", tmp_path / "m.json"], capsys)
    assert_refused(code, err, "r40.csv was recorded on a cylinder of another bore",
                   "bore 40 mm, rod 16 mm, stroke 250 mm in its header",
                   "bore 32 mm, rod 12 mm, stroke 100 mm in", "cyl_a_32x100.toml")
    from combined_reality.files import cylinder_for_runs

    cyl, which = cylinder_for_runs(None, [read_run(run)])
    assert cyl.geometry.bore == 0.032
    assert which == f"no --config: the built-in cylinder A (32 mm x 100 mm) is used (the run's header names {cfg}, " \
                    "which is not here)"


# ------------------------------------------------------------------ no false alarm


@pytest.mark.parametrize("cfg", sorted(CONFIGS.glob("*.toml")), ids=lambda p: p.stem)
def test_no_false_alarm_on_any_cylinder(cfg):
    """Every cylinder of configs/: position control at two seeds, the calibration program, an
    effect the nominal model lacks, the pulses program: no refusal and no note."""
    from combined_reality.simulation import simulate_run
    from sim.effects import parse_effect_spec

    cyl = load_cylinder(cfg)
    runs = [simulate_run(cyl, 5.0, seed=1), simulate_run(cyl, 5.0, seed=2),
            simulate_run(cyl, 5.0, seed=3, effects=[parse_effect_spec("valve_delay:tau=0.004")]),
            program_run(cyl, "calibration", 10.0), program_run(cyl, "pulses", 5.0)]
    found = preflight(cyl, runs)
    assert found.notes == ()
    for f in found.figures:  # NaN: too little motion or command for a verdict (the pulses' end stops)
        assert not f["friction_t"] <= 4.0 and not f["agree"] <= 0.75, f
    assert sum(np.isfinite(f["friction_t"]) and np.isfinite(f["agree"]) for f in found.figures) >= 3


def test_no_false_alarm_on_the_test_data(cyl_a):
    run = read_run(ROOT / "tests" / "data" / "lossy_serial_recording_7s5_10s.csv")
    assert preflight(cyl_a, [run]).notes == ()
