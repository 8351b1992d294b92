"""Numbers for people: significant digits, the units an engineer reads (um, mm/s, N/bar,
kPa, ms), and a value with its standard deviation to the precision the std supports.
Shared by every report, the console and the Rerun views; the data themselves stay SI."""
from __future__ import annotations

import math

__all__ = ["finite", "sig", "um", "pct", "DISPLAY_UNITS", "display_unit", "format_value"]


def finite(v) -> bool:
    try:
        return v is not None and math.isfinite(float(v))
    except (TypeError, ValueError):
        return False


def sig(v: float, digits: int = 3) -> str:
    """A number to `digits` significant digits, without exponent for ordinary magnitudes."""
    if not finite(v):
        return "n/a"
    v = float(v)
    if v == 0:
        return "0"
    mag = math.floor(math.log10(abs(v)))
    if mag < -3 or mag >= 6:
        return f"{v:.{digits - 1}e}"
    return f"{v:.{max(0, digits - 1 - mag)}f}"


def um(m: float) -> str:
    return f"{sig(float(m) * 1e6)} um" if finite(m) else "n/a"


def pct(s: float) -> str:
    if not finite(s):
        return "n/a"
    s = 100.0 * float(s)
    return f"{s:.1f} %" if 99 <= abs(s) < 100 or abs(s) < 1 else f"{s:.0f} %"


# the parameters' SI units, shown in the unit an engineer reads them in
DISPLAY_UNITS: dict[str, tuple[str, float]] = {
    "N/Pa": ("N/bar", 1e5),
    "m/s": ("mm/s", 1e3),
    "m^3/(s Pa)": ("m³/(s·Pa)", 1.0),
    "W/(m^2 K)": ("W/(m²·K)", 1.0),
    "1": ("", 1.0),
}


def display_unit(unit: str, value: float) -> tuple[str, float]:
    if unit == "s":
        return ("ms", 1e3) if abs(value) < 1 else ("s", 1.0)
    if unit == "m":
        return ("um", 1e6) if abs(value) < 1e-3 else ("mm", 1e3)
    if unit.startswith("1 "):  # "1 (of L)" and the like
        return unit[2:], 1.0
    return DISPLAY_UNITS.get(unit, (unit, 1.0))


def format_value(value: float, std: float | None, unit: str) -> str:
    """`1.41580 ms ± 0.00032 ms`: the value to the precision its standard deviation (2
    significant digits) supports, at least 3 and at most 6 significant digits, in a unit
    for people."""
    if not finite(value):
        return "n/a"
    value = float(value)
    u, k = display_unit(unit, value)
    v = value * k
    s = float(std) * k if finite(std) and float(std) > 0 else None
    sfx = f" {u}" if u else ""
    if v == 0:
        return f"0{sfx}" + (f" ± {sig(s, 2)}{sfx}" if s is not None else "")
    mag = math.floor(math.log10(abs(v)))
    if mag < -3 or mag >= 6:
        vs = f"{v:.{3 if s is None else min(5, max(2, mag - math.floor(math.log10(s)) + 1))}e}"
        return vs + sfx + (f" ± {s:.1e}{sfx}" if s is not None else "")
    if s is None:
        return f"{v:.{max(0, 3 - mag)}f}{sfx}"
    ms = math.floor(math.log10(s))
    if ms >= 6 or ms < mag - 5:
        # the std of an undetermined (1e26) or a degenerate (1e-34) fit: no 26-digit integer, no 35
        # decimals; the value to 3 significant digits, or to the 6 it is at most given with
        return f"{v:.{max(0, (2 if ms >= 6 else 5) - mag)}f}{sfx} ± {s:.1e}{sfx}"
    ds = max(0, 1 - ms)
    dv = min(max(max(0, 2 - mag), ds), max(0, 5 - mag))
    return f"{v:.{dv}f}{sfx} ± {s:.{ds}f}{sfx}"
