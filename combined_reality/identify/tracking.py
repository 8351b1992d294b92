"""Whether the rig changed: tests on the stream of what each short block of data says about
the parameters.

The online estimator cuts its stream into blocks of about 0.2 s (whole shooting intervals).
Profiling a block's own start state out of its Gauss-Newton model leaves what that block
alone says about the parameters theta: a quadratic of theta, given by its gradient s and
information A at the point theta_lin where it was linearised (residuals in units of the
sensor noise). Blocks share nothing, so under a rig that does not change their quadratics
add up, and the generalised likelihood ratio (GLR) of any alternative is the decrease of the
summed quadratic that the alternative's extra parameters allow (twice it is chi-square
with as many degrees of freedom as they have, Basseville & Nikiforov 1993, ch. 7):

- a step: the parameters jump by delta at a block boundary b (the change's time unknown:
  the largest statistic over the boundaries, and the boundaries weighted by
  exp(statistic / 2) locate it, with its standard deviation);
- a drift: theta(t) = theta_now + beta (t - t_now), a linear trend over the blocks.

Model error that the plant does not describe makes the blocks disagree more than their noise
says (an effect the model lacks moves the locally best friction with the operating regime).
Each statistic is therefore divided by the blocks' over-dispersion around the alternative
it tests (their residual chi-square per degree of freedom, at least 1), as an F test does:
a model that explains the rig to within its noise keeps its chi-square scale, one that
explains it less well asks for correspondingly more evidence, and the standard deviations
of the estimates grow by the same factor.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

_RCOND = 1e-9  # directions with less information than this (relative, on the unit-diagonal scale) are none


def _scaled(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(A on its unit-diagonal scaling, the scale) for a stack of symmetric matrices."""
    d = np.sqrt(np.maximum(np.diagonal(A, axis1=-2, axis2=-1), 1e-300))
    return A / (d[..., :, None] * d[..., None, :]), d


def pinv(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(pseudo-inverse, rank) of a stack of symmetric information matrices, on their
    unit-diagonal scaling (parameters differ by ten decades)."""
    As, d = _scaled(A)
    w, V = np.linalg.eigh(As)
    keep = w > _RCOND * np.maximum(w[..., -1:], 1e-300)
    inv_w = np.where(keep, 1.0 / np.where(keep, w, 1.0), 0.0)
    P = (V * inv_w[..., None, :]) @ np.swapaxes(V, -1, -2)
    return P / (d[..., :, None] * d[..., None, :]), keep.sum(axis=-1)


def gain(G: np.ndarray, A: np.ndarray):
    """(decrease 0.5 G' A+ G of the quadratic G' d + 0.5 d' A d at its minimum, the step
    -A+ G to it, the rank of A, A+), stacked over leading dimensions."""
    P, rank = pinv(A)
    step = -(P @ G[..., None])[..., 0]
    return -0.5 * np.einsum("...i,...i->...", G, step), step, rank, P


_FIELDS = ("t0", "t1", "k", "theta", "s", "A", "low", "rank")


@dataclass
class Blocks:
    """What blocks of the stream say about the parameters: per block its first and last
    sample times, the global index of its first shooting interval, the point theta it was
    linearised at, its gradient s and information A there (the quadratic
    q(x) = s'(x - theta) + 0.5 (x - theta)' A (x - theta)), the quadratic's minimum `low`
    and the rank of A."""

    nth: int
    t0: np.ndarray = None
    t1: np.ndarray = None
    k: np.ndarray = None
    theta: np.ndarray = None
    s: np.ndarray = None
    A: np.ndarray = None
    low: np.ndarray = None
    rank: np.ndarray = None

    def __post_init__(self):
        n = self.nth
        if self.t0 is None:
            self.t0, self.t1, self.k = np.empty(0), np.empty(0), np.empty(0, int)
            self.theta, self.s, self.A = np.empty((0, n)), np.empty((0, n)), np.empty((0, n, n))
        if self.low is None:
            g, _, self.rank, _ = gain(self.s, self.A)
            self.low = -g

    def __len__(self) -> int:
        return len(self.t0)

    def extend(self, other: "Blocks") -> "Blocks":
        return Blocks(self.nth, *(np.concatenate([getattr(self, f), getattr(other, f)]) for f in _FIELDS))

    def select(self, which) -> "Blocks":
        return Blocks(self.nth, *(getattr(self, f)[which] for f in _FIELDS))

    def since(self, t: float) -> "Blocks":
        """The blocks that begin at or after t."""
        return self.select(self.t0 >= t - 1e-9)

    def at(self, theta_r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every block's quadratic re-centred at theta_r: its gradient there, and how far its
        value there lies above its minimum."""
        d = theta_r[None, :] - self.theta
        Ad = np.einsum("jab,jb->ja", self.A, d)
        q = np.einsum("ja,ja->j", self.s + 0.5 * Ad, d)
        return self.s + Ad, q - self.low


@dataclass(frozen=True)
class Fit:
    """The parameters of a stretch of blocks: estimate (at the stretch's end for a trend),
    covariance (over-dispersion included), and for a trend the rate and its covariance."""

    value: np.ndarray
    cov: np.ndarray
    rate: np.ndarray | None = None
    rate_cov: np.ndarray | None = None


@dataclass(frozen=True)
class Analysis:
    """The tests over a stretch of blocks (see the module's docstring). z_step, z_drift: the
    square roots of the GLR statistics divided by their over-dispersion (in units of a
    standard deviation: chi-square with nth degrees of freedom under a rig that does not
    change); the step's located time (mean and standard deviation over the boundaries'
    weights), the fits before and after it, and the trend's fit."""

    z_step: float
    z_drift: float
    boundary: int  # index of the first block after the most likely step (-1: none tested)
    t_change: float
    t_change_std: float
    before: Fit | None
    after: Fit | None
    trend: Fit | None
    constant: Fit
    dispersion: dict = field(default_factory=dict)  # per model: its over-dispersion factor


@dataclass(frozen=True)
class Change:
    """A detected change of the rig: its located time (rig clock) and standard deviation, the
    test statistic (standard deviations), the rig time of the update that found it, and per
    parameter the values before and after with their standard deviations and that of the
    change (after - before)."""

    t: float
    t_std: float
    z: float
    t_detected: float
    before: dict[str, float]
    after: dict[str, float]
    std_before: dict[str, float]
    std_after: dict[str, float]
    std: dict[str, float]


@dataclass(frozen=True)
class Drift:
    """The rig's parameters drift: rates per second with their standard deviations, the test
    statistic, and since when (rig clock) the estimate follows the drift."""

    rate: dict[str, float]
    rate_std: dict[str, float]
    z: float
    since: float


def _dispersion(chi2: float, dof: float) -> float:
    return max(1.0, chi2 / dof) if dof > 0 else 1.0


def analyse(blocks: Blocks, theta_r: np.ndarray, t_ref: float, min_before_s: float = 1.0,
            min_after: int = 1) -> Analysis:
    """The step and drift tests over `blocks` (in time order), re-centred at theta_r; the
    trend's value is that at t_ref. A step is tested at the boundaries with at least
    min_before_s of data before and min_after blocks after."""
    J, nth = len(blocks), blocks.nth
    G, above = blocks.at(theta_r)
    A = blocks.A
    # what every block's own best would gain from theta_r
    sum_own, sum_rank = float(above.sum()), float(blocks.rank.sum())
    Gc, Ac = G.cumsum(axis=0), A.cumsum(axis=0)
    g_all, step_all, rank_all, P_all = gain(Gc[-1], Ac[-1])
    c_const = _dispersion(2 * (sum_own - g_all), sum_rank - rank_all)
    constant = Fit(theta_r + step_all, c_const * P_all)

    # a step at boundary b: the blocks before it and those from it on fitted apart
    z_step, b_best, t_c, t_std, before, after, c_step = 0.0, -1, math.nan, math.nan, None, None, 1.0
    dur = blocks.t1 - blocks.t0
    span_before = np.r_[0.0, np.cumsum(dur)[:-1]]  # data before each block
    cand = np.flatnonzero((span_before >= min_before_s) & (np.arange(J) <= J - min_after))
    if len(cand):
        Gb, Ab = Gc[cand - 1], Ac[cand - 1]
        n = len(cand)  # before and after each boundary, in one stack
        g2, step2, rank2, P2 = gain(np.concatenate([Gb, Gc[-1] - Gb]), np.concatenate([Ab, Ac[-1] - Ab]))
        gb, step_b, rank_b, Pb = g2[:n], step2[:n], rank2[:n], P2[:n]
        ga, step_a, rank_a, Pa = g2[n:], step2[n:], rank2[n:], P2[n:]
        stat = 2 * (gb + ga - g_all)
        i = int(np.argmax(stat))
        b_best = int(cand[i])
        c_step = _dispersion(2 * (sum_own - gb[i] - ga[i]), sum_rank - rank_b[i] - rank_a[i])
        z_step = math.sqrt(max(float(stat[i]), 0.0) / c_step)
        # the change's time: the boundaries weighted by their likelihood ratios
        w = np.exp(0.5 * (stat - stat[i]) / c_step)
        w /= w.sum()
        tb = blocks.t0[cand]
        t_c = float(w @ tb)
        width = float(dur[b_best])  # the change lies somewhere in a block
        t_std = math.sqrt(float(w @ (tb - t_c) ** 2) + width ** 2 / 12)
        before = Fit(theta_r + step_b[i], c_step * Pb[i])
        after = Fit(theta_r + step_a[i], c_step * Pa[i])
        chi2_step = 2 * (sum_own - float(gb[i] + ga[i]))
    else:
        chi2_step = math.inf

    # a drift: theta_now + beta (t - t_ref)
    trend, g_tr, c_tr = _trend(blocks, G, theta_r, t_ref, sum_own, sum_rank)
    z_drift = math.sqrt(max(2 * float(g_tr - g_all), 0.0) / c_tr)
    # the residual chi-square each alternative leaves (the better one explains the blocks)
    return Analysis(z_step, z_drift, b_best, t_c, t_std, before, after, trend, constant,
                    {"constant": c_const, "step": c_step, "drift": c_tr, "step_chi2": chi2_step,
                     "drift_chi2": 2 * (sum_own - g_tr)})


def _trend(blocks: Blocks, G: np.ndarray, theta_r: np.ndarray, t_ref: float, sum_own: float, sum_rank: float):
    """(the trend's Fit at t_ref, its decrease of the summed quadratic, its over-dispersion)."""
    nth, A = blocks.nth, blocks.A
    tau = 0.5 * (blocks.t0 + blocks.t1) - t_ref
    H = np.zeros((2 * nth, 2 * nth))
    H[:nth, :nth] = A.sum(axis=0)
    H[:nth, nth:] = H[nth:, :nth] = np.einsum("j,jab->ab", tau, A)
    H[nth:, nth:] = np.einsum("j,jab->ab", tau * tau, A)
    G2 = np.r_[G.sum(axis=0), tau @ G]
    g_tr, step_tr, rank_tr, P2 = gain(G2, H)
    c_tr = _dispersion(2 * (sum_own - g_tr), sum_rank - rank_tr)
    fit = Fit(theta_r + step_tr[:nth], c_tr * P2[:nth, :nth], step_tr[nth:], c_tr * P2[nth:, nth:])
    return fit, float(g_tr), c_tr


def trend_fit(blocks: Blocks, theta_r: np.ndarray, t_ref: float) -> Fit:
    """The linear trend over `blocks`: its value at t_ref, its rate, their covariances
    (over-dispersion included)."""
    G, above = blocks.at(theta_r)
    return _trend(blocks, G, theta_r, t_ref, float(above.sum()), float(blocks.rank.sum()))[0]
