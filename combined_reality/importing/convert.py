"""A lab recording into a run: read the mapped channels with the reader of the recording's
format, convert each to SI, refuse what cannot be a run (naming the recording's line, row or
sample), report the sampling and, on request, resample."""
from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..files import Run, first_implausible, time_unit_problem
from .mapping import ImportMapping, MappingError, format_of
from .raw import RawTable
from .sampling import SamplingReport, resample, sampling_report
from .units import SI_UNITS, convert_channel

__all__ = ["ImportResult", "import_recording", "READERS"]


def _delimited(path, mapping):
    from .delimited import read_delimited

    return read_delimited(path, mapping)


def _parquet(path, mapping):
    from .parquet import read_parquet

    return read_parquet(path, mapping)


def _mat(path, mapping):
    from .matlab import read_mat

    return read_mat(path, mapping)


def _tdms(path, mapping):
    from .tdms import read_tdms

    return read_tdms(path, mapping)


def _mdf(path, mapping):
    from .mdf import read_mdf

    return read_mdf(path, mapping)


def _can(path, mapping):
    from .canlog import read_can_log

    return read_can_log(path, mapping)


# format -> reader (each imports its library when used: the heavy ones are optional extras)
READERS: dict[str, Callable[[Path, ImportMapping], RawTable]] = {
    "csv": _delimited, "parquet": _parquet, "mat": _mat, "tdms": _tdms, "mdf": _mdf, "can": _can}


@dataclass(frozen=True)
class ImportResult:
    run: Run
    sampling: SamplingReport  # of the recording as read (before any resampling)
    comments: tuple[str, ...]  # the header the run is written with: where it came from, how converted
    notes: tuple[str, ...]  # what the user should hear (irregular sampling, rows left out)


def import_recording(raw_path: str | Path, mapping: ImportMapping, resample_rate: float | None = None) -> ImportResult:
    path = Path(raw_path)
    fmt = format_of(path, mapping.source)
    raw = READERS[fmt](path, mapping)
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
    comments = [f"imported by combined-reality import from {path.name} (sha256 {_digest(path)}), {raw.describe}",
                f"mapping: {mapping.path.name if mapping.path else '-'}", *how,
                f"sampling as recorded: {report.describe()}", *raw.notes]
    if resample_rate is not None:
        run, left_out = resample(run, resample_rate)
        if run.n < 2:
            raise MappingError(f"{path}: --resample {resample_rate:g} leaves {run.n} sample(s) of a "
                               f"{report.duration:.4g} s recording.")
        line = (f"resampled to {resample_rate:g} Hz: measurements interpolated linearly, the command held from its "
                f"last sample (zero-order hold)" + (f"; {left_out} instants inside gaps left out (no sample is "
                                                    f"invented across a gap)" if left_out else ""))
        comments.append(line)
        notes.append(line)
    return ImportResult(run=run, sampling=report, comments=tuple(comments), notes=tuple(notes))


def _digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]


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
