"""What a live or replayed session judges of the rig, from its online estimates in order.

- **Validity**: whether the model explains the recent data, on `identify`'s scale (each
  window's residual sigma in units of the sensor noise, 1 = a perfect model). Above
  `mismatch` (identify's own limit, 3) for `hold_s` of data the session says at once that
  the model does not explain the rig, that the estimate is not to be trusted and what to do;
  back below it for as long, that it explains the rig again.
- **Changes** of the rig's friction that the estimator detected (a step: when, how large,
  with standard deviations) and drifts it follows (rate per second).

Everything is decided on the estimates' data time, never on the wall clock, so a replay
judges alike at any machine load. Times in messages and the JSON are seconds since the
session's first sample.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from ..identify import MISMATCH, OnlineEstimate

__all__ = ["MonitorOptions", "RunSigma", "SessionMonitor", "change_message", "drift_message", "WHAT_TO_DO"]

WHAT_TO_DO = ("calibrate the cylinder file's valve, volumes and mass from a calibration run (combined-reality "
              "calibrate), or find the effect the model lacks (combined-reality diagnose)")


@dataclass(frozen=True)
class RunSigma:
    """`identify`'s residual sigma (x the sensor noise) of an estimate over a stretch of the
    recording (session times, s)."""

    sigma: float
    t_start: float
    t_end: float


@dataclass(frozen=True)
class MonitorOptions:
    mismatch: float = MISMATCH  # window residual sigma (x noise) above which the model does not explain the data
    hold_s: float = 1.0  # s of data a verdict on validity must hold before it is announced


@dataclass
class _Span:
    t_start: float  # the first window that the model did not explain began
    t_end: float | None  # the first window it explained again began (None: it still does not)
    sigma_max: float
    t_said: float  # when the session said so (the end of the window that made it hold_s)


@dataclass
class SessionMonitor:
    """Feed every estimate to `take` in order; it returns the messages the estimate brings
    (a change of validity, a change of the rig, a drift that begins or ends)."""

    t0: float = 0.0  # rig time of the session's first sample
    options: MonitorOptions = MonitorOptions()
    explained: bool | None = None  # None before the first estimate
    sigma_recent: float | None = None
    sigma_session: float | None = None  # RMS of the windows' residual sigma, each over the data it added
    _ss: float = 0.0
    _span_s: float = 0.0
    _t_last: float | None = None
    mismatch: list[_Span] = field(default_factory=list)
    changes: list = field(default_factory=list)  # identify.tracking.Change, as estimated
    drifts: list[dict] = field(default_factory=list)
    _pending: float | None = None  # rig time of the first window against the current verdict
    _pending_start: float | None = None
    _pending_sigma: float = 0.0
    _drift_on: bool = False
    _seen_explained: bool = False  # some window so far was explained
    # identify's residual of the final estimate over the end of the recording, where the model
    # did not explain the rig at the end (live.ending)
    run_sigma: RunSigma | None = None

    def take(self, e: OnlineEstimate) -> list[str]:
        out = []
        if e.change is not None:
            self.changes.append(e.change)
            out.append(change_message(e.change, e.units, self.t0))
        out += self._validity(e)
        out += self._drift(e)
        return out

    @property
    def trusted(self) -> bool:
        """Whether the last estimate may be trusted: the model explains the recent data."""
        return self.explained is not False

    def _validity(self, e: OnlineEstimate) -> list[str]:
        o, t = self.options, self.t0
        self.sigma_recent = e.sigma
        new = e.t - (e.window[0] if self._t_last is None else max(self._t_last, e.window[0]))
        self._t_last = e.t
        if new > 0 and math.isfinite(e.sigma):
            self._ss += e.sigma ** 2 * new
            self._span_s += new
            self.sigma_session = math.sqrt(self._ss / self._span_s)
        above = not e.sigma <= o.mismatch  # (a NaN sigma explains nothing)
        if self.explained is None:
            self.explained = True  # until the data say otherwise for hold_s
        # a step the estimator is about to judge may explain a residual, if a window before it was explained
        step_may_explain = e.step_pending and self._seen_explained
        self._seen_explained = self._seen_explained or not above
        if self.explained and (not above or step_may_explain) or not self.explained and above:
            self._pending = None
            if not self.explained:
                self.mismatch[-1].sigma_max = max(self.mismatch[-1].sigma_max, e.sigma)
            return []
        if self._pending is None:
            self._pending, self._pending_start, self._pending_sigma = e.t, e.window[0], 0.0
        self._pending_sigma = max(self._pending_sigma, e.sigma)
        if e.t - self._pending < o.hold_s:
            return []
        self._pending = None
        if above:
            self.explained = False
            self.mismatch.append(_Span(self._pending_start - t, None, self._pending_sigma, e.t - t))
            return [f"the model does not explain the rig (residual {e.sigma:.3g} x the sensor noise, above "
                    f"{o.mismatch:g}, since t = {self._pending_start - t:.1f} s): the estimate is not to be trusted; "
                    + WHAT_TO_DO]
        self.explained = True
        span = self.mismatch[-1]
        span.t_end = self._pending_start - t
        return [f"the model explains the rig again from t = {span.t_end:.1f} s (residual {e.sigma:.3g} x the sensor "
                "noise)"]

    def _drift(self, e: OnlineEstimate) -> list[str]:
        d = e.drift
        if d is not None and not self._drift_on:
            self._drift_on = True
            self.drifts.append({"t_start": d.since - self.t0, "t_end": None, "z": d.z,
                                "rate": dict(d.rate), "rate_std": dict(d.rate_std)})
            self.drifts[-1]["units"], self.drifts[-1]["values"] = dict(e.units), dict(e.values)
            return [f"the friction drifts (found at t = {d.since - self.t0:.1f} s, z = {d.z:.3g}): "
                    f"{drift_rates(self.drifts[-1])}; the estimate follows it"]
        if d is not None:
            self.drifts[-1].update(z=max(self.drifts[-1]["z"], d.z), rate=dict(d.rate), rate_std=dict(d.rate_std),
                                   values=dict(e.values))
        if d is None and self._drift_on:
            self._drift_on = False
            if self.drifts:
                self.drifts[-1]["t_end"] = e.t - self.t0
            return [f"the friction is steady again (t = {e.t - self.t0:.1f} s)"]
        return []

    def to_json(self) -> dict:
        t = self.t0
        r = self.run_sigma
        return {"explained": self.explained, "sigma_recent": self.sigma_recent, "sigma_session": self.sigma_session,
                "sigma_run": None if r is None else r.sigma,
                "sigma_run_span": None if r is None else [r.t_start, r.t_end],
                "mismatch_limit": self.options.mismatch,
                "mismatch": [{"t_start": s.t_start, "t_end": s.t_end, "sigma_max": s.sigma_max, "t_said": s.t_said}
                             for s in self.mismatch],
                "changes": [{"t": c.t - t, "t_std": c.t_std, "z": c.z, "t_detected": c.t_detected - t,
                             "params": {n: {"before": c.before[n], "after": c.after[n], "std": c.std[n],
                                            "std_before": c.std_before[n], "std_after": c.std_after[n]}
                                        for n in c.before}} for c in self.changes],
                "drifts": [{k: v for k, v in d.items() if k not in ("units", "values")} for d in self.drifts]}


def drift_rates(d: dict) -> str:
    """'Fc +8.66 N/min (+37.4 %/min), ...': a drift's rates per minute, also relative to the values."""
    out = []
    for n, rate in d["rate"].items():
        value = d.get("values", {}).get(n)
        rel = f" ({100 * 60 * rate / value:+.3g} %/min)" if value else ""
        out.append(f"{n} {60 * rate:+.3g} {d.get('units', {}).get(n, '')}/min{rel}")
    return ", ".join(out)


def drift_message(d: dict) -> str:
    """A drift the session followed, in words (session times)."""
    until = "on" if d["t_end"] is None else f"to {d['t_end']:.1f} s"
    return f"the friction drifted from t = {d['t_start']:.1f} s {until}: {drift_rates(d)}"


def change_message(c, units: dict[str, str], t0: float = 0.0) -> str:
    """'friction changed at t = 30.00 ± 0.06 s (...): Fc 22 -> 28.6 N (± 0.12), ...' (session time)."""
    parts = ", ".join(f"{n} {c.before[n]:.4g} -> {c.after[n]:.4g} {units.get(n, '')} (± {c.std[n]:.2g})"
                      for n in c.before)
    return (f"friction changed at t = {c.t - t0:.2f} ± {c.t_std:.2g} s (found at {c.t_detected - t0:.2f} s, "
            f"z = {c.z:.3g}): {parts}")
