"""Whether the data determine an estimate: the one rule behind every "not determined" and
"no estimate" the tool prints (identify, friction-compare, calibrate's identifiability, friction
maps): a standard deviation that is not finite, or whose effect is as large as a share of the
size it is judged by (`too_uncertain`)."""
from __future__ import annotations

import math
from typing import Collection, Mapping

from sim.cylinder import PARAMETERS

__all__ = ["not_determined", "too_uncertain"]


def too_uncertain(std: float, size: float, share: float = 1.0, sensitivity: float = 1.0) -> bool:
    """Not determined: `std` is not finite, or its effect (std x `sensitivity`) is as large as
    `share` of `size` (the value itself, for identify's estimates)."""
    return not math.isfinite(std) or std * sensitivity >= share * size


def not_determined(values: Mapping[str, float], std: Mapping[str, float],
                   at_bound: Collection[str] = ()) -> list[str]:
    """Estimated parameters the data do not determine: no finite standard deviation, or, for a
    quantity that is positive by nature and not held at a bound, one as large as the value (a
    signed quantity such as a sensor offset may well be zero). Such a fit is never reported as
    converged, and its value is no estimate."""
    def signed(n: str) -> bool:
        return n in PARAMETERS and PARAMETERS[n].lower < 0

    out = []
    for n, v in values.items():
        s = std.get(n, math.nan)
        by_value = not signed(n) and n not in at_bound
        if not math.isfinite(v) or (too_uncertain(s, abs(v)) if by_value else not math.isfinite(s)):
            out.append(n)
    return out
