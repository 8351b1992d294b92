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
  the boundary with the largest statistic, and the boundaries weighted by exp(statistic / 2)
  locate it, with its standard deviation);
- a drift: theta(t) = theta_now + beta (t - t_now), a linear trend over the blocks.

Model error that the plant does not describe breaks the "blocks share nothing": an effect the
model lacks moves the locally best friction with the operating regime (a ramp, a sine, a
hold), by amounts that more data of the same regime do not reduce, and some regimes far more
than most. The tests therefore add a regime covariance to every estimate's noise covariance,
measured on the stream itself: how far stretches of 0.5, 1, 2 and 4 s (sliding by a block)
stray from the blocks' common trend beyond what their noise explains, the largest such
excursion divided by ENVELOPE (`regime_variances`, `Regime`). A model that explains the rig
leaves about none (a floor of 0.5 % of each value is kept), one that explains it less well
asks for correspondingly more evidence. A step is then judged by the Wald statistic of the
difference of the estimates before and after it (where it lies: the noise's likelihood
ratios), a drift by that of its rate; both in standard deviations (z).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

_RCOND = 1e-9  # directions with less information than this (relative, on the unit-diagonal scale) are none


def _scaled(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(A on its unit-diagonal scaling, the scale) for a stack of symmetric matrices."""
    d = np.sqrt(np.maximum(np.diagonal(A, axis1=-2, axis2=-1), 1e-300))
    return A / (d[..., :, None] * d[..., None, :]), d


def pinv(A: np.ndarray, rcond: float = _RCOND) -> tuple[np.ndarray, np.ndarray]:
    """(pseudo-inverse, rank) of a stack of symmetric information matrices, on their
    unit-diagonal scaling (parameters differ by ten decades): directions with less than
    `rcond` of the largest eigenvalue there get none."""
    As, d = _scaled(A)
    w, V = np.linalg.eigh(As)
    keep = w > rcond * np.maximum(w[..., -1:], 1e-300)
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

    def rows(self) -> list[tuple]:
        return list(zip(*(getattr(self, f) for f in _FIELDS)))

    @staticmethod
    def of_rows(nth: int, rows: list[tuple]) -> "Blocks":
        if not rows:
            return Blocks(nth)
        return Blocks(nth, *(np.array(col) for col in zip(*rows)))

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
    covariance (regime included), and for a trend the rate and its covariance."""

    value: np.ndarray
    cov: np.ndarray
    rate: np.ndarray | None = None
    rate_cov: np.ndarray | None = None


@dataclass(frozen=True)
class Analysis:
    """The tests over a stretch of blocks (see the module's docstring). z_step, z_drift: the
    square roots of the Wald statistics of the step and of the drift rate, regime covariance
    included (in standard deviations: chi-square with nth degrees of freedom under a rig that
    does not change); the step's located time (mean and standard deviation over the
    boundaries' weights), the fits before and after it, and the trend's fit."""

    z_step: float
    z_drift: float
    boundary: int  # index of the first block after the most likely step (-1: none tested)
    t_change: float
    t_change_std: float
    before: Fit | None
    after: Fit | None
    trend: Fit | None
    constant: Fit
    dispersion: dict = field(default_factory=dict)  # per model: the residual chi-square it leaves
    pending: float = 0.0  # z of a step found where too little has come after it yet (0: none)


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


def _clusters(blocks: Blocks, G: np.ndarray, cluster_s: float):
    """(gradient, information) of clusters of consecutive blocks, each about cluster_s long."""
    c = np.floor((blocks.t0 - blocks.t0[0]) / cluster_s).astype(int)
    starts = np.flatnonzero(np.r_[True, c[1:] != c[:-1]])
    return np.add.reduceat(G, starts, axis=0), np.add.reduceat(blocks.A, starts, axis=0)


# the largest squared excursion beyond the noise among a history's stretches, divided by
# this, is the regime variance: a regime that varied like Gaussian noise would put the
# largest square of the dozen or so independent stretches a history holds near 4.6
# variances; the heavy tails that some regimes give count more
ENVELOPE = 4.0


def regime_variances(blocks: Blocks, theta_r: np.ndarray, scales: Sequence[float]) -> list[np.ndarray | None]:
    """Per scale (s): the covariance (diagonal) by which stretches of about that long scatter
    around the blocks' common trend beyond what their noise explains, from the largest
    excursion of each parameter among the stretches that determine every parameter
    (ENVELOPE), or None with fewer than 4 such stretches. A model that explains the rig leaves
    about 0; an effect it lacks moves the locally best parameters with the operating regime (a
    ramp, a sine, a hold), which no amount of data averages out, and some regimes far more
    than most."""
    if not len(blocks):
        return [None] * len(scales)
    G, _ = blocks.at(theta_r)
    Gs = np.concatenate([np.zeros((1,) + G.shape[1:]), G.cumsum(axis=0)])
    As = np.concatenate([np.zeros((1,) + blocks.A.shape[1:]), blocks.A.cumsum(axis=0)])
    mid = 0.5 * (blocks.t0 + blocks.t1)
    block_s = max(float(np.median(blocks.t1 - blocks.t0)), 1e-9)
    trend = None  # around the blocks' trend (a rig that drifts has no more regime than one that does not)
    out: list[np.ndarray | None] = []
    for cluster_s in scales:
        # every stretch of about cluster_s (sliding by a block): a regime is not aligned to a grid
        n = max(1, int(round(cluster_s / block_s)))
        if len(blocks) < n:
            out.append(None)
            continue
        _, step, rank, P = gain(Gs[n:] - Gs[:-n], As[n:] - As[:-n])
        full = rank == blocks.nth
        if full.sum() < 4:
            out.append(None)
            continue
        if trend is None:
            trend, _ = _trend(blocks, G, theta_r, float(mid[-1]))
        t_w = 0.5 * (mid[n - 1:] + mid[:len(mid) - n + 1])
        line = trend.value - theta_r + np.outer(t_w - mid[-1], trend.rate)
        dev = step[full] - line[full]
        var = np.diagonal(P[full], axis1=1, axis2=2)
        # beyond what noise alone would put at the top of that many stretches (the largest of m
        # chi-square(1) lies near 2 ln m); a stretch that determines a parameter to no better
        # than half its value tells nothing of its regime
        noise = 2 * math.log(max(int(full.sum()), 2)) + 4
        told = np.isfinite(dev) & (var <= (0.5 * np.abs(trend.value)) ** 2)
        beyond = np.where(told, dev ** 2 - noise * var, 0.0)
        out.append(np.diag(np.maximum(beyond.max(axis=0), 0.0) / ENVELOPE))
    return out


@dataclass(frozen=True)
class Regime:
    """The rig's regime covariance at a few time scales: `cov[i]` is what stretches of about
    `scales[i]` seconds scatter by beyond their noise (regime_variances). A stretch of length
    L counts that of the largest scale not above L (the smallest for shorter ones); beyond
    the largest, it falls as scales[-1] / L."""

    scales: np.ndarray
    cov: np.ndarray

    def at(self, length) -> np.ndarray:
        length = np.asarray(length, float)
        i = np.clip(np.searchsorted(self.scales, length, side="right") - 1, 0, len(self.scales) - 1)
        f = np.minimum(1.0, self.scales[-1] / np.maximum(length, 1e-9))
        return f[..., None, None] * self.cov[i]


def analyse(blocks: Blocks, theta_r: np.ndarray, t_ref: float, regime: Regime | None = None,
            noise: float = 1.0, min_before_s: float = 1.0, min_after_s: float = 0.0,
            cluster_s: float = 1.0, recent_s: float = math.inf, drift_regime: Regime | None = None) -> Analysis:
    """The step and drift tests over `blocks` (in time order), re-centred at theta_r; the
    trend's value is that at t_ref. A step is looked for at the boundaries of the last
    recent_s (a moving-window GLR: an older step would have been found when it was recent)
    with at least min_before_s of data before it, and judged once min_after_s of data have
    come after the boundary where it most likely lies (z_step is 0 until then).

    Each estimate's covariance is its noise part (the inverse information, times `noise`,
    the residual variance in units of the sensor noise when above 1) plus the rig's regime
    covariance for a stretch of its length (`regime`; `drift_regime` for the drift's test,
    when another): what one operating regime moves the
    locally best parameters by, which more data of the same regime do not reduce. A step is
    then judged by the Wald statistic of the difference before and after it, a drift by that
    of its rate (whose regime part is that of a regression slope over the stretch with
    errors correlated over the largest scale R: 12 R / length^3)."""
    nth = blocks.nth
    if regime is None:
        regime = Regime(np.array([1.0]), np.zeros((1, nth, nth)))
    drift_regime = regime if drift_regime is None else drift_regime
    R, reg = float(drift_regime.scales[-1]), drift_regime.cov[-1]
    G, _ = blocks.at(theta_r)
    A = blocks.A
    dur = blocks.t1 - blocks.t0
    total = float(dur.sum())
    regime_cov = regime.at

    Gc, Ac = G.cumsum(axis=0), A.cumsum(axis=0)
    g_all, step_all, rank_all, P_all = gain(Gc[-1], Ac[-1])
    constant = Fit(theta_r + step_all, noise * P_all + regime_cov(total))

    step = _step_test(blocks, theta_r, Gc, Ac, g_all, rank_all, regime_cov, noise, min_before_s, min_after_s,
                      t_ref - recent_s)
    # what clusters of 2 cluster_s would gain on their own: the residual chi-square each
    # alternative leaves is that less what it gains (the better one explains the blocks)
    g_own = float(gain(*_clusters(blocks, G, 2 * cluster_s))[0].sum())
    chi2_step = math.inf if step is None else 2 * (g_own - step.gain)

    # a drift: theta_now + beta (t - t_ref)
    trend, g_tr = _trend(blocks, G, theta_r, t_ref, noise)
    trend = Fit(trend.value, trend.cov + drift_regime.at(total), trend.rate,
                trend.rate_cov + reg * 12 * R / max(total, R) ** 3)
    W, _ = pinv(trend.rate_cov)
    z_drift = math.sqrt(max(float(trend.rate @ W @ trend.rate), 0.0))
    dispersion = {"step_chi2": chi2_step, "drift_chi2": 2 * (g_own - g_tr)}
    if step is None:
        return Analysis(0.0, z_drift, -1, math.nan, math.nan, None, None, trend, constant, dispersion)
    return Analysis(step.z, z_drift, step.boundary, step.t, step.t_std, step.before, step.after, trend, constant,
                    dispersion, step.pending)


@dataclass(frozen=True)
class _Step:
    """The most likely step: its Wald statistic (0 while pending), the first block after it,
    its located time, the fits before and after it, their summed gain, and the statistic of
    a step found where too little has come after it yet."""

    z: float
    boundary: int
    t: float
    t_std: float
    before: Fit
    after: Fit
    gain: float
    pending: float


def _step_test(blocks: Blocks, theta_r: np.ndarray, Gc, Ac, g_all: float, rank_all, regime_cov, noise: float,
               min_before_s: float, min_after_s: float, t_from: float) -> _Step | None:
    """The step most likely at a block boundary from t_from on with min_before_s of data before
    it (the blocks before it and those from it on fitted apart, re-centred at theta_r; Gc, Ac
    the blocks' running sums), or None where no boundary is judged."""
    J, dur = len(blocks), blocks.t1 - blocks.t0
    total = float(dur.sum())
    # data before and after each block's start (a block's last sample holds for a period too)
    period = float(np.median(blocks.t0[1:] - blocks.t1[:-1])) if J > 1 else 0.0
    span_before = np.r_[0.0, np.cumsum(dur + period)[:-1]]
    span_after = total + J * period - span_before
    cand = np.flatnonzero((span_before >= min_before_s) & (np.arange(J) >= 1) & (blocks.t0 >= t_from))
    if not len(cand):
        return None
    Gb, Ab = Gc[cand - 1], Ac[cand - 1]
    n = len(cand)  # before and after each boundary, in one stack
    g2, step2, rank2, P2 = gain(np.concatenate([Gb, Gc[-1] - Gb]), np.concatenate([Ab, Ac[-1] - Ab]))
    # a step is judged only where the data on each side determine what all of them do (a
    # hold at an end stop does not determine the friction: its pseudo-inverse would claim
    # the undetermined directions known exactly)
    judged = (rank2[:n] >= rank_all) & (rank2[n:] >= rank_all)
    cand, n = cand[judged], int(judged.sum())
    if not n:
        return None
    keep = np.concatenate([judged, judged])
    g2, step2, P2 = g2[keep], step2[keep], P2[keep]
    cov_b = noise * P2[:n] + regime_cov(span_before[cand])
    cov_a = noise * P2[n:] + regime_cov(span_after[cand])
    # where: the likelihood ratio of the noise alone (a regime's part depends on the
    # stretches' lengths, and would draw the boundary to where they are long)
    glr = 2 * (g2[:n] + g2[n:] - g_all)
    i = int(np.argmax(glr))
    d = step2[n + i] - step2[i]
    W, _ = pinv(cov_a[i] + cov_b[i])
    b_best, z_step, pending = int(cand[i]), math.sqrt(max(float(d @ W @ d), 0.0)), 0.0
    if span_after[b_best] < min_after_s:  # found where too little has come after it yet: wait
        pending, z_step = z_step, 0.0
    # the change's time: the boundaries weighted by their likelihood ratios
    w = np.exp(0.5 * (glr - glr[i]) / max(1.0, noise))
    w /= w.sum()
    tb = blocks.t0[cand]
    t_c = float(w @ tb)
    width = float(dur[b_best])  # the change lies somewhere in a block
    t_std = math.sqrt(float(w @ (tb - t_c) ** 2) + width ** 2 / 12)
    return _Step(z_step, b_best, t_c, t_std, Fit(theta_r + step2[i], cov_b[i]), Fit(theta_r + step2[n + i], cov_a[i]),
                 float(g2[i] + g2[n + i]), pending)


def _trend(blocks: Blocks, G: np.ndarray, theta_r: np.ndarray, t_ref: float, noise: float = 1.0):
    """(the trend's Fit at t_ref (noise part of the covariances), its decrease of the summed quadratic)."""
    nth, A = blocks.nth, blocks.A
    tau = 0.5 * (blocks.t0 + blocks.t1) - t_ref
    H = np.zeros((2 * nth, 2 * nth))
    H[:nth, :nth] = A.sum(axis=0)
    H[:nth, nth:] = H[nth:, :nth] = np.einsum("j,jab->ab", tau, A)
    H[nth:, nth:] = np.einsum("j,jab->ab", tau * tau, A)
    G2 = np.r_[G.sum(axis=0), tau @ G]
    g_tr, step_tr, _, P2 = gain(G2, H)
    fit = Fit(theta_r + step_tr[:nth], noise * P2[:nth, :nth], step_tr[nth:], noise * P2[nth:, nth:])
    return fit, float(g_tr)


def trend_fit(blocks: Blocks, theta_r: np.ndarray, t_ref: float, regime: Regime | None = None,
              noise: float = 1.0) -> Fit:
    """The linear trend over `blocks`: its value at t_ref and its rate, with covariances
    (the regime covariance included, as in `analyse`)."""
    G, _ = blocks.at(theta_r)
    fit, _ = _trend(blocks, G, theta_r, t_ref, noise)
    if regime is None:
        return fit
    total = float((blocks.t1 - blocks.t0).sum())
    R = float(regime.scales[-1])
    return Fit(fit.value, fit.cov + regime.at(total), fit.rate,
               fit.rate_cov + regime.cov[-1] * 12 * R / max(total, R) ** 3)
