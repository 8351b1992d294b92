"""A lab recording into a run: read the mapped channels with the reader of the recording's
format, convert each to SI, refuse what cannot be a run (naming the recording's line, row or
sample), report the sampling and, on request, resample."""
from __future__ import annotations

import hashlib
import importlib
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from sim.inputs import checked_size, shorten

from ..files import Run, first_implausible, time_unit_problem
from ..options import MAX_ROWS
from .mapping import PRESSURES, ImportMapping, MappingError, format_of
from .raw import RawTable
from .sampling import SamplingReport, resample, sampling_report
from .units import SI_UNITS, convert_channel

__all__ = ["ImportResult", "import_recording", "READERS", "reader"]


# format -> (module of this package, its reader). A module, and with it its format's library
# (the heavy ones are optional extras), is imported when a recording of that format is read
READERS: dict[str, tuple[str, str]] = {
    "csv": ("delimited", "read_delimited"), "parquet": ("parquet", "read_parquet"), "mat": ("matlab", "read_mat"),
    "tdms": ("tdms", "read_tdms"), "mdf": ("mdf", "read_mdf"), "can": ("canlog", "read_can_log")}


def reader(fmt: str) -> Callable[[Path, ImportMapping], RawTable]:
    """The reader of format `fmt` (a key of READERS), its module imported now."""
    module, function = READERS[fmt]
    return getattr(importlib.import_module(f".{module}", __package__), function)


@dataclass(frozen=True)
class ImportResult:
    run: Run
    sampling: SamplingReport  # of the recording as read (before any resampling)
    comments: tuple[str, ...]  # the header the run is written with: where it came from, how converted
    notes: tuple[str, ...]  # what the user should hear (irregular sampling, rows left out)
    warnings: tuple[str, ...] = ()  # what looks wrong though the run is readable (a unit, a column mapped twice)


# absolute pressures a pneumatic rig's chambers and supply plausibly show, Pa
PLAUSIBLE_PRESSURE = (0.5e5, 20e5)
_BELOW_ATMOSPHERE = 0.85  # of the atmosphere: a chamber reading lower for long is a gauge sensor
_RECORDING_MAX_BYTES_PER_ROW = 1024  # a recording larger than max_rows rows of this is refused unread


def import_recording(raw_path: str | Path, mapping: ImportMapping, resample_rate: float | None = None,
                     max_rows: int = MAX_ROWS) -> ImportResult:
    """The recording as a run (refused with a MappingError naming the place when it cannot be
    one); it may have at most `max_rows` rows (data lines of text: refused as soon as a text
    recording has more, read as a stream)."""
    path = Path(raw_path)
    fmt = format_of(path, mapping.source)
    _check_recording(path, mapping, fmt, max_rows)
    raw = reader(fmt)(path, mapping, *((max_rows,) if fmt == "csv" else ()))  # text: its lines bounded as read
    n = max((len(v) for v in raw.columns.values()), default=0)
    if n > max_rows:
        raise MappingError(f"{path}: {n} samples, more than the {max_rows} a run may have (--max-rows raises the "
                           "limit).")
    columns: dict[str, np.ndarray] = {}
    how: list[str] = []
    for ch in mapping.channels:
        try:
            values, line = convert_channel(ch, raw.columns[ch.name], mapping.atmosphere)
        except Exception as e:  # pint refuses e.g. arithmetic on offset units
            raise MappingError(f"{mapping.path}: key '{ch.key}': cannot convert {ch.unit!r} ({e}).") from None
        columns[ch.name] = values
        how.append(line)
    _check(path, mapping, raw, columns)
    run = Run(t=columns["t"], u=columns["u"], x=columns["x"], p1=columns["p1"], p2=columns["p2"],
              ps=columns.get("ps"), extra={k: v for k, v in columns.items() if k not in (*SI_UNITS, "u")},
              source=path)
    report = sampling_report(run.t)
    notes = list(raw.notes)
    if report.irregular:
        notes.append(f"irregular sampling: {report.describe()}" + ("" if resample_rate else
                                                                   "; --resample RATE puts it on a regular grid"))
    digest = (raw.digest or _digest(path))[:16]  # a library's reader reads the file itself: hashed apart
    comments = [f"imported by combined-reality import from {path.name} (sha256 {digest}), {raw.describe}",
                f"mapping: {mapping.path.name if mapping.path else '-'}", *how,
                f"sampling as recorded: {report.describe()}", *raw.notes]
    if resample_rate is not None:
        n_grid = math.floor(report.duration * resample_rate) + 1
        if n_grid > max_rows:
            raise MappingError(f"{path}: --resample {resample_rate:g} Hz over the {report.duration:.6g} s recording "
                               f"gives {n_grid:.4g} samples, more than the {max_rows} a run may have (--max-rows).")
        run, left_out = resample(run, resample_rate)
        if run.n < 2:
            raise MappingError(f"{path}: --resample {resample_rate:g} leaves {run.n} sample(s) of a "
                               f"{report.duration:.4g} s recording.")
        line = (f"resampled to {resample_rate:g} Hz: measurements interpolated linearly, the command held from its "
                f"last sample (zero-order hold)" + (f"; {left_out} instants inside gaps left out (no sample is "
                                                    f"invented across a gap)" if left_out else ""))
        comments.append(line)
        notes.append(line)
    warnings = _warnings(mapping, columns)
    comments += [f"warning: {w}" for w in warnings]
    return ImportResult(run=run, sampling=report, comments=tuple(comments), notes=tuple(notes),
                        warnings=tuple(warnings))


def _check_recording(path: Path, mapping: ImportMapping, fmt: str, max_rows: int) -> None:
    """A regular file (a device or FIFO refused before it is opened: /dev/zero would never end,
    a FIFO without a writer never start) of at most `max_rows` rows of 1 kB, and a CAN log's
    database a regular file too. Delimited text has its lines bounded by its reader, which
    reads it once."""
    files = [(path, "a recording")]
    if fmt == "can" and mapping.source.dbc is not None:
        files.append((mapping.source.dbc, "a DBC file"))
    for p, what in files:
        size = checked_size(p, what, MappingError)
        if p == path and size > max_rows * _RECORDING_MAX_BYTES_PER_ROW:
            raise MappingError(f"{p}: {size / 2**20:.4g} MiB, more than {max_rows} rows (--max-rows) of "
                               f"{_RECORDING_MAX_BYTES_PER_ROW} bytes would fill; raise --max-rows for a longer "
                               "recording.")


def _warnings(mapping: ImportMapping, columns: dict[str, np.ndarray]) -> list[str]:
    """What a readable run can still show to be wrong: two standard channels read from one
    column, pressures outside what a pneumatic rig shows ([0.5, 20] bar absolute: a unit
    declared wrongly), a pressure not declared gauge that stays below the atmosphere."""
    where = mapping.path.name if mapping.path else "the mapping"
    out = []
    by_source: dict[tuple, str] = {}
    for name in ("u", "x", "p1", "p2", "ps"):
        ch = mapping.channel(name)
        if ch is None or ch.source is None:
            continue
        key = (ch.source, ch.zero, ch.scale, ch.span)
        if key in by_source:
            out.append(f"columns.{by_source[key]} and columns.{name} of {where} both read the column "
                       f"'{shorten(ch.source)}' the same way, so {by_source[key]} and {name} are one signal; map "
                       "each to its own sensor")
        by_source.setdefault(key, name)
    lo_ok, hi_ok = PLAUSIBLE_PRESSURE
    atmosphere = mapping.atmosphere or 101325.0
    for name in PRESSURES:
        p = columns.get(name)
        if p is None or not np.isfinite(p).any():
            continue
        ch = mapping.channel(name)
        lo, hi = float(np.nanmin(p)), float(np.nanmax(p))
        if lo < lo_ok or hi > hi_ok:
            out.append(f"{name} spans {lo / 1e5:.4g} to {hi / 1e5:.4g} bar absolute, outside the "
                       f"[{lo_ok / 1e5:g}, {hi_ok / 1e5:g}] bar of a pneumatic rig: check unit "
                       f"'{shorten(ch.unit)}'" + ("" if ch.gauge else " and gauge") + f" of columns.{name} in {where}")
        elif not ch.gauge and np.mean(p < _BELOW_ATMOSPHERE * atmosphere) > 0.01:
            out.append(f"{name} stays below the atmosphere for {100 * np.mean(p < _BELOW_ATMOSPHERE * atmosphere):.3g} "
                       f"% of the recording (down to {lo / 1e5:.4g} bar), which a chamber does not: if its sensor "
                       f"reads gauge pressure, set gauge = true for columns.{name} in {where}")
    return out


def _digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _check(path: Path, mapping: ImportMapping, raw: RawTable, columns: dict[str, np.ndarray]) -> None:
    """Refuse what the run reader would refuse, naming the place in the recording and the
    mapping key that most likely needs a change."""
    where = mapping.path.name if mapping.path else "the mapping"
    t = columns["t"]
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        i = int(back[0]) + 1
        raise MappingError(f"{path}, {raw.locate(i)}: time {t[i]:.9g} s is not after the {t[i - 1]:.9g} s of "
                           f"{raw.locate(i - 1)}; times must be strictly increasing.")
    odd = first_implausible(columns)
    if odd is not None:
        ch = mapping.channel(odd.column)
        i = odd.index
        value = columns[odd.column][i]
        si = SI_UNITS.get(odd.column, "")
        fix = "zero and span" if odd.column == "u" else "unit" + (" and gauge" if odd.column.startswith("p") else "")
        raise MappingError(f"{path}, {raw.locate(i)}, column '{ch.source}': {odd.column} = {value:.6g}"
                           f"{' ' + si if si else ''} (recorded {raw.columns[odd.column][i]:.6g} {ch.unit or ''})"
                           f" {odd.reason}; check {fix} of columns.{odd.column} in {where}.".replace(" )", ")"))
    why = time_unit_problem(t)
    if why is not None:
        tch = mapping.channel("t")
        what = f"column '{tch.source}'" if tch.source is not None else f"the time track of '{tch.time_of}'"
        raise MappingError(f"{path}, {raw.locate(t.size - 1)}, {what}: {why}; check the unit of columns.t in {where} "
                           f"(\"ms\" for milliseconds).")
