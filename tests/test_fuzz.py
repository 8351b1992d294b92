"""Malformed inputs never end in an internal error (issue 17): mutated runs, cylinder files,
mappings, manifests, points tables and command files fed to the command line in-process give
exit status 2 with one sentence naming the file (or, for a batch, a failed row that names it),
option values are refused as they are parsed or lie within their documented range, and the two
crashes found by hand stay fixed in every subcommand that reads such files (issue 43 adds
tests/test_hostile.py: special files, huge inputs, impossible outputs)."""
from __future__ import annotations

import json
import math
import textwrap
from pathlib import Path

import pytest
from conftest import CONFIGS
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from combined_reality.batch import read_results_csv
from combined_reality.cli import main

CFG = CONFIGS / "cyl_a_32x100.toml"
# a short run without motion: every reader and check runs on it, and identify refuses it in milliseconds
STILL = "t,u,x,p1,p2\n" + "".join(f"{i * 1e-3:.3f},0.0,0.05,300000,300000\n" for i in range(40))
LAB = ("Zeit [ms];Ventil [V];Weg [mm];P_A [bar];P_B [bar]\n"
       + "".join(f"{i:d};5,0;50,0;2,0;2,0\n" for i in range(40)))
MAPPING = textwrap.dedent("""\
    [source]
    delimiter = ";"
    decimal = ","
    [columns]
    t = { from = "Zeit [ms]", unit = "ms" }
    u = { from = "Ventil [V]", unit = "V", zero = 5.0, span = 5.0 }
    x = { from = "Weg [mm]", unit = "mm" }
    p1 = { from = "P_A [bar]", unit = "bar", gauge = true }
    p2 = { from = "P_B [bar]", unit = "bar", gauge = true }
    [atmosphere]
    pressure = 101300.0
    """)
MANIFEST = textwrap.dedent("""\
    model = "nominal"
    [[cylinder]]
    name = "press 3"
    config = "cyl.toml"
    runs = ["run.csv"]
    """)
# what tends to break parsers: quotes, delimiters, numbers that are not, bytes that are not UTF-8, TOML syntax
TOKENS = ['"', "'", ",", ";", "\n", "\r", "\t", " ", "#", "=", "[", "]", "{", "}", "nan", "inf", "-1e309", "1e999",
          "-", "7", "0", "1e5", "\x00", "\ufeff", "ä", "[geometry]", "true", "x", "u", "bar", "ms", "zero = ",
          "[[cylinder]]", "simulate = {}", "runs = []", "1_0", "0x10"]
FUZZ = settings(max_examples=40, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


@st.composite
def mutated(draw, text: str) -> bytes:
    """A few edits of `text`: delete a stretch, insert a token or raw bytes, duplicate or drop a line."""
    data = text.encode("utf-8")
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(["delete", "token", "bytes", "dup_line", "drop_line"]))
        i = draw(st.integers(0, len(data)))
        if kind == "delete":
            data = data[:i] + data[i + draw(st.integers(1, 12)):]
        elif kind == "token":
            data = data[:i] + draw(st.sampled_from(TOKENS)).encode("utf-8") + data[i:]
        elif kind == "bytes":
            data = data[:i] + draw(st.binary(min_size=1, max_size=4)) + data[i:]
        else:
            lines = data.split(b"\n")
            k = draw(st.integers(0, len(lines) - 1))
            lines = lines[:k] + ([lines[k]] * 2 if kind == "dup_line" else []) + lines[k + 1:]
            data = b"\n".join(lines)
    return data


def _call(argv, capsys) -> tuple[int, str]:
    code = main([str(a) for a in argv])
    return code, capsys.readouterr().err


def _one_located_sentence(code: int, err: str, *files: str) -> None:
    assert "internal error" not in err and "Traceback" not in err, err
    assert code == 2, (code, err)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert any(f in lines[0] for f in files), (files, lines[0])


@pytest.fixture
def workdir(tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzz")
    (d / "cyl.toml").write_text(CFG.read_text())
    (d / "run.csv").write_text(STILL)
    (d / "lab.csv").write_text(LAB)
    (d / "map.toml").write_text(MAPPING)
    return d


@FUZZ
@given(data=mutated(STILL))
def test_mutated_runs(workdir, capsys, data):
    path = workdir / "mut_run.csv"
    path.write_bytes(data)
    code, err = _call(["identify", "--config", workdir / "cyl.toml", path, "-q"], capsys)
    _one_located_sentence(code, err, "mut_run.csv")


@FUZZ
@given(data=mutated(CFG.read_text()))
def test_mutated_cylinder_files(workdir, capsys, data):
    path = workdir / "mut_cyl.toml"
    path.write_bytes(data)
    code, err = _call(["identify", "--config", path, workdir / "run.csv", "-q"], capsys)
    _one_located_sentence(code, err, "mut_cyl.toml", "run.csv")  # a file still valid: the run cannot determine


@FUZZ
@given(data=mutated(MAPPING))
def test_mutated_mappings(workdir, capsys, data):
    path = workdir / "mut_map.toml"
    path.write_bytes(data)
    code, err = _call(["import", workdir / "lab.csv", "--map", path, "-o", workdir / "out.csv", "-q"], capsys)
    if code != 0:  # a mapping that is still valid imports
        _one_located_sentence(code, err, "mut_map.toml", "lab.csv")


@FUZZ
@given(data=mutated(LAB))
def test_mutated_recordings(workdir, capsys, data):
    path = workdir / "mut_lab.csv"
    path.write_bytes(data)
    code, err = _call(["import", path, "--map", workdir / "map.toml", "-o", workdir / "out.csv", "-q"], capsys)
    if code != 0:
        _one_located_sentence(code, err, "mut_lab.csv")


@FUZZ
@given(data=mutated(MANIFEST))
def test_mutated_manifests(workdir, capsys, data):
    path = workdir / "mut_fleet.toml"
    path.write_bytes(data)
    out = workdir / "out"
    code, err = _call(["batch", path, "--out", out, "--workers", "1", "--no-report", "-q"], capsys)
    assert "internal error" not in err and "Traceback" not in err, err
    if code == 2:
        _one_located_sentence(code, err, "mut_fleet.toml")
    else:  # a manifest that is still valid: its cylinders fail in their rows (the run cannot determine), by name
        assert code in (0, 1), (code, err)
        for row in read_results_csv(out / "results.csv"):
            assert row["status"] == "ok" or (row["error"] and "internal" not in row["error"]), row


# ------------------------------------------------------------------ the crashes found by hand


def _unclosed_quote_run(path: Path) -> Path:
    rows = "".join(f"{i * 1e-3:.3f},0.1,0.05,300000,300000\n" for i in range(2, 3000))
    path.write_text('t,u,x,p1,p2\n0,0.1,0.05,300000,300000\n0.001,"0.1,0.05,300000,300000\n' + rows)
    return path


# the line of the cylinder's name, where the latin-1 byte is
NAME_LINE = next(i for i, ln in enumerate(CFG.read_text().splitlines(), 1) if ln.startswith("name = "))


def _latin1_cylinder(path: Path) -> Path:
    path.write_bytes(CFG.read_text().replace('name = "', 'name = "Zylinder für ', 1).encode("latin-1"))
    return path


@pytest.mark.parametrize("what", ["unclosed quote", "not UTF-8"])
@pytest.mark.parametrize("command", ["identify", "friction-map", "diagnose"])
def test_crashes_found_by_hand_are_located(tmp_path, capsys, command, what):
    run = _unclosed_quote_run(tmp_path / "quoted.csv") if what == "unclosed quote" else tmp_path / "run.csv"
    if what != "unclosed quote":
        run.write_text(STILL)
    cfg = _latin1_cylinder(tmp_path / "latin1.toml") if what == "not UTF-8" else CFG
    argv = {"identify": ["identify", "--config", cfg, run, "-q"],
            "friction-map": ["friction-map", run, "--config", cfg, "--json", tmp_path / "m.json", "-q"],
            "diagnose": ["diagnose", run, "--validate", run, "--config", cfg]}[command]
    code, err = _call(argv, capsys)
    named = "quoted.csv, line 3" if what == "unclosed quote" else f"latin1.toml, line {NAME_LINE}: not UTF-8"
    _one_located_sentence(code, err, named)


@pytest.mark.parametrize("what", ["unclosed quote", "not UTF-8"])
def test_crashes_found_by_hand_are_located_in_a_batch_row(tmp_path, capsys, what):
    run = _unclosed_quote_run(tmp_path / "quoted.csv") if what == "unclosed quote" else tmp_path / "run.csv"
    if what != "unclosed quote":
        run.write_text(STILL)
    cfg = _latin1_cylinder(tmp_path / "latin1.toml") if what == "not UTF-8" else tmp_path / "cyl.toml"
    if what != "not UTF-8":
        cfg.write_text(CFG.read_text())
    (tmp_path / "fleet.toml").write_text(f'[[cylinder]]\nname = "c"\nconfig = "{cfg}"\nruns = ["{run}"]\n')
    code, err = _call(["batch", tmp_path / "fleet.toml", "--out", tmp_path / "out", "--workers", "1", "--no-report",
                       "-q"], capsys)
    assert code == 1 and "internal error" not in err
    row = read_results_csv(tmp_path / "out" / "results.csv")[0]
    assert ("quoted.csv, line 3" if what == "unclosed quote" else f"latin1.toml, line {NAME_LINE}: not UTF-8") \
        in row["error"]
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["failed"] == 1


def test_a_manifest_that_is_not_utf8_is_located(tmp_path, capsys):
    m = tmp_path / "fleet.toml"
    m.write_bytes('[[cylinder]]\nname = "Zylinder für Presse 3"\nconfig = "c.toml"\nruns = ["r.csv"]\n'.encode("latin-1"))
    code, err = _call(["batch", m, "--out", tmp_path / "out", "-q"], capsys)
    _one_located_sentence(code, err, "fleet.toml, line 2: not UTF-8")


POINTS = "# a sweep\nv,F,F_std,count\n" + "".join(f"{s * v:.3f},{s * (20 + 100 * v):.3f},0.5,100\n"
                                                   for v in (0.01, 0.02, 0.05, 0.1, 0.2) for s in (1, -1))
COMMANDS = "# a command file\nt,u\n0,0.1\n0.5,-0.2\n1.0,0.0\n1.5,0.3\n"


@FUZZ
@given(data=mutated(POINTS))
def test_mutated_points_tables(workdir, capsys, data):
    path = workdir / "mut_points.csv"
    path.write_bytes(data)
    code, err = _call(["friction-map", path, "--model", "cv", "--json", workdir / "m.json", "-q"], capsys)
    if code != 0:  # a table that is still valid is fitted
        _one_located_sentence(code, err, "mut_points.csv")


@FUZZ
@given(data=mutated(COMMANDS))
def test_mutated_command_files(workdir, cyl_a, data):
    from combined_reality.live import ProgramOptions, make_program

    path = workdir / "mut_cmds.csv"
    path.write_bytes(data)
    try:
        prog = make_program(f"file:{path}", cyl_a, 2.0)
    except ValueError as e:  # one sentence naming the file
        assert "mut_cmds.csv" in str(e) and "\n" not in str(e), e
        return
    u = [prog.command(t, 0.05) for t in (0.0, 0.7, 1.2, 3.0)]
    assert all(abs(v) <= ProgramOptions().u_max for v in u)


# every numeric option of the command line: a value is refused as it is parsed, in one line,
# or it lies within the option's documented range (so that no run can fail on it later)
OPTION_RANGES = {
    ("simulate", "--seed"): (0, 2**32 - 1), ("simulate", "--rate"): (10, 1e5), ("identify", "--interval"): (0, 10),
    ("identify", "--max-iter"): (1, 10_000), ("live", "--rate"): (10, 1e5), ("live", "--duration"): (0, 86_400),
    ("replay", "--window"): (0, 600), ("import", "--resample"): (10, 1e5), ("batch", "--workers"): (1, 1024),
    ("identify", "--max-rows"): (2, math.inf),
}
VALUES = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr), st.integers(-2**70, 2**70).map(str),
                   st.text(max_size=12), st.sampled_from(["1e9", "-1", "0", "1e-300", "nan", "inf", "0x10", "1_0"]))


@settings(max_examples=200, deadline=None, derandomize=True, database=None)
@given(option=st.sampled_from(sorted(OPTION_RANGES)), value=VALUES)
def test_option_values_are_refused_as_parsed_or_within_range(option, value):
    import contextlib
    import io

    from combined_reality.cli import build_parser

    command, flag = option
    base = {"simulate": ["--config", "c.toml", "-o", "o.csv"], "identify": ["--config", "c.toml", "r.csv"],
            "live": ["--virtual", "--duration", "1", "--record", "r.csv"], "replay": ["r.csv"],
            "import": ["raw.csv", "--map", "m.toml", "-o", "o.csv"], "batch": ["m.toml", "--out", "o"]}[command]
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        try:
            args = build_parser().parse_args([command, *base, f"{flag}={value}"])
        except SystemExit as e:
            assert e.code == 2 and len(err.getvalue().strip().splitlines()) == 1 and flag in err.getvalue(), \
                err.getvalue()
            return
    lo, hi = OPTION_RANGES[option]
    v = getattr(args, flag.lstrip("-").replace("-", "_"))
    assert lo <= v <= hi and (v > 0 or lo > 0 or flag in ("--seed",)), (option, value, v)
