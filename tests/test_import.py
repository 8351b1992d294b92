"""`combined-reality import`: lab recordings in their own units and formats into runs (issue 17)."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import CONFIGS, assert_refused

from combined_reality.cli import main
from combined_reality.files import Run, read_run

PA = 101300.0
# the mapping of the issue, exactly as written there
EXAMPLE_MAP = """\
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
"""
HEADER = "Zeit [ms];Ventil [V];Weg [mm];P_A [bar];P_B [bar]"


def lab_line(t, u, x, p1, p2) -> str:
    """One sample as a German DAQ program writes it: ms, volts around 5 V, mm, bar gauge, decimal comma."""
    cells = [f"{t * 1e3:.3f}", f"{u * 5 + 5:.7f}", f"{x * 1e3:.6f}", f"{(p1 - PA) / 1e5:.7f}", f"{(p2 - PA) / 1e5:.7f}"]
    return ";".join(c.replace(".", ",") for c in cells)


def write_lab_csv(path: Path, run: Run, preamble: str = "Messung 3\nPrüfstand B\n", encoding="cp1252") -> Path:
    lines = [lab_line(*s) for s in zip(run.t, run.u, run.x, run.p1, run.p2)]
    path.write_text(preamble + HEADER + "\n" + "\n".join(lines) + "\n", encoding=encoding)
    return path


def call(argv, capsys):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def do_import(tmp_path, capsys, raw: Path, mapping: str, *extra) -> tuple[int, str, Path]:
    m = tmp_path / "map.toml"
    m.write_text(mapping, encoding="utf-8")
    out = tmp_path / "imported.csv"
    code, _, err = call(["import", raw, "--map", m, "-o", out, *extra], capsys)
    return code, err, out


@pytest.fixture(scope="module")
def short_run(cyl_a):
    from combined_reality.simulation import simulate_run

    return simulate_run(cyl_a, 0.6, seed=5)


def assert_close(run: Run, ref: Run, *, u=2e-7, x=2e-9, p=0.02, t=1e-9) -> None:
    assert run.n == ref.n
    for name, tol in (("t", t), ("u", u), ("x", x), ("p1", p), ("p2", p)):
        err = np.max(np.abs(getattr(run, name) - getattr(ref, name)))
        assert err <= tol, (name, err)


# ------------------------------------------------------------------ the issue's example


def test_the_example_imports_and_identifies_as_accurately_as_the_si_original(tmp_path, capsys, cyl_a, run_a):
    from combined_reality.identify import IdentifyOptions, identify

    raw = write_lab_csv(tmp_path / "messung.csv", run_a)
    code, err, out = do_import(tmp_path, capsys, raw, EXAMPLE_MAP)
    assert code == 0, err
    imported = read_run(out)
    assert_close(imported, run_a)
    header = "\n".join(imported.comments)
    for says in ("messung.csv", "delimiter ';'", "decimal ','", "'Zeit [ms]' [ms] -> s",
                 "u = (value - 5) / 5", "gauge + atmosphere 101300 Pa", "1000 Hz"):
        assert says in header, says
    opts = IdentifyOptions(threads=1)
    si, lab = identify(cyl_a, [run_a], opts), identify(cyl_a, [imported], opts)
    assert si.solver["status"] == lab.solver["status"] == "converged"
    for name in ("Fc", "Fv", "kp"):
        a, b = si.params[name], lab.params[name]
        truth = cyl_a.value(name)
        # the same estimate to a tenth of its standard deviation, as close to the truth as the original
        assert abs(a.value - b.value) < 0.1 * a.std, (name, a.value, b.value, a.std)
        assert abs(b.value - truth) < abs(a.value - truth) + 0.1 * a.std


def test_imported_values_carry_the_recording_s_decimals_not_a_conversion_s_last_bit(tmp_path, capsys, short_run):
    """9 ms is written 0.009 (not 0.009000000000000001), 0.8 bar gauge 181300.0, 6.1 V around 5 V 0.22."""
    raw = write_lab_csv(tmp_path / "messung.csv", short_run)
    code, err, out = do_import(tmp_path, capsys, raw, EXAMPLE_MAP)
    assert code == 0, err
    rows = [ln.split(",") for ln in out.read_text().splitlines() if ln[:1].isdigit()]
    assert rows[8][0] == "0.009" and all(len(r[0]) <= 6 for r in rows)  # t: ms as the recording had them
    for r in rows:  # u, x, p1, p2 with the recording's digits: 7 decimals of V / 5, 6 of mm, 7 of bar
        assert len(r[1].lstrip("-")) <= 12 and len(r[2].lstrip("-")) <= 11, r
        assert all(len(c) <= 12 for c in r[3:5]), r


def test_the_example_mapping_needs_no_delimiter_or_decimal_when_they_can_be_found(tmp_path, capsys, short_run):
    raw = write_lab_csv(tmp_path / "messung.csv", short_run, preamble="", encoding="utf-8")
    mapping = EXAMPLE_MAP.replace('delimiter = ";"\n', "").replace('decimal = ","\n', "")
    code, err, out = do_import(tmp_path, capsys, raw, mapping)
    assert code == 0, err
    assert_close(read_run(out), short_run)


# ------------------------------------------------------------------ the other formats


def si_mapping(names=("t", "u", "x", "p1", "p2"), extra_source="", **units) -> str:
    units = {"t": "s", "u": "1", "x": "m", "p1": "Pa", "p2": "Pa", **units}
    rows = "\n".join(f'{n} = {{ from = "{src}", unit = "{units[n]}" }}'
                     for n, src in zip(("t", "u", "x", "p1", "p2"), names))
    return f"[source]\n{extra_source}[columns]\n{rows}\n"


def test_parquet(tmp_path, capsys, short_run):
    import pyarrow as pa
    import pyarrow.parquet as pq

    raw = tmp_path / "run.parquet"
    pq.write_table(pa.table({"time_ms": short_run.t * 1e3, "cmd_pct": short_run.u * 100, "pos": short_run.x,
                             "pa_kpa": short_run.p1 / 1e3, "pb_kpa": short_run.p2 / 1e3}), raw)
    mapping = si_mapping(("time_ms", "cmd_pct", "pos", "pa_kpa", "pb_kpa"), t="ms", u="percent", p1="kPa", p2="kPa")
    code, err, out = do_import(tmp_path, capsys, raw, mapping)
    assert code == 0, err
    assert_close(read_run(out), short_run, u=1e-12, x=1e-15, p=1e-9)


def test_matlab_v5_variables_struct_fields_and_matrix_columns(tmp_path, capsys, short_run):
    import scipy.io

    raw = tmp_path / "run.mat"
    scipy.io.savemat(raw, {"zeit": short_run.t, "messung": {"weg_mm": short_run.x * 1e3},
                           "data": np.column_stack([short_run.u, short_run.p1 / 1e5, short_run.p2 / 1e5])})
    mapping = si_mapping(("zeit", "data(:,1)", "messung.weg_mm", "data(:,2)", "data(:,3)"), x="mm", p1="bar",
                         p2="bar")
    code, err, out = do_import(tmp_path, capsys, raw, mapping)
    assert code == 0, err
    assert_close(read_run(out), short_run, u=1e-12, x=1e-15, p=1e-9)


def test_matlab_v73_through_h5py(tmp_path, capsys, short_run):
    h5py = pytest.importorskip("h5py")
    raw = tmp_path / "run73.mat"
    with h5py.File(raw, "w", userblock_size=512) as f:
        f["T"] = short_run.t[None, :]  # MATLAB's column vector, stored transposed
        f["U"], f["X"], f["P1"], f["P2"] = (v[None, :] for v in (short_run.u, short_run.x, short_run.p1, short_run.p2))
    with open(raw, "r+b") as f:  # the header MATLAB writes into the user block
        f.write(b"MATLAB 7.3 MAT-file".ljust(116) + b"\0" * 8 + b"\x00\x02IM")
    code, err, out = do_import(tmp_path, capsys, raw, si_mapping(("T", "U", "X", "P1", "P2")))
    assert code == 0, err
    assert_close(read_run(out), short_run, u=0, x=0, p=0, t=0)


def test_tdms_with_a_waveform_time_track_and_a_channel_at_another_rate(tmp_path, capsys, short_run):
    nptdms = pytest.importorskip("nptdms")
    raw = tmp_path / "run.tdms"
    props = {"wf_increment": 0.001, "wf_start_offset": float(short_run.t[0])}
    slow = {"wf_increment": 0.002, "wf_start_offset": float(short_run.t[0])}
    with nptdms.TdmsWriter(raw) as w:
        w.write_segment([nptdms.ChannelObject("Rig", "U", short_run.u, properties=props),
                         nptdms.ChannelObject("Rig", "X", short_run.x * 1e3, properties=props),
                         nptdms.ChannelObject("Rig", "P1", short_run.p1 / 1e5, properties=props),
                         nptdms.ChannelObject("Slow", "P2", short_run.p2[::2] / 1e5, properties=slow)])
    mapping = ("[columns]\nt = { time_of = \"Rig/U\" }\nu = { from = \"Rig/U\" }\n"
               "x = { from = \"Rig/X\", unit = \"mm\" }\np1 = { from = \"Rig/P1\", unit = \"bar\" }\n"
               "p2 = { from = \"Slow/P2\", unit = \"bar\" }\n")
    code, err, out = do_import(tmp_path, capsys, raw, mapping)
    assert code == 0, err
    run = read_run(out)
    n = run.n  # the last row lies beyond the slow channel's last sample: left out
    assert n == short_run.n - 1 and "rows left out" in err
    assert np.allclose(run.t, short_run.t[:n], atol=1e-12)
    assert np.allclose(run.p2[::2], short_run.p2[:n:2], rtol=0, atol=1e-6)  # on the slow instants: as recorded
    between = 0.5 * (short_run.p2[0:n - 2:2] + short_run.p2[2:n:2])
    assert np.allclose(run.p2[1::2][:len(between)], between)  # in between: interpolated linearly


def test_mdf4(tmp_path, capsys, short_run):
    asammdf = pytest.importorskip("asammdf")
    raw = tmp_path / "run.mf4"
    mdf = asammdf.MDF(version="4.10")
    mdf.append([asammdf.Signal(v, short_run.t, name=n) for n, v in
                (("Ventil", short_run.u), ("Weg", short_run.x), ("PA", short_run.p1), ("PB", short_run.p2))])
    mdf.save(raw, overwrite=True)
    mdf.close()
    mapping = ("[columns]\nt = { time_of = \"Ventil\" }\nu = { from = \"Ventil\" }\nx = { from = \"Weg\", unit = "
               "\"m\" }\np1 = { from = \"PA\", unit = \"Pa\" }\np2 = { from = \"PB\", unit = \"Pa\" }\n")
    code, err, out = do_import(tmp_path, capsys, raw, mapping)
    assert code == 0, err
    assert_close(read_run(out), short_run, u=0, x=0, p=0, t=0)


@pytest.mark.parametrize("suffix", [".asc", ".blf"])
def test_can_log_decoded_with_the_rigs_dbc(tmp_path, capsys, short_run, suffix):
    import can
    import cantools

    from hw.can_mapping import dbc_path

    db = cantools.database.load_file(dbc_path())
    raw = tmp_path / f"rig{suffix}"
    with can.Logger(str(raw)) as log:
        for k, (t, u, x, p1, p2) in enumerate(zip(short_run.t, short_run.u, short_run.x, short_run.p1, short_run.p2)):
            parts = (("RigSampleTime", {"Seq": k % 256, "Status": 1, "UApplied": u, "TimeUs": round(t * 1e6)}),
                     ("RigSamplePosition", {"Seq": k % 256, "X": x, "Ps": 0}),
                     ("RigSamplePressure", {"Seq": k % 256, "P1": p1, "P2": p2, "CmdSeq": k}))
            for j, (name, values) in enumerate(parts):  # the three frames of a sample, 100 us apart
                m = db.get_message_by_name(name)
                log.on_message_received(can.Message(timestamp=1000.0 + t + 1e-4 * j, arbitration_id=m.frame_id,
                                                    data=m.encode(values), is_extended_id=False))
    mapping = (f"[source]\ndbc = \"{dbc_path()}\"\n[columns]\n"
               "t = { from = \"RigSampleTime.TimeUs\", unit = \"us\" }\nu = { from = \"UApplied\" }\n"
               "x = { from = \"RigSamplePosition.X\", unit = \"m\" }\np1 = { from = \"P1\", unit = \"Pa\" }\n"
               "p2 = { from = \"P2\", unit = \"Pa\" }\n")
    code, err, out = do_import(tmp_path, capsys, raw, mapping)
    assert code == 0, err
    # the DBC's resolution: 1e-4 command, 10 nm, 20 Pa
    assert_close(read_run(out), short_run, t=6e-7, u=5.1e-5, x=5.1e-9, p=10.01)


@pytest.mark.parametrize("dbc, x_from, says", [
    (True, "Seq", "signal 'Seq' is in several messages (RigSampleTime, RigSamplePosition, RigSamplePressure, RigStatus); "
                  "write it as Message.Signal."),
    (True, "RigSamplePosition.Y", "message RigSamplePosition of rig_can.dbc has no signal 'Y' (it has Seq, X, Ps)."),
    (True, "Nowhere", "'Nowhere' is no message or signal of rig_can.dbc."),
    (False, "RigSamplePosition.X", "a CAN log needs [source] dbc = \"...\" (the database that decodes its frames)."),
])
def test_can_log_mapping_errors_name_the_dbc_and_the_fix(tmp_path, capsys, short_run, dbc, x_from, says):
    import can

    from hw.can_mapping import dbc_path

    raw = tmp_path / "rig.asc"
    with can.Logger(str(raw)) as log:
        log.on_message_received(can.Message(timestamp=1.0, arbitration_id=0x100, data=bytes(8)))
    mapping = ((f"[source]\ndbc = \"{dbc_path()}\"\n" if dbc else "") + "[columns]\n"
               "t = { from = \"RigSampleTime.TimeUs\", unit = \"us\" }\nu = { from = \"UApplied\" }\n"
               f"x = {{ from = \"{x_from}\", unit = \"m\" }}\np1 = {{ from = \"P1\", unit = \"Pa\" }}\n"
               "p2 = { from = \"P2\", unit = \"Pa\" }\n")
    code, err, _ = do_import(tmp_path, capsys, raw, mapping)
    assert code == 2 and says in err and "Traceback" not in err, err


# ------------------------------------------------------------------ sampling


def test_irregular_sampling_is_reported_and_resampled_without_bridging_gaps(tmp_path, capsys, short_run):
    rng = np.random.default_rng(1)
    keep = np.ones(short_run.n, bool)
    keep[200:230] = False  # 30 ms lost
    t = short_run.t + rng.uniform(-2e-4, 2e-4, short_run.n)
    idx = np.flatnonzero(keep)
    jittered = Run(t=t[idx], u=short_run.u[idx], x=short_run.x[idx], p1=short_run.p1[idx], p2=short_run.p2[idx])
    raw = write_lab_csv(tmp_path / "jitter.csv", jittered)
    json_out = tmp_path / "report.json"
    code, err, out = do_import(tmp_path, capsys, raw, EXAMPLE_MAP, "--resample", "1000", "--json", json_out)
    assert code == 0, err
    assert "irregular sampling" in err and "1 gap" in err and "zero-order hold" in err
    report = json.loads(json_out.read_text())
    assert report["sampling"]["gaps"] == 1 and report["sampling"]["irregular"]
    run = read_run(out)
    steps = np.diff(run.t)
    assert np.allclose(steps[steps < 0.0015], 1e-3)  # a regular grid ...
    assert np.sum(steps > 0.0015) == 1  # ... that keeps the gap
    # the command is held: every resampled value is one the valve had
    assert np.max(np.min(np.abs(run.u[:, None] - jittered.u[None, :]), axis=1)) < 1e-7


# ------------------------------------------------------------------ refusals


@pytest.mark.parametrize("edit, fragments", [
    (lambda m: m.replace('"Weg [mm]"', '"Weg [cm]"'), ["messung.csv, line 1", "header lacks 'Weg [cm]'"]),
    (lambda m: m.replace('unit = "mm"', 'unit = "bar"'), ["map.toml", "columns.x", "not a length"]),
    (lambda m: m.replace('unit = "ms"', 'unit = "parsec/fortnight"'), ["map.toml", "columns.t"]),
    (lambda m: m.replace('unit = "ms"', 'unit = "kg(("'), ["map.toml", "columns.t", "not a unit"]),
    (lambda m: m.replace("[atmosphere]\npressure = 101300.0\n", ""), ["map.toml", "[atmosphere] pressure"]),
    (lambda m: m.replace(", zero = 5.0, span = 5.0", ""), ["map.toml", "columns.u", "zero and span"]),
    (lambda m: m.replace("span = 5.0", "span = 0.5"), ["messung.csv, line ", "'Ventil [V]'", "outside [-1, 1]",
                                                       "zero and span of columns.u"]),
    (lambda m: m.replace('unit = "ms"', 'unit = "s"'), ["'Zeit [ms]'", "milliseconds", "columns.t"]),
    (lambda m: m.replace('decimal = ","', 'decimal = "."'), ["messung.csv, line 2", "not a number",
                                                             "decimal"]),
    (lambda m: m + "colour = 3\n", ["map.toml", "atmosphere.colour"]),
    (lambda m: m.replace("[columns]", "[columns]\nq = 3"), ["map.toml", "columns.q"]),
    (lambda m: "x = [", ["map.toml", "not valid TOML"]),
])
def test_bad_mappings_and_recordings_are_refused_with_a_located_sentence(tmp_path, capsys, short_run, edit,
                                                                         fragments):
    raw = write_lab_csv(tmp_path / "messung.csv", short_run, preamble="")
    code, err, out = do_import(tmp_path, capsys, raw, edit(EXAMPLE_MAP))
    assert_refused(code, err, *fragments)
    assert err.strip().endswith(".") and not err.strip().endswith("..")  # the importer's own sentence, one stop
    assert not out.exists()


def test_a_recording_of_too_many_lines_is_refused_by_its_line_count_whatever_ends_its_lines(tmp_path, capsys,
                                                                                           short_run):
    """--max-rows bounds a delimited recording's lines (besides the header's search) as it is
    read, before its text is split: lines that end in a bare \r (old Mac files) count too."""
    raw = write_lab_csv(tmp_path / "messung.csv", short_run, preamble="")
    lines = raw.read_text(encoding="cp1252").splitlines()
    raw.write_text("\r".join(lines) + "\r", encoding="cp1252")
    limit = 50  # the header may be sought in the first 500 lines: 601 lines are more than 550
    code, err, out = do_import(tmp_path, capsys, raw, EXAMPLE_MAP, "--max-rows", limit)
    assert_refused(code, err, f"messung.csv: {len(lines)} lines, more than the {limit} rows a run may have")
    assert not out.exists()


def test_missing_optional_reader_names_the_extra(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "nptdms", None)  # as if not installed
    raw = tmp_path / "r.tdms"
    raw.write_bytes(b"TDSm")
    code, err, _ = do_import(tmp_path, capsys, raw, si_mapping())
    assert_refused(code, err, "pip install 'combined-reality[tdms]'")


def test_identify_refuses_the_raw_lab_file_and_points_to_import(tmp_path, capsys, short_run):
    raw = write_lab_csv(tmp_path / "messung.csv", short_run, preamble="", encoding="utf-8")
    code, _, err = call(["identify", "--config", CONFIGS / "cyl_a_32x100.toml", raw], capsys)
    assert_refused(code, err, "messung.csv, line 1", "missing required columns", "'combined-reality import'")


def _long_lab_csv(path: Path, rows: int, line_end: str = "\n", bad_row: int | None = None) -> Path:
    """A lab CSV of `rows` samples (EXAMPLE_MAP's layout), over a MiB: read in several blocks."""
    i = np.arange(rows)
    lines = [f"{k},000;{5 + 0.5 * np.sin(k / 50):.7f};{50 + 40 * np.sin(k / 70):.6f};{2 + np.sin(k / 50):.7f};"
             f"{2 - np.sin(k / 50):.7f}".replace(".", ",") for k in i]
    if bad_row is not None:
        lines[bad_row] = lines[bad_row].replace(";", ";x", 1)
    path.write_bytes((HEADER + line_end + line_end.join(lines) + line_end).encode("cp1252"))
    return path


@pytest.mark.parametrize("line_end", ["\n", "\r\n", "\r"])
def test_a_long_recording_is_read_once_as_a_stream_whatever_ends_its_lines(tmp_path, capsys, monkeypatch,
                                                                             line_end):
    """Every sample of a recording read block by block (line ends split across blocks
    included), each byte read once, the run header's sha256 that of those bytes."""
    import builtins
    import hashlib

    raw = _long_lab_csv(tmp_path / "messung.csv", 30_000, line_end)
    assert raw.stat().st_size > 1 << 20  # more than one block
    got, real_open = [], builtins.open

    class Counted:
        def __init__(self, f):
            self.f = f

        def read(self, *a):
            data = self.f.read(*a)
            got.append(len(data))
            return data

        def __getattr__(self, name):
            return getattr(self.f, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return self.f.__exit__(*exc)

    def counting_open(file, mode="r", *a, **k):
        f = real_open(file, mode, *a, **k)
        return Counted(f) if str(file) == str(raw) and "b" in mode else f

    monkeypatch.setattr(builtins, "open", counting_open)
    code, err, out = do_import(tmp_path, capsys, raw, EXAMPLE_MAP)
    monkeypatch.undo()
    assert code == 0, err
    assert sum(got) == raw.stat().st_size  # once: no second read for the digest or the line count
    run = read_run(out)
    assert run.n == 30_000
    np.testing.assert_allclose(run.t, np.arange(30_000) * 1e-3)
    digest = hashlib.sha256(raw.read_bytes()).hexdigest()[:16]
    assert f"(sha256 {digest})" in out.read_text().splitlines()[0]


def test_a_bad_cell_deep_in_a_long_recording_names_its_physical_line(tmp_path, capsys):
    raw = _long_lab_csv(tmp_path / "messung.csv", 30_000, "\r\n", bad_row=25_000)
    code, err, out = do_import(tmp_path, capsys, raw, EXAMPLE_MAP)
    assert_refused(code, err, "messung.csv, line 25002, column 'Ventil [V]'", "is not a number")
    assert not out.exists()


def test_a_line_longer_than_a_line_of_delimited_text_is_refused(tmp_path, capsys):
    from combined_reality.importing.delimited import MAX_LINE

    raw = tmp_path / "messung.csv"
    raw.write_text(HEADER + "\n1,0;5,0;50,0;2,0;2,0\n" + "9" * (MAX_LINE + 10) + "\n", encoding="cp1252")
    code, err, out = do_import(tmp_path, capsys, raw, EXAMPLE_MAP)
    assert_refused(code, err, "messung.csv, line 3: longer than", "not a line of delimited text")
    assert not out.exists()
