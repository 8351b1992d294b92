"""Whether the data determine an estimate: the one rule behind every "not determined" and
"no estimate" the tool prints (identify, friction-compare)."""
from __future__ import annotations

import math
from typing import Collection, Mapping

from sim.cylinder import PARAMETERS

__all__ = ["not_determined"]


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
        if not math.isfinite(s) or not math.isfinite(v) or (not signed(n) and n not in at_bound and s >= abs(v)):
            out.append(n)
    return out
