"""The mapping file of `import` (docs/formats.md, "The mapping file"): for each run channel
its source column, its unit, whether a pressure is gauge, and for the command a linear map.

    [source]                       # all optional
    format = "csv"                 # csv, parquet, mat, tdms, mdf, can (default: from the file's suffix)
    delimiter = ";"                # delimited text: detected from the header if absent
    decimal = ","                  # delimited text: "." or ","; detected if absent
    encoding = "utf-8"             # delimited text (default: UTF-8, else Windows-1252)
    header_line = 1                # delimited text: line of the column names (default: the first
                                   # line that names every mapped column)
    skip_after_header = 0          # delimited text: lines between the header and the data (a units row)
    dbc = "rig.dbc"                # CAN logs: the database that decodes the frames (relative to this file)
    [columns]
    t  = { from = "Zeit [ms]", unit = "ms" }            # or { time_of = "CHANNEL" }: its time track
    u  = { from = "Ventil [V]", unit = "V", zero = 5.0, span = 5.0 }    # u = (value - zero) / span
    x  = { from = "Weg [mm]", unit = "mm", zero = 2.0 }                  # zero: subtracted first
    p1 = { from = "P_A [bar]", unit = "bar", gauge = true }
    p2 = { from = "P_B [V]", unit = "V", scale = "2 bar/V", gauge = true }   # scale: a sensor's gain
    T1 = { from = "Temp [°C]", unit = "degC" }           # any other name: an extra column, in SI
    [atmosphere]
    pressure = 101300.0            # Pa (or a quantity, "1013 mbar"): added to gauge readings

Loading refuses anything it cannot use with one sentence naming the file and the key
(MappingError); units are checked against what each channel measures here already.
"""
from __future__ import annotations

import math
import os
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sim.inputs import TOML_MAX_BYTES, decode_text, parse_toml, read_checked, shorten

from ..errors import InputError
from .units import UnitProblem, check_unit, quantity_in

__all__ = ["MappingError", "SOURCE_FORMATS", "SourceOptions", "ChannelMap", "ImportMapping", "load_mapping",
           "parse_mapping", "format_of"]


class MappingError(InputError):
    """A mapping file (or a recording read through it) that cannot be used; one sentence
    naming the file and the key, line or channel (exit status 2)."""


# file suffix -> format
SOURCE_FORMATS: dict[str, tuple[str, ...]] = {
    "csv": (".csv", ".txt", ".dat", ".tsv"),
    "parquet": (".parquet", ".pq"),
    "mat": (".mat",),
    "tdms": (".tdms",),
    "mdf": (".mf4", ".mdf"),
    "can": (".asc", ".blf", ".log", ".trc"),
}
_SOURCE_KEYS = {"format", "delimiter", "decimal", "encoding", "header_line", "skip_after_header", "dbc"}
_CHANNEL_KEYS = {"from", "time_of", "unit", "zero", "span", "scale", "gauge"}
# what each run channel measures: the unit must have this dimension (u: none, after its map)
_DIMENSION = {"t": "[time]", "x": "[length]", "p1": "[pressure]", "p2": "[pressure]", "ps": "[pressure]",
              "u": "dimensionless"}
REQUIRED = ("t", "u", "x", "p1", "p2")
PRESSURES = ("p1", "p2", "ps")


@dataclass(frozen=True)
class SourceOptions:
    format: str | None = None
    delimiter: str | None = None
    decimal: str | None = None
    encoding: str | None = None  # None: UTF-8, else Windows-1252 (what Windows DAQ programs write)
    header_line: int | None = None
    skip_after_header: int = 0
    dbc: Path | None = None


@dataclass(frozen=True)
class ChannelMap:
    """How one run channel comes from the recording:
    value = (raw - zero) * scale  (measured channels, then gauge + atmosphere),
    u = (raw - zero) / span       (the command)."""

    name: str  # the run's column: t, u, x, p1, p2, ps or an extra column
    source: str | None  # the recording's column or channel (None with time_of)
    unit: str  # unit of the raw values ("" = dimensionless)
    time_of: str | None = None  # t only: the time track of this channel
    zero: float = 0.0
    span: float | None = None  # u only
    scale: str | None = None  # a quantity that turns `unit` into a physical one, e.g. "25 mm/V"
    gauge: bool = False  # pressures only

    @property
    def key(self) -> str:
        return f"columns.{self.name}"


@dataclass(frozen=True)
class ImportMapping:
    source: SourceOptions
    channels: tuple[ChannelMap, ...]  # t, u, x, p1, p2 first, then ps and extras in file order
    atmosphere: float | None  # Pa, for gauge channels
    path: Path | None = None

    def channel(self, name: str) -> ChannelMap | None:
        return next((c for c in self.channels if c.name == name), None)

    def source_names(self) -> list[str]:
        """The recording's columns the mapping reads (time_of channels included), in order."""
        names = [c.source if c.source is not None else c.time_of for c in self.channels]
        return list(dict.fromkeys(n for n in names if n is not None))


def format_of(path: Path, options: SourceOptions) -> str:
    """The recording's format: [source] format, else from the suffix."""
    if options.format is not None:
        return options.format
    suffix = path.suffix.lower()
    for fmt, suffixes in SOURCE_FORMATS.items():
        if suffix in suffixes:
            return fmt
    raise MappingError(f"{path}: cannot tell the format from the suffix '{path.suffix}'; set [source] format "
                       f"to one of {', '.join(SOURCE_FORMATS)}.")


def load_mapping(path: str | os.PathLike[str]) -> ImportMapping:
    path = Path(path)
    text = decode_text(read_checked(path, "a mapping file", MappingError, TOML_MAX_BYTES),
                       lambda _, byte: MappingError(f"{path}: not UTF-8 text at byte {byte} (a mapping file is TOML)."))
    try:
        data = parse_toml(text)
    except tomllib.TOMLDecodeError as e:
        raise MappingError(f"{path}: not valid TOML ({e}).") from None
    return parse_mapping(data, path)


def parse_mapping(data: dict[str, Any], path: Path | None = None) -> ImportMapping:
    where = str(path) if path is not None else "<mapping>"

    def fail(msg: str) -> MappingError:
        return MappingError(f"{where}: {msg}")

    unknown = set(data) - {"source", "columns", "atmosphere"}
    if unknown:
        raise fail(f"unknown table or key '{shorten(sorted(unknown)[0])}' (expected [source], [columns], "
                   "[atmosphere]).")
    source = _source(_table(data, "source", fail), path, fail)
    columns = data.get("columns")
    if not isinstance(columns, dict) or not columns:
        raise fail("missing table [columns] naming where t, u, x, p1 and p2 come from.")
    missing = [c for c in REQUIRED if c not in columns]
    if missing:
        raise fail(f"[columns] lacks {', '.join(missing)} (a run needs t, u, x, p1, p2).")
    channels = [_channel(name, columns[name], fail) for name in (*REQUIRED, *(n for n in columns if n not in REQUIRED))]
    atmosphere = None
    atm = _table(data, "atmosphere", fail)
    unknown = set(atm) - {"pressure"}
    if unknown:
        raise fail(f"unknown key 'atmosphere.{shorten(sorted(unknown)[0])}' (expected pressure).")
    if "pressure" in atm:
        atmosphere = _pressure_value(atm["pressure"], "atmosphere.pressure", fail)
        if not 5e4 <= atmosphere <= 1.2e5:
            raise fail(f"key 'atmosphere.pressure' must be the absolute atmospheric pressure in Pa (about 101325), "
                       f"not {atmosphere:g}.")
    gauge = [c.name for c in channels if c.gauge]
    if gauge and atmosphere is None:
        raise fail(f"{', '.join(gauge)} {'is' if len(gauge) == 1 else 'are'} gauge, so the mapping needs "
                   f"[atmosphere] pressure = ... (Pa, about 101325) to make them absolute.")
    return ImportMapping(source=source, channels=tuple(channels), atmosphere=atmosphere, path=path)


def _table(data: dict, key: str, fail) -> dict:
    value = data.get(key, {})
    if not isinstance(value, dict):
        raise fail(f"key '{key}' must be a table [{key}].")
    return value


def _source(src: dict, path: Path | None, fail) -> SourceOptions:
    unknown = set(src) - _SOURCE_KEYS
    if unknown:
        raise fail(f"unknown key 'source.{shorten(sorted(unknown)[0])}' (expected one of "
                   f"{', '.join(sorted(_SOURCE_KEYS))}).")
    kw: dict[str, Any] = {}
    fmt = src.get("format")
    if fmt is not None:
        if fmt not in SOURCE_FORMATS:
            raise fail(f"key 'source.format' must be one of {', '.join(SOURCE_FORMATS)}, not {shorten(repr(fmt))}.")
        kw["format"] = fmt
    delimiter = src.get("delimiter")
    if delimiter is not None:
        if not isinstance(delimiter, str) or len(delimiter) != 1 or delimiter in "\r\n\"" or delimiter.isalnum():
            raise fail(f"key 'source.delimiter' must be one character such as \";\", \",\" or \"\\t\", "
                       f"not {shorten(repr(delimiter))}.")
        kw["delimiter"] = delimiter
    decimal = src.get("decimal")
    if decimal is not None:
        if decimal not in (".", ","):
            raise fail(f"key 'source.decimal' must be \".\" or \",\", not {shorten(repr(decimal))}.")
        if decimal == delimiter:
            raise fail("keys 'source.decimal' and 'source.delimiter' are the same character; a number could not "
                       "be told from the next cell.")
        kw["decimal"] = decimal
    encoding = src.get("encoding")
    if encoding is not None:
        import codecs

        try:
            if not isinstance(encoding, str):
                raise LookupError
            codecs.lookup(encoding)
        except LookupError:
            raise fail(f"key 'source.encoding' names no known text encoding: {shorten(repr(encoding))} "
                       f"(e.g. \"utf-8\", "
                       f"\"cp1252\", \"latin-1\").") from None
        kw["encoding"] = encoding
    for key, low in (("header_line", 1), ("skip_after_header", 0)):
        v = src.get(key)
        if v is not None:
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise fail(f"key 'source.{key}' must be a whole number >= {low}, not {shorten(repr(v))}.")
            kw[key] = v
    dbc = src.get("dbc")
    if dbc is not None:
        if not isinstance(dbc, str) or not dbc.strip():
            raise fail("key 'source.dbc' must name a DBC file (relative to the mapping file).")
        kw["dbc"] = (path.parent / dbc) if path is not None else Path(dbc)
    return SourceOptions(**kw)


def _channel(name: str, spec: Any, fail) -> ChannelMap:
    key = f"columns.{name}"
    if not isinstance(spec, dict):
        raise fail(f"key '{key}' must be a table such as {{ from = \"column\", unit = \"s\" }}, "
                   f"not {shorten(repr(spec))}.")
    unknown = set(spec) - _CHANNEL_KEYS
    if unknown:
        raise fail(f"unknown key '{key}.{shorten(sorted(unknown)[0])}' (expected {', '.join(sorted(_CHANNEL_KEYS))}).")
    source, time_of = spec.get("from"), spec.get("time_of")
    if time_of is not None and name != "t":
        raise fail(f"key '{key}.time_of' is for t only (the time track of a channel).")
    if (source is None) == (time_of is None):
        raise fail(f"key '{key}' needs exactly one of from = \"column\"" + (" or time_of = \"channel\"."
                                                                            if name == "t" else "."))
    text = source if source is not None else time_of
    if not isinstance(text, str) or not text.strip():
        raise fail(f"key '{key}.{'from' if source is not None else 'time_of'}' must be a non-empty string.")
    unit = spec.get("unit", "s" if time_of is not None else None)
    if unit is None:
        if name != "u":
            raise fail(f"key '{key}.unit' is missing: say what unit '{text}' is recorded in (e.g. "
                       f"{_EXAMPLE_UNITS.get(name, 'V')}).")
        unit = ""
    if not isinstance(unit, str):
        raise fail(f"key '{key}.unit' must be a unit as text, such as \"ms\", \"mm\" or \"bar\", "
                   f"not {shorten(repr(unit))}.")
    zero = spec.get("zero", 0.0)
    if isinstance(zero, bool) or not isinstance(zero, (int, float)) or not math.isfinite(zero):
        raise fail(f"key '{key}.zero' must be a finite number in the channel's unit, not {shorten(repr(zero))}.")
    span = spec.get("span")
    if span is not None and name != "u":
        raise fail(f"key '{key}.span' is for the command u only (use scale for a sensor's gain).")
    if span is not None and (isinstance(span, bool) or not isinstance(span, (int, float)) or not math.isfinite(span)
                             or span == 0):
        raise fail(f"key '{key}.span' must be a non-zero number: the change of the raw value from centre to full "
                   f"opening, not {shorten(repr(span))}.")
    scale = spec.get("scale")
    if scale is not None and name in ("u", "t"):
        raise fail(f"key '{key}.scale' is for measured channels (x, p1, p2, ps, extras); "
                   + ("map the command with zero and span." if name == "u" else "give the time's unit."))
    if scale is not None and not isinstance(scale, str):
        raise fail(f"key '{key}.scale' must be a quantity as text such as \"25 mm/V\", not {shorten(repr(scale))}.")
    gauge = spec.get("gauge", False)
    if not isinstance(gauge, bool):
        raise fail(f"key '{key}.gauge' must be true or false, not {shorten(repr(gauge))}.")
    if gauge and name not in PRESSURES:
        raise fail(f"key '{key}.gauge' is for the pressures p1, p2, ps only.")
    channel = ChannelMap(name=name, source=source, unit=unit, time_of=time_of, zero=float(zero),
                         span=None if span is None else float(span), scale=scale, gauge=gauge)
    try:
        check_unit(channel.unit, channel.scale, _DIMENSION.get(name), channel.span is not None)
    except UnitProblem as e:
        raise fail(f"key '{key}': {e}") from None
    return channel


_EXAMPLE_UNITS = {"t": "\"s\" or \"ms\"", "x": "\"m\" or \"mm\"", "p1": "\"Pa\", \"kPa\", \"bar\" or \"psi\"",
                  "p2": "\"Pa\", \"kPa\", \"bar\" or \"psi\"", "ps": "\"Pa\", \"kPa\", \"bar\" or \"psi\""}


def _pressure_value(value: Any, key: str, fail) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise fail(f"key '{key}' must be a number in Pa or a quantity such as \"1013 mbar\", "
                   f"not {shorten(repr(value))}.")
    if isinstance(value, str):
        try:
            return quantity_in(value, "Pa")
        except UnitProblem as e:
            raise fail(f"key '{key}': {e}") from None
    v = float(value)
    if not math.isfinite(v):
        raise fail(f"key '{key}' must be finite, not {v}.")
    return v
