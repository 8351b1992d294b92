"""combined_reality/runs.py: the recorded-run CSV of docs/formats.md."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from combined_reality.files import REQUIRED_COLUMNS, Run, RunFormatError, RunRecorder, read_run, write_run

HEADER = "t,u,x,p1,p2"
ROW = "{t},0.1,0.05,300000,200000"


def rows(n: int, start: int = 0) -> str:
    return "".join(ROW.format(t=f"{0.001 * i:.3f}") + "\n" for i in range(start, start + n))


def put(tmp_path: Path, text: str | bytes, name: str = "run.csv") -> Path:
    path = tmp_path / name
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text, encoding="utf-8", newline="")
    return path


def refused(path: Path, *, line: int | None = None, column: str | None = None, says: str = "") -> str:
    """Reading ``path`` fails with one sentence naming the file, the line and the column."""
    with pytest.raises(RunFormatError) as info:
        read_run(path)
    msg = str(info.value)
    assert msg.startswith(str(path)), msg
    if line is not None:
        assert f"line {line}," in msg or f"line {line}:" in msg, msg
    if column is not None:
        assert f"column '{column}'" in msg, msg
    assert says in msg, (says, msg)
    assert "\n" not in msg and msg.endswith("."), msg
    return msg


def random_run(n: int = 500, seed: int = 0, **kw) -> Run:
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.9e-3, 1.1e-3, n))  # jittered, awkward decimals
    return Run(t=t, u=rng.uniform(-1.0, 1.0, n), x=rng.uniform(0.0, 0.2, n),
               p1=rng.uniform(1e5, 7e5, n), p2=rng.uniform(1e5, 7e5, n), **kw)


def assert_same(a: Run, b: Run) -> None:
    for name in REQUIRED_COLUMNS:
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert (a.ps is None) == (b.ps is None)
    if a.ps is not None:
        assert np.array_equal(a.ps, b.ps)
    assert list(a.extra) == list(b.extra)
    for name in a.extra:
        assert np.array_equal(a.extra[name], b.extra[name], equal_nan=a.extra[name].dtype.kind == "f"), name


# --------------------------------------------------------------------------- reading valid files


def test_reads_a_minimal_file(tmp_path: Path) -> None:
    path = put(tmp_path, HEADER + "\n" + rows(3))
    run = read_run(path)
    assert run.n == 3
    assert run.source == path
    for name in REQUIRED_COLUMNS:
        arr = getattr(run, name)
        assert arr.dtype == np.float64 and arr.shape == (3,)
    assert np.array_equal(run.t, [0.0, 0.001, 0.002])
    assert np.array_equal(run.p1, [3e5] * 3)
    assert run.ps is None and run.extra == {}


def test_properties_and_slice(tmp_path: Path) -> None:
    t = [0.0, 0.001, 0.0021, 0.003, 0.004, 0.006]  # jitter and one dropped sample
    text = HEADER + ",ps,temp\n" + "".join(f"{v},0,0,2e5,2e5,6e5,{i}\n" for i, v in enumerate(t))
    run = read_run(put(tmp_path, text))
    assert run.n == 6
    assert run.duration == pytest.approx(0.006)
    assert run.sample_period == pytest.approx(0.001)  # the median, not the mean
    part = run.slice(1, 3)
    assert part.n == 2
    assert np.array_equal(part.t, [0.001, 0.0021])
    assert np.array_equal(part.ps, [6e5, 6e5])
    assert np.array_equal(part.extra["temp"], [1.0, 2.0])
    assert part.source == run.source
    assert run.slice(-2, None).n == 2
    with pytest.raises(ValueError):
        run.slice(0, 1).sample_period


def test_comments_before_between_and_after(tmp_path: Path) -> None:
    text = "# rig A, cylinder 1\n# recorded 2024-05-01\n" + HEADER + "\n" + rows(2) \
        + "# valve reset\n" + rows(2, start=2) + "  # indented comment\n# the end\n"
    run = read_run(put(tmp_path, text))
    assert run.n == 4
    assert np.array_equal(run.t, [0.0, 0.001, 0.002, 0.003])


def test_trailing_blank_lines_crlf_and_bom(tmp_path: Path) -> None:
    text = "\ufeff" + (HEADER + "\n" + rows(3)).replace("\n", "\r\n") + "\r\n  \r\n\r\n"
    run = read_run(put(tmp_path, text))
    assert run.n == 3


def test_no_newline_at_end(tmp_path: Path) -> None:
    assert read_run(put(tmp_path, HEADER + "\n" + rows(2).rstrip("\n"))).n == 2


def test_columns_in_any_order_with_spaces_and_quotes(tmp_path: Path) -> None:
    text = '"p2", x ,t,u,p1\n2e5, 0.01 ,0,0.5,3e5\n2.1e5,0.02,0.01,-0.5,3.1e5\n'
    run = read_run(put(tmp_path, text))
    assert np.array_equal(run.x, [0.01, 0.02])
    assert np.array_equal(run.p2, [2e5, 2.1e5])
    assert np.array_equal(run.u, [0.5, -0.5])


@pytest.mark.parametrize("u", ["7", "-1.5", "50"])  # one stray cell in volts, a slip, percent
def test_command_outside_unit_range_is_refused_with_its_line(tmp_path: Path, u: str) -> None:
    text = HEADER + "\n0,1,0,2e5,2e5\n0.001,-1,0,2e5,2e5\n" + f"0.002,{u},0,2e5,2e5\n"
    refused(put(tmp_path, text), line=4, column="u", says=f"{u} is outside [-1, 1]")


@pytest.mark.parametrize("step, n", [("1.0", 30), ("0.1", 120_000)])  # 1 kHz in ms; 10 kHz in ms for 12 s
def test_time_in_milliseconds_is_refused(tmp_path: Path, step: str, n: int) -> None:
    text = HEADER + "\n" + "".join(f"{i * float(step):.1f},0,0,2e5,2e5\n" for i in range(n))
    refused(put(tmp_path, text), line=n + 1, column="t", says="looks like a time in milliseconds")


def test_slow_but_plausible_sampling_is_accepted(tmp_path: Path) -> None:
    text = HEADER + "\n" + "".join(f"{i * 0.1:.1f},0,0,2e5,2e5\n" for i in range(100))  # 10 Hz for 10 s
    assert read_run(put(tmp_path, text)).n == 100


def test_unclosed_quote_in_a_big_file_is_located(tmp_path: Path) -> None:
    # csv's reader, left to itself, swallows the rest of the file into one field ("field larger than field
    # limit", which was an internal error)
    body = "".join(f"{0.001 * i:.3f},0,0,2e5,2e5\n" for i in range(2, 30_000))
    text = HEADER + '\n0,0,0,2e5,2e5\n0.001,"0,0,2e5,2e5\n' + body
    refused(put(tmp_path, text), line=3, says="2 cells, but the header on line 1 has 5 columns")


def test_negative_small_position_and_supply_column(tmp_path: Path) -> None:
    text = HEADER + ",ps\n0,0,-0.001,2e5,2e5,7e5\n0.001,0,9.5,2e5,2e5,6.9e5\n"
    run = read_run(put(tmp_path, text))
    assert np.array_equal(run.x, [-0.001, 9.5])
    assert np.array_equal(run.ps, [7e5, 6.9e5])
    assert run.extra == {}


def test_extra_columns_are_kept_numeric_or_not(tmp_path: Path) -> None:
    text = ("t,u,x,p1,p2,T1,note,flag\n"
            "0,0,0,2e5,2e5,293.1,start,nan\n"
            '0.001,0,0,2e5,2e5,293.2,"valve, reset",1\n'
            "0.002,0,0,2e5,2e5,293.3,,2\n")
    run = read_run(put(tmp_path, text))
    assert list(run.extra) == ["T1", "note", "flag"]
    assert run.extra["T1"].dtype == np.float64
    assert np.array_equal(run.extra["T1"], [293.1, 293.2, 293.3])
    assert list(run.extra["note"]) == ["start", "valve, reset", ""]
    assert np.array_equal(run.extra["flag"], [np.nan, 1, 2], equal_nan=True)  # extras are not checked


def test_empty_named_extra_column_as_pandas_writes_it(tmp_path: Path) -> None:
    text = ",t,u,x,p1,p2\n0,0,0,0,2e5,2e5\n1,0.001,0,0,2e5,2e5\n"
    run = read_run(put(tmp_path, text))
    assert np.array_equal(run.extra[""], [0.0, 1.0])


# --------------------------------------------------------------------------- refusals


def test_missing_file(tmp_path: Path) -> None:
    refused(tmp_path / "absent.csv", says="not found")


def test_directory_instead_of_file(tmp_path: Path) -> None:
    (tmp_path / "dir.csv").mkdir()
    refused(tmp_path / "dir.csv")


@pytest.mark.parametrize("text", ["", "\n\n  \n"])
def test_empty_file(tmp_path: Path, text: str) -> None:
    refused(put(tmp_path, text), says="empty")


def test_only_comments(tmp_path: Path) -> None:
    refused(put(tmp_path, "# nothing recorded\n# really\n"), says="header")


def test_header_only(tmp_path: Path) -> None:
    refused(put(tmp_path, "# c\n" + HEADER + "\n\n"), line=2, says="data rows")


def test_single_sample(tmp_path: Path) -> None:
    refused(put(tmp_path, HEADER + "\n# c\n" + rows(1)), line=3, says="at least 2")


@pytest.mark.parametrize("header, missing", [
    ("t,u,x,p1", "p2"),
    ("time,u,x,p1,p2", "t"),
    ("t,U,x,p1,p2", "u"),  # names are exact: nothing is guessed
])
def test_missing_required_column(tmp_path: Path, header: str, missing: str) -> None:
    text = "# comment\n" + header + "\n" + "0,0,0,2e5,2e5\n0.1,0,0,2e5,2e5\n"
    msg = refused(put(tmp_path, text), line=2, says=f"'{missing}'")
    assert "missing" in msg


def test_data_without_header(tmp_path: Path) -> None:
    refused(put(tmp_path, rows(3)), line=1, says="looks like data, not a header")
    refused(put(tmp_path, "0,0,0,2e5,2e5\n1,0,0,2e5,2e5\n"), line=1, says="looks like data, not a header")


def test_duplicate_column(tmp_path: Path) -> None:
    text = "t,u,x,p1,p2,x\n0,0,0,2e5,2e5,0\n0.1,0,0,2e5,2e5,0\n"
    refused(put(tmp_path, text), line=1, says="'x' appears more than once")


@pytest.mark.parametrize("bad", ["0.002,0.1,0.05,300000", "0.002,0.1,0.05,300000,200000,7"])
def test_row_with_wrong_number_of_cells(tmp_path: Path, bad: str) -> None:
    text = "# c\n" + HEADER + "\n" + rows(2) + bad + "\n" + rows(2, start=3)
    refused(put(tmp_path, text), line=5, says="the header on line 2 has 5 columns")


def test_blank_line_inside_the_data(tmp_path: Path) -> None:
    text = HEADER + "\n" + rows(2) + "\n" + rows(2, start=2)
    refused(put(tmp_path, text), line=4, says="blank line")


@pytest.mark.parametrize("cell, says", [
    ("abc", "'abc' is not a number"),
    ("3,0e5", ""),  # a decimal comma shifts the cells: caught as a wrong cell count
    ("1_000", "is not a number"),  # Python would take it; numpy and spreadsheets would not
    ("0x10", "is not a number"),
])
def test_non_numeric_cell(tmp_path: Path, cell: str, says: str) -> None:
    text = "# c\n" + HEADER + "\n" + rows(3) + f"0.003,0.1,0.05,{cell},200000\n"
    msg = refused(put(tmp_path, text), line=6, says=says)
    if says:
        assert "column 'p1'" in msg


def test_non_numeric_cell_found_among_text_extra_columns(tmp_path: Path) -> None:
    # the slow path (text in an extra column) must refuse exactly what the fast path refuses
    text = HEADER + ",note\n" + "0,0,0,2e5,2e5,a\n0.001,0,0,2e5,2e5,b\n0.002,0,0,2e5,2e5x,c\n"
    refused(put(tmp_path, text), line=4, column="p2", says="'2e5x' is not a number")


@pytest.mark.parametrize("cell", ["nan", "NaN", "inf", "-inf", "1e999"])
@pytest.mark.parametrize("column", ["t", "u", "x", "p1", "ps"])
def test_non_finite(tmp_path: Path, cell: str, column: str) -> None:
    names = ["t", "u", "x", "p1", "p2", "ps"]
    good = {"t": "0.002", "u": "0", "x": "0", "p1": "2e5", "p2": "2e5", "ps": "7e5"}
    bad_row = ",".join(cell if n == column else good[n] for n in names)
    text = ",".join(names) + "\n0,0,0,2e5,2e5,7e5\n0.001,0,0,2e5,2e5,7e5\n" + bad_row + "\n"
    refused(put(tmp_path, text), line=4, column=column, says="not a finite number")


@pytest.mark.parametrize("t3", ["0.001", "0.0005"])
def test_time_not_strictly_increasing(tmp_path: Path, t3: str) -> None:
    text = "# c\n" + HEADER + "\n" + rows(2) + "# c\n" + ROW.format(t=t3) + "\n" + rows(2, start=5)
    msg = refused(put(tmp_path, text), line=6, column="t", says="strictly increasing")
    assert "line 4" in msg  # and the sample it fails to follow


@pytest.mark.parametrize("column, value", [
    ("p1", "7.0"),  # bar
    ("p1", "6.0"),
    ("p2", "0"),  # gauge, at rest
    ("p2", "-2000"),  # gauge, a little vacuum
    ("p1", "600"),  # kPa
    ("ps", "19999"),
])
def test_bar_or_gauge_pressure(tmp_path: Path, column: str, value: str) -> None:
    names = ["t", "u", "x", "p1", "p2", "ps"]
    good = {"t": "0.002", "u": "0", "x": "0", "p1": "2e5", "p2": "2e5", "ps": "7e5"}
    bad_row = ",".join(value if n == column else good[n] for n in names)
    text = ",".join(names) + "\n0,0,0,2e5,2e5,7e5\n0.001,0,0,2e5,2e5,7e5\n" + bad_row + "\n"
    refused(put(tmp_path, text), line=4, column=column,
            says="looks like bar or gauge pressure; absolute Pa required")


def test_lowest_plausible_absolute_pressure_is_accepted(tmp_path: Path) -> None:
    text = HEADER + "\n0,0,0,2e4,2e4\n0.001,0,0,2e4,2e4\n"
    assert read_run(put(tmp_path, text)).p1[0] == 2e4


@pytest.mark.parametrize("x", ["150", "-12.5"])
def test_position_in_mm(tmp_path: Path, x: str) -> None:
    text = HEADER + "\n" + rows(2) + f"0.002,0,{x},2e5,2e5\n"
    refused(put(tmp_path, text), line=4, column="x", says="metres required")


def test_not_utf8(tmp_path: Path) -> None:
    data = (HEADER + "\n" + rows(2)).encode() + b"0.002,0,0,\xff\xfe,2e5\n"
    refused(put(tmp_path, data), line=4, says="UTF-8")


def test_bad_file_is_a_value_error_to_callers(tmp_path: Path) -> None:
    with pytest.raises(ValueError):  # callers that only know ValueError still catch it
        read_run(put(tmp_path, HEADER + "\n" + "0.001,0,0,nan,2e5\n"))


# --------------------------------------------------------------------------- writing


def test_round_trip_is_exact(tmp_path: Path) -> None:
    run = random_run()
    path = tmp_path / "out.csv"
    write_run(path, run)
    back = read_run(path)
    assert_same(run, back)
    assert back.source == path


def test_round_trip_awkward_values(tmp_path: Path) -> None:
    t = np.array([0.0, 1e-9, 0.1, 1 / 3, 2 / 3, 1.0, 9e3 + 1e-7])
    n = len(t)
    run = Run(t=t, u=np.array([-0.0, 5e-324, 1e-300, -1 / 7, 1.0, -1.0, np.nextafter(1.0, 0)]),
              x=np.array([0.0, -1e-12, np.nextafter(0.1, 1), 9.999999999999998, 0.2, 1e-17, 3.0]),
              p1=np.full(n, 101325.00000000001), p2=np.linspace(2e4, 1e7, n), ps=np.full(n, 7e5 + 1 / 3))
    write_run(tmp_path / "r.csv", run)
    back = read_run(tmp_path / "r.csv")
    assert_same(run, back)
    assert np.signbit(back.u[0])


def test_empty_cells_are_channels_not_measured_and_round_trip(tmp_path: Path) -> None:
    """FORMATS.md: an empty cell in x, p1, p2 or ps means not measured at that sample (NaN in
    the Run); written back as an empty cell, so the round trip is exact."""
    text = ("t,u,x,p1,p2,ps,note\n0,0.1,0.05,3e5,2e5,7e5,a\n0.001,0.1,,3e5,2e5,,b\n"
            "0.002,0.1,0.05, ,2e5,7e5,c\n0.003,0.2,0.06,3e5,,7e5,d\n")
    run = read_run(put(tmp_path, text))
    assert np.array_equal(run.x, [0.05, np.nan, 0.05, 0.06], equal_nan=True)
    assert np.array_equal(run.p1, [3e5, 3e5, np.nan, 3e5], equal_nan=True)
    assert np.array_equal(run.p2, [2e5, 2e5, 2e5, np.nan], equal_nan=True)
    assert np.array_equal(run.ps, [7e5, np.nan, 7e5, 7e5], equal_nan=True)
    write_run(tmp_path / "back.csv", run)
    assert (tmp_path / "back.csv").read_text().splitlines()[2] == "0.001,0.1,,300000.0,200000.0,,b"
    back = read_run(tmp_path / "back.csv")
    for name in ("t", "u", "x", "p1", "p2", "ps"):
        assert np.array_equal(getattr(back, name), getattr(run, name), equal_nan=True), name


@pytest.mark.parametrize("column, says", [
    ("t", "empty cell: every sample needs its time"),
    ("u", "empty cell: a sample whose command is unknown cannot be simulated, so leave the line out"),
])
def test_an_empty_time_or_command_is_refused(tmp_path: Path, column: str, says: str) -> None:
    good = {"t": "0.002", "u": "0", "x": "0", "p1": "2e5", "p2": "2e5"}
    bad_row = ",".join("" if n == column else good[n] for n in good)
    text = HEADER + "\n0,0,0,2e5,2e5\n0.001,0,0,2e5,2e5\n" + bad_row + "\n"
    refused(put(tmp_path, text), line=4, column=column, says=says)


def test_split_at_gaps_cuts_at_lost_samples_and_at_channels_not_measured() -> None:
    from combined_reality.files import split_at_gaps

    t = np.r_[np.arange(10), np.arange(12, 20)] * 1e-3  # samples 10 and 11 lost
    p1 = np.full(len(t), 3e5)
    p1[[3, 4, 15]] = np.nan
    run = Run(t=t, u=np.zeros(len(t)), x=np.zeros(len(t)), p1=p1, p2=np.full(len(t), 2e5))
    assert [(p.t[0], p.n) for p in split_at_gaps(run)] == [(0.0, 10), (0.012, 8)]
    pieces = split_at_gaps(run, channels=("p1",))
    assert [(round(p.t[0] * 1e3), p.n) for p in pieces] == [(0, 3), (5, 5), (12, 5), (18, 2)]
    assert all(np.all(np.isfinite(p.p1)) for p in pieces)


def test_round_trip_keeps_extra_columns_and_comments(tmp_path: Path) -> None:
    text = ("# from the rig\n"
            "t,u,x,p1,p2,ps,T1,note\n"
            '0,0,0,2e5,2e5,7e5,293.15,"a ""quoted"", text"\n'
            "0.001,0,0,2e5,2e5,7e5,293.25,plain\n")
    first = read_run(put(tmp_path, text))
    out = tmp_path / "rewritten.csv"
    write_run(out, first, comments=["rewritten by the tool", "second line\nthird line"])
    written = out.read_text().splitlines()
    assert written[:4] == ["# rewritten by the tool", "# second line", "# third line", "t,u,x,p1,p2,ps,T1,note"]
    again = read_run(out)
    assert_same(first, again)
    assert list(again.extra["note"]) == ['a "quoted", text', "plain"]


def test_write_replaces_atomically_and_leaves_no_temp_files(tmp_path: Path) -> None:
    path = tmp_path / "r.csv"
    path.write_text("old content\n")
    write_run(path, random_run(10))
    assert read_run(path).n == 10
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.csv"]


def test_failed_write_leaves_the_old_file(tmp_path: Path) -> None:
    path = tmp_path / "r.csv"
    path.write_text("old content\n")
    run = random_run(2, extra={"note": np.array(["fine", "two\nlines"])})
    with pytest.raises(ValueError, match="note"):
        write_run(path, run)
    assert path.read_text() == "old content\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.csv"]


def test_run_checks_its_shape() -> None:
    with pytest.raises(ValueError, match="'p2'"):
        Run(t=[0, 1], u=[0, 0], x=[0, 0], p1=[2e5, 2e5], p2=[2e5])
    with pytest.raises(ValueError, match="'ps'"):
        Run(t=[0, 1], u=[0, 0], x=[0, 0], p1=[2e5, 2e5], p2=[2e5, 2e5], ps=[7e5])
    with pytest.raises(ValueError, match="'extra1'"):
        Run(t=[0, 1], u=[0, 0], x=[0, 0], p1=[2e5, 2e5], p2=[2e5, 2e5], extra={"extra1": [1, 2, 3]})
    with pytest.raises(ValueError, match="'x'"):
        Run(t=[0, 1], u=[0, 0], x=[[0, 0]], p1=[2e5, 2e5], p2=[2e5, 2e5])
    run = Run(t=[0, 1], u=[0, 0], x=[0, 0], p1=[2e5, 2e5], p2=[2e5, 2e5])
    assert run.t.dtype == np.float64
    with pytest.raises(AttributeError):
        run.t = np.zeros(2)  # type: ignore[misc]


# --------------------------------------------------------------------------- recorder


def test_recorder_writes_a_readable_file(tmp_path: Path) -> None:
    path = tmp_path / "live.csv"
    with RunRecorder(path, with_ps=True, comments=["live"]) as rec:
        for i in range(5):
            rec.append(i * 0.001 + 1 / 3, np.float64(0.1 * i), 0.01, 2e5 + i, 3e5, ps=7e5)
        assert rec.n == 5
    assert rec.closed
    run = read_run(path)
    assert run.n == 5
    assert np.array_equal(run.t, [i * 0.001 + 1 / 3 for i in range(5)])
    assert np.array_equal(run.ps, [7e5] * 5)
    assert path.read_text().startswith("# live\nt,u,x,p1,p2,ps\n")
    with pytest.raises(ValueError, match="closed"):
        rec.append(1.0, 0, 0, 2e5, 2e5, ps=7e5)


def test_recorder_ps_must_match_its_header(tmp_path: Path) -> None:
    with RunRecorder(tmp_path / "a.csv") as rec:
        with pytest.raises(ValueError, match="with_ps"):
            rec.append(0.0, 0, 0, 2e5, 2e5, ps=7e5)


def test_recorder_writes_missing_and_non_finite_channels_as_empty_cells(tmp_path: Path) -> None:
    """A supply sensor that stops reporting, a NaN or infinite reading: an empty cell (not
    measured at that sample), so the file stays readable and nothing else is lost."""
    path = tmp_path / "holes.csv"
    with RunRecorder(path, with_ps=True) as rec:
        rec.append(0.0, 0.1, 0.01, 2e5, 3e5, ps=7e5)
        rec.append(0.001, 0.2, float("nan"), 2e5, 3e5, ps=None)
        rec.append(0.002, 0.3, 0.01, float("inf"), None, ps=float("nan"))
        rec.append(0.003, 0.4, 0.02, 2e5, 3e5, ps=7e5)
        with pytest.raises(ValueError, match="time and the command"):
            rec.append(0.004, float("nan"), 0.02, 2e5, 3e5)
    assert path.read_text().splitlines()[1:4] == ["0.0,0.1,0.01,200000.0,300000.0,700000.0",
                                                 "0.001,0.2,,200000.0,300000.0,",
                                                 "0.002,0.3,0.01,,,"]
    run = read_run(path)
    assert run.n == 4 and np.array_equal(run.u, [0.1, 0.2, 0.3, 0.4])
    assert np.array_equal(run.x, [0.01, np.nan, 0.01, 0.02], equal_nan=True)
    assert np.array_equal(run.p1, [2e5, 2e5, np.nan, 2e5], equal_nan=True)
    assert np.array_equal(run.p2, [3e5, 3e5, np.nan, 3e5], equal_nan=True)
    assert np.array_equal(run.ps, [7e5, np.nan, np.nan, 7e5], equal_nan=True)


def test_recorder_lines_reach_the_file_at_once(tmp_path: Path) -> None:
    path = tmp_path / "live.csv"
    rec = RunRecorder(path)
    try:
        rec.append(0.0, 0, 0, 2e5, 2e5)
        rec.append(0.001, 0, 0, 2e5, 2e5)
        assert read_run(path).n == 2  # readable while still open
    finally:
        rec.close()


def _child(path: Path, body: str) -> subprocess.Popen[str]:
    script = textwrap.dedent("""
        import os, sys, time
        from combined_reality.files import RunRecorder
        rec = RunRecorder(sys.argv[1])
    """) + textwrap.dedent(body)
    return subprocess.Popen([sys.executable, "-c", script, str(path)], stdout=subprocess.PIPE, text=True)


def test_recorder_survives_abrupt_exit(tmp_path: Path) -> None:
    path = tmp_path / "crash.csv"
    child = _child(path, """
        for i in range(100):
            rec.append(i * 1e-3, 0.5, 0.01, 2e5, 3e5)
        os._exit(1)  # no close(), no flush at exit, no finalizers
    """)
    assert child.wait(timeout=60) == 1
    run = read_run(path)
    assert run.n == 100
    assert run.t[-1] == pytest.approx(0.099)


@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs SIGKILL")
def test_recorder_killed_mid_stream_leaves_whole_lines(tmp_path: Path) -> None:
    path = tmp_path / "killed.csv"
    child = _child(path, """
        for i in range(2_000_000):
            rec.append(i * 1e-3, 0.5, 0.01, 2e5 + i, 3e5)
            if i == 1000:
                print("ready", flush=True)
        time.sleep(60)
    """)
    try:
        assert child.stdout is not None and child.stdout.readline() == "ready\n"
        os.kill(child.pid, signal.SIGKILL)  # while it is still appending
        assert child.wait(timeout=60) == -signal.SIGKILL
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
        if child.stdout is not None:
            child.stdout.close()
    assert path.read_bytes().endswith(b"\n")
    run = read_run(path)
    assert run.n > 1000
    assert np.array_equal(run.p1, 2e5 + np.arange(run.n))
