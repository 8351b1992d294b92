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

import csv
import math
import os
import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import TracebackType
from typing import Callable, Iterable, Sequence

import numpy as np

from .atomic import atomic_write
from .plausibility import first_implausible, time_unit_problem

__all__ = ["REQUIRED_COLUMNS", "MEASURED_CHANNELS", "RunFormatError", "Run", "read_run", "write_run", "RunRecorder",
           "split_at_gaps", "cylinder_identity", "cylinder_tag", "recorded_cylinder", "recorded_elsewhere",
           "recorded_geometry", "recorded_file", "GEOMETRY"]

REQUIRED_COLUMNS: tuple[str, ...] = ("t", "u", "x", "p1", "p2")
# measured channels: an empty cell (not measured at that sample) is read as NaN
MEASURED_CHANNELS: tuple[str, ...] = ("x", "p1", "p2", "ps")

# fail(message, line=None, column=None) -> the error to raise, prefixed with file, line and column
_Fail = Callable[..., "RunFormatError"]


class RunFormatError(ValueError):
    """A run file that cannot be used; the message is one sentence naming file, line and column."""


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


def read_run(path: str | os.PathLike[str]) -> Run:
    """Load a run CSV, refusing anything docs/formats.md does not allow with a RunFormatError."""
    path = Path(path)
    lines = _read_lines(path)

    def fail(msg: str, line: int | None = None, column: str | None = None) -> RunFormatError:
        where = str(path)
        if line is not None:
            where += f", line {line}"
        if column is not None:
            where += f", column '{column}'"
        return RunFormatError(f"{where}: {msg}")

    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        raise fail(f"the file is empty; expected a header with columns {', '.join(REQUIRED_COLUMNS)}.")
    h = next((i for i, ln in enumerate(lines) if ln.strip() and not _is_comment(ln)), None)
    if h is None:
        raise fail(f"the file holds only comments; expected a header with columns {', '.join(REQUIRED_COLUMNS)}.")
    header_line = h + 1
    names = _header(lines[h], header_line, fail)

    rows: list[str] = []
    linenos: list[int] = []
    for no, ln in enumerate(lines[h + 1:], start=h + 2):
        if _is_comment(ln):
            continue
        if not ln.strip():
            raise fail("blank line inside the data (only trailing blank lines are allowed).", no)
        rows.append(ln)
        linenos.append(no)
    if not rows:
        raise fail("the header is not followed by any data rows; at least 2 samples are required.", header_line)
    if len(rows) == 1:
        raise fail("only one sample; at least 2 are required.", linenos[0])

    columns, empty = _parse_cells(rows, linenos, names, header_line, fail)

    # Extra columns are not checked: docs/formats.md says they are ignored (but kept).
    standard = [c for c in REQUIRED_COLUMNS + ("ps",) if c in columns]
    for name in standard:
        finite = np.isfinite(columns[name])
        bad = np.flatnonzero(~finite if name not in empty else ~finite & ~empty[name])
        if bad.size:
            i = int(bad[0])
            raise fail(f"{_cell_text(rows[i], names.index(name))!r} is not a finite number.", linenos[i], name)

    t = columns["t"]
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise fail(f"time {_cell_text(rows[i], names.index('t'))} s is not after the "
                   f"{_cell_text(rows[i - 1], names.index('t'))} s of line {linenos[i - 1]}; "
                   "times must be strictly increasing.", linenos[i], "t")

    odd = first_implausible(columns)
    if odd is not None:
        i = odd.index
        raise fail(f"{_cell_text(rows[i], names.index(odd.column))} {odd.reason}.", linenos[i], odd.column)
    why = time_unit_problem(t)
    if why is not None:
        raise fail(f"{why}.", linenos[-1], "t")

    return Run(
        t=columns["t"], u=columns["u"], x=columns["x"], p1=columns["p1"], p2=columns["p2"],
        ps=columns.get("ps"),
        extra={k: v for k, v in columns.items() if k not in standard},
        source=path,
        comments=tuple(ln.lstrip()[1:].strip() for ln in lines if _is_comment(ln)),
    )


def _read_lines(path: Path) -> list[str]:
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise RunFormatError(f"{path}: file not found.") from None
    except IsADirectoryError:
        raise RunFormatError(f"{path}: is a directory, not a run file.") from None
    except OSError as e:
        raise RunFormatError(f"{path}: cannot read the file ({e.strerror}).") from None
    if data.startswith(b"\xef\xbb\xbf"):  # spreadsheet programs like to add a UTF-8 BOM
        data = data[3:]
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        line = data.count(b"\n", 0, e.start) + 1
        raise RunFormatError(f"{path}, line {line}: not UTF-8 text (is this a CSV file?).") from None
    # Universal newlines, but only \n, \r\n and \r: str.splitlines would also split on
    # form feeds and the like and so shift the physical line numbers in messages.
    return text.replace("\r\n", "\n").replace("\r", "\n").split("\n")


def _is_comment(line: str) -> bool:
    return line.lstrip().startswith("#")


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
            raise fail(f"column '{name}' appears more than once in the header "
                       f"(columns {seen[name] + 1} and {j + 1}).", lineno)
        seen[name] = j
    missing = [c for c in REQUIRED_COLUMNS if c not in seen]
    if missing:
        what = "column" if len(missing) == 1 else "columns"
        found = ", ".join(repr(n) for n in names)
        raise fail(f"missing required {what} {', '.join(repr(c) for c in missing)} "
                   f"(the header has {found}); a recording with other columns or units converts with "
                   "'combined-reality import'.", lineno)
    return names


def _parse_cells(rows: list[str], linenos: list[int], names: list[str], header_line: int,
                 fail: _Fail) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Column name -> array (float64 for numeric columns, str for non-numeric extra columns),
    and for the measured channels with empty cells, where they are (read as NaN)."""
    ncol = len(names)
    # Fast path: numpy's C parser, valid only when every cell is a plain number.
    try:
        table = np.loadtxt(rows, delimiter=",", comments=None, quotechar=None, ndmin=2, dtype=np.float64)
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
        blank = None
        if name in MEASURED_CHANNELS:
            blank = np.fromiter((not s.strip() for s in col), bool, len(col))
            if blank.any():
                empty[name] = blank
            else:
                blank = None
        filled = col if blank is None else [s for s, b in zip(col, blank) if not b]
        try:  # C parser first; the Python loop below only runs to find what is wrong
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
                    raise fail(f"{s.strip()!r} is not a number.", linenos[i], name) from None
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


def write_run(path: str | os.PathLike[str], run: Run, comments: Sequence[str] | None = None) -> None:
    """Write ``run`` as CSV atomically (readers never see a partial file); round-trips exactly."""
    path = Path(path)
    names, cols = _columns_of(run)

    def parts():
        yield (_comment_lines(comments or ()) + _join(names) + "\n").encode("utf-8")
        for a in range(0, run.n, _WRITE_ROWS):
            formatted = [_format_column(name, col[a:a + _WRITE_ROWS]) for name, col in zip(names, cols)]
            yield "".join(",".join(row) + "\n" for row in zip(*formatted)).encode("utf-8")

    atomic_write(path, parts())


# rows formatted at a time: with the text of the whole run held, simulate --duration 3600 peaked at
# 2.66 GB (273 MB so)
_WRITE_ROWS = 1 << 16


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


def _cell(value: float | None) -> str:
    """A measured value as a cell: empty when it was not measured (None) or is not finite."""
    if value is None:
        return ""
    v = float(value)
    return repr(v) if math.isfinite(v) else ""


class RunRecorder:
    """Streams samples to a run CSV as they arrive, one complete line per ``append``.

    Each line goes to the OS in a single unbuffered write, so a crash or kill of the process
    leaves a file of whole lines that :func:`read_run` accepts (power loss is only covered up
    to the last :meth:`sync`). Values are written as given; :func:`read_run` checks them. A
    measured channel that is missing (None) or not finite is written as an empty cell (not
    measured at that sample); the time and the command must be finite.
    An existing file at ``path`` is replaced.
    """

    def __init__(self, path: str | os.PathLike[str], *, with_ps: bool = False,
                 comments: Sequence[str] | None = None) -> None:
        self.path = Path(path)
        self.with_ps = with_ps
        self.n = 0
        names = list(REQUIRED_COLUMNS) + (["ps"] if with_ps else [])
        self._f = open(self.path, "wb", buffering=0)
        try:
            self._write((_comment_lines(comments or ()) + _join(names) + "\n").encode("utf-8"))
        except BaseException:
            self._f.close()
            raise

    def append(self, t: float, u: float, x: float | None, p1: float | None, p2: float | None,
               ps: float | None = None) -> None:
        if self._f.closed:
            raise ValueError(f"RunRecorder for {self.path} is closed.")
        if ps is not None and not self.with_ps:
            raise ValueError(f"RunRecorder for {self.path} was opened with with_ps=False, but append got ps={ps!r}.")
        t, u = float(t), float(u)
        if not (math.isfinite(t) and math.isfinite(u)):
            raise ValueError(f"RunRecorder for {self.path}: the time and the command of a sample must be finite "
                             f"(got t={t!r}, u={u!r}).")
        cells = [repr(t), repr(u), _cell(x), _cell(p1), _cell(p2)]
        if self.with_ps:
            cells.append(_cell(ps))
        self._write((",".join(cells) + "\n").encode("ascii"))
        self.n += 1

    def sync(self) -> None:
        """Force the lines written so far onto the disk (survives power loss, costs a disk flush)."""
        if not self._f.closed:
            os.fsync(self._f.fileno())

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
        while view:
            written = self._f.write(view)
            view = view[written:]

    def __enter__(self) -> "RunRecorder":
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
