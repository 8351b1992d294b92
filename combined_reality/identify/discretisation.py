"""The identifier's own discretisation error: measured at the solution and taken out of the estimates.

The identifier integrates each 1 ms sample with one Rosenbrock step (refined only where its
error estimate asks for it, IntegratorOptions); a rig is continuous. That difference is a model
error: it shifts the estimates by an amount that does not shrink with the length of the run,
while the statistical standard deviation does (as one over its square root): 0.01-0.9 of the
statistical std in runs of 10-30 s, 3.3-4.0 of it in an hour at 1 kHz.

The shift is measured deterministically, without a second fit: at the solution, the same
intervals are simulated once more by a much finer integration (FINE_FACTOR times every
tolerance) and one Gauss-Newton step is taken with the residuals and defects of the fine
simulation and one with those of the fit's own, both on the fit's linearisation. Their
difference in the parameters is what a fit with the fine integration would move to, to first
order and free of the noise (the data cancel): on a 600 s run it agreed with such a refit to
three digits, on noise-free runs it is the estimates' error to 0.5 %. The estimates are moved
by it; the reported covariance owns what that leaves uncertain: the fine integration's own
error (FINE_FACTOR times the shift: the error scales with the tolerance) and, where the shift
was measured on stretches of the data only, their spread.

Its cost is one linearisation and one fine simulation of the data (~12 % of a fit). Runs of
more than SPAN_S are measured on SPAN_S of them, in stretches of STRETCH_S spread evenly over
the data, so the cost stays bounded; the stretches' spread then enters the std. Shorter runs
are measured whole: the shift of a single 60 s stretch scatters by about its own size.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from sim.compiled import ShootingFunctions, shooting_functions
from sim.integrator import IntegratorOptions

from .shooting import NormalEquations, RunLayout, ShootingProblem, linearize, scaled_inverse

# the fine integration's tolerances, times the fit's: its own error is then a small fraction
# of the fit's (the virtual rig's truth is integrated so too, sim.integrator.TRUTH_OPTIONS)
FINE_FACTOR = 0.05
SPAN_S = 3600.0  # at most this much of the fit's data is simulated finely
STRETCH_S = 60.0  # beyond SPAN_S, in stretches of this length spread evenly over the data


def fine_functions(sf: ShootingFunctions, opts: IntegratorOptions, progress=None) -> ShootingFunctions:
    """The interval function of the same plant at FINE_FACTOR times the tolerances (no sensitivities)."""
    return shooting_functions(sf.plant, sf.interval_len, (), opts.scaled(FINE_FACTOR), progress=progress,
                              with_sens=False)


def stretches(layouts: Sequence[RunLayout], M: int) -> list[tuple[int, int]]:
    """(first interval, intervals) of the stretches measured: every run or piece when their data
    hold at most SPAN_S, else SPAN_S / STRETCH_S stretches of about STRETCH_S of data each,
    centred at equal spacing over all intervals. A stretch may hold several gap-free pieces
    (a recording that loses a sample a second is pieces of a second): they stay apart in it."""
    total = sum(l.K for l in layouts)
    seconds = sum(float(l.H.sum()) for l in layouts)  # the data's, padding left out
    if seconds <= SPAN_S * (1 + 1e-9):
        return [(l.node0, l.K) for l in layouts]
    per_interval = seconds / total
    each = min(total, max(1, int(round(STRETCH_S / per_interval))))
    n = max(1, int(SPAN_S // STRETCH_S))
    return [(min(max(0, int((j + 0.5) * total / n) - each // 2), total - each), each) for j in range(n)]


def pieces_within(layouts: Sequence[RunLayout], k0: int, K: int) -> list[tuple[int, int]]:
    """(first interval relative to k0, intervals) of the runs' or pieces' parts in k0..k0+K-1."""
    out = []
    for l in layouts:
        a, b = max(k0, l.node0), min(k0 + K, l.node0 + l.K)
        if a < b:
            out.append((a - k0, b - a))
    return out


@dataclass(frozen=True)
class Discretisation:
    """The estimates' shift from the fit's integration to the fine one (free parameters, in
    order), the covariance of what it leaves uncertain (the fine integration's own error and the
    spread of a shift measured on stretches of the data only) and the seconds of data it was
    measured on."""

    shift: np.ndarray
    cov: np.ndarray
    span_s: float

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diag(self.cov), 0.0))

    def to_json(self, names: Sequence[str]) -> dict:
        return {"shift": dict(zip(names, self.shift.tolist())), "std": dict(zip(names, self.std.tolist())),
                "span_s": self.span_s}


def _sub_problem(problem: ShootingProblem, sf: ShootingFunctions, k0: int, K: int, pieces: Sequence[tuple[int, int]],
                 threads: int) -> ShootingProblem:
    """The problem restricted to intervals k0..k0+K-1, its pieces (relative) kept apart."""
    M = problem.M
    possible = None if problem.possible is None else (problem.possible[0][:, 0], problem.possible[1][:, 0])
    links = np.concatenate([np.arange(a, a + n - 1) for a, n in pieces]).astype(int)
    return ShootingProblem(sf, K, threads, problem.W[:, k0 * (M + 1):(k0 + K) * (M + 1)],
                           problem.H[:, k0 * M:(k0 + K) * M], problem.Y[k0:k0 + K], problem.mask[k0:k0 + K],
                           problem.wts, problem.sscale, links, possible)


def _stretch_terms(problem: ShootingProblem, sf: ShootingFunctions, fine: ShootingFunctions,
                   layouts: Sequence[RunLayout], k0: int, K: int, S: np.ndarray, p: np.ndarray,
                   threads: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(F, b) of one stretch: the parameters' information and the difference of the gradients
    with the fine and with the fit's residuals and defects, node states eliminated, both on the
    fit's linearisation: the Gauss-Newton steps (-F^-1 times the gradient) differ by -F^-1 b."""
    pieces = pieces_within(layouts, k0, K)
    coarse, finer = (_sub_problem(problem, f, k0, K, pieces, threads) for f in (sf, fine))
    Ss = S[:, k0:k0 + K]
    nx, nth = coarse.nx, coarse.nth
    eqs = [NormalEquations(pieces, nx, nth, K), NormalEquations(pieces, nx, nth, K)]
    has_next = np.zeros(K, bool)
    has_next[coarse.nxt] = True
    for a, b in coarse.spans:
        sim = coarse.span_simulation(Ss, p, a, b, True)
        other = finer.span_simulation(Ss, p, a, b, False)
        if sim is None or other is None:
            return None
        X, Sens = sim
        E, D = coarse.span_residuals(Ss, X, a, b)
        lin = linearize((E, D, X, Sens), coarse.out_idx, coarse.wts, coarse.mask[a:b], coarse.M, nx,
                        len(coarse.out_idx), nth)
        Ef, Df = coarse.span_residuals(Ss, other[0], a, b)
        eqs[0].add(lin, E, D * coarse.sscale[:, None], D, has_next)
        eqs[1].add(lin, Ef, Df * coarse.sscale[:, None], Df, has_next)
    E = eqs[0].N.schur()
    return E.information(), E.reduced(eqs[1].g - eqs[0].g)


def discretisation(problem: ShootingProblem, sf: ShootingFunctions, opts: IntegratorOptions,
                   layouts: Sequence[RunLayout], S: np.ndarray, p: np.ndarray, threads: int = 1,
                   progress=None) -> Discretisation | None:
    """The discretisation term of a fit at its solution (node states S, parameters p) on the
    problem it solved (`sf` with `opts`: its functions); None when a simulation is not finite
    or the normal equations are singular.

    Measured on stretches, the shift is their information-weighted mean; its uncertainty the
    spread between them (a sandwich over the stretches), times the share of the data they leave."""
    parts = stretches(layouts, problem.M)
    fine = fine_functions(sf, opts, progress)
    found = [_stretch_terms(problem, sf, fine, layouts, k0, K, S, p, threads) for k0, K in parts]
    if any(f is None for f in found):
        return None
    Fs = np.array([f[0] for f in found])
    bs = np.array([f[1] for f in found])
    try:
        Finv = scaled_inverse(Fs.sum(axis=0))
    except np.linalg.LinAlgError:
        return None
    shift = -Finv @ bs.sum(axis=0)  # the stretches' shifts -F_j^-1 b_j weighted by F_j
    cov = np.outer(shift, shift) * FINE_FACTOR ** 2
    n = len(parts)
    covered = sum(K for _, K in parts) / max(1, sum(l.K for l in layouts))
    if n > 1 and covered < 1:
        u = -bs - Fs @ shift  # F_j (shift_j - shift)
        cov = cov + (1 - covered) * (Finv @ (u.T @ u) @ Finv) * n / (n - 1)
    if not np.all(np.isfinite(cov)):
        return None
    M = problem.M
    return Discretisation(shift, cov, round(sum(float(problem.H[0, k0 * M:(k0 + K) * M].sum()) for k0, K in parts), 6))


def corrected(theta: np.ndarray, cov: np.ndarray | None, term: Discretisation | None, lower: np.ndarray,
              upper: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """(estimates, covariance) with the discretisation term: the estimates moved by its shift
    (kept within their bounds), its covariance added to the statistical one."""
    if term is None:
        return theta, cov
    return np.clip(theta + term.shift, lower, upper), None if cov is None else cov + term.cov


__all__ = ["Discretisation", "FINE_FACTOR", "SPAN_S", "STRETCH_S", "corrected", "discretisation",
           "fine_functions", "stretches"]
