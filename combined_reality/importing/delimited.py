"""Delimited text as DAQ programs write it: any one-character delimiter, a decimal point or
comma, a preamble before the column names, a units row after them. The standard csv module
splits lines one at a time (a quote left open cannot swallow the rest of the file); the
delimiter and the decimal mark are taken from [source] or found from the header and the data."""
from __future__ import annotations

import csv
import re
from pathlib import Path

import numpy as np

from sim.inputs import decode_text, line_breaks, read_checked, shorten

from .mapping import ImportMapping, MappingError
from .raw import RawTable, require_column_time

__all__ = ["read_delimited", "DELIMITERS", "HEADER_SEARCH_LINES"]

DELIMITERS = (";", "\t", ",", "|")
HEADER_SEARCH_LINES = 500  # the column names must be within the first lines
_COMMA_DECIMAL = re.compile(r"^\s*[-+]?\d*,\d+([eE][-+]?\d+)?\s*$")


def read_delimited(path: Path, mapping: ImportMapping, max_rows: int | None = None) -> RawTable:
    """The mapped columns of delimited text; with `max_rows`, a file of more lines than that
    (and the header's search) is refused before its text is split."""
    opts = mapping.source
    require_column_time(mapping, "column")
    lines, encoding = _lines(path, opts.encoding, max_rows)
    wanted = mapping.source_names()
    header_index, delimiter = _find_header(path, lines, wanted, opts.header_line, opts.delimiter)
    names = _split(lines[header_index], delimiter)
    col_of = {name: names.index(name) for name in wanted}
    start = header_index + 1 + opts.skip_after_header
    while lines and not lines[-1].strip():
        lines.pop()
    rows, linenos = [], []
    for i in range(start, len(lines)):
        if not lines[i].strip():
            raise MappingError(f"{path}, line {i + 1}: blank line inside the data.")
        rows.append(lines[i])
        linenos.append(i + 1)
    if len(rows) < 2:
        raise MappingError(f"{path}: {len(rows)} data line(s) after the header on line {header_index + 1}; a run "
                           f"needs at least 2 samples.")
    quoted = any('"' in r for r in rows)
    cells = [_split(r, delimiter) if quoted else r.split(delimiter) for r in rows]
    need = max(col_of.values()) + 1
    for c, no in zip(cells, linenos):
        if len(c) < need:
            missing = next(n for n, j in col_of.items() if j >= len(c))
            raise MappingError(f"{path}, line {no}: {len(c)} cells, so column '{missing}' (cell {col_of[missing] + 1} "
                               f"of the header on line {header_index + 1}) is missing.")
    decimal = opts.decimal or _decimal_mark(cells, col_of.values(), delimiter)
    by_source = {name: _numbers(path, [c[j] for c in cells], linenos, name, decimal) for name, j in col_of.items()}
    columns = {ch.name: by_source[ch.source] for ch in mapping.channels}
    shown = {"\t": "tab"}.get(delimiter, repr(delimiter))
    return RawTable(columns=columns, locate=lambda i: f"line {linenos[i]}",
                    describe=f"delimited text, header on line {header_index + 1}, delimiter {shown}, "
                             f"decimal {decimal!r}, encoding {encoding}")


def _lines(path: Path, encoding: str | None, max_rows: int | None) -> tuple[list[str], str]:
    data = read_checked(path, "a recording", MappingError, None)  # its size bounded by import_recording
    lines = line_breaks(data) + (not data.endswith((b"\n", b"\r")))
    if max_rows is not None and lines > max_rows + HEADER_SEARCH_LINES:
        raise MappingError(f"{path}: {lines} lines, more than the {max_rows} rows a run may have (--max-rows "
                           "raises the limit).")
    if encoding is None:  # UTF-8, else what Windows DAQ programs write (the header must still match exactly)
        try:
            return _text_lines(path, decode_text(data)), "utf-8"
        except UnicodeDecodeError:
            encoding = "cp1252"
    text = decode_text(data, lambda line, _: MappingError(f"{path}, line {line}: not {encoding} text; set [source] "
                                                          f"encoding to the file's (e.g. \"latin-1\")."), encoding)
    return _text_lines(path, text), encoding


def _text_lines(path: Path, text: str) -> list[str]:
    if "\0" in text:
        raise MappingError(f"{path}: holds NUL bytes, so it is not delimited text; set [source] format if it is "
                           f"another format.")
    return text.replace("\r\n", "\n").replace("\r", "\n").split("\n")


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


def _numbers(path: Path, texts: list[str], linenos: list[int], column: str, decimal: str) -> np.ndarray:
    out = np.empty(len(texts))
    for i, s in enumerate(texts):
        cell = s.strip()
        if decimal == ",":
            if "." in cell and "," in cell:
                raise MappingError(f"{path}, line {linenos[i]}, column '{column}': {shorten(cell)!r} has both a point "
                                   f"and a comma; thousands separators are not read (export without them).")
            cell = cell.replace(",", ".")
        if not cell:
            raise MappingError(f"{path}, line {linenos[i]}, column '{column}': empty cell; every mapped channel needs "
                               f"a value in every row.")
        try:
            if "_" in cell or not cell.isascii():
                raise ValueError(cell)
            v = float(cell)
        except ValueError:
            hint = " (the decimal mark is ','? set [source] decimal = \",\")" if decimal == "." and "," in cell else ""
            raise MappingError(f"{path}, line {linenos[i]}, column '{column}': {shorten(s.strip())!r} is not a number"
                               f"{hint}.") from None
        if not np.isfinite(v):
            raise MappingError(f"{path}, line {linenos[i]}, column '{column}': {shorten(s.strip())!r} is not a "
                               "finite number.")
        out[i] = v
    return out
