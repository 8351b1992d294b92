"""The multiple-shooting least-squares problem shared by the offline identifier and the
moving-horizon estimator: the layout of runs into shooting intervals, the weighted
residuals and defects, their linearisation, the condensing of node increments, the
bounded Gauss-Newton step with its line search, and the covariance of the estimate.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace
from typing import Callable, Mapping, Sequence

import numpy as np

from sim.compiled import NumpyCall, ShootingFunctions
from sim.cylinder import ESTIMABLE, PARAMETERS, Cylinder
from sim.extension import Effect
from sim.plant import Plant

from ..errors import ToolFailure
from ..files import Run
from .smoothing import fill_missing, velocity_estimate

UNITS = {name: spec.unit for name, spec in PARAMETERS.items()}


class IdentificationError(ToolFailure, RuntimeError):
    """The identification could not be carried out (the message says why; exit status 1)."""


@dataclass(frozen=True)
class PriorRow:
    """Prior knowledge of the estimated parameters as one more least-squares residual,
    (sum_i coefficients[i] * theta_i - target) / std: what the runs leave undetermined
    follows it, what they determine hardly notices it."""

    coefficients: Mapping[str, float]
    target: float
    std: float


def prior_matrix(rows: Sequence[PriorRow], estimate: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """(G, t) with the prior residual G theta - t (rows scaled by 1/std), for the rows whose
    parameters are all estimated."""
    index = {n: i for i, n in enumerate(estimate)}
    use = [r for r in rows if r.coefficients and all(n in index for n in r.coefficients)]
    G = np.zeros((len(use), len(estimate)))
    t = np.zeros(len(use))
    for k, r in enumerate(use):
        for n, c in r.coefficients.items():
            G[k, index[n]] = c / r.std
        t[k] = r.target / r.std
    return G, t


@dataclass
class RunLayout:
    """One run cut into K shooting intervals of M samples (the last one padded)."""

    run: Run
    K: int  # intervals
    node0: int  # index of its first node among all nodes
    W: np.ndarray  # (nw, K*(M+1)) inputs at both ends of every sample step
    H: np.ndarray  # (1, K*M) step lengths (0 = padding)
    Y: np.ndarray  # (K, M, ny) measured outputs (0 where not measured)
    mask: np.ndarray  # (K, M, ny) True where a sample exists and that output was measured (1 byte a value)
    S0: np.ndarray  # (nx, K) initial node states


def concatenated_layouts(layouts: Sequence[RunLayout]) -> tuple[list[RunLayout], tuple[np.ndarray, ...]]:
    """The runs' W, H, Y, mask and S0 side by side (intervals in the order of the runs), and the
    layouts again with views of them: each run's data are held once."""
    if len(layouts) == 1:
        l = layouts[0]
        return list(layouts), (l.W, l.H, l.Y, l.mask, l.S0)
    M = layouts[0].Y.shape[1]
    W = np.hstack([l.W for l in layouts])
    H = np.hstack([l.H for l in layouts])
    Y = np.concatenate([l.Y for l in layouts])  # (Ktot, M, ny)
    mask = np.concatenate([l.mask for l in layouts])  # (Ktot, M, ny)
    S = np.hstack([l.S0 for l in layouts])  # (nx, Ktot)
    views = [replace(l, W=W[:, l.node0 * (M + 1):(l.node0 + l.K) * (M + 1)], H=H[:, l.node0 * M:(l.node0 + l.K) * M],
                     Y=Y[l.node0:l.node0 + l.K], mask=mask[l.node0:l.node0 + l.K], S0=S[:, l.node0:l.node0 + l.K])
             for l in layouts]
    return views, (W, H, Y, mask, S)


def free_parameters(plant: Plant, estimate: Sequence[str]) -> list[int]:
    """Indices of the estimated parameters in the plant's parameter vector (checked)."""
    for name in estimate:
        if name not in plant.param_names or (name in PARAMETERS and name not in ESTIMABLE):
            raise IdentificationError(f"parameter '{name}' cannot be estimated (estimable: "
                                      f"{', '.join(ESTIMABLE + tuple(n for n in plant.param_names if '.' in n))}).")
    return [plant.param_names.index(n) for n in estimate]


def sensor_noise(cyl: Cylinder, outputs: Sequence[str]) -> np.ndarray:
    """Standard deviation of the sensor noise of each output (x, p1, p2)."""
    sen = cyl.sensors
    return np.array([sen.position_noise if o == "x" else sen.pressure_noise for o in outputs])


def residual_scales(plant: Plant, cyl: Cylinder, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Output weights (1 / sensor noise) and defect scales (what a state can be trusted to
    from the sensors)."""
    sen = cyl.sensors
    wts = 1.0 / sensor_noise(cyl, plant.output_names)
    sscale = np.array([{"p1": sen.pressure_noise, "p2": sen.pressure_noise, "x": sen.position_noise,
                        "v": sen.position_noise / dt}.get(n, 1e-3) for n in plant.state_names])
    return wts, sscale


def run_layout(run: Run, plant: Plant, cyl: Cylinder, M: int, node0: int) -> RunLayout:
    """The run's intervals, inputs, measurements and initial node states (from the measured
    state and a smoothed velocity); `node0` is the index of its first node among all runs'.
    An output not measured at a sample (NaN) has no residual there; the node states, only a
    starting guess, take the nearest measured values."""
    N = run.n
    K = math.ceil(N / M)
    pad = K * M + 1 - N
    x, p1, p2 = (fill_missing(run.t, c) for c in (run.x, run.p1, run.p2))
    v = velocity_estimate(run.t, x)
    # a driving velocity: central differences of the measured position, interpolated linearly
    # over each sample like the position (a sum of them telescopes, so its noise does not
    # accumulate, and unlike a smoothed velocity it keeps the fast changes of an impact)
    signals = {"u": run.u, "x": x, "v": np.gradient(x, run.t), "p1": p1, "p2": p2}
    w = np.vstack([signals[n] for n in plant.input_names])
    w_pad = np.hstack([w, np.repeat(w[:, -1:], pad, axis=1)])  # (nw, K*M+1)
    idx = (np.arange(K)[:, None] * M + np.arange(M + 1)[None, :]).ravel()
    W = w_pad[:, idx]
    dt = np.diff(run.t)
    H = np.concatenate([dt, np.zeros(K * M - len(dt))])[None, :]
    meas = {"x": run.x, "p1": run.p1, "p2": run.p2}
    ys = np.stack([meas[n] for n in plant.output_names], axis=-1)  # (N, ny)
    ys = np.vstack([ys, np.full((K * M - N, ys.shape[1]), np.nan)])
    mask = np.isfinite(ys)
    ys = np.where(mask, ys, 0.0)
    nodes = np.arange(K) * M
    S0 = np.array([plant.initial_state(cyl, x[i], p1[i], p2[i], v[i]) for i in nodes]).T
    return RunLayout(run, K, node0, W, H, ys.reshape(K, M, -1), mask.reshape(K, M, -1), S0)



# a line search's trial is simulated in this many pieces of its intervals, so that one whose
# merit the first pieces already put above the acceptance bound is given up early
TRIAL_CHUNKS = 8

# The intervals of a fit are simulated and linearised a chunk of about this many samples at a
# time: what a fit holds then grows with the run only by the data and a few numbers per interval,
# never by the sensitivities (1.2 kB per sample with Fc, Fv, kp free: a 1000 s run at 1 kHz
# passed 2 GiB). A 20 s run at 1 kHz is one chunk, fitted as a whole.
CHUNK_SAMPLES = 1 << 15
# ... and a chunk's sensitivities (nx * (nx + nth) numbers a sample) at most this many numbers:
# a fit of many parameters takes shorter chunks (calibrate's whole model, 42 free: 7.4 kB a
# sample in all its copies, 240 MB a chunk of CHUNK_SAMPLES). A 20 s run at 1 kHz of that
# model is still one chunk.
CHUNK_SENSITIVITIES = 1 << 22


def chunk_intervals(M: int, nx: int, nth: int) -> int:
    """Intervals of M samples in a chunk (ShootingProblem.spans): CHUNK_SAMPLES at most, and
    CHUNK_SENSITIVITIES numbers of sensitivities to (nx states, nth parameters) at most; a
    multiple of TRIAL_CHUNKS (a chunk's sensitivities are computed in that many pieces)."""
    samples = min(CHUNK_SAMPLES, CHUNK_SENSITIVITIES // (nx * (nx + nth)))
    return max(TRIAL_CHUNKS, samples // M // TRIAL_CHUNKS * TRIAL_CHUNKS)


class ShootingProblem:
    """Weighted output residuals and scaled continuity defects of K shooting intervals."""

    def __init__(self, sf: ShootingFunctions, K: int, threads: int, W, H, Y, mask, wts, sscale, nxt,
                 possible: tuple[np.ndarray, np.ndarray] | None = None):
        plant = sf.plant
        # node states outside this range (Plant.possible_states) are not simulated
        self.possible = None if possible is None else (possible[0][:, None], possible[1][:, None])
        self.W, self.H, self.Y, self.mask, self.wts, self.sscale, self.nxt = W, H, Y, mask, wts, sscale, nxt
        self.K, self.M = K, sf.interval_len
        self.plant = plant
        self._sf, self._threads = sf, threads
        self.nx, self.nth = plant.nx, len(sf.free)
        self.out_idx = [plant.state_names.index(n) for n in plant.output_names]
        self._maps: dict[tuple[bool, int], NumpyCall] = {}
        size = chunk_intervals(self.M, self.nx, self.nth)
        # (first, end) intervals of each chunk: linearised, and a trial's merit summed, a chunk at a time
        self.spans = [(a, min(a + size, K)) for a in range(0, K, size)]
        # a chunk's sensitivities are computed this many intervals at a time, into one array: a
        # map function holds its results between calls, the pieces' (at most two sizes) are small
        self.sens_piece = size // TRIAL_CHUNKS

    @functools.cached_property
    def f_sens(self) -> NumpyCall:
        """The sensitivities of all K intervals in one call (the online window's)."""
        return self._map(True, self.K)

    @functools.cached_property
    def f_sim(self) -> NumpyCall:
        return self._map(False, self.K)

    def _map(self, with_sens: bool, n: int) -> NumpyCall:
        """The interval function (or its sensitivities) over n intervals, on the problem's threads."""
        if (with_sens, n) not in self._maps:
            f = self._sf.sens if with_sens else self._sf.interval
            threads = min(self._threads, n)
            self._maps[with_sens, n] = NumpyCall(f.map(n, "thread", threads) if threads > 1 else f.map(n))
        return self._maps[with_sens, n]

    def evaluate(self, S: np.ndarray, p: np.ndarray, with_sens: bool):
        """(E, D, X, Sens) of all intervals at once, or None when the simulation is not finite or a
        node state impossible."""
        sim = self.simulate(S, p, with_sens)
        if sim is None:
            return None
        E, D = self.residuals(S, sim[0])
        return E, D, *sim

    def span_simulation(self, S: np.ndarray, p: np.ndarray, a: int, b: int, with_sens: bool,
                        W: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None] | None:
        """(X, Sens) of intervals a..b-1 (with the inputs W, default the problem's), or None when
        not finite. The node states must be possible (allows)."""
        nx, M = self.nx, self.M
        W = self.W if W is None else W
        if not with_sens:
            out = self._map(False, b - a)(S[:, a:b], W[:, a * (M + 1):b * (M + 1)], p, self.H[:, a * M:b * M])
            X = out[0].reshape(nx, b - a, M)
            return (X, None) if np.all(np.isfinite(X)) else None
        X = np.empty((nx, b - a, M))
        Sens = np.empty((nx, b - a, M, nx + self.nth))
        for c in range(a, b, self.sens_piece):
            d = min(c + self.sens_piece, b)
            out = self._map(True, d - c)(S[:, c:d], W[:, c * (M + 1):d * (M + 1)], p, self.H[:, c * M:d * M])
            X[:, c - a:d - a] = out[0].reshape(nx, d - c, M)
            Sens[:, c - a:d - a] = out[1].reshape(nx, d - c, M, nx + self.nth)
        if not np.all(np.isfinite(X)):
            return None
        return X, Sens

    def span_residuals(self, S: np.ndarray, X: np.ndarray, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        """E (b-a, M, ny) and the defects D of the links from intervals a..b-1 (their successors'
        node states are known), as `residuals` gives them for those intervals."""
        E = shooting_residuals(S[:, a:b], X, self.Y[a:b], self.mask[a:b], self.wts, self.sscale, self.nxt[:0],
                               self.out_idx)[0]
        links = self.nxt[(self.nxt >= a) & (self.nxt < b)]
        D = (X[:, links - a, self.M - 1] - S[:, links + 1]) / self.sscale[:, None]
        return E, D

    def merit_terms(self, S: np.ndarray, p: np.ndarray,
                    give_up: Callable[[np.ndarray, np.ndarray], bool] | None = None
                    ) -> tuple[float, np.ndarray] | None:
        """(sum of the squared residuals, defects D) of a trial, or None when its simulation is not
        finite or a node state impossible.

        Each chunk is simulated in pieces (TRIAL_CHUNKS for the whole run): `give_up(E, D)` is
        called with the residuals and defects of each piece as it is simulated, in order (never
        with the last: that one is whole); True ends the simulation there (None). A line search's
        trial whose merit the first pieces already put above the acceptance bound is rejected at
        a fraction of a whole simulation; one that is not given up gives the same numbers."""
        nx, M = self.nx, self.M
        if not self.allows(S):
            return None
        piece = -(-self.K // TRIAL_CHUNKS)
        total, defects = None, []
        for a0, b0 in self.spans:
            X = np.empty((nx, b0 - a0, M))
            for a in range(a0, b0, piece):
                b = min(a + piece, b0)
                sim = self.span_simulation(S, p, a, b, False)
                if sim is None:
                    return None
                X[:, a - a0:b - a0] = sim[0]
                if give_up is not None and b < self.K and give_up(*self.span_residuals(S, sim[0], a, b)):
                    return None
            E, D = self.span_residuals(S, X, a0, b0)
            part = float(np.sum(E * E))
            total = part if total is None else total + part
            defects.append(D)
        return total, np.hstack(defects)

    def linearise(self, S: np.ndarray, p: np.ndarray, eqs: "NormalEquations") -> "NormalEquations | None":
        """The condensed normal equations at (S, p), accumulated into `eqs` (fresh) a chunk of
        intervals at a time; None when the simulation is not finite or a node state impossible."""
        if not self.allows(S):
            return None
        has_next = np.zeros(self.K, bool)
        has_next[self.nxt] = True
        for a, b in self.spans:
            sim = self.span_simulation(S, p, a, b, True)
            if sim is None:
                return None
            X, Sens = sim
            E, D = self.span_residuals(S, X, a, b)
            lin = linearize((E, D, X, Sens), self.out_idx, self.wts, self.mask[a:b], self.M, self.nx,
                            len(self.out_idx), self.nth)
            eqs.add(lin, E, D * self.sscale[:, None], D, has_next, keep=len(self.spans) == 1)
        return eqs

    def allows(self, S: np.ndarray) -> bool:
        """Whether every node state in S is a possible state of the plant."""
        return self.possible is None or bool(np.all((S >= self.possible[0]) & (S <= self.possible[1])))

    def simulate(self, S: np.ndarray, p: np.ndarray, with_sens: bool):
        """(X, Sens) of the intervals from node states S, or None when the simulation is not
        finite or a node state impossible.

        A step from a far-off linearisation can put node states at 1e20 Pa: simulating from
        there refines every sample and costs ten normal evaluations (a strong dead zone's
        nominal fit spent 12.7 of its 13.2 s so), and the line search rejects the result anyway."""
        nx, K, M = self.nx, self.K, self.M
        if not self.allows(S):
            return None
        if with_sens:
            Xr, Sr = self.f_sens(S, self.W, p, self.H)
            X = Xr.reshape(nx, K, M)
            Sens = Sr.reshape(nx, K, M, nx + self.nth)
        else:
            X = self.f_sim(S, self.W, p, self.H)[0].reshape(nx, K, M)
            Sens = None
        if not np.all(np.isfinite(X)):
            return None
        return X, Sens

    def residuals(self, S: np.ndarray, X: np.ndarray):
        return shooting_residuals(S, X, self.Y, self.mask, self.wts, self.sscale, self.nxt, self.out_idx)


def shooting_residuals(S: np.ndarray, X: np.ndarray, Y: np.ndarray, mask: np.ndarray, wts: np.ndarray,
                       sscale: np.ndarray, nxt: np.ndarray, out_idx: Sequence[int]):
    """Weighted output residuals E (K, M, ny) and scaled continuity defects D (nx, len(nxt)) of
    node states S (nx, K) and trajectories X (nx, K, M); nxt: the intervals whose successor is
    joined to them by continuity."""
    M = X.shape[2]
    # predicted outputs at the interval's own samples: node state, then the first M-1 steps
    Ypred = np.concatenate([S[out_idx, :, None], X[out_idx][:, :, : M - 1]], axis=2).transpose(1, 2, 0)
    E = (Ypred - Y) * wts * mask  # (K, M, ny)
    D = (X[:, nxt, M - 1] - S[:, nxt + 1]) / sscale[:, None]  # scaled defects (nx, n_links)
    return E, D


def warm_nodes(plant: Plant, cyl: Cylinder, S: np.ndarray, warm: np.ndarray) -> np.ndarray:
    """Node states of an earlier solution on the same runs and intervals (a warm start, e.g.
    another model's): its drive states are taken (where one is NaN, S's from the data), the
    states this plant adds start from their initial values at those nodes."""
    nb = 4 if plant.drive == "command" else 2
    if warm.ndim != 2 or warm.shape[1] != S.shape[1] or warm.shape[0] < nb:
        raise ValueError(f"warm-start nodes of shape {warm.shape} do not fit {S.shape[1]} intervals")
    out = S.copy()
    out[:nb] = np.where(np.isfinite(warm[:nb]), warm[:nb], S[:nb])
    # the chambers drive has no motion states (x, v are its inputs): its added states keep S's,
    # which run_layout took from the measured motion
    if plant.nx > nb and "x" in plant.state_names:
        names = plant.state_names
        ix, iv = names.index("x"), names.index("v")
        ip1 = names.index("p1") if "p1" in names else None
        for k in range(S.shape[1]):
            p1 = out[ip1, k] if ip1 is not None else 0.0
            p2 = out[ip1 + 1, k] if ip1 is not None else 0.0
            out[nb:, k] = plant.initial_state(cyl, out[ix, k], p1, p2, out[iv, k])[nb:]
    return out


def with_effect_values(e: Effect, values: Mapping[str, float]) -> Effect:
    """The effect with some parameter values replaced (e.g. by their estimates)."""
    return replace(e, **values) if values else e


def parameter_unit(plant: Plant, name: str) -> str:
    if name in UNITS:
        return UNITS[name]
    ename, pname = name.split(".", 1)
    eff = next(e for e in plant.effects if e.name == ename)
    return eff.PARAMS[pname].unit


def at_bounds(value, lower, upper):
    """Whether a value sits at a bound of its range. The tolerance is relative to the range,
    not to the value's magnitude: a leak conductance of 1e-11 m^3/(s Pa) is far from its bound
    0 in a range of 1e-7."""
    value, lower, upper = (np.asarray(a, float) for a in (value, lower, upper))
    tol = 1e-9 * (upper - lower)
    return (value - lower <= tol) | (upper - value <= tol)


def parameter_bounds(plant: Plant, names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = [], []
    for n in names:
        if n in PARAMETERS:
            lo.append(PARAMETERS[n].lower)
            hi.append(PARAMETERS[n].upper)
        else:
            ename, pname = n.split(".", 1)
            info = next(e for e in plant.effects if e.name == ename).PARAMS[pname]
            lo.append(info.lower)
            hi.append(info.upper)
    return np.array(lo, float), np.array(hi, float)


def line_search(evaluate, merit, S, dS, theta, dth, p, free, lower, upper, m0: float, slope: float,
                min_alpha: float, part: Callable[[np.ndarray, np.ndarray], float] | None = None):
    """Backtracking from the full step on an l1 merit (Armijo, or a tie at the numerical noise
    floor): (alpha, S, theta, p, evaluation) of the first accepted trial, or None.

    With `part(E, D)`, the merit's share of some intervals' residuals and defects (the rest,
    a prior, is >= 0), a trial whose first intervals already put the merit above m0 is given
    up there (ShootingProblem.merit_terms): such a trial could not be accepted, so the steps are
    the same, found with less simulation."""
    bound = m0 + 1e-9 * max(abs(m0), 1.0)  # above it neither the Armijo test nor a tie can hold
    alpha = 1.0
    while alpha >= min_alpha:
        th = np.clip(theta + alpha * dth, lower, upper)
        p_try = p.copy()
        p_try[free] = th
        S_try = S + alpha * dS
        if part is None:
            ev = evaluate(S_try, p_try, False)
        else:
            so_far = [0.0]

            def give_up(E, D) -> bool:
                so_far[0] += part(E, D)
                return so_far[0] > bound

            ev = evaluate(S_try, p_try, False, give_up)
        if ev is not None:
            m1 = merit(ev, th)
            if m1 <= m0 + 1e-4 * alpha * slope or abs(m1 - m0) <= 1e-12 * max(m0, 1.0):
                return alpha, S_try, th, p_try, ev
        alpha *= 0.5
    return None


@dataclass(frozen=True)
class ReducedNormal:
    """The reduced normal matrix in (the start state of each of R runs or gap-free pieces, the
    parameters): a piece's start state couples with the parameters only (an arrowhead), so the
    matrix is held as its blocks, per piece S (R, nx, nx) and C (R, nx, nth), and T (nth, nth);
    solves and covariances eliminate the start states piece by piece (a Schur complement, see
    `schur`), in time and memory linear in the pieces (an hour with one lost sample a second:
    3600 pieces, whose dense matrix took 1.7 GB). Accumulated in place (NormalEquations), used
    as a value."""

    S: np.ndarray
    C: np.ndarray
    T: np.ndarray

    @classmethod
    def zeros(cls, R: int, nx: int, nth: int) -> "ReducedNormal":
        return cls(np.zeros((R, nx, nx)), np.zeros((R, nx, nth)), np.zeros((nth, nth)))

    @property
    def n_state(self) -> int:
        return self.S.shape[0] * self.S.shape[1]

    def diagonal(self) -> np.ndarray:
        return np.concatenate([np.diagonal(self.S, axis1=1, axis2=2).ravel(), np.diag(self.T)])

    def finite(self) -> bool:
        return bool(np.all(np.isfinite(self.S)) and np.all(np.isfinite(self.C)) and np.all(np.isfinite(self.T)))

    def with_parameters(self, A: np.ndarray) -> "ReducedNormal":
        """The matrix with A added to its parameter block (a prior, an arrival cost)."""
        return replace(self, T=self.T + A)

    def with_states(self, diag: np.ndarray) -> "ReducedNormal":
        """The matrix with `diag` (one per start state, in order) added to its diagonal."""
        S = self.S.copy()
        idx = np.arange(S.shape[1])
        S[:, idx, idx] += np.reshape(diag, S.shape[:2])
        return replace(self, S=S)

    def quadratic(self, z: np.ndarray) -> float:
        """z'Nz."""
        zs, zt = z[:self.n_state].reshape(self.S.shape[:2]), z[self.n_state:]
        return float(np.sum(zs * ((self.S @ zs[:, :, None])[..., 0] + 2.0 * (self.C @ zt)))) + float(zt @ self.T @ zt)

    def scaled(self) -> "ScaledNormal":
        """The matrix with its unit-diagonal scaling: parameters differ by 10 decades."""
        scale = np.sqrt(np.maximum(self.diagonal(), 1e-300))
        ss, st = scale[:self.n_state].reshape(self.S.shape[:2]), scale[self.n_state:]
        unit = ReducedNormal(self.S / (ss[:, :, None] * ss[:, None, :]), self.C / (ss[:, :, None] * st),
                             self.T / np.outer(st, st))
        return ScaledNormal(self, unit, ss, st)

    def schur(self, keep: int | None = None) -> "Schur":
        """The start states eliminated (and the parameters after the first `keep`): ScaledNormal.schur."""
        return self.scaled().schur(keep)


@dataclass(frozen=True)
class ScaledNormal:
    """A reduced normal matrix N and its unit-diagonal scaling `unit` = N / (s s') (damped:
    its diagonal times 1 + lam), the scales s held as those of the start states ss (R, nx) and
    of the parameters st (nth): scaled once for any damping."""

    N: ReducedNormal
    unit: ReducedNormal
    ss: np.ndarray
    st: np.ndarray

    @property
    def scale(self) -> np.ndarray:
        return np.concatenate([self.ss.ravel(), self.st])

    def damped(self, lam: float) -> "ScaledNormal":
        """The unit-diagonal matrix with its diagonal times 1 + lam (Levenberg-Marquardt)."""
        U = self.unit
        return replace(self, unit=U.with_states(lam * np.diagonal(U.S, axis1=1, axis2=2))
                       .with_parameters(lam * np.diag(np.diag(U.T))))

    def schur(self, keep: int | None = None, rhs: np.ndarray | None = None) -> "Schur":
        """The start states eliminated piece by piece from the unit-diagonal matrix, and with
        them the parameters after the first `keep` (nuisances: the online window's gap offsets;
        None: none); `rhs` (R, nx): the state parts of a right-hand side (unit-diagonal)
        eliminated along (Schur.solve)."""
        U, nth = self.unit, len(self.st)
        B = U.C if rhs is None else np.concatenate([U.C, rhs[:, :, None]], axis=2)
        try:
            WB, singular = np.linalg.solve(U.S, B), False
        except np.linalg.LinAlgError:
            WB, singular = np.linalg.pinv(U.S, rcond=1e-12, hermitian=True) @ B, True
        CtW = np.sum(U.C.transpose(0, 2, 1) @ WB, axis=0)
        return Schur(self, WB[..., :nth], U.T - CtW[:, :nth], singular, nth if keep is None else keep,
                     WB[..., nth:], CtW[:, nth:])


@dataclass(frozen=True)
class Schur:
    """The start states eliminated from a scaled reduced normal matrix (ScaledNormal.schur), on
    its unit-diagonal scaling: W = S^-1 C per piece and the parameters' Schur complement
    A = T - sum C'W; the parameters after the first `keep` (nuisances) are eliminated from A in
    turn (`profile`); x = S^-1 rhs and Cx = sum C'x of a right-hand side eliminated along.
    Where a block S is `singular`, its pseudo-inverse stands for S^-1: steps are least-squares
    ones and N has no inverse (LinAlgError)."""

    scaled: ScaledNormal
    W: np.ndarray
    A: np.ndarray
    singular: bool
    keep: int
    x: np.ndarray
    Cx: np.ndarray

    @functools.cached_property
    def profile(self) -> tuple[np.ndarray, np.ndarray]:
        """(X, H): the nuisances' response A_nn^-1 A_nk to the kept parameters and the kept
        parameters' information A_kk - A_kn X (unit-diagonal); LinAlgError where A_nn is singular."""
        k = self.keep
        if k == len(self.A):
            return np.zeros((0, k)), self.A
        X = np.linalg.solve(self.A[k:, k:], self.A[k:, :k])
        return X, self.A[:k, :k] - self.A[:k, k:] @ X

    @functools.cached_property
    def inverse(self) -> np.ndarray:
        """The kept parameters' block of the unit-diagonal N^-1; LinAlgError where N is singular."""
        if self.singular:
            raise np.linalg.LinAlgError("a start state's block is singular")
        return np.linalg.inv(self.profile[1])

    @property
    def _st(self) -> np.ndarray:  # the kept parameters' scales
        return self.scaled.st[:self.keep]

    def _eliminated(self, vs: np.ndarray, piece, vt) -> np.ndarray:
        """v_t - C' S^-1 v_s on the unit-diagonal scaling, of vectors v given by their start-state
        parts vs (m, nx), each in its piece (`piece`: m indices, or a slice of all), and their
        parameter parts vt (m, nth)."""
        sc = self.scaled
        return vt / sc.st - np.einsum("mif,mi->mf", self.W[piece], vs / sc.ss[piece])

    def _kept(self, w: np.ndarray) -> np.ndarray:
        """Such parameter parts with the nuisances eliminated too."""
        k = self.keep
        return w[..., :k] - w[..., k:] @ self.profile[0] if k < w.shape[-1] else w

    def information(self) -> np.ndarray:
        """The kept parameters' information, the start states and nuisances eliminated."""
        return self.profile[1] * np.outer(self._st, self._st)

    def parameter_inverse(self) -> np.ndarray:
        """The kept parameters' block of N^-1; LinAlgError where N is singular."""
        return self.inverse / np.outer(self._st, self._st)

    def reduced(self, v: np.ndarray) -> np.ndarray:
        """A right-hand side v (of all unknowns) with the start states and nuisances eliminated:
        v_k - N_kn N_nn^-1 v_n."""
        n, ss = self.scaled.N.n_state, self.scaled.ss
        w = self._eliminated(v[:n].reshape(ss.shape), slice(None), 0.0).sum(axis=0) + v[n:] / self.scaled.st
        return self._kept(w) * self._st

    def profiled(self, vs: np.ndarray, piece: np.ndarray, vt: np.ndarray) -> np.ndarray:
        """reduced(v) of vectors v (m of them), each with its start-state part vs (m, nx) in
        one piece (piece, m) and its parameter part vt (m, nth): (m, keep)."""
        return self._kept(self._eliminated(vs, piece, vt)) * self._st

    def parameter_rows(self, vs: np.ndarray, piece: np.ndarray, vt: np.ndarray) -> np.ndarray:
        """The kept parameters' part of N^-1 v of such vectors: (m, keep). LinAlgError where N
        is singular."""
        return (self._kept(self._eliminated(vs, piece, vt)) @ self.inverse) / self._st  # inverse symmetric

    def solve(self, rt: np.ndarray, free: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(x, y), the start states and the parameters `free` (the others' columns taken out),
        solving the unit-diagonal system with the right-hand side (rhs given to schur, rt[free]);
        no parameter kept apart (keep: all). Where it is singular, its least-squares solution (a
        start state no residual sees has no row or column in a positive semidefinite N, so it is
        left alone)."""
        Sc, rhs = self.A[np.ix_(free, free)], (rt - self.Cx[:, 0])[free]
        if not len(rhs):
            y = rhs
        else:
            try:
                y = np.linalg.solve(Sc, rhs)
            except np.linalg.LinAlgError:
                y = np.linalg.lstsq(Sc, rhs, rcond=1e-12)[0]
        return self.x[..., 0] - np.compress(free, self.W, axis=2) @ y, y


def scaled_inverse(N: np.ndarray) -> np.ndarray:
    """N^-1 computed on the unit-diagonal scaling of N (parameters differ by 10 decades)."""
    scale = np.sqrt(np.maximum(np.diag(N), 1e-300))
    return np.linalg.inv(N / np.outer(scale, scale)) / np.outer(scale, scale)


# weight of the proximal term on the free node states, per squared defect scale, that the fits
# add once a step has failed: next to the data's curvature of an observable state (the samples
# of a whole interval) it is nothing, but it bounds the step of a state the data cannot see (the
# velocity of a piston that sticks at the start of a gap-free piece, which the Gauss-Newton step
# of a lossy recording moved by 10 m/s)
NODE_PROXIMAL = 1e-2


@np.errstate(over="ignore", invalid="ignore")  # see node_transitions
def step_matrix(N: ReducedNormal, state_scale: np.ndarray | None = None) -> ScaledNormal:
    """N as solve_bounded takes it, scaled once for any damping: with `state_scale` (the defect
    scale of each free node state) a proximal term NODE_PROXIMAL * |ds / state_scale|^2 / 2 keeps
    the steps of unobservable node states bounded."""
    if state_scale is not None and N.n_state:
        N = N.with_states(NODE_PROXIMAL / np.asarray(state_scale, float) ** 2)
    return N.scaled()


@np.errstate(over="ignore", invalid="ignore")  # see node_transitions
def solve_bounded(Ns: ScaledNormal, g: np.ndarray, theta, lower, upper, lam: float):
    """min 0.5 d'Nd + g'd (N: step_matrix's) with theta + d_theta kept in bounds (active set on
    the parameters), on the unit-diagonal scaling with Levenberg-Marquardt damping lam. None
    where N or the step is not finite."""
    N = Ns.N
    if not (N.finite() and np.all(np.isfinite(g))):
        return None
    ss, st = Ns.ss, Ns.st
    Ns = Ns.damped(lam)
    gs, gt = g[:N.n_state].reshape(ss.shape), g[N.n_state:]
    fixed = np.zeros(len(theta), bool)
    dt = np.zeros(len(theta))
    for _ in range(len(theta) + 1):
        free = ~fixed
        rs = -(gs + N.C[:, :, fixed] @ dt[fixed]) / ss
        rt = -(gt + N.T[:, fixed] @ dt[fixed]) / st
        x, y = Ns.schur(rhs=rs).solve(rt, free)
        ds = x / ss
        dt[free] = y / st[free]
        th_new = theta + dt
        viol = (th_new < lower) | (th_new > upper)
        if not viol.any():
            d = np.concatenate([ds.ravel(), dt])
            return d if np.all(np.isfinite(d)) else None
        for i in np.flatnonzero(viol):
            dt[i] = (lower[i] if th_new[i] < lower[i] else upper[i]) - theta[i]
            fixed[i] = True
    return np.concatenate([ds.ravel(), dt])


def linearize(ev, out_idx, wts, mask, M, nx, ny, nth):
    """Weighted residual Jacobians G = dE/ds_k, Hth = dE/dtheta and the transition
    Jacobians A = ds_end/ds_k, B = ds_end/dtheta of every interval."""
    E, D, X, Sens = ev
    Ktot = E.shape[0]
    G = np.empty((Ktot, M, ny, nx))
    Hth = np.empty((Ktot, M, ny, nth))
    G[:, 0] = np.eye(nx)[out_idx][None]  # the node state is itself the first prediction
    Hth[:, 0] = 0.0
    SensO = Sens[out_idx][:, :, : M - 1]  # (ny, K, M-1, nz)
    G[:, 1:] = SensO[..., :nx].transpose(1, 2, 0, 3)
    Hth[:, 1:] = SensO[..., nx:].transpose(1, 2, 0, 3)
    wm = (wts[None, None, :] * mask)[..., None]
    G *= wm
    Hth *= wm
    A = Sens[:, :, M - 1, :nx].transpose(1, 0, 2)  # (K, nx, nx)
    B = Sens[:, :, M - 1, nx:].transpose(1, 0, 2)  # (K, nx, nth)
    return G, Hth, A, B


# The transition products of a long piece overflow where a linearised model is unstable: the
# normal equations are then not finite, solve_bounded returns no step and the fit ends saying
# so; numpy's overflow warnings would only alarm the user.
@np.errstate(over="ignore", invalid="ignore")
def node_transitions(A, B, Draw, has_next, start=None):
    """P, Q, q of ds_k = P_k ds0 + Q_k dtheta + q_k: every node increment in terms of the
    start state of its run (or gap-free piece), from the intervals' transition Jacobians A, B
    and the defects Draw (one column per link). `start`: (P, Q, q) of the first interval where
    it continues a piece begun in an earlier chunk of intervals (next_transition of its last)."""
    Ktot, nx, nth = B.shape
    P = np.empty((Ktot, nx, nx))
    Q = np.empty((Ktot, nx, nth))
    q = np.empty((Ktot, nx))
    eye = np.eye(nx)
    link = 0
    for k in range(Ktot):
        if k == 0 and start is not None:
            P[k], Q[k], q[k] = start
        elif k == 0 or not has_next[k - 1]:
            P[k], Q[k], q[k] = eye, 0.0, 0.0
        else:
            j = k - 1
            P[k], Q[k], q[k] = next_transition(A[j], B[j], Draw[:, link], P[j], Q[j], q[j])
            link += 1
    return P, Q, q


def next_transition(A, B, d, P, Q, q):
    """(P, Q, q) of the interval after one with transition Jacobians A, B, defect d and (P, Q, q)."""
    return A @ P, A @ Q + B, A @ q + d


@np.errstate(over="ignore", invalid="ignore")  # see node_transitions
def reduced_jacobians(G, Hth, P, Q, q):
    """Js = dr/ds0, Jt = dr/dtheta and the residuals' change c = G q by the constant part of the
    node increments (the linearised residual is E + c), per interval."""
    Ktot, nx = G.shape[0], G.shape[-1]
    # batched matrix products (BLAS) rather than einsum: the same sums, several times faster
    Gf = G.reshape(Ktot, -1, nx)
    Js = (Gf @ P).reshape(G.shape[:3] + (nx,))
    Jt = (Gf @ Q).reshape(G.shape[:3] + (Q.shape[-1],)) + Hth
    c = (Gf @ q[:, :, None]).reshape(G.shape[:3])
    return Js, Jt, c


@np.errstate(over="ignore", invalid="ignore")  # see node_transitions
def reduce_nodes(lin, E, Draw, has_next, nx, nth):
    """Eliminate the node increments: ds_k = P_k ds0 + Q_k dtheta + q_k within each run.

    Returns P, Q, q and the reduced residual Jacobians Js = dr/ds0, Jt = dr/dtheta and the
    linearised residual r0 (all per interval)."""
    G, Hth, A, B = lin
    P, Q, q = node_transitions(A, B, Draw, has_next)
    Js, Jt, c = reduced_jacobians(G, Hth, P, Q, q)
    return P, Q, q, Js, Jt, E + c


@np.errstate(over="ignore", invalid="ignore")  # see node_transitions
def add_gradient(g, js, jt, r, a, th):
    """g[a] += js' r (the run's start state), g[th] += jt' r (the parameters)."""
    g[a] += js.T @ r
    g[th] += jt.T @ r


@np.errstate(over="ignore", invalid="ignore")  # see node_transitions
def normal_equations(Js, Jt, r0, layouts, nx, nth):
    """(N, g, scores) of the reduced problem in (ds0 of every run or gap-free piece, dtheta):
    `layouts` give each piece's first interval (node0) and its number of intervals (K);
    scores are the per-interval gradient contributions (for the cluster-robust covariance)."""
    Ktot, R = Js.shape[0], len(layouts)
    nred = R * nx + nth
    N = ReducedNormal.zeros(R, nx, nth)
    g = np.zeros(nred)
    # per-interval gradient contributions ("scores") for the cluster-robust covariance
    scores = np.zeros((Ktot, nred))
    for ri, l in enumerate(layouts):
        sl = slice(l.node0, l.node0 + l.K)
        scores[sl, ri * nx:(ri + 1) * nx] = np.einsum("kmoi,kmo->ki", Js[sl], r0[sl])
        add_normal_block(N, g, Js[sl], Jt[sl], r0[sl], ri)
    scores[:, R * nx:] = np.einsum("kmoi,kmo->ki", Jt, r0)
    return N, g, scores


def add_normal_block(N: ReducedNormal, g, Js, Jt, r0, ri):
    """Add the intervals (Js, Jt, r0) of piece ri to N and g."""
    R, nx, nth = N.C.shape
    js = Js.reshape(-1, nx)
    jt = Jt.reshape(js.shape[0], nth)  # explicit rows: nth may be 0 (states only)
    N.S[ri] += js.T @ js
    N.C[ri] += js.T @ jt
    N.T[...] += jt.T @ jt
    add_gradient(g, js, jt, r0.reshape(-1), slice(ri * nx, (ri + 1) * nx), slice(R * nx, None))


@dataclass(frozen=True)
class Clusters:
    """The gradient contributions summed by cluster of consecutive intervals (the cluster-robust
    covariance): a cluster lies in one piece, so its contribution is its piece's start-state part
    `states` (n, nx), its parameter part `params` (n, nth) and the piece `piece` (n,)."""

    states: np.ndarray
    params: np.ndarray
    piece: np.ndarray

    def __len__(self) -> int:
        return len(self.piece)


class NormalEquations:
    """The condensed Gauss-Newton model of a fit at one point, accumulated chunk by chunk of
    intervals in their order (node transitions carried from one chunk to the next), so that no
    sensitivity of the whole run is ever held: the reduced normal equations N (ReducedNormal), g
    in (ds0 of every run or gap-free piece, dtheta), the node transitions P, Q, q, the defects,
    the sum of squared residuals, the gradient contributions summed by cluster (the
    cluster-robust covariance) and what the decrease a step predicts needs (`predicted`).

    `pieces`: (first interval, intervals) of each run or gap-free piece, in order; `block`:
    intervals per cluster. Summed in one chunk, everything is the same to the last digit as the
    whole problem condensed at once; in several, to rounding. What it holds grows with the
    pieces linearly (never as their square)."""

    def __init__(self, pieces: Sequence[tuple[int, int]], nx: int, nth: int, block: int):
        R = len(pieces)
        self.nx, self.nth, self.R = nx, nth, R
        self.Ktot = sum(K for _, K in pieces)
        nred = R * nx + nth
        self.N = ReducedNormal.zeros(R, nx, nth)
        self.g = np.zeros(nred)
        self._Jc = np.zeros(nred)  # J'c (J'E = g - J'c: one product less per chunk)
        self._Ec, self._cc = 0.0, 0.0  # E'c, c'c
        self.cost2: float | None = None  # sum of squared weighted residuals
        self.P = np.empty((self.Ktot, nx, nx))
        self.Q = np.empty((self.Ktot, nx, nth))
        self.q = np.empty((self.Ktot, nx))
        # the pieces tile the intervals in order
        self._starts, Ks = (np.array([p[i] for p in pieces], int).reshape(R) for i in (0, 1))
        self._ends = self._starts + Ks
        # clusters: `block` consecutive intervals of one piece
        n_of = -(-Ks // block)  # clusters of each piece
        self._cluster_of = (np.repeat(np.cumsum(n_of) - n_of, Ks)
                            + (np.arange(self.Ktot) - np.repeat(self._starts, Ks)) // block)
        n = int(n_of.sum())
        self.clusters = Clusters(np.zeros((n, nx)), np.zeros((n, nth)), np.repeat(np.arange(R), n_of))
        self.kept: tuple[np.ndarray, np.ndarray] | None = None  # (G, E) of a run linearised as one chunk
        self._defects: list[np.ndarray] = []
        self._next, self._start = 0, None

    @property
    def D(self) -> np.ndarray:
        """The scaled defects of every link, in order."""
        if len(self._defects) > 1:
            self._defects = [np.hstack(self._defects)]
        return self._defects[0]

    @np.errstate(over="ignore", invalid="ignore")  # see node_transitions
    def add(self, lin, E, Draw, D, has_next, keep: bool = False) -> None:
        """Add the next chunk of intervals: `lin` = (G, Hth, A, B) of linearize, residuals E,
        defects Draw (unscaled) and D (scaled) of its links, `has_next` of every interval of the
        problem; `keep` holds G and E (a run linearised as one chunk)."""
        G, Hth, A, B = lin
        nx, nth, R = self.nx, self.nth, self.R
        a, b = self._next, self._next + G.shape[0]
        P, Q, q = node_transitions(A, B, Draw, has_next[a:b], self._start)
        self.P[a:b], self.Q[a:b], self.q[a:b] = P, Q, q
        self._start = next_transition(A[-1], B[-1], Draw[:, -1], P[-1], Q[-1], q[-1]) if has_next[b - 1] else None
        Js, Jt, c = reduced_jacobians(G, Hth, P, Q, q)
        r0 = E + c
        part = float(np.sum(E * E))
        self.cost2 = part if self.cost2 is None else self.cost2 + part
        self._Ec += float(np.sum(E * c))
        self._cc += float(np.sum(c * c))
        th = slice(R * nx, None)
        states = np.einsum("kmoi,kmo->ki", Js, r0)  # per-interval gradient contributions (scores)
        # the pieces this chunk holds a part of
        for ri in range(int(np.searchsorted(self._starts, a, side="right")) - 1,
                        int(np.searchsorted(self._starts, b, side="left"))):
            lo, hi = max(self._starts[ri], a) - a, min(self._ends[ri], b) - a
            add_normal_block(self.N, self.g, Js[lo:hi], Jt[lo:hi], r0[lo:hi], ri)
            js = Js[lo:hi].reshape(-1, nx)
            jt = Jt[lo:hi].reshape(js.shape[0], nth)
            add_gradient(self._Jc, js, jt, c[lo:hi].reshape(-1), slice(ri * nx, (ri + 1) * nx), th)
        params = np.einsum("kmoi,kmo->ki", Jt, r0)
        cl = self._cluster_of[a:b]
        first = np.flatnonzero(np.r_[True, cl[1:] != cl[:-1]])  # clusters are runs of intervals
        self.clusters.states[cl[first]] += np.add.reduceat(states, first, axis=0)
        self.clusters.params[cl[first]] += np.add.reduceat(params, first, axis=0) if nth else 0.0
        self._defects.append(D)
        self.kept = (G, E) if keep else None
        self._next = b

    @np.errstate(over="ignore", invalid="ignore")  # see node_transitions
    def predicted(self, step: np.ndarray) -> tuple[float, float]:
        """(gdir, quad) of a step z in (ds0, dtheta): the residuals' linearised change is
        l = J z + c, gdir = E'l and quad = l'l (the cost changes by gdir + quad / 2)."""
        z = np.asarray(step, float)
        gdir = float((self.g - self._Jc) @ z) + self._Ec
        quad = self.N.quadratic(z) + 2.0 * float(self._Jc @ z) + self._cc
        return gdir, quad


def covariance(E: Schur, cost: float, nres: float) -> np.ndarray | None:
    """The parameters' Gauss-Newton covariance, sigma^2 times the parameter block of N^-1 (E:
    N's start states eliminated, N.schur())."""
    N = E.scaled.N
    sigma2 = 2 * cost / max(1.0, nres - N.n_state - len(N.T))
    try:
        return sigma2 * E.parameter_inverse()
    except np.linalg.LinAlgError:
        return None


def cluster_covariance(E: Schur, clusters: Clusters) -> np.ndarray | None:
    """Sandwich covariance N^-1 (sum_b s_b s_b') N^-1 (its parameter block) with the gradient
    contributions s_b summed over clusters of consecutive intervals (about one second;
    NormalEquations.clusters): honest when residuals are correlated in time."""
    nb = len(clusters)
    if nb < 5:
        return None
    with np.errstate(over="ignore", invalid="ignore"):  # a score beyond float range: no robust estimate
        try:
            u = E.parameter_rows(clusters.states, clusters.piece, clusters.params)  # (N^-1 s_b) of the parameters
        except np.linalg.LinAlgError:
            return None
        cov = u.T @ u * nb / (nb - 1)
    return cov if np.all(np.isfinite(cov)) else None


def reported_covariance(N: ReducedNormal, clusters: Clusters, cost: float, nres: float) -> np.ndarray | None:
    """The parameter covariance a fit reports: residuals of real rigs (and of a drive by noisy
    measured signals) are not white, so each variance is the larger of the Gauss-Newton and
    the cluster-robust one (NormalEquations.clusters), correlations as Gauss-Newton's."""
    E = N.schur()
    cov_gn = covariance(E, cost, nres)
    cov_robust = cluster_covariance(E, clusters)
    if cov_gn is None or cov_robust is None:
        return cov_gn
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        scale = np.sqrt(np.maximum(np.diag(cov_robust), 0) / np.maximum(np.diag(cov_gn), 1e-300))
    scale = np.where(np.isfinite(scale), np.maximum(scale, 1.0), 1.0)
    return cov_gn * np.outer(scale, scale)


def correlation(cov: np.ndarray) -> np.ndarray:
    """The correlation matrix of a covariance; NaN where it is not defined: a variance that is
    not positive and finite (an undetermined parameter), or a coefficient beyond +-1 (a
    covariance that rounding left indefinite there)."""
    var = np.diag(cov)
    ok = np.isfinite(var) & (var > 0)
    d = np.sqrt(np.where(ok, var, 1.0))
    with np.errstate(over="ignore", invalid="ignore"):
        r = cov / np.outer(d, d)
    r[~(ok[:, None] & ok[None, :]) | ~(np.abs(r) <= 1.0 + 1e-9)] = np.nan
    return np.clip(r, -1.0, 1.0)


def standard_deviations(N: ReducedNormal, cost, nres) -> np.ndarray:
    cov = covariance(N.schur(), cost, nres)
    if cov is None:
        return np.full(len(N.T), np.inf)
    return np.sqrt(np.maximum(np.diag(cov), 0.0))


def simulate_layout(sf: ShootingFunctions, s0: np.ndarray, p: np.ndarray, l: RunLayout, M: int) -> np.ndarray:
    """Single-shooting simulation of a whole run from its first node state: (n_outputs, N)."""
    plant = sf.plant
    out_idx = [plant.state_names.index(n) for n in plant.output_names]
    nw = l.W.shape[0]
    # the layout holds M+1 inputs per interval (both ends of each step): back to one per sample
    w = np.hstack([l.W.reshape(nw, l.K, M + 1)[:, :, :M].reshape(nw, l.K * M), l.W[:, -1:]])
    return sf.simulate(s0, w, p, l.H[0], rows=out_idx)[:, : l.run.n]


def rmse_r2(meas: np.ndarray, sim: np.ndarray) -> tuple[float, float]:
    """Over the samples where the output was measured."""
    ok = np.isfinite(meas)
    meas, sim = meas[ok], sim[ok]
    err = sim - meas
    with np.errstate(over="ignore"):  # a diverged simulation (a start validation drops): inf, said so
        rmse = float(np.sqrt(np.mean(err * err))) if err.size else float("nan")
        sst = float(np.sum((meas - meas.mean()) ** 2)) if err.size else 0.0
        r2 = 1.0 - float(np.sum(err * err)) / sst if sst > 0 else float("nan")
    return rmse, r2


def fit_metrics(run: Run, sim: np.ndarray, outputs: Sequence[str]) -> dict[str, float]:
    meas = {"x": run.x, "p1": run.p1, "p2": run.p2}
    out: dict[str, float] = {"source": str(run.source) if run.source else None}
    for i, n in enumerate(outputs):
        rmse, r2 = rmse_r2(meas[n], sim[i])
        out[f"rmse_{n}"], out[f"r2_{n}"] = rmse, r2
    return out


def pooled_fit(runs: Sequence[Run], sims: Sequence[np.ndarray], outputs: Sequence[str]) -> dict[str, float]:
    meas_all = {n: np.concatenate([getattr(r, n) for r in runs]) for n in outputs}
    fit = {}
    for i, n in enumerate(outputs):
        sim = np.concatenate([s[i] for s in sims])
        fit[f"rmse_{n}"], fit[f"r2_{n}"] = rmse_r2(meas_all[n], sim)
    return fit



# measured signals a drive takes as inputs, and the sensor noise each carries
_MEASURED_INPUTS = {"p1": "pressure_noise", "p2": "pressure_noise", "x": "position_noise"}


def _beyond_node_states(G: np.ndarray, R: np.ndarray) -> np.ndarray:
    """What of the residuals R (K, M, ny) no initial state of its own interval could remove:
    R less its least-squares projection on the interval's state sensitivities G (K, M, ny, nx)."""
    K = G.shape[0]
    A = G.reshape(K, -1, G.shape[-1])
    b = R.reshape(K, -1)
    AtA = np.einsum("kri,krj->kij", A, A) + 1e-12 * np.eye(A.shape[-1])
    coef = np.linalg.solve(AtA, np.einsum("kri,kr->ki", A, b)[..., None])[..., 0]
    return (b - np.einsum("kri,ki->kr", A, coef)).reshape(R.shape)


def interval_residual_sigma(problem: "ShootingProblem", layouts: Sequence[RunLayout], cyl: Cylinder,
                            S: np.ndarray, p: np.ndarray, eqs: "NormalEquations", dof: float,
                            reps: int = 4, seed: int = 0) -> tuple[float, float]:
    """The residual of a drive that takes measured signals as inputs, in units of what their
    noise alone leaves: (residual sigma, the noise floor it was divided by).

    Noisy inputs drive the model too: a position driven by noisy pressures wanders off like a
    random walk, so over a whole run the residual says little. Here each shooting interval is
    judged on its own: what its own initial state cannot remove (a projection on the state
    sensitivities G at (S, p), linearised in `eqs`), divided by the same for `reps` simulations
    with the inputs perturbed by their sensors' noise (seeded: the same figure on every machine).
    A run of several chunks (problem.spans) is taken a chunk at a time, its sensitivities
    computed again for each simulation with noise unless the chunks' G and E together hold at
    most CHUNK_SENSITIVITIES numbers (then kept: the simulations with noise need them again)."""
    plant = problem.plant
    spans = problem.spans
    if not problem.allows(S):
        return math.nan, 1.0
    kept: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
    room = CHUNK_SENSITIVITIES

    def state_sensitivities(a: int, b: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(G, E) of intervals a..b-1 at (S, p)."""
        nonlocal room
        if eqs.kept is not None:
            return eqs.kept
        if (a, b) in kept:
            return kept[a, b]
        sim = problem.span_simulation(S, p, a, b, True)
        if sim is None:
            return None
        E = problem.span_residuals(S, sim[0], a, b)[0]
        GE = linearize((E, None, *sim), problem.out_idx, problem.wts, problem.mask[a:b], problem.M, problem.nx,
                       len(problem.out_idx), problem.nth)[0], E
        if GE[0].size + E.size <= room:
            kept[a, b] = GE
            room -= GE[0].size + E.size
        return GE

    raw2 = 0.0
    for a, b in spans:
        GE = state_sensitivities(a, b)
        if GE is None:
            return math.nan, 1.0
        raw2 += float(np.sum(_beyond_node_states(*GE) ** 2))
    raw = math.sqrt(raw2 / max(dof, 1.0))
    rng = np.random.default_rng(seed)
    saved, dev2 = problem.W, 0.0

    def simulated(a: int, b: int, W: np.ndarray) -> np.ndarray | None:
        sim = problem.span_simulation(S, p, a, b, False, W)
        return None if sim is None else problem.span_residuals(S, sim[0], a, b)[0]

    base = simulated(0, problem.K, saved) if len(spans) == 1 else None
    if len(spans) == 1 and base is None:
        return raw, 1.0
    for _ in range(reps):
        noisy = []
        for lay in layouts:
            r = lay.run
            kw = {n: getattr(r, n) + getattr(cyl.sensors, _MEASURED_INPUTS[n]) * rng.standard_normal(r.n)
                  for n in ("p1", "p2", "x") if n in plant.input_names}
            noisy.append(run_layout(replace(r, **kw), plant, cyl, problem.M, lay.node0).W)
        W_noisy = np.hstack(noisy) if len(noisy) > 1 else noisy[0]
        dev2_rep = 0.0
        for a, b in spans:
            GE = state_sensitivities(a, b)
            base_ab = base if base is not None else simulated(a, b, saved)
            E_noisy = simulated(a, b, W_noisy)
            if GE is None or base_ab is None or E_noisy is None:
                return raw, 1.0
            dev2_rep += float(np.sum(_beyond_node_states(GE[0], E_noisy - base_ab) ** 2))
        dev2 += dev2_rep / reps
    floor = math.sqrt(1.0 + dev2 / max(float(np.sum(problem.mask)), 1.0))
    return raw / floor, floor


def drives_with_measured_inputs(plant: Plant) -> bool:
    return any(n in _MEASURED_INPUTS for n in plant.input_names)
