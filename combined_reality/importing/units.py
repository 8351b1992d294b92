"""Units at the edge, through pint: every unit pint knows (ms, mm, bar, psi, kPa, V, percent,
degC, ...) is converted to the SI unit of the run channel; gauge is not a unit here but the
mapping's `gauge = true` plus the atmosphere."""
from __future__ import annotations

import functools

import numpy as np

from sim.inputs import shorten

from ..errors import InputError

__all__ = ["UnitProblem", "registry", "check_unit", "quantity_in", "convert_channel", "decimal_clean"]

# the run channels' SI units (extras: pint's base units)
SI_UNITS = {"t": "s", "x": "m", "p1": "Pa", "p2": "Pa", "ps": "Pa"}


class UnitProblem(InputError):
    """A unit or quantity text pint cannot read, or of the wrong dimension (one sentence; exit status 2)."""


@functools.lru_cache(maxsize=1)
def registry():
    """pint's unit registry (built once per process: reading its definitions takes ~0.5 s)."""
    import pint

    return pint.UnitRegistry(cache_folder=None)


def _units(text: str):
    try:
        return registry().Quantity(1.0, text) if text.strip() else registry().Quantity(1.0)
    except Exception as e:  # pint's parser raises its own errors, TokenError, SyntaxError, AttributeError ...
        raise UnitProblem(f"'{shorten(text)}' is not a unit pint knows ({_first_line(e)}); use e.g. s, ms, m, mm, "
                          f"Pa, kPa, bar, psi, V, percent.") from None


def _quantity(text: str):
    try:
        q = registry().Quantity(text)
    except Exception as e:  # as in _units
        raise UnitProblem(f"'{shorten(text)}' is not a quantity pint can read ({_first_line(e)}); write e.g. "
                          "\"25 mm/V\".") from None
    if not np.isfinite(float(np.asarray(q.magnitude, dtype=float))) or float(q.magnitude) == 0:
        raise UnitProblem(f"'{shorten(text)}' must be a finite, non-zero quantity.")
    return q


def _first_line(e: Exception) -> str:
    return (str(e).strip().splitlines() or [type(e).__name__])[0].rstrip(".")


def check_unit(unit: str, scale: str | None, dimension: str | None, has_span: bool) -> None:
    """Refuse a unit (times the scale) that cannot measure what the channel holds."""
    q = _units(unit)
    if scale is not None:
        s = _quantity(scale)
        try:
            q = q * s
        except Exception as e:  # offset units (degC) cannot be multiplied
            raise UnitProblem(f"the unit '{unit}' cannot be scaled by '{scale}' ({_first_line(e)}).") from None
    if dimension is None or has_span:
        return  # extras: any unit; the command with span: the map makes it dimensionless
    if dimension == "dimensionless":
        if not q.dimensionless:
            raise UnitProblem(f"the command in '{unit}' needs zero and span (u = (value - zero) / span), e.g. "
                              f"zero = 5.0, span = 5.0 for 0..10 V around 5 V.")
        return
    if not q.check(dimension):
        what = {"[time]": "a time", "[length]": "a length", "[pressure]": "a pressure"}[dimension]
        raise UnitProblem(f"'{unit}'{f' x {scale}' if scale else ''} is not {what} "
                          f"({q.dimensionality}); " + ("a sensor in volts needs scale = \"... per V\"."
                                                       if "[current]" in str(q.dimensionality) else
                                                       "check the unit."))


def quantity_in(text: str, target: str) -> float:
    """A quantity given as text ("1013 mbar") in the target unit."""
    q = _quantity(text)
    try:
        return float(q.to(target).magnitude)
    except Exception as e:
        raise UnitProblem(f"'{shorten(text)}' is not in units convertible to {target} ({_first_line(e)}).") from None


_DIGITS = 15  # a recording holds fewer significant digits than this; a double more (17)


def decimal_clean(values: np.ndarray, magnitude: np.ndarray | None = None) -> np.ndarray:
    """Each value as the double nearest to itself rounded to 15 significant digits (of
    `magnitude` where given: a difference such as value - zero keeps the decimals of its
    terms): a unit conversion's last-bit error is gone (9 ms is 0.009 s, not
    0.009000000000000001) and the run file shows the decimals the recording had. Changes a
    value by at most 5e-15 of itself (of `magnitude`)."""
    v = np.asarray(values, dtype=float)
    size = np.abs(v) if magnitude is None else np.broadcast_to(np.abs(np.asarray(magnitude, dtype=float)), v.shape)
    out = v.copy()
    ok = np.isfinite(v) & (v != 0) & np.isfinite(size) & (size > 0)
    if not ok.any():
        return out
    keep = _DIGITS - 1 - np.floor(np.log10(size[ok])).astype(int)  # decimals to keep
    up = (keep >= 0) & (keep <= 22)  # powers of ten up to 1e22 are exact doubles
    down = (keep < 0) & (keep >= -22)
    w = v[ok]
    res = w.copy()
    scale = 10.0 ** np.abs(keep)
    res[up] = np.round(w[up] * scale[up]) / scale[up]  # an exact integer over an exact power: correctly rounded
    res[down] = np.round(w[down] / scale[down]) * scale[down]
    out[ok] = res
    return out


def convert_channel(channel, raw: np.ndarray, atmosphere: float | None) -> tuple[np.ndarray, str]:
    """The channel's values in SI (the command: dimensionless) and a line saying how they
    were converted (for the run's header comments)."""
    reg = registry()
    src = repr(channel.source) if channel.source is not None else f"the time track of {channel.time_of!r}"
    unit = channel.unit or "1"
    raw = np.asarray(raw, dtype=float)
    # value - zero keeps the recording's decimals (4.9747532 V - 5 is -0.0252468, not ...79999)
    shifted = decimal_clean(raw - channel.zero, np.maximum(np.abs(raw), abs(channel.zero))) if channel.zero else raw
    zero = f" - {channel.zero:g}" if channel.zero else ""
    if channel.name == "u":
        if channel.span is not None:
            return decimal_clean(shifted / channel.span), f"u <- {src} [{unit}]: u = (value{zero}) / {channel.span:g}"
        factor = float(reg.Quantity(1.0, unit).to("dimensionless").magnitude) if channel.unit else 1.0
        return _cleaned(shifted * factor, raw), f"u <- {src} [{unit}]: u = (value{zero}) x {factor:g}"
    q = reg.Quantity(shifted, channel.unit) if channel.unit.strip() else reg.Quantity(shifted)
    if channel.scale is not None:
        q = q * _quantity(channel.scale)
    target = SI_UNITS.get(channel.name)
    if target is None:
        q = q.to_base_units()
        target = f"{q.units:~}" or "1"
    else:
        q = q.to(target)
    values = np.asarray(q.magnitude, dtype=float)
    how = f"{channel.name} <- {src} [{unit}]" + (f", value{zero}" if zero else "") \
        + (f" x {channel.scale}" if channel.scale else "") + f" -> {target}"
    if channel.gauge:
        values = values + atmosphere
        how += f", gauge + atmosphere {atmosphere:g} Pa -> Pa absolute"
    return _cleaned(values, raw), how


def _cleaned(values: np.ndarray, raw: np.ndarray) -> np.ndarray:
    """decimal_clean where a conversion changed the values; values already in SI stay as
    they were, bit for bit (a binary recording's doubles)."""
    return values if np.array_equal(values, raw, equal_nan=True) else decimal_clean(values)
