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
from ..identify import IdentifyResult, too_uncertain, velocity_estimate

__all__ = ["Identifiability", "assess", "separability", "MIN_COVERAGE", "STRONG_CORRELATION"]

MIN_COVERAGE = 0.003  # share of the samples a flow segment needs to count as measured
STRONG_CORRELATION = 0.95  # |r| above which two estimates are not told apart
# std from this share of the value (or of 1e-3 x the range, near zero) on: not determined.
_UNDETERMINED = 0.5  # half, not identify's 1 (no estimate at all): it says what to record before that

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
    effects: list[dict] = field(default_factory=list)  # separability: the effects the runs cannot tell apart

    def to_json(self) -> dict:
        return {"determined": self.determined, "undetermined": self.undetermined, "correlated": self.correlated,
                "flow_coverage": self.coverage, "effects_not_separated": self.effects}

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
        if self.effects:
            out.append("Effects these runs cannot tell from calibrated quantities (what they would need):")
            out += [f"  {e['effect']} from {e['from']}: {e['found']}; record {e['needs']}." for e in self.effects]
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


# what tells each effect from the calibrated quantities it can imitate: (the quantities, the
# run content that separates them, how much of it is enough). An effect the runs hold too little
# of that content for is fitted all the same, but a calibrated quantity may stand in for it
SEPARATES = {
    "leakage": ("the valve's opening near closed (overlap, first segments) and the dead volumes",
                "holds with the valve closed at a pressure difference of 1 bar or more (the pressures relax "
                "towards each other)", 1.0, "s"),
    "heat_transfer": ("the dead volumes and the critical ratio",
                      "holds with the valve closed right after moves (the pressures relax as the air's temperature "
                      "returns)", 1.0, "s"),
    "valve_delay": ("the flow characteristic at small openings",
                    "steps or pulses of the command (a jump of 0.1 or more from one sample to the next)", 10, "steps"),
    "supply_droop": ("the flow characteristic at large openings",
                     "sustained large openings (|u| above 0.5)", 0.5, "s"),
    "friction_asymmetry": ("the constant external force and the pressure sensors' offsets",
                           "slow moves in both directions (5 to 50 mm/s; a Coulomb level that differs by direction "
                           "stays a constant force while sliding: only an external force known and held tells it "
                           "apart)", 1.0, "s each way"),
    "friction_position": ("the friction's level (Fc, kp)", "moves over the whole stroke", 0.8, "of the stroke"),
    "stiction": ("the Coulomb friction Fc", "starts from rest in both directions", 10, "starts"),
    "friction_dynamics": ("the Coulomb and viscous friction", "reversals of the motion", 10, "reversals"),
}
_CLOSED = 0.01  # a command below this (or below the valve's overlap) leaves the valve all but closed
_AT_REST = 1e-3  # m/s


def separability(cyl: Cylinder, runs: Sequence[Run], names: Sequence[str] = tuple(SEPARATES)) -> list[dict]:
    """The effects (of `names`) whose separating content (SEPARATES) these runs hold too little of:
    effect, from (the quantities), needs, found (in words), amount and enough."""
    out = []
    L = cyl.geometry.stroke
    closed_below = max(_CLOSED, cyl.valve.overlap_extend, cyl.valve.overlap_retract)
    amount = {n: 0.0 for n in SEPARATES}
    ext = ret = 0.0
    lo, hi = math.inf, -math.inf
    for r in runs:
        ok = np.isfinite(r.x) & np.isfinite(r.p1) & np.isfinite(r.p2)
        if r.n < 30 or ok.sum() < 30:
            continue
        dt = r.sample_period
        v = velocity_estimate(r.t, np.where(ok, r.x, np.interp(r.t, r.t[ok], r.x[ok])))
        rest = np.abs(v) < _AT_REST
        closed = np.abs(r.u) < closed_below
        moving = np.abs(v) > 5 * _AT_REST
        # within 2 s after motion
        last_move = np.maximum.accumulate(np.where(moving, np.arange(r.n), -10 ** 9))
        after_move = (np.arange(r.n) - last_move) * dt < 2.0
        amount["leakage"] += dt * float(np.sum(ok & rest & closed & (np.abs(r.p1 - r.p2) > 1e5)))
        amount["heat_transfer"] += dt * float(np.sum(ok & rest & closed & after_move))
        amount["valve_delay"] += float(np.sum(np.abs(np.diff(r.u)) >= 0.1))
        amount["supply_droop"] += dt * float(np.sum(np.abs(r.u) > 0.5))
        slow = (np.abs(v) > 5e-3) & (np.abs(v) < 5e-2)
        ext += dt * float(np.sum(slow & (v > 0)))
        ret += dt * float(np.sum(slow & (v < 0)))
        lo, hi = min(lo, float(np.nanmin(r.x))), max(hi, float(np.nanmax(r.x)))
        # the motion as a sequence of rest (0) and directions (+-1), samples in between left out
        label = np.where(rest, 0, np.where(moving, np.sign(v), 9))
        keep = label != 9
        seq, idx = label[keep], np.flatnonzero(keep)
        change = np.flatnonzero(np.diff(seq) != 0) + 1
        runs_of = np.split(seq, change)
        firsts = np.r_[0, change]
        lengths = np.diff(np.r_[idx[firsts], r.n])
        kinds = [int(x[0]) for x in runs_of]
        moves = [k for k in kinds if k != 0]
        amount["friction_dynamics"] += float(sum(a != b for a, b in zip(moves[:-1], moves[1:])))
        # a start: 50 ms or more at rest, then motion
        started = [(k1, n0) for k0, k1, n0 in zip(kinds[:-1], kinds[1:], lengths[:-1]) if k0 == 0 and k1 != 0
                   and n0 * dt >= 0.05]
        amount["stiction"] += 2.0 * min(sum(k > 0 for k, _ in started), sum(k < 0 for k, _ in started))
    amount["friction_asymmetry"] = min(ext, ret)
    amount["friction_position"] = max(0.0, hi - lo) / L if math.isfinite(hi) else 0.0
    for n in names:
        if n not in SEPARATES:
            continue
        quantities, needs, enough, unit = SEPARATES[n]
        have = amount[n]
        if have >= enough:
            continue
        shown = f"{have:.2g} {unit}" if unit not in ("steps", "starts", "reversals") else f"{have:.0f} {unit}"
        out.append({"effect": n, "from": quantities, "needs": needs, "amount": have, "enough": enough, "unit": unit,
                    "found": f"these runs hold {shown} of it ({enough:g} needed)"})
    return out


def assess(result: IdentifyResult, runs: Sequence[Run]) -> Identifiability:
    """The identifiability of the estimates of a fit on these runs (module docstring)."""
    rep = Identifiability(coverage=flow_coverage(result.cylinder, runs),
                          effects=separability(result.cylinder, runs))
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
        elif too_uncertain(e.std, max(abs(e.value), 1e-3 * span), share=_UNDETERMINED):
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
