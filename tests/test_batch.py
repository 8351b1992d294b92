"""`combined-reality batch`: a manifest of cylinders in, one row per cylinder out.

Bad manifests are refused with one sentence (exit 2); bad files fail their own row, not the
batch (exit 1); results.csv, results.parquet and summary.json agree; unchanged cylinders are
reused, changed ones recomputed; an interrupted batch leaves valid files; a dask cluster gives
the same table as local processes; the seed papers' published friction is recovered.
"""
import json
import math
import os
import shutil
import subprocess
import sys
import textwrap
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import pytest
from conftest import CONFIGS, ROOT, assert_refused

from combined_reality import batch
from combined_reality.batch import execution as batch_execution
from combined_reality.batch import ManifestError, load_manifest, read_results_csv, run_batch
from combined_reality.cli import main

CFG_A = CONFIGS / "cyl_a_32x100.toml"
CFG_B = CONFIGS / "cyl_b_16x40.toml"
SEED_PAPERS = CONFIGS / "manifests" / "seed_papers.toml"  # names the cylinder files one folder up
SHORT = 4.0  # s: simulated runs of the quick tests
DIRS = ("pos", "neg")


# ------------------------------------------------------------------ helpers

def _write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(textwrap.dedent(text).lstrip(), encoding="utf-8")
    return path


def _cli(argv, capsys):
    code = main(["batch", *map(str, argv)])
    out = capsys.readouterr()
    return code, out.out, out.err


def _data_lines(text: str) -> tuple[list[str], int, list[str]]:
    """(lines, index of the header line, column names) of a run CSV."""
    lines = text.splitlines()
    h = next(i for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#"))
    return lines, h, [c.strip() for c in lines[h].split(",")]


def _edit_cell(path: Path, data_row: int, column: str, new: str | None = None, scale: float = 1.0) -> int:
    """Replace one cell of a run CSV (by `new`, or scaled); returns its 1-based file line number."""
    lines, h, names = _data_lines(path.read_text())
    i = h + 1 + data_row if data_row >= 0 else len(lines) + data_row
    cells = lines[i].split(",")
    j = names.index(column)
    cells[j] = new if new is not None else repr(float(cells[j]) * scale)
    lines[i] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    return i + 1


def _parquet_rows(path: Path) -> tuple[list[str], list[dict]]:
    import pyarrow.parquet as pq

    t = pq.read_table(path)
    return t.column_names, t.to_pylist()


def _assert_same_cell(csv_v, pq_v, where):
    """A results.csv cell (as read_results_csv gives it) against the same results.parquet cell."""
    if csv_v is None:  # an empty cell: a CSV cannot tell a missing value from an empty text
        assert pq_v in (None, "") or (isinstance(pq_v, float) and math.isnan(pq_v)), where
    elif isinstance(pq_v, bool):
        assert csv_v == str(pq_v), where
    elif isinstance(pq_v, (int, float)):
        assert float(csv_v) == float(pq_v), where  # floats are written with repr: exact
    else:
        assert str(csv_v) == pq_v, where


def _assert_csv_matches_parquet(out: Path) -> list[dict]:
    rows = read_results_csv(out / "results.csv")
    with open(out / "results.csv", encoding="utf-8") as f:
        header = f.readline().strip().split(",")
    cols, prows = _parquet_rows(out / "results.parquet")
    assert cols == header
    assert len(prows) == len(rows)
    for r, p in zip(rows, prows):
        for c in cols:
            _assert_same_cell(r[c], p[c], (r["name"], c))
    return rows


def _no_temporary_files(out: Path) -> list[str]:
    return [str(p.relative_to(out)) for p in out.rglob("*") if ".tmp" in p.name]


@pytest.fixture(scope="module")
def recorded_run(tmp_path_factory, cyl_a) -> Path:
    """A 4 s run of cylinder A recorded by the virtual rig, tagged with its cylinder."""
    from combined_reality.simulation import simulate_run
    from combined_reality.files import cylinder_tag, write_run

    p = tmp_path_factory.mktemp("recorded") / "a.csv"
    write_run(p, simulate_run(cyl_a, SHORT, seed=5), comments=[cylinder_tag(cyl_a)])
    return p


@pytest.fixture
def folder(tmp_path, recorded_run) -> Path:
    """A manifest folder with copies of cylinder files A and B and a recorded run of A."""
    d = tmp_path / "m"
    d.mkdir()
    shutil.copy(CFG_A, d / "cyl.toml")
    shutil.copy(CFG_B, d / "cyl_b.toml")
    shutil.copy(recorded_run, d / "good.csv")
    return d


# ------------------------------------------------------------------ the manifest

_OK = 'name = "a"\nconfig = "cyl.toml"\n'
BAD_MANIFESTS = {
    "toml syntax": ('[[cylinder]\nname = "a"\n', ["manifest.toml", "not valid TOML"]),
    "no cylinder": ('model = "cvs"\n', ["manifest.toml", "lists no cylinders", "[[cylinder]]"]),
    "cylinder not a table": ("cylinder = 3\n", ["lists no cylinders"]),
    "missing name": ('[[cylinder]]\nconfig = "cyl.toml"\nruns = ["r.csv"]\n', ["cylinder 1", "needs a name"]),
    "empty name": ('[[cylinder]]\nname = " "\nconfig = "cyl.toml"\nruns = ["r.csv"]\n',
                   ["cylinder 1", "needs a name"]),
    "duplicate name": (f'[[cylinder]]\n{_OK}runs = ["r.csv"]\n[[cylinder]]\n{_OK}runs = ["s.csv"]\n',
                       ["'a'", "used twice"]),
    "unknown key": (f'[[cylinder]]\n{_OK}runs = ["r.csv"]\ncolour = "red"\n', ["'a'", "unknown key", "colour"]),
    "unknown top-level key": (f'workers = 3\n[[cylinder]]\n{_OK}runs = ["r.csv"]\n',
                              ["unknown top-level key", "workers"]),
    "missing config": ('[[cylinder]]\nname = "a"\nruns = ["r.csv"]\n', ["'a'", "config"]),
    "unknown model": (f'[[cylinder]]\n{_OK}runs = ["r.csv"]\nmodel = "magic"\n',
                      ["'a'", "unknown model 'magic'", "cvs"]),
    "unknown default model": (f'model = "magic"\n[[cylinder]]\n{_OK}runs = ["r.csv"]\n',
                              ["'a'", "unknown model 'magic'"]),
    "runs and simulate": (f'[[cylinder]]\n{_OK}runs = ["r.csv"]\nsimulate = {{duration = 4}}\n',
                          ["'a'", "runs", "simulate", "exactly one"]),
    "neither runs nor simulate": (f"[[cylinder]]\n{_OK}", ["'a'", "runs", "simulate", "exactly one"]),
    "empty runs": (f"[[cylinder]]\n{_OK}runs = []\n", ["'a'", "non-empty list"]),
    "runs not strings": (f"[[cylinder]]\n{_OK}runs = [3]\n", ["'a'", "non-empty list"]),
    "simulate not a table": (f"[[cylinder]]\n{_OK}simulate = 4\n", ["'a'", "simulate must be a table"]),
    "default simulate not a table": (f"simulate = 4\n[[cylinder]]\n{_OK}runs = ['r.csv']\n",
                                     ["top-level simulate"]),
    # each value is held to its command-line option's rule, in the same words
    "negative duration": (f"[[cylinder]]\n{_OK}simulate = {{duration = -1}}\n",
                          ["'a'", "simulate.duration must be a positive number of seconds, not -1"]),
    "infinite duration": (f"[[cylinder]]\n{_OK}simulate = {{duration = inf}}\n",
                          ["'a'", "simulate.duration must be a positive number of seconds, not inf"]),
    "negative seed": (f"[[cylinder]]\n{_OK}simulate = {{seed = -1}}\n",
                      ["'a'", "simulate.seed must be a whole number from 0 to 4294967295, not -1"]),
    "too short": (f"[[cylinder]]\n{_OK}simulate = {{duration = 1e-6}}\n", ["'a'", "a run needs at least 10"]),
    "duration not a number": (f'[[cylinder]]\n{_OK}simulate = {{duration = "long"}}\n',
                              ["'a'", "simulate.duration must be a number, not 'long'"]),
    "duration a boolean": (f"[[cylinder]]\n{_OK}simulate = {{duration = true}}\n",
                           ["'a'", "simulate.duration must be a number, not True"]),
    "seed not whole": (f"[[cylinder]]\n{_OK}simulate = {{seed = 1.5}}\n",
                       ["'a'", "simulate.seed must be a whole number, not 1.5"]),
    "runs a boolean": (f"[[cylinder]]\n{_OK}simulate = {{runs = true}}\n",
                       ["'a'", "simulate.runs must be a whole number"]),
    "rate too low": (f"[[cylinder]]\n{_OK}simulate = {{rate = 5}}\n", ["'a'", "rate"]),
    "no runs": (f"[[cylinder]]\n{_OK}simulate = {{runs = 0}}\n",
                ["'a'", "simulate.runs must be a whole number at least 1"]),
    "bad default simulate": (f"[simulate]\nduration = 0\n[[cylinder]]\n{_OK}simulate = {{seed = 2}}\n",
                             ["'a'", "simulate.duration must be a positive number"]),
    "outside the folder": (f'[[cylinder]]\n{_OK}runs = ["/etc/shadow"]\n',
                           ["'a'", "runs '/etc/shadow' lies outside the manifest's folder", "--allow-outside"]),
    "climbing out": ('[[cylinder]]\nname = "a"\nconfig = "../../cyl.toml"\nruns = ["r.csv"]\n',
                     ["'a'", "config '../../cyl.toml' lies outside"]),
    "unknown simulate key": (f"[[cylinder]]\n{_OK}simulate = {{durations = 4}}\n",
                             ["'a'", "unknown simulate key", "durations"]),
    "effect not a string": (f"[[cylinder]]\n{_OK}simulate = {{effect = 3}}\n", ["'a'", "simulate.effect"]),
    "effect list of numbers": (f"[[cylinder]]\n{_OK}simulate = {{effect = [3]}}\n", ["'a'", "simulate.effect"]),
    "noise not a boolean": (f'[[cylinder]]\n{_OK}simulate = {{noise = "false"}}\n', ["'a'", "simulate.noise"]),
}


@pytest.mark.parametrize("text, fragments", BAD_MANIFESTS.values(), ids=BAD_MANIFESTS.keys())
def test_bad_manifest_is_refused_with_one_sentence(tmp_path, capsys, text, fragments):
    m = tmp_path / "manifest.toml"
    m.write_text(text)
    with pytest.raises(ManifestError) as e:
        load_manifest(m)
    msg = str(e.value)
    assert "\n" not in msg
    for f in fragments:
        assert f in msg, (f, msg)
    code, out, err = _cli([m, "--out", tmp_path / "out", "--no-report", "--workers", "1"], capsys)
    assert_refused(code, err, "manifest.toml", *fragments)
    assert not (tmp_path / "out").exists()  # a refused manifest writes nothing


def test_missing_manifest(tmp_path, capsys):
    code, _, err = _cli([tmp_path / "nope.toml", "--out", tmp_path / "out", "--no-report"], capsys)
    assert_refused(code, err, "nope.toml", "cannot read the manifest")


def test_relative_paths_resolve_against_the_manifest_folder(tmp_path, monkeypatch):
    deep = tmp_path / "project" / "manifests"
    m = _write(deep / "manifest.toml", """
        model = "cvs"
        [simulate]
        duration = 6
        [[cylinder]]
        name = "rec"
        config = "cyl.toml"
        runs = ["../runs/r1.csv", "r2.csv"]
        model = "nominal"
        [[cylinder]]
        name = "sim"
        config = "../cyl.toml"
        simulate = {seed = 7, effect = "cvs:Fs_pos=6"}
        """)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    with pytest.raises(ManifestError, match="lies outside the manifest's folder"):
        load_manifest(Path("../project/manifests/manifest.toml"))  # ../runs and ../cyl.toml leave its folder
    rec, sim = load_manifest(Path("../project/manifests/manifest.toml"), allow_outside=True)
    assert rec.config == str(deep / "cyl.toml")
    assert rec.runs == (str(tmp_path / "project" / "runs" / "r1.csv"), str(deep / "r2.csv"))
    assert rec.model == "nominal" and rec.simulate is None
    assert sim.config == str(tmp_path / "project" / "cyl.toml")
    assert sim.model == "cvs"  # the manifest's default
    assert sim.simulate == batch.SimulateSpec(duration=6.0, seed=7, effects=("cvs:Fs_pos=6",), runs=1)
    assert load_manifest(m, diagnose=True, allow_outside=True)[1].simulate.runs == 2  # TRAIN and VALID


# ------------------------------------------------------------------ failures fail their row only

def test_bad_files_fail_their_rows_and_the_batch_finishes(folder, tmp_path, capsys, monkeypatch, cyl_a):
    bad = folder / "bad.csv"
    shutil.copy(folder / "good.csv", bad)
    line = _edit_cell(bad, 10, "x", new="abc")
    m = _write(folder / "manifest.toml", f"""
        [simulate]
        duration = {SHORT}

        [[cylinder]]
        name = "sim_ok"
        config = "cyl.toml"
        simulate = {{seed = 3}}

        [[cylinder]]
        name = "corrupt"
        config = "cyl.toml"
        runs = ["good.csv", "bad.csv"]

        [[cylinder]]
        name = "recorded_ok"
        config = "cyl.toml"
        runs = ["good.csv"]

        [[cylinder]]
        name = "no_cylinder_file"
        config = "nope.toml"
        simulate = {{seed = 4}}

        [[cylinder]]
        name = "no_run_file"
        config = "cyl.toml"
        runs = ["missing.csv"]

        [[cylinder]]
        name = "wrong_cylinder"
        config = "cyl_b.toml"
        runs = ["good.csv"]
        """)
    monkeypatch.chdir(tmp_path)  # paths in the manifest are relative to its folder, not to here
    out = tmp_path / "out"
    code, _, err = _cli([m, "--out", out, "--workers", "1", "--no-report", "--json", tmp_path / "s.json"], capsys)
    assert code == 1, err
    assert "2 of 6 cylinders identified, 4 failed" in err

    rows = _assert_csv_matches_parquet(out)
    by = {r["name"]: r for r in rows}
    assert [r["name"] for r in rows] == ["sim_ok", "corrupt", "recorded_ok", "no_cylinder_file", "no_run_file",
                                         "wrong_cylinder"]  # manifest order
    expected_errors = {
        "corrupt": ["bad.csv", f"line {line}", "'x'", "abc"],
        "no_cylinder_file": ["nope.toml", "not found"],
        "no_run_file": ["missing.csv", "not found"],
        "wrong_cylinder": ["good.csv", "recorded on a cylinder of another bore", "bore 32 mm",
                           "cyl_b.toml"],
    }
    for name, fragments in expected_errors.items():
        r = by[name]
        assert r["status"] == "failed", r
        for f in fragments:
            assert f in r["error"], (name, f, r["error"])
        assert r["Fc"] is None  # no parameters for a failed row
        assert f"{name}: {r['error']}" in err  # listed at the end
    # the good rows are really identified: cylinder A's published friction, from 4 s of data
    a = {k: cyl_a.value(k) for k in ("Fc", "Fv", "kp")}
    for name in ("sim_ok", "recorded_ok"):
        r = by[name]
        assert r["status"] == "ok" and r["error"] is None, r
        assert r["solver_status"] == "converged"
        for k, truth in a.items():
            assert r[k] == pytest.approx(truth, rel=0.1), (name, k)
    assert by["sim_ok"]["truth_Fc"] == a["Fc"] and by["recorded_ok"]["truth_Fc"] is None
    assert by["sim_ok"]["source"] == "simulated" and by["recorded_ok"]["source"] == "recorded"
    assert by["recorded_ok"]["config"] == str(folder / "cyl.toml")

    summary = json.loads((out / "summary.json").read_text())
    assert json.loads((tmp_path / "s.json").read_text()) == summary
    assert (summary["cylinders"], summary["ok"], summary["failed"], summary["reused_unchanged"]) == (6, 2, 4, 0)
    assert {f["name"]: f["error"] for f in summary["failures"]} == {n: by[n]["error"] for n in expected_errors}
    assert [(r["name"], r["status"]) for r in summary["rows"]] == [(r["name"], r["status"]) for r in rows]
    for s, r in zip(summary["rows"], rows):
        for k in ("Fc", "Fv", "kp", "rmse_x"):
            assert s.get(k) == r[k]
    # the simulated run is kept, tagged with its cylinder
    from combined_reality.files import read_run, recorded_cylinder

    kept = read_run(out / "runs" / "sim_ok_1.csv")
    assert recorded_cylinder(kept).startswith("seed 002 cylinder A")
    assert _no_temporary_files(out) == []


# ------------------------------------------------------------------ incremental

def test_unchanged_cylinders_are_reused_and_changed_ones_recomputed(folder, tmp_path, monkeypatch):
    manifest = """
        [[cylinder]]
        name = "rec"
        config = "cyl.toml"
        runs = ["good.csv"]

        [[cylinder]]
        name = "sim"
        config = "cyl_b.toml"
        simulate = {{duration = {d}, seed = 2}}
        model = "{model}"

        [[cylinder]]
        name = "broken"
        config = "nope.toml"
        simulate = {{duration = {d}}}
        """
    m = _write(folder / "manifest.toml", manifest.format(d=SHORT, model="nominal"))
    calls = []
    real = batch.run_job

    def spy(job):
        calls.append(job.name)
        return real(job)

    monkeypatch.setattr(batch_execution, "run_job", spy)
    out = tmp_path / "out"

    def run():
        calls.clear()
        s = run_batch(load_manifest(m), out, None, report=False)
        return s, {r["name"]: r for r in read_results_csv(out / "results.csv")}

    first, rows1 = run()
    assert calls == ["rec", "sim", "broken"]
    assert (first.ok, first.failed, first.cached) == (2, 1, 0)

    os.utime(folder / "good.csv", (1e9, 1e9))  # touched, same content: still unchanged
    second, rows2 = run()
    assert calls == ["broken"]  # a failed row is tried again, ok rows are not
    assert (second.ok, second.failed, second.cached) == (2, 1, 2)
    assert json.loads((out / "summary.json").read_text())["reused_unchanged"] == 2
    assert second.wall_s < 0.3 * first.wall_s, (second.wall_s, first.wall_s)
    for name in ("rec", "sim"):
        assert rows2[name]["cached"] == "True"
        assert {k: v for k, v in rows2[name].items() if k != "cached"} == \
               {k: v for k, v in rows1[name].items() if k != "cached"}
    assert rows2["broken"]["cached"] is None
    _, prows = _parquet_rows(out / "results.parquet")
    assert [p["cached"] for p in prows] == [True, True, None]

    _edit_cell(folder / "good.csv", -1, "p1", scale=1.0001)  # the run's content changes
    third, rows3 = run()
    assert calls == ["rec", "broken"]
    assert third.cached == 1 and rows3["sim"]["cached"] == "True" and rows3["rec"]["cached"] is None
    assert rows3["rec"]["status"] == "ok" and rows3["rec"]["hash"] != rows1["rec"]["hash"]
    assert len(list((out / "cache").glob("rec.*.json"))) == 1  # the outdated row is dropped

    m.write_text(textwrap.dedent(manifest).format(d=SHORT, model="cv"))  # the model changes
    fourth, rows4 = run()
    assert calls == ["sim", "broken"]
    assert fourth.cached == 1 and rows4["rec"]["cached"] == "True"
    assert rows4["sim"]["model"] == "cv" and rows4["sim"]["status"] == "ok", rows4["sim"]
    assert rows4["sim"]["Fc_pos"] is not None and rows4["sim"]["Fv"] is None  # the new model's parameters
    assert rows4["rec"]["Fc"] == rows3["rec"]["Fc"]


def test_interrupted_batch_leaves_valid_files_with_the_finished_rows(folder, tmp_path):
    m = _write(folder / "manifest.toml", f"""
        [[cylinder]]
        name = "first"
        config = "cyl.toml"
        simulate = {{duration = {SHORT}, seed = 9}}

        [[cylinder]]
        name = "second"
        config = "nope.toml"
        simulate = {{duration = {SHORT}}}

        [[cylinder]]
        name = "third"
        config = "cyl.toml"
        runs = ["missing.csv"]
        """)
    out = tmp_path / "out"
    seen = []

    def ctrl_c(done, total, row, elapsed):
        seen.append(row["name"])
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_batch(load_manifest(m), out, None, progress=ctrl_c, report=False)
    assert seen == ["first"]
    rows = _assert_csv_matches_parquet(out)
    assert [(r["name"], r["status"]) for r in rows] == [("first", "ok")]
    assert _no_temporary_files(out) == []

    # started again, the finished row is reused and the rest computed
    s = run_batch(load_manifest(m), out, None, report=False)
    assert (s.total, s.ok, s.failed, s.cached) == (3, 1, 2, 1)
    rows2 = _assert_csv_matches_parquet(out)
    assert [r["name"] for r in rows2] == ["first", "second", "third"]
    assert rows2[0]["Fc"] == rows[0]["Fc"]


def test_html_report(folder, tmp_path):
    m = _write(folder / "manifest.toml", f"""
        [[cylinder]]
        name = "identified_one"
        config = "cyl.toml"
        simulate = {{duration = {SHORT}, seed = 9}}

        [[cylinder]]
        name = "failed_one"
        config = "nope.toml"
        simulate = {{duration = {SHORT}}}
        """)
    out = tmp_path / "out"
    s = run_batch(load_manifest(m), out, None, report=True)
    assert (s.ok, s.failed) == (1, 1)
    html = (out / "report.html").read_text(encoding="utf-8")
    assert "<html" in html.lower()
    assert "identified_one" in html and "failed_one" in html
    assert "nope.toml" in html  # the failed row says why
    assert json.loads((out / "summary.json").read_text())["report"] == str(out / "report.html")


# ------------------------------------------------------------------ friction recovery

def _seed_papers_job(name: str, duration: float | None = None):
    job = next(j for j in load_manifest(SEED_PAPERS, allow_outside=True) if j.name == name)
    return job if duration is None else replace(job, simulate=replace(job.simulate, duration=duration))


def test_a_row_reports_the_status_identify_reports(monkeypatch):
    """A fit that converged with an estimate the data do not determine is `not_determined` in
    the row, as in identify's JSON, with the parameters named in the row's warning."""
    from combined_reality.identify import Estimate, IdentifyResult

    def undetermined(cyl, runs, model, options):
        est = lambda n, v, s: Estimate(n, v, s, "N/Pa", v)  # noqa: E731
        return IdentifyResult(params={"Fc": est("Fc", 24.8, 0.1), "Fv": est("Fv", 13.0, 0.2),
                                      "kp": est("kp", 2e-7, 3e-7)},
                              fit={"rmse_x": 5e-6, "r2_x": 0.99}, fit_per_run=[], cylinder=cyl, effects=(),
                              drive="command", solver={"status": "converged", "iterations": 8, "wall_s": 1.0,
                                                       "n_samples": 100, "residual_sigma": 1.0})

    monkeypatch.setattr(batch_execution, "identify_model", undetermined)
    row = batch.run_job(_seed_papers_job("seed004_4", duration=1.0))
    assert row["status"] == "ok", row
    assert row["solver_status"] == "not_determined"
    assert "the data do not determine kp" in row["warning"]


def _assert_cvs_recovered(row: dict) -> None:
    """seed 004's per-direction model: Fs, Fc, B within 5 %; the truth of the Stribeck velocity
    inside four standard deviations of the estimate, and that interval informative."""
    assert row["status"] == "ok", row
    for d in DIRS:
        for p in ("Fs", "Fc", "B"):
            k = f"{p}_{d}"
            assert row[k] == pytest.approx(row[f"truth_{k}"], rel=0.05), (row["name"], k, row[k], row[f"truth_{k}"])
        vs, std, truth = row[f"vs_{d}"], row[f"vs_{d}_std"], row[f"truth_vs_{d}"]
        assert 0 < std < 0.2 * vs, (row["name"], d, vs, std)
        assert abs(vs - truth) <= 4 * std, (row["name"], d, vs, std, truth)


def test_per_direction_stribeck_model_recovered():
    """Actuator 4 of seed 004 (Table 3), 5 s on the virtual rig."""
    row = batch.run_job(_seed_papers_job("seed004_4", duration=5.0))
    assert row["model"] == "cvs"
    assert (row["truth_Fs_pos"], row["truth_Fc_neg"], row["truth_B_neg"], row["truth_vs_pos"]) == \
           (6.0, 6.1, 259.13, 0.0085)  # the published values, from the manifest
    _assert_cvs_recovered(row)


# ------------------------------------------------------------------ dask

def test_dask_cluster_gives_the_table_of_local_processes(folder, tmp_path, capsys):
    import distributed
    m = _write(folder / "manifest.toml", f"""
        [simulate]
        duration = {SHORT}

        [[cylinder]]
        name = "nominal_A"
        config = "cyl.toml"
        simulate = {{seed = 1}}

        [[cylinder]]
        name = "stribeck_B"
        config = "cyl_b.toml"
        model = "cvs"
        simulate = {{seed = 2, effect = "cvs:Fs_pos=8,Fs_neg=6,Fc_pos=6.4,Fc_neg=4,B_pos=10.4,B_neg=30.4,vs_pos=0.02,vs_neg=0.02"}}

        [[cylinder]]
        name = "broken"
        config = "cyl.toml"
        runs = ["missing.csv"]
        """)
    local_out, dask_out = tmp_path / "local", tmp_path / "dask"
    with ProcessPoolExecutor(2) as pool:
        local = run_batch(load_manifest(m), local_out, pool, report=False, workers=2)
    assert (local.ok, local.failed) == (2, 1)

    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        addr = cluster.scheduler_address
        code, _, err = _cli([m, "--out", dask_out, "--scheduler", addr, "--no-report", "-q"], capsys)
        assert code == 1, err
        with distributed.Client(addr) as client:  # the tasks really ran on the cluster
            ran = client.run_on_scheduler(
                lambda dask_scheduler: {name: tp.state_counts["memory"]  # entries into state memory
                                        for name, tp in dask_scheduler.task_prefixes.items()})
        assert ran.get("run_job") == 3, ran

    summary = json.loads((dask_out / "summary.json").read_text())
    assert summary["scheduler"] == addr and summary["workers"] == 2
    a, b = read_results_csv(local_out / "results.csv"), _assert_csv_matches_parquet(dask_out)
    assert list(a[0]) == list(b[0])  # the same columns
    assert [(r["name"], r["status"], r["error"]) for r in a] == [(r["name"], r["status"], r["error"]) for r in b]
    for ra, rb in zip(a, b):
        for k, va in ra.items():
            if k == "wall_s":
                continue
            vb = rb[k]
            if isinstance(va, float):
                assert vb == pytest.approx(va, rel=1e-9, nan_ok=True), (ra["name"], k)
            else:
                assert va == vb, (ra["name"], k)
    assert {r["name"]: r["status"] for r in b} == {"nominal_A": "ok", "stribeck_B": "ok", "broken": "failed"}


# ------------------------------------------------------------------ the must-show: the seed papers

@pytest.fixture(scope="module")
def seed_papers_rows(tmp_path_factory):
    """The ten cylinders of configs/manifests/seed_papers.toml on two processes, with 10 s runs
    instead of the manifest's 20 s (the batch and the recovery are the same; CI is shorter)."""
    out = tmp_path_factory.mktemp("seed_papers")
    jobs = [replace(j, simulate=replace(j.simulate, duration=10.0))
            for j in load_manifest(SEED_PAPERS, allow_outside=True)]
    with ProcessPoolExecutor(2) as pool:
        summary = run_batch(jobs, out, pool, report=False, workers=2)
    return summary, out, _assert_csv_matches_parquet(out)


@pytest.mark.slow
@pytest.mark.xdist_group("seed_papers")  # one worker computes the fixture, not two
def test_seed_papers_batch(seed_papers_rows):
    summary, out, rows = seed_papers_rows
    assert (summary.total, summary.ok, summary.failed) == (10, 10, 0), summary.to_json()["failures"]
    assert [r["name"] for r in rows] == [j.name for j in load_manifest(SEED_PAPERS, allow_outside=True)]
    assert len(list((out / "runs").glob("*.csv"))) == 10
    assert _no_temporary_files(out) == []


@pytest.mark.slow
@pytest.mark.xdist_group("seed_papers")  # one worker computes the fixture, not two
def test_seed004_per_direction_friction_recovered(seed_papers_rows):
    rows = [r for r in seed_papers_rows[2] if r["name"].startswith("seed004_")]
    assert len(rows) == 8
    for r in rows:
        _assert_cvs_recovered(r)


@pytest.mark.slow
@pytest.mark.xdist_group("seed_papers")  # one worker computes the fixture, not two
def test_seed002_nominal_friction_recovered(seed_papers_rows):
    rows = [r for r in seed_papers_rows[2] if r["name"].startswith("seed002_")]
    assert len(rows) == 2
    for r in rows:
        assert r["status"] == "ok" and r["model"] == "nominal", r
        for k in ("Fc", "Fv", "kp"):
            assert r[k] == pytest.approx(r[f"truth_{k}"], rel=0.05), (r["name"], k, r[k], r[f"truth_{k}"])


# ------------------------------------------------------------------ a real cluster (issue 17)

def _start(argv, cwd: Path, log: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.Popen([sys.executable, "-m", "dask", *argv], cwd=cwd, env=env, stdout=log.open("wb"),
                            stderr=subprocess.STDOUT, start_new_session=True)


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.mark.slow
def test_dask_scheduler_and_worker_processes_elsewhere_write_nothing_in_their_folder(tmp_path, monkeypatch, capsys):
    """A `dask scheduler` and a `dask worker` started as their own processes in another folder: every output of
    the batch lies under --out on the client's side (workers return data), and two names that differ only in
    punctuation get files of their own."""
    import distributed

    client_dir, cluster_dir, scratch = tmp_path / "client", tmp_path / "cluster", tmp_path / "scratch"
    for d in (client_dir, cluster_dir, scratch):
        d.mkdir()
    shutil.copy(CFG_A, client_dir / "cyl.toml")
    _write(client_dir / "fleet.toml", f"""
        [simulate]
        duration = {SHORT}

        [[cylinder]]
        name = "press 3/cylinder 2"
        config = "cyl.toml"
        simulate = {{seed = 1}}

        [[cylinder]]
        name = "press 3 cylinder 2"
        config = "cyl.toml"
        simulate = {{seed = 2}}
        """)
    sched_file = tmp_path / "scheduler.json"
    scheduler = _start(["scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard", "--scheduler-file",
                        str(sched_file)], cluster_dir, tmp_path / "scheduler.log")
    worker = None
    try:
        deadline = time.monotonic() + 60
        while not sched_file.exists() and time.monotonic() < deadline:
            time.sleep(0.2)
        address = json.loads(sched_file.read_text())["address"]
        worker = _start(["worker", address, "--nworkers", "1", "--nthreads", "1", "--no-dashboard",
                         "--local-directory", str(scratch), "--name", "w1"], cluster_dir, tmp_path / "worker.log")
        with distributed.Client(address, timeout="60s") as c:
            c.wait_for_workers(1, timeout=60)
        monkeypatch.chdir(client_dir)  # --out relative: it is the client's folder, not a worker's
        code, _, err = _cli(["fleet.toml", "--out", "out", "--scheduler", address, "--no-report"], capsys)
        assert code == 0, err
    finally:
        for p in (worker, scheduler):
            if p is not None:
                _stop(p)
    assert sorted(p.name for p in cluster_dir.iterdir()) == []  # nothing in the workers' folder
    out = client_dir / "out"
    rows = {r["name"]: r for r in read_results_csv(out / "results.csv")}
    files = {name: r["run_files"] for name, r in rows.items()}
    assert len(set(files.values())) == 2  # no name overwrites the other's runs
    for f in files.values():
        assert (out / f).is_file() and f.startswith("runs/")
    assert len(list((out / "cache").glob("*.json"))) == 2  # nor its cache entry
    assert "file names of cylinders" in err and "'press 3/cylinder 2' -> press_3_cylinder_2-" in err
    written = {p.relative_to(tmp_path).parts[0] for p in tmp_path.rglob("*") if p.is_file()}
    assert written <= {"client", "scratch", "scheduler.json", "scheduler.log", "worker.log"}


def test_names_that_differ_only_in_punctuation_or_case_get_their_own_files(tmp_path):
    _write(tmp_path / "cyl.toml", CFG_A.read_text())
    names = ["cyl A", "cyl/A", "CYL_a", "plain"]
    _write(tmp_path / "m.toml", "".join(f'[[cylinder]]\nname = "{n}"\nconfig = "cyl.toml"\nsimulate = {{}}\n\n'
                                        for n in names))
    stems = [j.file_stem for j in load_manifest(tmp_path / "m.toml")]
    assert len({s.lower() for s in stems}) == 4 and stems[3] == "plain"
    # the same stems whatever the order of the manifest
    _write(tmp_path / "r.toml", "".join(f'[[cylinder]]\nname = "{n}"\nconfig = "cyl.toml"\nsimulate = {{}}\n\n'
                                        for n in reversed(names)))
    assert [j.file_stem for j in load_manifest(tmp_path / "r.toml")] == stems[::-1]


@pytest.mark.parametrize("sim, says", [
    ("{duration = 1e9}", "simulate.duration 1e+09 s at 1000 Hz gives 1e+12 samples"),
    ("{duration = 600, rate = 2000}", "at most 1e+06 per cylinder"),
    ("{duration = 400, runs = 3}", "x 3 run(s)"),
])
def test_simulation_lengths_are_bounded(tmp_path, capsys, sim, says):
    _write(tmp_path / "cyl.toml", CFG_A.read_text())
    m = _write(tmp_path / "m.toml", f'[[cylinder]]\nname = "big"\nconfig = "cyl.toml"\nsimulate = {sim}\n')
    code, _, err = _cli([m, "--out", tmp_path / "out"], capsys)
    assert_refused(code, err, "m.toml", "cylinder 'big'", says)
    assert not (tmp_path / "out").exists()
