"""Scoring a model on a run it was not fitted to (VALID).

VALID is cut into segments of about `horizon_s` (cut where the piston moves, so that its
state is well determined), and each segment is simulated open loop with the recorded
command from an initial state fitted to that segment alone (the model's parameters stay
fixed: nothing of VALID enters the model). A correct model then leaves the sensor noise,
whatever the horizon. The diagnosis, the friction-model comparison and the calibration
all score models this way.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from sim.cylinder import Cylinder
from sim.extension import Effect

from ..files import Run, split_at_gaps
from ..parallel import run_jobs
from .offline import IdentifyOptions, identify
from .shooting import IdentificationError, sensor_noise
from .smoothing import velocity_estimate

__all__ = ["validation_segments", "Validation", "validate", "validation_gain"]


def validation_segments(run: Run, horizon_s: float) -> list[tuple[int, int]]:
    """(start, stop) sample ranges of about `horizon_s`, cut where the piston moves fastest
    within a quarter horizon of the nominal cut (a piston at rest hides its friction state,
    so an initial state fitted there is ill-determined); never across a gap."""
    out = []
    offset = 0
    for piece in split_at_gaps(run):
        n = max(10, int(round(horizon_s / piece.sample_period)))
        v = np.abs(velocity_estimate(piece.t, piece.x)) if piece.n > 30 else np.zeros(piece.n)
        cuts = [0]
        for c in range(n, piece.n - n // 2, n):
            lo, hi = c - n // 4, min(piece.n - 1, c + n // 4)
            cuts.append(lo + int(np.argmax(v[lo:hi])))
        cuts.append(piece.n)
        out.extend((offset + a, offset + b) for a, b in zip(cuts[:-1], cuts[1:]) if b - a >= 10)
        offset += piece.n
    return out


@dataclass
class Validation:
    """A model scored on VALID: simulated outputs, residuals and per-segment costs."""

    outputs: tuple[str, ...]
    simulated: np.ndarray  # (n_outputs, n), NaN outside the segments
    residual: np.ndarray  # measured - simulated
    segments: list[tuple[int, int]]
    segment_cost: np.ndarray  # sum of (residual / noise)^2 per segment, all outputs
    noise: np.ndarray  # sensor noise per output
    status: str  # the worst of the segments' fits
    nodes: list = field(default_factory=list, repr=False)  # per segment: the fitted node states

    def rmse(self, output: str = "x", mask: np.ndarray | None = None) -> float:
        r = self.residual[self.outputs.index(output)]
        r = r[np.isfinite(r) if mask is None else (mask & np.isfinite(r))]
        return float(np.sqrt(np.mean(r * r))) if r.size else math.nan

    def normalized_rms(self) -> float:
        """RMS of the noise-weighted residuals of all outputs (1 = sensor noise)."""
        n = int(np.isfinite(self.residual).sum())  # measured samples inside the segments
        return float(math.sqrt(self.segment_cost.sum() / max(n, 1)))


def validate(cyl: Cylinder, effects: Sequence[Effect], run: Run, horizon_s: float = 1.0, drive: str = "command",
             segments: list[tuple[int, int]] | None = None, fallback: "Validation | None" = None,
             workers: int = 1) -> Validation:
    """Score a model on `run`: every segment simulated from its own fitted initial state.

    The initial-state fit starts from the measured state; a segment that stays well above
    the noise is fitted again from `fallback`'s trajectory there (another model's validation,
    e.g. the nominal one), and the better fit is kept: stick-slip and friction memory give
    the initial-state fit local minima. Only states are fitted, never parameters. The
    segments share nothing: with `workers` > 1 they are fitted in that many processes, with
    the same results."""
    segments = segments or validation_segments(run, horizon_s)
    if not segments:
        raise IdentificationError("the validation run has no gap-free stretch of 10 samples or more to score on")
    # one problem per segment: they share nothing, and one line search for all would let the
    # hardest segment set the step of every other
    opts = IdentifyOptions(drive=drive, estimate=(), prefit=False, max_iter=30, threads=1)
    jobs = [(cyl, effects, run.slice(a, b), None if fallback is None else fallback.nodes[j], opts)
            for j, (a, b) in enumerate(segments)]
    # the first segment the model cannot be simulated on ends the validation
    fits = run_jobs(_fit_segment, jobs, workers, enough=lambda fit: fit is None)
    if fits[-1] is None:
        a, b = segments[len(fits) - 1]
        raise IdentificationError(f"the model cannot be simulated on the validation segment "
                                  f"{run.t[a]:.2f}-{run.t[b - 1]:.2f} s")
    outputs = fits[0].outputs
    meas = np.vstack([getattr(run, o) for o in outputs])
    sim = np.full_like(meas, np.nan)
    for (a, b), fit in zip(segments, fits):
        sim[:, a:b] = fit.simulated
    noise = sensor_noise(cyl, outputs)
    statuses = [f.status for f in fits]
    worst = next((st for st in ("line_search_failed", "time_limit", "max_iterations") if st in statuses), "converged")
    return Validation(outputs, sim, meas - sim, segments, np.array([f.cost for f in fits]), noise, worst,
                      [f.nodes for f in fits])


@dataclass(frozen=True)
class _SegmentFit:
    """One segment's best prediction: its simulated outputs, their noise-weighted cost, the
    fit's status and the fitted node states."""

    outputs: tuple[str, ...]
    simulated: np.ndarray
    cost: float
    status: str
    nodes: np.ndarray


def _fit_segment(job) -> _SegmentFit | None:
    """The initial-state fit of one validation segment that predicts it best (None when no
    start can be simulated). job: (cylinder, effects, segment, fallback nodes or None,
    IdentifyOptions)."""
    cyl, effects, piece, warm_nodes, opts = job
    tries = [(None, opts)]
    if warm_nodes is not None:
        tries.append((warm_nodes, opts))
        # and the fallback's start simulated as it is (added states at their initial
        # values): states an effect barely couples to are undetermined in the fit, which
        # may then drive them anywhere (heat exchange with h near 0)
        tries.append((warm_nodes, replace(opts, max_iter=0)))
    best = None
    for warm, try_opts in tries:
        try:
            res = identify(cyl, [piece], try_opts, effects=effects, nodes=warm)
        except IdentificationError:
            continue
        status = "converged" if try_opts.max_iter == 0 else res.solver["status"]  # a simulation, not a fit that ran out
        meas = np.vstack([getattr(piece, o) for o in res.output_names])
        sim = res.simulated[0]
        if not np.all(np.isfinite(sim)):
            continue  # diverged: its cost would count only the samples before
        # outputs not measured at a sample (NaN) have no residual there
        cost = float(np.nansum(((meas - sim) / sensor_noise(cyl, res.output_names)[:, None]) ** 2))
        if not math.isfinite(cost):
            continue
        if best is None or cost < best.cost:
            best = _SegmentFit(tuple(res.output_names), sim, cost, status, res.nodes)
        if cost < 1.5 * np.isfinite(meas).sum():  # near the noise: nothing to gain from another start
            break
    return best


def validation_gain(base: Validation, cand: Validation) -> tuple[float, float]:
    """(shrink of the all-output normalised RMS, z statistic of the gain): how much better the
    candidate predicts VALID, and how sure that is.

    With d the difference of the two models' predictions (in noise units) and J their
    validation costs, were the baseline the truth with white sensor noise, the gain
    J_base - J_cand would have mean -|d|^2 and standard deviation 2|d|. z = gain / (2|d|)
    above 3 therefore says that no noise makes the baseline look this bad next to the
    candidate; it does not need the gain to be spread evenly over the segments."""
    shrink = 1.0 - cand.normalized_rms() / base.normalized_rms()
    d = (cand.simulated - base.simulated) / base.noise[:, None]
    d2 = float(np.nansum(d * d))
    gain = float(base.segment_cost.sum() - cand.segment_cost.sum())
    z = gain / (2.0 * math.sqrt(d2)) if d2 > 0 else 0.0
    return shrink, z
