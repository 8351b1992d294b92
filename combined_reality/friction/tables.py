"""Points tables: a CSV with columns v,F (m/s, N; both directions in one file, the sign
of v gives the direction), optionally F_std, count, dp, pc, load, and `breakaway` (1 marks
a breakaway force, the static end of the map, as `procedure breakaway` writes it; 0 or
no column: a sliding point).
"""
from __future__ import annotations

import math
import os
from pathlib import Path

from sim.inputs import InputFileError, regular_file_size, shorten

from ..files.plausibility import MAX_ABS_PRESSURE
from .points import MapPoint
from .specs import PointsFormatError

__all__ = ["is_points_table", "read_points"]


_TABLE_OPTIONAL = ("F_std", "v_std", "count", "dp", "pc", "load", "breakaway")
_MAX_SPEED = 10.0  # m/s: above this, v is not in m/s


_POINTS_MAX_BYTES = 64 << 20  # a points table: a point per constant-speed stroke, far below this
_MAX_FORCE = 1.0e6  # N: beyond any pneumatic cylinder (a 320 mm bore at 10 bar makes 80 kN)
_POINTS_MAX_LINE = 1 << 16  # characters


def _lines(path: Path, limit: int | None = _POINTS_MAX_BYTES):
    """The file's lines, lazily; missing, unreadable or special files (a device, a FIFO:
    refused before opening), files beyond `limit` bytes and overlong lines in one sentence."""
    try:
        regular_file_size(path, "a points table" if limit else "a points table or run", limit)
        with open(path, encoding="utf-8-sig") as f:
            for n, line in enumerate(f, 1):
                if len(line) > _POINTS_MAX_LINE:
                    raise PointsFormatError(f"{path}: line {n} is longer than {_POINTS_MAX_LINE} characters.")
                yield line.rstrip("\r\n")
    except InputFileError as e:
        raise PointsFormatError(str(e)) from None
    except FileNotFoundError:
        raise PointsFormatError(f"{path}: file not found.") from None
    except (OSError, UnicodeDecodeError) as e:
        raise PointsFormatError(f"{path}: cannot be read ({shorten(str(e))}).") from None


def _is_data(line: str) -> bool:
    return bool(line.strip()) and not line.lstrip().startswith("#")


def is_points_table(path: str | os.PathLike[str]) -> bool:
    """A points table has v and F in its header (a run has t,u,x,p1,p2); reads up to the header."""
    header = next((line for line in _lines(Path(path), None) if _is_data(line)), None)
    cells = [c.strip() for c in header.split(",")] if header is not None else []
    return "v" in cells and "F" in cells


def read_points(path: str | os.PathLike[str]) -> list[MapPoint]:
    """Points of a CSV table with columns v,F (m/s, N), optionally F_std, v_std, count, dp,
    pc, load, breakaway (1: a breakaway force, 0: a sliding point); `#` lines are comments,
    other columns are ignored."""
    path = Path(path)
    lines = list(_lines(path))
    hline = next((n for n, line in enumerate(lines, 1) if _is_data(line)), None)
    if hline is None:
        raise PointsFormatError(f"{path}: the file is empty (a points table needs a header v,F and rows).")
    header = [c.strip() for c in lines[hline - 1].split(",")]
    if len(set(header)) != len(header):
        dup = next(c for c in header if header.count(c) > 1)
        raise PointsFormatError(f"{path}: line {hline}: column '{shorten(dup)}' appears twice in the header.")
    for col in ("v", "F"):
        if col not in header:
            raise PointsFormatError(f"{path}: line {hline}: the header has no column '{col}' "
                                    f"(a points table needs columns v,F in m/s and N).")
    cols = {c: header.index(c) for c in ("v", "F", *_TABLE_OPTIONAL) if c in header}
    points = []
    for n in range(hline + 1, len(lines) + 1):
        line = lines[n - 1]
        if not _is_data(line):
            continue
        cells = [c.strip() for c in line.split(",")]
        if len(cells) != len(header):
            raise PointsFormatError(f"{path}: line {n} has {len(cells)} cells but the header has {len(header)}.")
        vals = {}
        for c, j in cols.items():
            try:
                x = float(cells[j])
            except ValueError:
                raise PointsFormatError(f"{path}: line {n}, column '{c}': '{shorten(cells[j])}' is not a "
                                        "number.") from None
            if not math.isfinite(x):
                raise PointsFormatError(f"{path}: line {n}, column '{c}': '{shorten(cells[j])}' is not a finite "
                                        "number.")
            vals[c] = x
        for c in ("F_std", "v_std", "dp", "load"):
            if vals.get(c, 0.0) < 0:
                raise PointsFormatError(f"{path}: line {n}, column '{c}': {shorten(cells[cols[c]])} is negative; "
                                        f"{'a spread' if c.endswith('_std') else 'it'} cannot be.")
        for c in ("F", "F_std", "load"):
            if abs(vals.get(c, 0.0)) > _MAX_FORCE:
                raise PointsFormatError(f"{path}: line {n}, column '{c}': {shorten(cells[cols[c]])} N is beyond any "
                                        f"pneumatic cylinder's force ({_MAX_FORCE:g} N); F is in N.")
        for c in ("dp", "pc"):
            if abs(vals.get(c, 0.0)) > MAX_ABS_PRESSURE:
                raise PointsFormatError(f"{path}: line {n}, column '{c}': {shorten(cells[cols[c]])} Pa is beyond any "
                                        f"pneumatic pressure ({MAX_ABS_PRESSURE:g} Pa); pressures are in Pa.")
        if vals["v"] == 0.0:
            raise PointsFormatError(f"{path}: line {n}, column 'v': v = 0 has no direction "
                                    f"(extension v > 0, retraction v < 0).")
        if abs(vals["v"]) > _MAX_SPEED:
            raise PointsFormatError(f"{path}: line {n}, column 'v': {shorten(cells[cols['v']])} m/s is implausibly "
                                    f"fast (v must be in m/s, not mm/s).")
        if "count" in vals and (vals["count"] < 1 or vals["count"] != int(vals["count"])):
            raise PointsFormatError(f"{path}: line {n}, column 'count': {shorten(cells[cols['count']])} is not a "
                                    f"positive whole number.")
        if vals.get("breakaway", 0.0) not in (0.0, 1.0):
            raise PointsFormatError(f"{path}: line {n}, column 'breakaway': {shorten(cells[cols['breakaway']])} is "
                                    f"neither 1 (a breakaway force) nor 0 (a sliding point).")
        points.append(MapPoint(v=vals["v"], F=vals["F"], F_std=vals.get("F_std", math.nan),
                               v_std=vals.get("v_std", math.nan), count=int(vals.get("count", 1)),
                               dp=vals.get("dp", math.nan), pc=vals.get("pc", math.nan),
                               load=vals.get("load", math.nan), source=str(path),
                               breakaway=vals.get("breakaway", 0.0) == 1.0))
    if not points:
        raise PointsFormatError(f"{path}: no points after the header (a points table needs rows v,F).")
    return points
