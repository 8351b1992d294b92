"""How regularly a recording was sampled, and its resampling onto a regular grid."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..files import Run
from .units import decimal_clean

__all__ = ["SamplingReport", "sampling_report", "resample"]

GAP_FACTOR = 1.5  # a step longer than this many median periods is a gap (lost samples), as files.split_at_gaps
JITTER_NOTICE = 0.01  # relative spread of the steps above which the sampling is called irregular


@dataclass(frozen=True)
class SamplingReport:
    n: int
    duration: float  # s
    median_period: float  # s
    jitter: float  # standard deviation of the steps / median period, excluding gaps
    shortest_step: float  # s
    gaps: int  # steps longer than GAP_FACTOR median periods
    longest_gap: float  # s, 0 without gaps

    @property
    def irregular(self) -> bool:
        return self.gaps > 0 or self.jitter > JITTER_NOTICE

    def describe(self) -> str:
        rate = 1.0 / self.median_period
        text = (f"{self.n} samples over {self.duration:.6g} s, median period {self.median_period * 1e3:.6g} ms "
                f"({rate:.6g} Hz), jitter {100 * self.jitter:.2g} %, shortest step {self.shortest_step * 1e3:.4g} ms")
        if self.gaps:
            text += f", {self.gaps} gap{'s' if self.gaps > 1 else ''} (longest {self.longest_gap * 1e3:.4g} ms)"
        else:
            text += ", no gaps"
        return text

    def to_json(self) -> dict:
        return {"samples": self.n, "duration_s": self.duration, "median_period_s": self.median_period,
                "jitter": self.jitter, "shortest_step_s": self.shortest_step, "gaps": self.gaps,
                "longest_gap_s": self.longest_gap, "irregular": self.irregular}


def sampling_report(t: np.ndarray) -> SamplingReport:
    dt = np.diff(t)
    median = float(np.median(dt))
    gap = dt > GAP_FACTOR * median
    regular = dt[~gap]
    return SamplingReport(n=int(t.size), duration=float(t[-1] - t[0]), median_period=median,
                          # below 1e-6 it is the rounding of the recorded times, not the clock
                          jitter=_rounded(float(np.std(regular) / median)) if regular.size else 0.0,
                          shortest_step=float(dt.min()), gaps=int(gap.sum()),
                          longest_gap=float(dt[gap].max()) if gap.any() else 0.0)


def _rounded(jitter: float) -> float:
    return jitter if jitter >= 1e-6 else 0.0


def resample(run: Run, rate: float) -> tuple[Run, int]:
    """The run on the regular grid t0 + k / rate: measurements (x, pressures, numeric extras)
    interpolated linearly, the command held from its last sample (zero-order hold: what the
    valve had). Grid instants inside a gap are left out, so a gap stays a gap and no
    simulation bridges it. Returns the run and the number of grid instants left out."""
    t = run.t
    period = 1.0 / rate
    grid = decimal_clean(t[0] + np.arange(int(math.floor((t[-1] - t[0]) / period + 1e-9)) + 1) / rate)
    dt = np.diff(t)
    slot = np.clip(np.searchsorted(t, grid, side="right") - 1, 0, t.size - 2)
    in_gap = (dt[slot] > GAP_FACTOR * np.median(dt)) & (grid > t[slot]) & (grid < t[slot + 1])
    grid = grid[~in_gap]
    held = np.clip(np.searchsorted(t, grid, side="right") - 1, 0, None)

    def lin(values: np.ndarray) -> np.ndarray:
        return np.interp(grid, t, values)

    extra = {k: (lin(v) if v.dtype.kind in "biuf" else v[held]) for k, v in run.extra.items()}
    out = replace(run, t=grid, u=run.u[held], x=lin(run.x), p1=lin(run.p1), p2=lin(run.p2),
                  ps=None if run.ps is None else lin(run.ps), extra=extra)
    return out, int(in_gap.sum())
