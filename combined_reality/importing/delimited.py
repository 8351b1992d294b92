"""Delimited text as DAQ programs write it: any one-character delimiter, a decimal point or
comma, a preamble before the column names, a units row after them. The standard csv module
splits lines one at a time (a quote left open cannot swallow the rest of the file); the
delimiter and the decimal mark are taken from [source] or found from the header and the data."""
from __future__ import annotations

import codecs
import csv
import hashlib
import itertools
import re
from pathlib import Path

import numpy as np

from sim.inputs import checked_size, is_utf8, line_breaks, shorten

from .mapping import ImportMapping, MappingError
from .raw import RawTable, require_column_time

__all__ = ["read_delimited", "DELIMITERS", "HEADER_SEARCH_LINES"]

DELIMITERS = (";", "\t", ",", "|")
HEADER_SEARCH_LINES = 500  # the column names must be within the first lines
_COMMA_DECIMAL = re.compile(r"^\s*[-+]?\d*,\d+([eE][-+]?\d+)?\s*$")


# bytes read (and hashed) at a time, data lines split and converted at a time, characters a
# line may have: a recording is read once, as a stream, and never held whole
_BLOCK = 1 << 20
_BATCH = 1 << 14
MAX_LINE = 1 << 20


class _NotUtf8(Exception):
    """The recording is not UTF-8 (without a declared encoding: read again as cp1252)."""


class _TooMany(Exception):
    """More data lines than a run may have rows."""


def read_delimited(path: Path, mapping: ImportMapping, max_rows: int | None = None) -> RawTable:
    """The mapped columns of delimited text, read once as a stream of lines (its sha256 taken
    as it is read: RawTable.digest); with `max_rows`, a recording of more data lines than that
    is refused as soon as it has them. Without a declared encoding UTF-8, else (a byte that is
    not) what Windows DAQ programs write, cp1252: the header must still match exactly."""
    require_column_time(mapping, "column")
    if mapping.source.encoding is not None:
        return _read(path, mapping, mapping.source.encoding, max_rows, fallback=False)
    try:
        return _read(path, mapping, "utf-8", max_rows, fallback=True)
    except _NotUtf8:
        return _read(path, mapping, "cp1252", max_rows, fallback=False)


def _read(path: Path, mapping: ImportMapping, encoding: str, max_rows: int | None, fallback: bool) -> RawTable:
    opts = mapping.source
    digest = hashlib.sha256()
    size = checked_size(path, "a recording", MappingError)  # a device or FIFO refused before it is opened
    try:
        f = open(path, "rb")
    except OSError as e:
        raise MappingError(f"{path}: cannot read it ({e.strerror or e}).") from None
    with f:
        lines = _Lines(f, path, encoding, digest, fallback)
        stream = iter(lines)
        head = list(itertools.islice(stream, opts.header_line or HEADER_SEARCH_LINES))
        wanted = mapping.source_names()
        header_index, delimiter = _find_header(path, head, wanted, opts.header_line, opts.delimiter)
        names = _split(head[header_index], delimiter)
        col_of = {name: names.index(name) for name in wanted}
        first = header_index + 2 + opts.skip_after_header  # the line of the first sample
        data = itertools.chain(head[first - 1:], stream)
        try:
            by_source = _columns(path, data, first, col_of, delimiter, opts.decimal, header_index + 1, max_rows,
                                 size)
        except _TooMany:
            for _ in stream:  # the rest counted, not split
                pass
            raise MappingError(f"{path}: {lines.lineno - (lines.last == '')} lines, more than the {max_rows} rows a "
                               f"run may have (--max-rows raises the limit).") from None
    decimal = by_source.pop(None)
    n = len(by_source[wanted[0]])
    if n < 2:
        raise MappingError(f"{path}: {n} data line(s) after the header on line {header_index + 1}; a run "
                           f"needs at least 2 samples.")
    columns = {ch.name: by_source[ch.source] for ch in mapping.channels}
    shown = {"\t": "tab"}.get(delimiter, repr(delimiter))
    return RawTable(columns=columns, locate=lambda i: f"line {first + i}",
                    describe=f"delimited text, header on line {header_index + 1}, delimiter {shown}, "
                             f"decimal {decimal!r}, encoding {encoding}", digest=digest.hexdigest())


class _Lines:
    """The lines of a recording in order (ending at \n, \r\n or a bare \r; the last one may lack
    its break), decoded a block of bytes at a time, each block hashed into `digest` as it is
    read. A UTF-8 byte order mark opening the file is dropped."""

    def __init__(self, f, path: Path, encoding: str, digest, fallback: bool):
        self.f, self.path, self.encoding, self.digest, self.fallback = f, path, encoding, digest, fallback
        self.lineno = 0  # lines given so far
        self.last: str | None = None  # the last one ('' where the file ends with a line break)

    def __iter__(self):
        decoder = codecs.getincrementaldecoder("utf-8-sig" if is_utf8(self.encoding) else self.encoding)("strict")
        carry = ""
        while True:
            block = self.f.read(_BLOCK)
            self.digest.update(block)
            final = not block
            try:
                text = decoder.decode(block, final=final)
            except UnicodeDecodeError as e:
                if self.fallback:
                    raise _NotUtf8() from None
                # e.object: the bytes the codec was decoding (held ones first, a byte order mark dropped)
                line = self.lineno + 1 + carry.endswith("\r") + line_breaks(bytes(e.object[:max(e.start, 0)]))
                raise MappingError(f"{self.path}, line {line}: not {self.encoding} text; set [source] encoding "
                                   f"to the file's (e.g. \"latin-1\").") from None
            if "\0" in text:
                raise MappingError(f"{self.path}: holds NUL bytes, so it is not delimited text; set [source] "
                                   f"format if it is another format.")
            text = carry + text
            hold = ""
            if not final and text.endswith("\r"):  # its \n may open the next block
                text, hold = text[:-1], "\r"
            parts = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
            carry = "" if final else parts.pop() + hold
            if len(text) > MAX_LINE:  # only then can a line be longer
                long = next((k for k, p in enumerate([*parts, carry]) if len(p) > MAX_LINE), None)
                if long is not None:
                    raise MappingError(f"{self.path}, line {self.lineno + long + 1}: longer than {MAX_LINE} "
                                       f"characters, so not a line of delimited text.")
            for line in parts:
                self.lineno += 1
                yield line
            if final:
                self.last = parts[-1]
                return


def _columns(path: Path, lines, first: int, col_of: dict[str, int], delimiter: str, decimal: str | None,
             header: int, max_rows: int | None, size: int) -> dict:
    """The mapped columns (source name -> values) of the data lines, numbered from `first`, a
    batch of lines at a time; under the key None the decimal mark (given, or found in the first
    batch). A blank line is refused where data follow it; trailing ones end the data. The
    columns are sized from the rows the first batch's line length foretells in `size` bytes."""
    need = max(col_of.values()) + 1
    cols = {name: np.empty(0) for name in col_of}  # sized at the first batch, grown by half if short
    n, blank = 0, None  # rows so far; the first blank line not yet followed by data
    batch: list[str] = []

    def flush() -> None:
        nonlocal decimal
        quoted = any('"' in r for r in batch)
        cells = [_split(r, delimiter) if quoted else r.split(delimiter) for r in batch]
        for k, c in enumerate(cells):
            if len(c) < need:
                missing = next(name for name, j in col_of.items() if j >= len(c))
                raise MappingError(f"{path}, line {first + n - len(batch) + k}: {len(c)} cells, so column "
                                   f"'{missing}' (cell {col_of[missing] + 1} of the header on line {header}) is "
                                   f"missing.")
        decimal = decimal or _decimal_mark(cells, col_of.values(), delimiter)
        at = n - len(batch)
        if n > cols[next(iter(cols))].size:  # the rows the bytes foretell at this batch's line length, at first
            foretold = size // (sum(map(len, batch)) // len(batch) + 1) + 1
            grow = max(n, cols[next(iter(cols))].size * 3 // 2, min(foretold + foretold // 50, max_rows or foretold))
        for name, j in col_of.items():
            if n > cols[name].size:
                grown = np.empty(grow)
                grown[:at] = cols[name][:at]
                cols[name] = grown
            cols[name][at:n] = _numbers(path, [c[j] for c in cells], first + at, name, decimal)
        batch.clear()

    for lineno, line in enumerate(lines, first):
        if not line.strip():
            blank = lineno if blank is None else blank
            continue
        if blank is not None:
            raise MappingError(f"{path}, line {blank}: blank line inside the data.")
        n += 1
        if max_rows is not None and n > max_rows:
            raise _TooMany()
        batch.append(line)
        if len(batch) == _BATCH:
            flush()
    if batch:
        flush()
    out: dict = {name: c[:n].copy() if c.size > n + n // 8 else c[:n] for name, c in cols.items()}
    out[None] = decimal or "."
    return out


def _split(line: str, delimiter: str) -> list[str]:
    return [c.strip() for c in next(csv.reader((line,), delimiter=delimiter), [])]


def _find_header(path: Path, lines: list[str], wanted: list[str], header_line: int | None,
                 delimiter: str | None) -> tuple[int, str]:
    """The header's index and the delimiter: the given ones, or the first line (and the first
    delimiter) whose cells name every mapped column."""
    candidates = (delimiter,) if delimiter else DELIMITERS
    if header_line is not None:
        if header_line > len(lines):
            raise MappingError(f"{path}: [source] header_line = {header_line}, but the file has {len(lines)} lines.")
        indices = [header_line - 1]
    else:
        indices = range(min(len(lines), HEADER_SEARCH_LINES))
    best: tuple[int, int, str] | None = None  # (names found, index, delimiter)
    for i in indices:
        for d in candidates:
            if d not in lines[i] and len(wanted) > 1:
                continue
            cells = _split(lines[i], d)
            found = sum(n in cells for n in wanted)
            if found == len(wanted):
                dup = next((n for n in wanted if cells.count(n) > 1), None)
                if dup is not None:
                    raise MappingError(f"{path}, line {i + 1}: column '{dup}' appears more than once in the header.")
                return i, d
            if found and (best is None or found > best[0]):
                best = (found, i, d)
    if best is None:
        where = f"line {header_line}" if header_line is not None else f"the first {len(indices)} lines"
        tried = "" if delimiter else f" with any delimiter of {' '.join(map(repr, DELIMITERS))}"
        raise MappingError(f"{path}: no line names the mapped columns ({', '.join(repr(n) for n in wanted)}) in "
                           f"{where}{tried}; check [columns] ... from = against the file's header.")
    _, i, d = best
    cells = _split(lines[i], d)
    missing = [n for n in wanted if n not in cells]
    raise MappingError(f"{path}, line {i + 1}: the header lacks {', '.join(repr(n) for n in missing)} (it has "
                       f"{shorten(', '.join(repr(c) for c in cells[:12]))}{' ...' if len(cells) > 12 else ''}).")


def _decimal_mark(cells: list[list[str]], cols, delimiter: str) -> str:
    if delimiter == ",":
        return "."
    for j in cols:
        for c in cells[:200]:
            if _COMMA_DECIMAL.match(c[j]):
                return ","
    return "."


def _numbers(path: Path, texts: list[str], line0: int, column: str, decimal: str) -> np.ndarray:
    """The cells of a column as numbers, the first on line `line0`; a bad one refused naming its
    line. Cells that are all plain numbers are converted at once (float's own parsing, as one
    by one), the others one by one to find the bad one."""
    joined = "\n".join(texts)  # no cell holds a line break
    if "_" not in joined and joined.isascii() and not (decimal == "," and "." in joined):
        try:
            out = np.array((joined.replace(",", ".") if decimal == "," else joined).split("\n"), dtype=np.float64)
        except ValueError:
            out = None
        if out is not None and np.isfinite(out).all():
            return out
    out = np.empty(len(texts))
    for i, s in enumerate(texts):
        cell = s.strip()
        if decimal == ",":
            if "." in cell and "," in cell:
                raise MappingError(f"{path}, line {line0 + i}, column '{column}': {shorten(cell)!r} has both a point "
                                   f"and a comma; thousands separators are not read (export without them).")
            cell = cell.replace(",", ".")
        if not cell:
            raise MappingError(f"{path}, line {line0 + i}, column '{column}': empty cell; every mapped channel needs "
                               f"a value in every row.")
        try:
            if "_" in cell or not cell.isascii():
                raise ValueError(cell)
            v = float(cell)
        except ValueError:
            hint = " (the decimal mark is ','? set [source] decimal = \",\")" if decimal == "." and "," in cell else ""
            raise MappingError(f"{path}, line {line0 + i}, column '{column}': {shorten(s.strip())!r} is not a number"
                               f"{hint}.") from None
        if not np.isfinite(v):
            raise MappingError(f"{path}, line {line0 + i}, column '{column}': {shorten(s.strip())!r} is not a "
                               "finite number.")
        out[i] = v
    return out
