"""Recorded runs: the CSV layout of docs/formats.md ("A recorded run: CSV").

A run is the sampled time series ``t, u, x, p1, p2`` (s, 1, m, Pa absolute), an optional
measured supply pressure ``ps`` and any further columns, which are kept so that a rewrite
does not lose them. Reading is strict: a file that breaks the rules is refused with a
one-sentence :class:`RunFormatError` naming the file, the physical line and the column;
nothing is dropped or guessed.

An empty cell in ``x``, ``p1``, ``p2`` or ``ps`` means the channel was not measured at that
sample (a lost reading, a sensor that dropped out): it is read as NaN, and every consumer
skips what it cannot use. The time and the command must be there: a sample whose held
command is unknown cannot be simulated, so it is a gap (the line left out), not a row.
"""
from __future__ import annotations

import bisect
import csv
import io
import math
import os
import re
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import TracebackType
from typing import Callable, Iterable, Sequence

import numpy as np

from sim.inputs import checked_size, decode_text, line_breaks, shorten

from ..errors import InputError
from ..options import MAX_ROWS
from .atomic import atomic_writer
from .outputs import os_error, refuse_special
from .plausibility import first_implausible, measured_value, time_unit_problem

__all__ = ["REQUIRED_COLUMNS", "MEASURED_CHANNELS", "MAX_ROWS", "RunFormatError", "Run", "read_run", "write_run",
           "RunRecorder", "split_at_gaps", "cylinder_identity", "cylinder_tag", "recorded_cylinder",
           "recorded_elsewhere", "recorded_geometry", "recorded_file", "GEOMETRY"]

REQUIRED_COLUMNS: tuple[str, ...] = ("t", "u", "x", "p1", "p2")
# measured channels: an empty cell (not measured at that sample) is read as NaN
MEASURED_CHANNELS: tuple[str, ...] = ("x", "p1", "p2", "ps")

# fail(message, line=None, column=None) -> the error to raise, prefixed with file, line and column
_Fail = Callable[..., "RunFormatError"]


class RunFormatError(InputError):
    """A run file that cannot be used; the message is one sentence naming file, line and column
    (exit status 2)."""


@dataclass(frozen=True, eq=False)  # eq=False: element-wise array equality has no single truth value
class Run:
    """One recorded (or simulated) run in SI units; all arrays 1-D and of equal length."""

    t: np.ndarray  # s, strictly increasing when read from a file
    u: np.ndarray  # 1, valve command as sent (not clipped: the model saturates)
    # measured channels; NaN where the channel was not measured at that sample (an empty cell)
    x: np.ndarray  # m, 0 = fully retracted
    p1: np.ndarray  # Pa absolute, cap side
    p2: np.ndarray  # Pa absolute, rod side
    ps: np.ndarray | None = None  # Pa absolute, measured supply pressure if recorded
    # Further columns in file order: float64 if numeric, else numpy str arrays (kept verbatim).
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    source: Path | None = None
    comments: tuple[str, ...] = ()  # the file's comment lines, without '# '

    def __post_init__(self) -> None:
        n = None
        for name in REQUIRED_COLUMNS + ("ps",):
            value = getattr(self, name)
            if value is None:
                if name != "ps":
                    raise ValueError(f"Run column '{name}' is missing.")
                continue
            arr = _as_column(value, name)
            n = len(arr) if n is None else n
            if len(arr) != n:
                raise ValueError(f"Run column '{name}' has {len(arr)} samples, expected {n}.")
            object.__setattr__(self, name, arr)
        extra: dict[str, np.ndarray] = {}
        for name, value in self.extra.items():
            if name in REQUIRED_COLUMNS or name == "ps":
                raise ValueError(f"Run extra column '{name}' clashes with a standard column.")
            arr = np.asarray(value)
            if arr.dtype.kind in "biuf":
                arr = _as_column(arr, name)
            elif arr.ndim != 1:
                raise ValueError(f"Run extra column '{name}' must be 1-D, not shape {arr.shape}.")
            if len(arr) != n:
                raise ValueError(f"Run extra column '{name}' has {len(arr)} samples, expected {n}.")
            extra[name] = arr
        object.__setattr__(self, "extra", extra)
        if self.source is not None:
            object.__setattr__(self, "source", Path(self.source))

    @property
    def n(self) -> int:
        """Number of samples."""
        return len(self.t)

    @property
    def duration(self) -> float:
        """Time from the first to the last sample, s (0 for fewer than two samples)."""
        return float(self.t[-1] - self.t[0]) if self.n >= 2 else 0.0

    @property
    def sample_period(self) -> float:
        """Median time step, s (robust to jitter and the odd dropped sample)."""
        if self.n < 2:
            raise ValueError("a run needs at least 2 samples to have a sample period.")
        return float(np.median(np.diff(self.t)))

    def slice(self, i0: int | None, i1: int | None = None) -> "Run":
        """Samples i0 (inclusive) to i1 (exclusive), Python slice rules; arrays are views."""
        s = slice(i0, i1)
        return replace(
            self,
            t=self.t[s], u=self.u[s], x=self.x[s], p1=self.p1[s], p2=self.p2[s],
            ps=None if self.ps is None else self.ps[s],
            extra={k: v[s] for k, v in self.extra.items()},
        )


def split_at_gaps(run: Run, factor: float = 1.5, channels: Sequence[str] = ()) -> list[Run]:
    """The gap-free pieces of a run: a step longer than `factor` median periods means lost
    samples, whose commands are unknown, so no simulation may bridge it. Samples where one of
    `channels` was not measured (NaN) are left out and cut the run too (e.g. the measured
    pressures that drive the pressure-driven plant)."""
    if run.n < 3:
        return [run]
    dt = np.diff(run.t)
    cut = np.zeros(run.n, bool)
    cut[1:] = dt > factor * np.median(dt)
    usable = np.ones(run.n, bool)
    for name in channels:
        usable &= np.isfinite(getattr(run, name))
    cut[1:] |= ~usable[:-1]
    piece = np.cumsum(cut)  # piece number of every sample; unusable samples belong to none
    bounds = np.flatnonzero(np.diff(np.r_[-1, np.where(usable, piece, -1), -1]) != 0)
    return [run.slice(a, b) for a, b in zip(bounds, bounds[1:]) if usable[a]]


def _as_column(value: object, name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 1:
        raise ValueError(f"Run column '{name}' must be 1-D, not shape {arr.shape}.")
    return arr


# --------------------------------------------------------------------------- reading

# Limits of the reader (docs/formats.md, "Limits"): a run file is read as a stream of blocks,
# its memory a little more than the columns it holds.
MAX_LINE = 1 << 16  # bytes of one line
_MAX_ROW_BYTES = 256  # a file larger than max_rows lines of this length is refused unread
_BLOCK = 8 << 20  # bytes read at a time: a block after the first is parsed by pyarrow's CSV reader


def read_run(path: str | os.PathLike[str], max_rows: int = MAX_ROWS) -> Run:
    """Load a run CSV, refusing anything docs/formats.md does not allow with a RunFormatError:
    also a file that is not a regular file (a device, a FIFO: refused before it is opened) or
    has more than `max_rows` lines."""
    path = Path(path)

    def fail(msg: str, line: int | None = None, column: str | None = None) -> RunFormatError:
        where = str(path)
        if line is not None:
            where += f", line {line}"
        if column is not None:
            where += f", column '{shorten(column)}'"
        return RunFormatError(f"{where}: {msg}")

    size = _regular_size(path, max_rows)
    with open(path, "rb") as f:
        text_columns: frozenset[str] = frozenset()
        while True:
            reader = _RunReader(path, f, size, max_rows, fail, text_columns)
            try:
                reader.read()
                return reader.run(f)
            except _TextColumn as e:  # a further column holds text: read again, keeping it as text
                text_columns = e.names
                f.seek(0)


def _regular_size(path: Path, max_rows: int) -> int:
    size = checked_size(path, "a run file", RunFormatError)
    if size > max_rows * _MAX_ROW_BYTES:
        raise RunFormatError(f"{path}: {size / 2**20:.4g} MiB, more than {max_rows} lines (--max-rows) of "
                             f"{_MAX_ROW_BYTES} bytes would fill; raise --max-rows for a longer run.")
    return size


def _lines_through(line0: int, block: bytes, breaks: int) -> int:
    """The lines of the file up to the end of this block (the last one may lack its break)."""
    return line0 - 1 + breaks + (not block.endswith((b"\n", b"\r")))


def _too_many(lines: int, max_rows: int, fail: _Fail) -> RunFormatError:
    return fail(f"{lines} lines, more than the {max_rows} a run file may have (--max-rows raises the limit).")


def _count_to_end(blocks, lines: int) -> int:
    """`lines` so far and those of the blocks still to come (read, not parsed)."""
    for _, line0, block, breaks in blocks:
        lines = _lines_through(line0, block, breaks)
    return lines


def _count_lines(f) -> int:
    """The lines of the file from its start, read piece by piece and not kept."""
    f.seek(0)
    breaks, last, after_cr = 0, b"", False
    while data := f.read(_BLOCK):
        breaks += line_breaks(data) - (after_cr and data.startswith(b"\n"))  # \r\n across two pieces
        after_cr, last = data.endswith(b"\r"), data[-1:]
    return breaks + (last not in (b"", b"\n", b"\r"))


def _blocks(f, fail: _Fail, first: bytes | None = None):
    """(byte offset, first line, bytes, line breaks) of whole lines, about _BLOCK bytes at a
    time (`first`: the file's first bytes, already read); a line longer than MAX_LINE is
    refused. A block ends after a line break, or at the end of the file."""
    offset, line, rest = 0, 1, b""
    while True:
        chunk = f.read(_BLOCK) if first is None else first
        first = None
        data = rest + chunk
        if not chunk:
            if data:
                yield offset, line, data, line_breaks(data)
            return
        end = len(data) - 1 if data.endswith(b"\r") else len(data)  # \r\n must stay together
        cut = max(data.rfind(b"\n", 0, end), data.rfind(b"\r", 0, end))
        block, rest = data[:cut + 1], data[cut + 1:]
        breaks = line_breaks(block)
        if len(rest) > MAX_LINE:
            raise fail(f"longer than {MAX_LINE} bytes: not a line of a run CSV.", line + breaks)
        if block:
            yield offset, line, block, breaks
            offset += len(block)
            line += breaks


def _split_lines(text: str) -> list[str]:
    # Universal newlines, but only \n, \r\n and \r: str.splitlines would also split on form
    # feeds and the like and so shift the physical line numbers in messages.
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    if lines and lines[-1] == "":
        lines.pop()  # the block ended with its last line's break
    return lines


def _decoded(block: bytes, line0: int, fail: _Fail) -> str:
    """The block's text (the first drops a UTF-8 byte order mark)."""
    return decode_text(block, lambda line, _: fail("not UTF-8 text (is this a CSV file?).", line), line0=line0,
                       cr_ends_lines=True)


def _is_comment(line: str) -> bool:
    return line.lstrip().startswith("#")


class _TextColumn(Exception):
    def __init__(self, names: frozenset[str]):
        self.names = names


@dataclass(frozen=True)
class _Block:
    """Where a block's rows lie, to find a row's line and text again for a message."""
    row0: int
    line0: int
    offset: int
    size: int
    linenos: np.ndarray | None  # the line of each row; None: every line of the block is a row


class _Column:
    """A column filled block by block: sized at first from an estimate of the rows, grown in
    place when the estimate falls short (ndarray.resize: realloc, which moves a large array's
    pages without copying them), cut to its rows at the end. Rows not yet written cost no
    memory."""

    def __init__(self, capacity: int, dtype=np.float64):
        self.a = np.zeros(capacity, dtype) if dtype is bool else np.empty(capacity, dtype)

    def put(self, at: int, values: np.ndarray) -> None:
        end = at + len(values)
        if end > self.a.size:
            self.a.resize(max(end, self.a.size + self.a.size // 2), refcheck=False)  # no view of it is held
        self.a[at:end] = values

    def cut(self, n: int) -> np.ndarray:
        self.a.resize(n, refcheck=False)
        return self.a


class _RunReader:
    """One pass over a run file: the header, then the rows block by block into columns sized
    from the first block (the rows its size foretells), a block of plain numbers parsed at C
    speed, anything else line by line with the exact line and column of a problem. More than
    max_rows lines are refused: unparsed when the first block foretells it (the lines counted
    first), else as soon as a block passes the limit (the rest counted, not parsed)."""

    def __init__(self, path: Path, f, size: int, max_rows: int, fail: _Fail,
                 text_columns: frozenset[str] = frozenset()):
        self.path, self.f, self.size, self.max_rows, self.fail = path, f, size, max_rows, fail
        self.text_columns = text_columns
        self.capacity = 0
        self.names: list[str] | None = None
        self.header_line = 0
        self.comments: list[str] = []
        self.n = 0
        self.blank: int | None = None  # a blank line after the header, refused if anything follows it
        self.blocks: list[_Block] = []
        self.numeric: dict[str, _Column] = {}
        self.text: dict[str, list[np.ndarray]] = {}
        self.empty: dict[str, _Column] = {}
        self.last_line = 0

    def _first(self) -> bytes:
        """The first block, and from it the columns' size; a file that it foretells to be longer
        than max_rows lines has its lines counted before any is parsed (refused if so)."""
        head = self.f.read(_BLOCK)
        lines = line_breaks(head) + 1
        if len(head) < _BLOCK:
            self.capacity = lines
            return head
        foretold = math.ceil(self.size * lines / len(head))
        if foretold > self.max_rows:
            del head  # the count reads the file again from its start, holding one piece at a time
            total = _count_lines(self.f)
            if total > self.max_rows:
                raise _too_many(total, self.max_rows, self.fail)
            self.f.seek(0)
            head = self.f.read(_BLOCK)
            foretold = total
        self.capacity = min(self.max_rows, foretold + foretold // 20) + 1
        return head

    def read(self) -> None:
        blocks = _blocks(self.f, self.fail, self._first())
        for offset, line0, block, breaks in blocks:
            lines = _lines_through(line0, block, breaks)
            if lines > self.max_rows:
                self.numeric.clear()
                self.empty.clear()
                raise _too_many(_count_to_end(blocks, lines), self.max_rows, self.fail)
            if self.names is None or not self._plain(offset, line0, block, breaks):
                self._lines(offset, line0, block)
        if self.names is None:
            if self.comments:
                raise self.fail(f"the file holds only comments; expected a header with columns "
                                f"{', '.join(REQUIRED_COLUMNS)}.")
            raise self.fail(f"the file is empty; expected a header with columns {', '.join(REQUIRED_COLUMNS)}.")
        if self.n == 0:
            raise self.fail("the header is not followed by any data rows; at least 2 samples are required.",
                            self.header_line)
        if self.n == 1:
            raise self.fail("only one sample; at least 2 are required.", self.last_line)

    def _start(self, names: list[str]) -> None:
        self.names = names
        for name in names:
            if name in self.text_columns:
                self.text[name] = []
            else:
                self.numeric[name] = _Column(self.capacity)

    def _plain(self, offset: int, line0: int, block: bytes, breaks: int) -> bool:
        """Parse a block of nothing but rows of plain numbers at C speed; False if it is not one
        (then the line by line pass says what is wrong, and where)."""
        if (self.text or self.blank is not None or b"#" in block or b"\r" in block or b"\n\n" in block
                or block.startswith(b"\n")):
            return False
        k = breaks + (not block.endswith(b"\n"))
        cols = self._arrow(block, k)
        if cols is None:
            return False
        self._store(cols, k)
        self.blocks.append(_Block(self.n - k, line0, offset, len(block), None))
        self.last_line = line0 + k - 1
        return True

    def _arrow(self, block: bytes, k: int) -> dict[str, np.ndarray] | None:
        import pyarrow as pa
        import pyarrow.csv as pacsv

        try:
            table = pacsv.read_csv(
                io.BytesIO(block), read_options=pacsv.ReadOptions(column_names=self.names, use_threads=False),
                parse_options=pacsv.ParseOptions(newlines_in_values=False),
                convert_options=pacsv.ConvertOptions(column_types={n: pa.float64() for n in self.names},
                                                     null_values=[""], strings_can_be_null=False,
                                                     quoted_strings_can_be_null=False))
        except (pa.ArrowInvalid, ValueError):
            return None
        if table.num_rows != k:
            return None
        out, empty = {}, {}
        for name in self.names:
            col = table.column(name)
            if col.null_count:
                if name not in MEASURED_CHANNELS:
                    return None  # an empty time, command or further cell: said line by line
                empty[name] = col.is_null().to_numpy(zero_copy_only=False)
            out[name] = col.to_numpy(zero_copy_only=False).astype(np.float64, copy=False)
        for name, mask in empty.items():
            out[name] = np.where(mask, np.nan, out[name])
            self._mark_empty(name, mask, self.n)
        return out

    def _lines(self, offset: int, line0: int, block: bytes) -> None:
        """A block line by line: comments, blank lines, the header, rows of any kind."""
        rows: list[str] = []
        linenos: list[int] = []
        for lineno, line in enumerate(_split_lines(_decoded(block, line0, self.fail)), start=line0):
            if len(line) > MAX_LINE:
                raise self.fail(f"longer than {MAX_LINE} characters: not a line of a run CSV.", lineno)
            if not line.strip():
                if self.names is not None and self.blank is None:
                    self.blank = lineno
                continue
            if self.blank is not None:
                raise self.fail("blank line inside the data (only trailing blank lines are allowed).", self.blank)
            if _is_comment(line):
                self.comments.append(line.lstrip()[1:].strip())
            elif self.names is None:
                self.header_line = lineno
                self._start(_header(line, lineno, self.fail))
            else:
                rows.append(line)
                linenos.append(lineno)
        if not rows:
            return
        columns, empty = _parse_cells(rows, linenos, self.names, self.header_line, self.fail, self.text_columns)
        textual = frozenset(n for n, c in columns.items() if c.dtype.kind not in "biuf" and n not in self.text)
        if textual:
            raise _TextColumn(self.text_columns | textual)
        for name, mask in empty.items():
            self._mark_empty(name, mask, self.n)
        self._store(columns, len(rows))
        self.blocks.append(_Block(self.n - len(rows), line0, offset, len(block), np.array(linenos)))
        self.last_line = linenos[-1]

    def _mark_empty(self, name: str, mask: np.ndarray, at: int) -> None:
        if mask.any():
            if name not in self.empty:
                self.empty[name] = _Column(self.capacity, bool)
            self.empty[name].put(at, mask)

    def _store(self, columns: dict[str, np.ndarray], k: int) -> None:
        for name, col in columns.items():
            if name in self.text:
                self.text[name].append(col)
            else:
                self.numeric[name].put(self.n, col)
        self.n += k

    def row(self, f, i: int) -> tuple[int, str]:
        """The line number and the text of row i (read again from the file)."""
        b = self.blocks[bisect.bisect_right([b.row0 for b in self.blocks], i) - 1]
        f.seek(b.offset)
        lines = _split_lines(f.read(b.size).decode("utf-8", errors="replace"))
        lineno = b.line0 + (i - b.row0) if b.linenos is None else int(b.linenos[i - b.row0])
        return lineno, lines[lineno - b.line0]

    def run(self, f) -> Run:
        names, n, fail = self.names, self.n, self.fail
        columns = {name: (np.concatenate(self.text[name]) if name in self.text else self.numeric[name].cut(n))
                   for name in names}
        empty = {name: mask.cut(n) for name, mask in self.empty.items()}

        def cell(i: int, name: str) -> tuple[int, str]:
            lineno, text = self.row(f, i)
            return lineno, shorten(_cell_text(text, names.index(name)))

        # Extra columns are not checked: docs/formats.md says they are ignored (but kept).
        standard = [c for c in REQUIRED_COLUMNS + ("ps",) if c in columns]
        for name in standard:
            finite = np.isfinite(columns[name])
            bad = np.flatnonzero(~finite if name not in empty else ~finite & ~empty[name])
            if bad.size:
                lineno, text = cell(int(bad[0]), name)
                raise fail(f"{text!r} is not a finite number.", lineno, name)
        t = columns["t"]
        bad = np.flatnonzero(np.diff(t) <= 0)
        if bad.size:
            i = int(bad[0]) + 1
            lineno, text = cell(i, "t")
            before_line, before = cell(i - 1, "t")
            raise fail(f"time {text} s is not after the {before} s of line {before_line}; times must be strictly "
                       "increasing.", lineno, "t")
        odd = first_implausible(columns)
        if odd is not None:
            lineno, text = cell(odd.index, odd.column)
            raise fail(f"{text} {odd.reason}.", lineno, odd.column)
        why = time_unit_problem(t)
        if why is not None:
            raise fail(f"{why}.", self.last_line, "t")
        return Run(t=columns["t"], u=columns["u"], x=columns["x"], p1=columns["p1"], p2=columns["p2"],
                   ps=columns.get("ps"), extra={k: v for k, v in columns.items() if k not in standard},
                   source=self.path, comments=tuple(self.comments))


def _split(row: str) -> list[str]:
    # csv only where quoting is present: plain split is much faster, and one reader per row
    # stops an unbalanced quote from swallowing the following lines.
    return next(csv.reader((row,))) if '"' in row else row.split(",")


def _cell_text(row: str, j: int) -> str:
    cells = _split(row)
    return cells[j].strip() if j < len(cells) else ""


def _header(line: str, lineno: int, fail: _Fail) -> list[str]:
    names = [c.strip() for c in _split(line)]
    if all(_is_number(n) for n in names):
        raise fail(f"this looks like data, not a header; the first line that is not a comment must name "
                   f"the columns ({', '.join(REQUIRED_COLUMNS)}).", lineno)
    seen: dict[str, int] = {}
    for j, name in enumerate(names):
        if name in seen:
            raise fail(f"column '{shorten(name)}' appears more than once in the header "
                       f"(columns {seen[name] + 1} and {j + 1}).", lineno)
        seen[name] = j
    missing = [c for c in REQUIRED_COLUMNS if c not in seen]
    if missing:
        what = "column" if len(missing) == 1 else "columns"
        found = shorten(", ".join(repr(n) for n in names))
        raise fail(f"missing required {what} {', '.join(repr(c) for c in missing)} "
                   f"(the header has {found}); a recording with other columns or units converts with "
                   "'combined-reality import'.", lineno)
    return names


def _parse_cells(rows: list[str], linenos: list[int], names: list[str], header_line: int,
                 fail: _Fail, text_columns: frozenset[str] = frozenset()
                 ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Column name -> array (float64 for numeric columns, str for non-numeric extra columns and
    those of `text_columns`), and for the measured channels with empty cells, where they are
    (read as NaN)."""
    ncol = len(names)
    # Fast path: numpy's C parser, valid only when every cell is a plain number.
    try:
        table = None if text_columns else np.loadtxt(rows, delimiter=",", comments=None, quotechar=None, ndmin=2,
                                                     dtype=np.float64)
    except ValueError:
        table = None
    if table is not None and table.shape == (len(rows), ncol):
        return {name: np.ascontiguousarray(table[:, j]) for j, name in enumerate(names)}, {}

    # Slow path: empty cells of measured channels, and the exact line and column of a problem.
    if any('"' in r for r in rows):
        try:
            cells = list(csv.reader(rows))
        except csv.Error:  # a quote left open swallowed the rest of the file ("field larger than field limit")
            cells = []
        if len(cells) != len(rows):  # a quote left open swallowed line breaks: go row by row
            cells = [_split(r) for r in rows]
    else:
        cells = [r.split(",") for r in rows]
    for i, c in enumerate(cells):
        if len(c) != ncol:
            raise fail(f"{len(c)} cells, but the header on line {header_line} has {ncol} columns.", linenos[i])
    columns: dict[str, np.ndarray] = {}
    empty: dict[str, np.ndarray] = {}
    for j, name in enumerate(names):
        col = [c[j] for c in cells]
        if name in text_columns:
            columns[name] = np.array(col, dtype=str)
            continue
        blank = None
        if name in MEASURED_CHANNELS:
            blank = np.fromiter((not s.strip() for s in col), bool, len(col))
            if blank.any():
                empty[name] = blank
            else:
                blank = None
        filled = col if blank is None else [s for s, b in zip(col, blank) if not b]
        try:  # C parser first; the Python loop below only runs to find what is wrong
            with warnings.catch_warnings():  # an empty cell is said below, not warned about
                warnings.simplefilter("ignore")
                arr = np.loadtxt(filled, delimiter=",", comments=None, quotechar=None, ndmin=1, dtype=np.float64)
        except ValueError:
            arr = None
        if arr is not None and arr.shape == (len(filled),):
            if blank is not None:
                full = np.full(len(col), np.nan)
                full[~blank] = arr
                arr = full
            columns[name] = arr
            continue
        arr = np.full(len(col), np.nan)
        for i, s in enumerate(col):
            if blank is not None and blank[i]:
                continue
            try:
                arr[i] = _to_float(s)
            except ValueError:
                if name in ("t", "u") and not s.strip():
                    what = ("every sample needs its time" if name == "t" else
                            "a sample whose command is unknown cannot be simulated, so leave the line out "
                            "(the time step then shows the gap)")
                    raise fail(f"empty cell: {what}.", linenos[i], name) from None
                if name in REQUIRED_COLUMNS or name == "ps":
                    raise fail(f"{shorten(s.strip())!r} is not a number.", linenos[i], name) from None
                # docs/formats.md: further columns are ignored, so text there is kept, not refused.
                columns[name] = np.array(col, dtype=str)
                break
        else:
            columns[name] = arr
    return columns, empty


def _is_number(s: str) -> bool:
    try:
        _to_float(s)
    except ValueError:
        return False
    return True


def _to_float(s: str) -> float:
    # Same acceptance as np.loadtxt, so the fast and slow paths agree: Python's float() also
    # takes digit separators and non-ASCII digits, which numpy refuses.
    if "_" in s or not s.isascii():
        raise ValueError(s)
    return float(s)


# --------------------------------------------------------------------------- writing


CYLINDER_TAG = "cylinder:"


def cylinder_identity(cyl) -> str:
    """What makes a cylinder that cylinder: its name and geometry. Friction may be re-identified
    and mass, volumes, valve and sensors calibrated into a new file: the identity stays."""
    g = cyl.geometry
    return f"{cyl.name}; bore {g.bore:g} m, rod {g.rod:g} m, stroke {g.stroke:g} m"


GEOMETRY = ("bore", "rod", "stroke")  # what makes a run belong to a cylinder (a tag names it)
_TAG_GEOMETRY = re.compile(r"; bore (\S+) m, rod (\S+) m, stroke (\S+) m(?:, mass [^;]*)?$")


def cylinder_tag(cyl) -> str:
    """The comment line that says which cylinder a run was recorded on."""
    return f"{CYLINDER_TAG} {cylinder_identity(cyl)}; file {cyl.source or '-'}"


def _tag(run: Run) -> str | None:
    return next((c[len(CYLINDER_TAG):].strip() for c in run.comments if c.startswith(CYLINDER_TAG)), None)


def recorded_cylinder(run: Run) -> str | None:
    """The recorded cylinder's identity (the tag without its file), or None if not recorded."""
    tag = _tag(run)
    return None if tag is None else tag.rsplit("; file ", 1)[0].strip()


def recorded_geometry(run: Run) -> dict[str, float] | None:
    """Bore, rod and stroke (m) of the cylinder the run's tag names, or None without a tag."""
    identity = recorded_cylinder(run)
    m = _TAG_GEOMETRY.search(identity or "")
    if m is None:
        return None
    try:
        return {k: float(v) for k, v in zip(GEOMETRY, m.groups())}
    except ValueError:
        return None


def recorded_file(run: Run) -> str | None:
    """The cylinder file the run's tag names (as it was given then), or None."""
    tag = _tag(run)
    if tag is None or "; file " not in tag:
        return None
    path = tag.rsplit("; file ", 1)[1].strip()
    return None if path in ("", "-") else path


def recorded_elsewhere(run: Run, cyl) -> str | None:
    """The identity of the cylinder the run was recorded on if its geometry (bore, rod, stroke)
    is not `cyl`'s, else None: a cylinder renamed, re-identified or calibrated into a new
    file is the same cylinder. Also None for runs without a cylinder tag (other tools' files)."""
    theirs = recorded_geometry(run)
    if theirs is None:
        return None
    g = cyl.geometry
    same = all(math.isclose(theirs[k], getattr(g, k), rel_tol=1e-5, abs_tol=1e-9) for k in GEOMETRY)
    return None if same else recorded_cylinder(run)


_WRITE_ROWS = 1 << 16  # rows formatted at a time: the text of a long run is never held whole


def write_run(path: str | os.PathLike[str], run: Run, comments: Sequence[str] | None = None) -> None:
    """Write ``run`` as CSV atomically (readers never see a partial file); round-trips exactly."""
    names, cols = _columns_of(run)
    with atomic_writer(path) as f:
        f.write((_comment_lines(comments or ()) + _join(names) + "\n").encode("utf-8"))
        for i in range(0, run.n, _WRITE_ROWS):
            formatted = [_format_column(name, col[i:i + _WRITE_ROWS]) for name, col in zip(names, cols)]
            f.write("".join(",".join(row) + "\n" for row in zip(*formatted)).encode("utf-8"))


def _columns_of(run: Run) -> tuple[list[str], list[np.ndarray]]:
    names = list(REQUIRED_COLUMNS)
    cols = [run.t, run.u, run.x, run.p1, run.p2]
    if run.ps is not None:
        names.append("ps")
        cols.append(run.ps)
    for name, col in run.extra.items():
        names.append(name)
        cols.append(col)
    return names, cols


def _format_column(name: str, col: np.ndarray) -> list[str]:
    if col.dtype.kind in "biuf":
        # repr of a Python float is the shortest string that parses back to the same double;
        # a channel not measured at a sample (NaN) is an empty cell
        if name in MEASURED_CHANNELS:
            return ["" if v != v else repr(v) for v in col.astype(np.float64).tolist()]
        return [repr(v) for v in col.astype(np.float64).tolist()]
    return [_quote(str(v), name) for v in col.tolist()]


def _quote(cell: str, column: str) -> str:
    if "\n" in cell or "\r" in cell:
        raise ValueError(f"column '{column}' holds a line break, which a run CSV cannot store.")
    if "," in cell or '"' in cell:
        return '"' + cell.replace('"', '""') + '"'
    return cell


def _join(names: Iterable[str]) -> str:
    return ",".join(_quote(n, n) for n in names)


def _comment_lines(comments: Iterable[str]) -> str:
    out = []
    for c in comments:
        for line in c.splitlines() or [""]:  # a multi-line comment must not break the file
            out.append(f"# {line}".rstrip() + "\n")
    return "".join(out)


def _cell(name: str, value: float | None) -> str:
    """A measured value as a cell: empty when it was not measured (None), is not finite or is
    beyond what a reading can be (files.plausibility.measured_value)."""
    return _checked_cell(name, measured_value(name, value))


def _checked_cell(name: str, value: float | None) -> str:
    """A value measured_value has judged already: empty when not measured (NaN or None)."""
    return "" if value is None or value != value else repr(float(value))


class RunRecorder:
    """Streams samples to a run CSV as they arrive, one complete line per ``append``.

    Each line goes to the OS in a single unbuffered write, so a crash or kill of the process
    leaves a file of whole lines that :func:`read_run` accepts (power loss is only covered up
    to the last :meth:`sync`). A measured channel that is missing (None), not finite or
    beyond what a reading can be is written as an empty cell (not measured at that sample:
    files.plausibility.measured_value); the time and the command must be finite.
    An existing file at ``path`` is replaced; a device, a FIFO or a folder is refused.
    When a write fails (the disk is full), the file is cut back to its last whole line, or
    removed if it holds no sample, and every later call raises the same WriteError, which
    says so.
    """

    def __init__(self, path: str | os.PathLike[str], *, with_ps: bool = False,
                 comments: Sequence[str] | None = None) -> None:
        self.path = Path(path)
        self.with_ps = with_ps
        self.n = 0
        self._whole = 0  # bytes of whole lines written
        self._error: Exception | None = None
        names = list(REQUIRED_COLUMNS) + (["ps"] if with_ps else [])
        refuse_special(self.path)
        try:
            self._f = open(self.path, "wb", buffering=0)
        except OSError as e:
            raise os_error(e, self.path, doing="cannot record to") from None
        self._write((_comment_lines(comments or ()) + _join(names) + "\n").encode("utf-8"))

    def append(self, t: float, u: float, x: float | None, p1: float | None, p2: float | None,
               ps: float | None = None, *, checked: bool = False) -> None:
        """One sample as one line. `checked`: x, p1, p2 (and ps) have been through
        files.plausibility.measured_value already (NaN: not measured), so they are written as
        they are, without judging them again (a live session's samples)."""
        if self._error is not None:
            raise self._error
        if self._f.closed:
            raise ValueError(f"RunRecorder for {self.path} is closed.")
        if ps is not None and not self.with_ps:
            raise ValueError(f"RunRecorder for {self.path} was opened with with_ps=False, but append got ps={ps!r}.")
        t, u = float(t), float(u)
        if not (math.isfinite(t) and math.isfinite(u)):
            raise ValueError(f"RunRecorder for {self.path}: the time and the command of a sample must be finite "
                             f"(got t={t!r}, u={u!r}).")
        cell = _checked_cell if checked else _cell
        cells = [repr(t), repr(u), cell("x", x), cell("p1", p1), cell("p2", p2)]
        if self.with_ps:
            cells.append(cell("ps", ps))
        self._write((",".join(cells) + "\n").encode("ascii"))
        self.n += 1

    def sync(self) -> None:
        """Force the lines written so far onto the disk (survives power loss, costs a disk flush)."""
        if not self._f.closed:
            try:
                os.fsync(self._f.fileno())
            except OSError as e:
                self._failed(e)

    def close(self) -> None:
        if not self._f.closed:
            try:
                self.sync()
            finally:
                self._f.close()

    @property
    def closed(self) -> bool:
        return self._f.closed

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        try:
            while view:
                written = self._f.write(view)
                view = view[written:]
        except OSError as e:
            self._failed(e)
        self._whole += len(data)

    def _failed(self, e: OSError):
        """Keep the whole lines (or nothing, without a sample), close, and raise what failed."""
        kept = (f"; it holds the {self.n} sample{'s' if self.n != 1 else ''} recorded before, each line whole"
                if self.n else "; nothing was recorded, so the file was removed")
        try:
            if self.n:
                os.ftruncate(self._f.fileno(), self._whole)
            self._f.close()
            if not self.n:
                os.unlink(self.path)
        except OSError:
            pass
        err = os_error(e, self.path, doing="cannot record to")
        self._error = type(err)(str(err).rstrip(".") + kept + ".")
        raise self._error from None

    def __enter__(self) -> "RunRecorder":
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
