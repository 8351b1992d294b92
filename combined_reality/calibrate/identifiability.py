"""What a calibration run determines, told plainly: which parameters the data pin down, which
they cannot (and what motion would), which pairs they cannot separate.

Three sources: the fit's standard deviations against the values and the bounds; its
correlations; and the run's coverage of the valve's openings (a segment of the flow
characteristic that no sample opens is not measured but follows its neighbours through the
smoothness prior, however small its standard deviation looks)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from sim.cylinder import OPENING_GRID, PARAMETERS, Cylinder

from ..files import Run
from ..identify import IdentifyResult

__all__ = ["Identifiability", "assess", "MIN_COVERAGE", "STRONG_CORRELATION"]

MIN_COVERAGE = 0.003  # share of the samples a flow segment needs to count as measured
STRONG_CORRELATION = 0.95  # |r| above which two estimates are not told apart
_UNDETERMINED = 0.5  # std above this share of the value (or of the range, near zero): not determined

# what motion determines each kind of parameter
_ADVICE = {
    "Fc": "motion in both directions",
    "Fv": "motion at clearly different speeds",
    "kp": "motion at clearly different pressure differences |p1 - p2| (light and heavy loads, both directions)",
    "mass": "fast accelerations: steps or pulses of the command",
    "external_force": "motion in both directions (a constant force shifts both the same way)",
    "offset_p1": "holding against an end stop with the valve open (the chambers settle at supply and atmosphere)",
    "offset_p2": "holding against an end stop with the valve open (the chambers settle at supply and atmosphere)",
    "dead_volume_cap": "moves into the retracted end (x = 0: the cap chamber is then its dead volume alone)",
    "dead_volume_rod": "moves into the extended end (x = stroke: the rod chamber is then its dead volume alone)",
    "critical_ratio": "fast moves from rest (choked flow) and slow ones near the end pressures (subsonic flow)",
    "overlap": "slow commands creeping through zero in that direction",
    "conductance": "moves at several command levels",
}


@dataclass
class Identifiability:
    determined: list[str] = field(default_factory=list)
    undetermined: list[dict] = field(default_factory=list)  # name, why, advice
    correlated: list[dict] = field(default_factory=list)  # a, b, r
    coverage: dict[str, float] = field(default_factory=dict)  # flow segment -> share of the samples

    def to_json(self) -> dict:
        return {"determined": self.determined, "undetermined": self.undetermined, "correlated": self.correlated,
                "flow_coverage": self.coverage}

    def lines(self) -> list[str]:
        """The report for people, a sentence per line: what the runs lacked (neighbouring
        segments of a flow characteristic that the runs reached too little, together) and
        which motion would give it."""
        out = []
        if self.undetermined:
            out.append("Not determined by these runs:")
            out += [f"  {u['name']}: {u['why']}; to determine it, record {u['advice']}."
                    for u in grouped(self.undetermined)]
        if self.correlated:
            out.append("Not separated by these runs (their estimates trade off against each other):")
            out += [f"  {c['a']} and {c['b']} (correlation {c['r']:+.2f})" for c in self.correlated]
        if not out:
            out.append("Every calibrated parameter is determined by these runs.")
        return out


def _segment(name: str) -> tuple[str, int]:
    _, direction, k = name.split("_")
    return direction, int(k)


def _openings(k1: int, k2: int) -> str:
    lo = 0.0 if k1 == 1 else OPENING_GRID[k1 - 2]
    return f"{lo:.0%} to {OPENING_GRID[k2 - 1]:.0%} of the opening beyond the overlap"


def grouped(undetermined: list[dict]) -> list[dict]:
    """The undetermined entries with neighbouring flow segments of one direction that the runs
    reached too little merged into one ('flow_extend_11..15'): one line per stretch of the
    characteristic the runs lacked."""
    out: list[dict] = []
    for u in undetermined:
        prev = out[-1] if out else None
        if (prev is not None and u["name"].startswith("flow_") and "reached" in u
                and prev.get("direction") == _segment(u["name"])[0] and prev.get("last") == _segment(u["name"])[1] - 1):
            d, k = _segment(u["name"])
            first = prev["first"]
            seconds = prev["seconds"] + u["seconds"]
            sign = "positive" if d == "extend" else "negative"
            out[-1] = {**prev, "name": f"flow_{d}_{first}..{k}", "last": k, "seconds": seconds,
                       "why": (f"the runs held {sign} commands at {_openings(first, k)} for {seconds:.2g} s in all, "
                               "too little to measure, so the characteristic there follows its neighbours (a smooth "
                               "valve) rather than the data"),
                       "advice": _advice(f"flow_{d}_{first}", last=k)}
        else:
            out.append(u)
    return out


def _advice(name: str, last: int | None = None) -> str:
    if name.startswith("flow_"):
        direction, k = _segment(name)
        sign = "positive" if direction == "extend" else "negative"
        return (f"more and longer moves or pulses at {sign} commands of {_openings(k, last or k)} "
                f"(at least {MIN_COVERAGE:.1%} of the samples there)")
    if name.startswith("overlap_"):
        return _ADVICE["overlap"]
    return _ADVICE.get(name, "motion that excites it")


def flow_coverage(cyl: Cylinder, runs: Sequence[Run]) -> dict[str, float]:
    """Share of the samples whose command lies in each segment of each direction's flow
    characteristic (beyond that direction's overlap)."""
    u = np.concatenate([r.u for r in runs])
    out = {}
    for d, sign in (("extend", 1.0), ("retract", -1.0)):
        a = np.clip(sign * u, 0.0, None)
        overlap = getattr(cyl.valve, f"overlap_{d}")
        s = np.where(a > overlap, (a - overlap) / (1.0 - overlap), -1.0)
        lo = 0.0
        for k, hi in enumerate(OPENING_GRID):
            out[f"flow_{d}_{k + 1}"] = float(np.mean((s > lo) & (s <= hi))) if len(u) else 0.0
            lo = hi
    return out


def assess(result: IdentifyResult, runs: Sequence[Run]) -> Identifiability:
    """The identifiability of the estimates of a fit on these runs (module docstring)."""
    rep = Identifiability(coverage=flow_coverage(result.cylinder, runs))
    duration = sum(r.duration for r in runs)
    names = list(result.params)
    for n in names:
        e = result.params[n]
        spec = PARAMETERS.get(n)
        span = (spec.upper - spec.lower) if spec else math.inf
        why = None
        if n in rep.coverage and rep.coverage[n] < MIN_COVERAGE:
            d, k = _segment(n)
            seconds = rep.coverage[n] * duration
            sign = "positive" if d == "extend" else "negative"
            why = (f"the runs held {sign} commands at {_openings(k, k)} for {seconds:.2g} s in all, too little to "
                   "measure, so the characteristic there follows its neighbours (a smooth valve) rather than the data")
            rep.undetermined.append({"name": n, "why": why, "advice": _advice(n), "reached": rep.coverage[n],
                                     "seconds": seconds, "direction": d, "first": k, "last": k})
            continue
        if not math.isfinite(e.std):
            why = "the data do not constrain it at all"
        elif e.std > _UNDETERMINED * max(abs(e.value), 1e-3 * span):
            why = f"its standard deviation ({e.std:.3g} {e.unit}) is as large as the value itself ({e.value:.3g})"
        elif e.at_bound and n.startswith("overlap_") and e.value <= spec.lower:
            why = None  # the data want no overlap, which is the least there is: the valve opens at once
        elif e.at_bound:
            why = "the fit ended at a bound of its range"
        if why:
            rep.undetermined.append({"name": n, "why": why, "advice": _advice(n)})
        else:
            rep.determined.append(n)
    corr = result.correlation
    if corr is not None:
        for i in range(len(names)):
            for j in range(i + 1, len(names)):
                r = float(corr[i, j])
                if math.isfinite(r) and abs(r) > STRONG_CORRELATION:
                    rep.correlated.append({"a": names[i], "b": names[j], "r": round(r, 3)})
    return rep
