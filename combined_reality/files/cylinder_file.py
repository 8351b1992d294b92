"""Writing a cylinder file back with new values, the user's own file kept: its comments (the
stated assumptions), order and layout stay; a changed value is replaced in place on its
own line (its comment kept); a key the file did not have is added at the end of its table,
with a comment saying where it came from; a missing table is added at the end.

The values are written in the file's units (the angle in degrees), each as the shortest
decimal that reads back as the same double (a written file loses nothing of what a fit
found); `load_cylinder` reads the result back (a test holds it to that). A changed value's
comment keeps what stays true (its unit, what it is) and loses what restated the old value
("(= 1 N/bar)", "(6 bar gauge)"): the writer cannot keep such a restatement true."""
from __future__ import annotations

import math
import os
import re
import tomllib
from dataclasses import MISSING, fields
from pathlib import Path
from typing import Sequence

from sim.cylinder import Cylinder, cylinder_to_toml

from .atomic import write_text_atomic

__all__ = ["cylinder_file_text", "write_cylinder_file"]

# the file's keys per table, as Cylinder holds them (section, attribute)
_KEYS = {"geometry": ("bore", "rod", "stroke", "dead_volume_cap", "dead_volume_rod"),
         "mechanics": ("moving_mass", "angle", "external_force", "end_stiffness", "end_damping"),
         "supply": ("pressure", "atmosphere", "temperature"),
         "valve": ("sonic_conductance", "critical_ratio", "overlap_extend", "overlap_retract", "flow_extend",
                   "flow_retract"),
         "friction": ("Fc", "Fv", "kp", "v_smooth"),
         "sensors": ("position_noise", "pressure_noise", "offset_p1", "offset_p2")}
_HEADER = re.compile(r"^\s*\[\s*([A-Za-z0-9_.\-]+)\s*\]\s*(#.*)?$")
_KEY = re.compile(r"^(\s*)([A-Za-z0-9_\-]+)(\s*=\s*)")
# in a value's comment, a restatement of the value: a parenthesis that opens with "=" or a number
_RESTATED = re.compile(r"\s*\(\s*(?:=|[-+]?\.?\d)[^()]*\)")


def _number(v: float) -> str:
    """A float that TOML reads back exactly (the shortest repr): a written file loses nothing."""
    return repr(float(v))


def _render(value) -> str:
    if isinstance(value, tuple):
        return "[" + ", ".join(_number(x) for x in value) + "]"
    return _number(value)


def _file_values(cyl: Cylinder) -> dict[tuple[str, str], object]:
    out = {}
    for section, keys in _KEYS.items():
        obj = getattr(cyl, section)
        for key in keys:
            v = getattr(obj, key)
            if (section, key) == ("mechanics", "angle"):
                v = math.degrees(v)
            out[(section, key)] = tuple(float(x) for x in v) if isinstance(v, tuple) else float(v)
    return out


def _defaults(cyl: Cylinder) -> dict[tuple[str, str], object]:
    """What the loader assumes for a key the file leaves out."""
    return {(section, f.name): f.default for section in _KEYS for f in fields(getattr(cyl, section))
            if f.default is not MISSING}


def _same(a, b) -> bool:
    if isinstance(a, tuple) or isinstance(b, tuple):
        return isinstance(a, tuple) and isinstance(b, tuple) and len(a) == len(b) and all(map(_same, a, b))
    return math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=0.0)


def _value_span(lines: list[str], i: int, start: int) -> tuple[int, int]:
    """(last line index, column where the value ends on it) of the value starting at
    lines[i][start:]: a number, or an array that may run over several lines."""
    depth, j, col = 0, i, start
    while True:
        line = lines[j]
        while col < len(line):
            c = line[col]
            if c == "#" and depth == 0:
                return j, col
            if c == "[":
                depth += 1
            elif c == "]":
                depth -= 1
                if depth == 0:
                    return j, col + 1
            col += 1
        if depth == 0 or j + 1 >= len(lines):
            return j, len(line)
        j, col = j + 1, 0


def cylinder_file_text(cyl: Cylinder, template: str | None = None, note: str = "",
                       header: Sequence[str] = ()) -> str:
    """TOML text of `cyl`: `template` (the user's file; default: the file `cyl` was loaded
    from, else the plain layout) with every value of `cyl` that differs replaced, and what the
    template lacks added with the comment `note`; `header` lines are put on top as comments."""
    if template is None:
        template = _source_text(cyl)
    values, defaults = _file_values(cyl), _defaults(cyl)
    lines = template.splitlines()
    out: list[str] = []
    table, seen = "", set()
    last_key: dict[str, int] = {}  # table -> index in `out` of its last key line (or its header)
    i = 0
    while i < len(lines):
        line = lines[i]
        m = _HEADER.match(line)
        if m:
            table = m.group(1)
            out.append(line)
            last_key[table] = len(out) - 1
            i += 1
            continue
        k = _KEY.match(line)
        if k and (table, k.group(2)) in values:
            key = k.group(2)
            seen.add((table, key))
            j, end = _value_span(lines, i, k.end())
            tail = lines[j][end:]
            new = values[(table, key)]
            written = "\n".join([lines[i][k.end():], *lines[i + 1:j + 1]]) if j > i else lines[i][k.end():end]
            if _same(new, _parse_number_or_array(written)):
                out.extend(lines[i:j + 1])
            else:
                tail = _without_restatement(tail)
                out.append(k.group(1) + key + k.group(3) + _render(new) + (" " + tail.lstrip() if tail.strip() else ""))
            last_key[table] = len(out) - 1
            i = j + 1
            continue
        if k:
            last_key[table] = len(out)
        out.append(line)
        i += 1
    # keys the file does not have: at the end of their table, or in a new table at the end
    added: dict[str, list[str]] = {}
    for (section, key), new in values.items():
        if (section, key) in seen or _same(new, defaults.get((section, key), math.nan)):
            continue  # a default the file leaves out, it means exactly that
        comment = f"  # {note}" if note else ""
        added.setdefault(section, []).append(f"{key} = {_render(new)}{comment}")
    for section in sorted((s for s in added if s in last_key), key=lambda s: -last_key[s]):
        at = last_key[section] + 1
        out[at:at] = added.pop(section)
    for section, new_lines in added.items():
        out.extend(["", f"[{section}]", *new_lines])
    text = "\n".join(out) + "\n"
    if header:
        text = "".join(f"# {line}".rstrip() + "\n" for line in header) + "\n" + text
    return text


def _without_restatement(comment: str) -> str:
    """A changed value's trailing comment without what restated the old value; nothing left
    of it but '#' drops it."""
    kept = _RESTATED.sub("", comment).rstrip()
    return "" if kept.strip() in ("", "#") else kept


def _parse_number_or_array(text: str):
    """The value of a number or array as written in the file (for comparing), else NaN."""
    try:
        v = tomllib.loads("v = " + "\n".join(ln.split("#", 1)[0] for ln in text.splitlines()).strip())["v"]
    except (tomllib.TOMLDecodeError, KeyError):
        return math.nan
    if isinstance(v, list):
        return tuple(float(x) for x in v if isinstance(x, (int, float)))
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else math.nan


def _source_text(cyl: Cylinder) -> str:
    if cyl.source is not None:
        try:
            return Path(cyl.source).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError):
            pass
    return cylinder_to_toml(cyl)


def write_cylinder_file(path: str | os.PathLike[str], cyl: Cylinder, note: str = "",
                        header: Sequence[str] = (), template: str | None = None) -> None:
    """Write `cyl` atomically as a cylinder file (cylinder_file_text)."""
    write_text_atomic(path, cylinder_file_text(cyl, template=template, note=note, header=header))
