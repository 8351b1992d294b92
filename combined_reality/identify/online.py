"""Online estimation: moving-horizon multiple shooting over the last seconds of a stream.

Each update solves the identification problem of `identify` (same plant, same condensed
Gauss-Newton, same compiled functions) on a window of the latest `window_s` of samples,
warm-started from the previous solution. An arrival cost carries what the data that left
the window said about the parameters: when intervals leave, their Gauss-Newton model (their
start state marginalised out) is merged into the prior, mean and information alike, as a
Kalman update would. So the estimate keeps using the whole stream while every update costs
one window. A finite `memory_s` discounts old information, to follow slowly drifting friction.

Lost samples: multiple shooting needs no sample where none arrived. The stream is cut into
shooting intervals of up to `interval_s`, and an interval ends at a gap. Across a short gap
(up to `bridge_s`) the simulation runs on: the sample before the gap held its command for
one period (known); from the first lost tick on, the rig latched commands nobody saw, most
often the one reported after the gap (a host answers only what it receives). That command
is one unknown per gap, estimated with the window (one sample period of a wrong command
moves a chamber pressure by kilopascals, so holding the old one does not fit): position
and velocity stay continuous, the pressures take what the data after the gap say. Only a
gap long enough to lose the state (or more bridged gaps in a window than `max_bridged`)
starts a new gap-free piece with a free node state. A window thus holds one or more
pieces and is never restarted: the estimate goes on across lost samples and outages alike.
Outputs not measured at a sample (NaN) have no residual there.

Windows slide by whole intervals and never by more than a window, so no sample is skipped
when the estimator falls behind (it then slides further per update instead).

Cost: most updates of a warm stream find no step worth taking (less to gain than fitting
the unknowns to noise). Such an update leaves its linearisation where the next window
starts, so the next one simulates only its new intervals, with their sensitivities, and
takes the shared ones as they are: on a 2-core machine an update then costs about 5 ms
instead of 16 ms (2 s window at 1 kHz, one thread), and a window is evaluated whole only
after a step. A gap's offset is never a dense column of the residual Jacobian: it moves the
node states after its gap only, so its products go through the intervals' nx-by-nx blocks
(`_ReducedWindow`), and a step is taken when it gains more than fitting the window's
unknowns to noise would in nine windows of ten (`_noise_gain`), however many gaps it holds.

The standard deviation is that of the whole-session estimate: the Gauss-Newton covariance
of window and arrival cost together, scaled by the residual variance of the whole session,
or the cluster-robust (sandwich) covariance over clusters of `cluster_s` when residuals
are correlated in time, whichever is larger (as `identify` reports).
"""
from __future__ import annotations

import bisect
import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import numpy as np

from sim.compiled import NumpyCall, shooting_functions
from sim.cylinder import Cylinder
from sim.extension import Effect
from sim.integrator import IntegratorOptions
from sim.plant import plant_for

from ..files import Run
from .gauss_newton import Damping, Exit, Prediction, StepOutcome, damped_step
from .newton import equation_error_friction
from .offline import MISMATCH
from .shooting import (ReducedNormal, ShootingProblem, free_parameters, line_search, linearize, node_transitions,
                       normal_equations, parameter_bounds, parameter_unit, residual_scales, shooting_residuals)
from .smoothing import fill_missing, velocity_estimate
from .tracking import Blocks, Change, Drift, Regime, analyse, pinv, regime_variances, trend_fit

# node states and gap offsets profiled out of a window: directions with less than this of the
# largest information (on the unit-diagonal scale) are left undetermined
_NUISANCE_RCOND = 1e-10


@dataclass(frozen=True)
class OnlineOptions:
    window_s: float = 2.0  # moving horizon
    update_s: float = 0.2  # slide between updates when keeping up (rounded to whole intervals)
    interval_s: float = 0.1  # shooting interval
    # Gauss-Newton iterations per update: one suffices once warm-started on overlapping
    # windows (the real-time iteration of Diehl et al.: what one update leaves, the next one
    # takes up; over 20 s runs, with and without lost samples, the final estimates and the
    # window fits agree with those of up to 3 iterations, at a third less time per update at
    # the 95th percentile); with `max_iterations` > 1 more are taken while the step still
    # promises a real decrease; the first window may take `first_iterations`
    iterations: int = 1
    max_iterations: int = 1
    first_iterations: int = 6
    estimate: tuple[str, ...] = ("Fc", "Fv", "kp")
    memory_s: float = math.inf  # forgetting time constant of the arrival cost
    prefit: bool = True  # first window: start from the equation-error fit
    integrator: IntegratorOptions = IntegratorOptions()
    # threads of the compiled window evaluation (the estimates do not depend on it). One by
    # default: the estimator runs beside acquisition, and a second thread took a core from
    # whatever else runs (a host-side velocity loop on the other core came late). Where nothing
    # real-time can suffer, two share a whole window's evaluation: a live session whose
    # acquisition runs at real-time priority, and replay. Since most updates evaluate only their
    # new intervals, the gain is small (update p95 17.8 -> 14.4 ms in one benchmark run on a
    # 2-core machine, 17.9 -> 20.0 ms in another)
    threads: int = 1
    # a window may grow to hold_s (when longer than window_s) before its oldest data leave it,
    # a window's worth at once: what leaves enters the arrival cost with its own start state
    # profiled out, so chunks of a whole window keep more of their information than halves
    hold_s: float = 0.0
    bridge_s: float = 0.01  # lost samples up to this long are bridged (their command estimated)
    max_bridged: int = 100  # bridged gaps per window at most (each adds an unknown); more start new pieces
    cluster_s: float = 1.0  # residuals may be correlated within about this long (the robust std)
    # a rig that changes (identify/tracking.py): blocks of about block_s of the stream say what
    # they alone tell about the parameters; over the last history_s of them a step is announced
    # beyond change_z standard deviations and a drift followed beyond drift_z (False: the
    # estimator of a rig that never changes). A finite memory_s replaces the drift's model
    track: bool = True
    block_s: float = 0.2
    history_s: float = 20.0
    change_z: float = 6.0
    drift_z: float = 5.5
    # an effect the model lacks moves the locally best friction with the operating regime: by
    # how much is measured on stretches of regime_s / 8 to regime_s (averaged over the session
    # with a time constant of regime_memory_s), and at least regime_floor of the friction force
    # for each of its terms (the smallest change worth a word is some times this)
    regime_s: float = 4.0
    recent_s: float = 6.0  # a step is looked for in the last recent_s (older ones were looked for when recent)
    # ... with at least min_after_s of data after it: the newest data of a window are the
    # least settled (their last node state has nothing after it)
    min_after_s: float = 1.5
    regime_memory_s: float = 60.0
    regime_floor: float = 0.005
    # until settle_s of the history lies beyond regime_s (the regimes seen for a while), a
    # step is judged against young_floor times the floor
    settle_s: float = 12.0
    young_floor: float = 4.0


@dataclass
class OnlineEstimate:
    t: float  # rig time of the window's last sample
    values: dict[str, float]
    std: dict[str, float]
    units: dict[str, str]
    window: tuple[float, float]
    samples_seen: int  # samples that have entered the estimate so far
    sigma: float  # RMS of the weighted residuals in the window (1 = at sensor noise)
    rmse: dict[str, float]  # over the window, per output
    iterations: int
    wall_s: float
    pieces: int = 1  # pieces (parts joined by continuity) in the window
    gaps: int = 0  # bridged gaps in the window (their held command estimated)
    state: np.ndarray = field(repr=False, default=None)  # model state at t, to resynchronise a simulation
    params: np.ndarray = field(repr=False, default=None)  # the full plant parameter vector
    change: Change | None = None  # a change of the rig detected by this update (the estimate is after it)
    drift: Drift | None = None  # the rig's friction drifts: its rate (the estimate follows it)
    step_pending: bool = False  # a step found where too little has come after it yet (judged later)


_NEW_PIECE, _JOINED, _BRIDGED = 0, 1, 2  # how an interval joins the one before it
_DU_RANGE = 2.0  # bound (and weak prior scale) of a command offset over a bridged gap


@dataclass(frozen=True)
class _Piece:
    """Consecutive intervals joined by continuity (the `layouts` of normal_equations)."""

    node0: int
    K: int


class _PaddedProblem:
    """The shooting problem of a window of up to `capacity` intervals. A smaller window is
    padded with empty intervals (zero-length steps, no samples), which cost next to nothing,
    so that the compiled maps are built once rather than for every window size.

    With threads, the compiled map gives each thread a contiguous block of its slots: the
    window's intervals are dealt to the blocks in turn (interval i to block i mod threads), so
    that every thread gets its share of the real ones, not one thread all and the others the
    padding. Everything outside the compiled call is in the window's order."""

    def __init__(self, sf, capacity: int, threads: int, wts, sscale, possible=None):
        M, nw, ny = sf.interval_len, len(sf.plant.input_names), len(wts)
        T = max(1, min(threads, capacity))
        capacity = -(-capacity // T) * T
        self.capacity, self.M, self.Kw = capacity, M, capacity
        i = np.arange(capacity)
        self.slot = (i % T) * (capacity // T) + i // T  # slot of the window's interval i
        self.interval_at = np.argsort(self.slot)  # the window's interval in slot j
        self.prob = ShootingProblem(sf, capacity, T, np.zeros((nw, capacity * (M + 1))),
                                    np.zeros((1, capacity * M)), np.zeros((capacity, M, ny)),
                                    np.zeros((capacity, M, ny)), wts, sscale, np.empty(0, int), possible)
        self.out_idx = self.prob.out_idx
        self.Y = self.mask = self.nxt = None

    def _slots(self, A: np.ndarray, width: int) -> np.ndarray:
        """Columns of A in blocks of `width` per interval, window order -> slot order."""
        return A.reshape(A.shape[0], self.capacity, width)[:, self.interval_at].reshape(A.shape[0], -1)

    def set(self, lay: dict) -> None:
        M, self.Kw = self.M, len(lay["starts"])
        H = np.zeros((1, self.capacity * M))
        H[:, :self.Kw * M] = lay["H"]
        self.prob.H = self._slots(H, M)
        self.Y, self.mask = lay["Y"], lay["mask"]
        self.nxt = np.flatnonzero(lay["has_next"])
        self.set_commands(lay["W"])

    def set_commands(self, W: np.ndarray) -> None:
        W = np.hstack([W, np.repeat(W[:, -1:], (self.capacity - self.Kw) * (self.M + 1), axis=1)])
        self.prob.W = self._slots(W, self.M + 1)

    def _pad(self, A: np.ndarray) -> np.ndarray:
        return np.concatenate([A, np.repeat(A[:, -1:], self.capacity - self.Kw, axis=1)], axis=1)

    def evaluate(self, S: np.ndarray, p: np.ndarray, with_sens: bool):
        """(E, D, X, Sens) of the window, as ShootingProblem.evaluate gives them."""
        sim = self.prob.simulate(self._pad(S)[:, self.interval_at], p, with_sens)
        if sim is None:
            return None
        mine = self.slot[:self.Kw]  # back to the window's order
        X, Sens = sim[0][:, mine], None if sim[1] is None else sim[1][:, mine]
        E, D = self.residuals(S, X)
        return E, D, X, Sens

    def allows(self, S: np.ndarray) -> bool:
        return self.prob.allows(S)

    def residuals(self, S: np.ndarray, X: np.ndarray):
        return shooting_residuals(S, X, self.Y, self.mask, self.prob.wts, self.prob.sscale, self.nxt, self.out_idx)


@dataclass(frozen=True)
class _Window:
    """An update's window: intervals k0 .. k0 + Kw - 1 (`left` of the last window's left it),
    their layout (MovingHorizonEstimator._layout) and problem, and its last real sample
    (row r_last of the buffer, sample last_row of interval last_k)."""

    k0: int
    Kw: int
    left: int
    lay: dict
    prob: _PaddedProblem
    npar: int  # the plant's parameters (the gap offsets follow them in p)
    r_first: int
    r_last: int
    last_k: int
    last_row: int
    t_first: float
    t_last: float

    @property
    def pieces(self) -> list[_Piece]:
        return self.lay["pieces"]

    @property
    def piece_of(self) -> np.ndarray:
        return self.lay["piece_of"]

    @property
    def R(self) -> int:  # pieces: free node states
        return len(self.lay["pieces"])

    @property
    def G(self) -> int:  # bridged gaps: command offsets estimated
        return len(self.lay["after_gap"])

    def commands(self, p: np.ndarray) -> np.ndarray:
        """The held commands with the offsets over the bridged gaps (p[npar:]) added."""
        W = self.lay["W"].copy()
        W[0, self.lay["gap_w"]] += p[self.npar:]
        return W

    def evaluate(self, S: np.ndarray, p: np.ndarray, with_sens: bool):
        self.prob.set_commands(self.commands(p))
        return self.prob.evaluate(S, p[:self.npar], with_sens)


@dataclass(frozen=True)
class _Unknowns:
    """An update's unknowns besides the node states: the parameters, then the command offsets
    over the bridged gaps, with their bounds, the plant's parameter vector they sit in, and the
    arrival cost's information and mean."""

    theta: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    free: list[int]
    p: np.ndarray
    info: np.ndarray
    mean: np.ndarray


@dataclass(frozen=True)
class _Solved:
    """Where an update's iterations ended, with the last linearisation (red, Nm, the sensitivities
    `sens`) and the step taken from it (None: the linearisation holds where the solution is)."""

    iterations: int
    S: np.ndarray
    X: np.ndarray
    E: np.ndarray
    theta: np.ndarray
    p: np.ndarray
    red: "_ReducedWindow"
    Nm: ReducedNormal
    sens: np.ndarray | None
    step_taken: tuple | None


# a bounded search: an update that cannot improve keeps the previous estimate and tries again
# with the next data, instead of stalling the stream; its retry bounds the free node states
# too (as the offline fit does)
ONLINE_DAMPING = Damping(attempts=2, floor=1e-2, bound_states_on_retry=True)


class _OnlineStep:
    """The step model of one update's iteration (gauss_newton.StepModel)."""

    def __init__(self, w: _Window, u: _Unknowns, red: "_ReducedWindow", Nm: ReducedNormal, g: np.ndarray,
                 S: np.ndarray, theta: np.ndarray, p: np.ndarray, dev: np.ndarray, cost: float, viol: float, nu: int):
        self.w, self.u, self.red, self.Nm, self.g = w, u, red, Nm, g
        self.S, self.theta, self.p, self.dev = S, theta, p, dev
        self.cost, self.viol, self.nu = cost, viol, nu

    def _split(self, step: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        R, nx = self.w.R, self.S.shape[0]
        return step[:R * nx].reshape(R, nx), step[R * nx:]

    def predict(self, step: np.ndarray) -> Prediction:
        """The decrease the linear model promises, closing the defects included."""
        ds0, dth = self._split(step)
        r_lin = self.red.r0 + self.red.apply(ds0[self.w.piece_of], dth)
        d_lin = self.dev + dth
        return Prediction(self.cost - 0.5 * float(np.sum(r_lin * r_lin)) - 0.5 * float(d_lin @ self.u.info @ d_lin))

    def nothing_to_gain(self, pred: Prediction) -> bool:
        # less to gain than fitting nu unknowns to noise would
        return pred.decrease < max(_noise_gain(self.nu), 1e-3 * self.cost) and self.viol < 1e-2 * self.w.Kw

    def penalty(self, mu: float, pred: Prediction) -> float:
        # the penalty on the defects needs only outweigh a cost the step would add to close them;
        # a penalty sized by the decrease over a vanishing violation would refuse any step that
        # opens a defect of a thousandth of the noise, as a nonlinear step does
        d, viol = pred.decrease, self.viol
        return max(mu, 1.0, 2.0 * -d / viol + 1.0 if d < 0 < viol else 0.0)

    def search(self, step: np.ndarray, pred: Prediction, mu: float):
        ds0, dth = self._split(step)
        red, u = self.red, self.u
        dS = (np.einsum("kij,kj->ki", red.P, ds0[self.w.piece_of]) + red.Q @ dth + red.q).T
        return line_search(self.w.evaluate, lambda ev_, th: _merit(ev_, th, u.mean, u.info, mu), self.S, dS,
                           self.theta, dth, self.p, u.free, u.lower, u.upper, self.cost + mu * self.viol,
                           -max(pred.decrease, 0.0), 1 / 4)


def _update_end(out: StepOutcome, it: int, iterations: int, cost: float) -> Exit | None:
    """Why an update stops after iteration `it` (None: on, up to its iterations): nothing left to
    gain, no step accepted (the estimate stays, the next data try again), or a full step with
    little left to gain once `iterations` are done (the warm start was good: the real-time
    iteration was enough)."""
    if out.converged:
        return Exit.NOTHING_TO_GAIN
    if out.found is None:
        return Exit.LINE_SEARCH_FAILED
    pred = out.predicted
    if it >= iterations and out.found[0] == 1.0 and (pred < 1e-3 * cost or pred < 1.0):
        return Exit.WARM_START_ENOUGH
    return None


class MovingHorizonEstimator:
    """Feed rows with `add`, call `update` when `ready`; each update returns an estimate.
    `flush()` at the end of a stream lets the last, partly filled interval in too."""

    def __init__(self, cyl: Cylinder, sample_period: float, options: OnlineOptions = OnlineOptions(),
                 effects: Sequence[Effect] = (), progress: Callable[[str], None] | None = None):
        self.cyl, self.options, self.dt = cyl, options, float(sample_period)
        self.plant = plant = plant_for(cyl, "command", effects, options.estimate)
        self.names = tuple(options.estimate)
        self.free = free_parameters(plant, self.names)
        self.M = M = max(5, int(round(options.interval_s / self.dt)))
        self.K = K = max(2, int(round(options.window_s / (M * self.dt))))
        self.N = K * M  # samples in a window
        self.slide_min = max(1, int(round(options.update_s / (M * self.dt)))) * M
        self.sf = shooting_functions(plant, M, self.free, options.integrator, progress=progress)
        self.wts, self.sscale = residual_scales(plant, cyl, self.dt)
        self.p = np.array(plant.parameter_vector(cyl), float)
        self.lower, self.upper = parameter_bounds(plant, self.names)
        self.theta = np.clip(self.p[self.free], self.lower, self.upper)
        # a weak prior (ten times the starting value) keeps an unexcited first window solvable
        typical = np.maximum(np.abs(self.theta), 1e-3 * (self.upper - self.lower))
        self.info = np.diag(1.0 / (10.0 * typical) ** 2)
        self.prior_mean = self.theta.copy()
        self.units = {n: parameter_unit(plant, n) for n in self.names}
        self._prob: _PaddedProblem | None = None
        # one step for each side of the central differences over the bridged gaps of a window,
        # by size in steps of 8 (a few compiled maps, few unused columns)
        self._gap_steps: dict[int, NumpyCall] = {}
        self._gap_slopes: dict[tuple, np.ndarray] = {}  # the last evaluation's, by gap and where its step began
        self._sens_one = NumpyCall(self.sf.sens)  # one interval with its sensitivities
        self._buf = np.empty((5, 0))  # rows t, u, x, p1, p2
        self._base = 0  # stream index of _buf[:, 0]
        self._seen = 0  # stream index one past the newest row
        self._last_row: tuple[float, float] | None = None  # (t, u) of the newest row
        self._virtual: list[int] = []  # stream indices of the rows that mark where bridged gaps begin
        self._virtual_gone = 0  # such rows no window can need any more (dropped from the list)
        # complete shooting intervals: first row, rows, and how each joins the one before
        # (_NEW_PIECE, _JOINED, or _BRIDGED across lost samples)
        self._iv_start: list[int] = []
        self._iv_rows: list[int] = []
        self._iv_link: list[int] = []
        self._iv_base = 0  # global index of the first interval still held
        self._open: list | None = None  # [first row, rows, link] of the interval being filled
        self._bridged_rows: list[int] = []  # rows after recent bridged gaps (for max_bridged)
        self._du: dict[int, float] = {}  # estimated command offset over the gap before an interval
        self._w = 0  # global index of the window's first interval; those before are in the arrival cost
        self._ended = False  # flush() was called: a last, shorter slide may follow
        self._fitted = False
        self._prev: dict | None = None  # the last update's window, solution and linearisation
        self.gaps_cut = self.gaps_bridged = 0
        # what left the window, for the std of the whole-session estimate: residual sum of
        # squares, residual count, node states fitted, and gradient contributions per cluster
        self._ssr = self._nres = self._nstates = 0.0
        self._clusters = _Clusters(len(self.free))
        self._weak = self.info.copy()  # the weak prior, kept under every prior built later
        # a rig that changes: the stream in blocks of SUB intervals; the blocks that left the
        # window (the tests' history), the drift being followed, and a restart after a step
        self.SUB = max(1, int(round(options.block_s / (M * self.dt))))
        self._history = Blocks(len(self.free))
        self._drift: Drift | None = None
        self._drift_quiet = 0.0  # s of data since the drift last tested significant
        self._restarting = False
        self._change: Change | None = None  # found by the update that restarts, reported by the refit
        self._t_tested = 0.0  # rig time of the last update tested
        self._sigmas: list[tuple[float, float]] = []  # (rig time, residual sigma) of the windows of the history
        self._regime: np.ndarray | None = None  # the rig's regime variance per parameter (see _update_regime)
        self._regime_recent: np.ndarray | None = None  # that of the history alone
        self._regime_slide = 0.0  # s of data since they were last measured
        self._block_cache: dict | None = None  # the last window's blocks by global intervals (see _track)
        # its scales: doubling from regime_s / 8 up to regime_s
        self._scales = options.regime_s / 2.0 ** np.arange(3, -1, -1)
        self.analysis = None  # the last update's tests (identify/tracking.Analysis)

    # ------------------------------------------------------------ data
    def add(self, t, u, x, p1, p2, lost_before=None) -> None:
        """Append rows (u is the command held from t until the next sample; x, p1, p2 may be
        NaN where not measured). `lost_before` flags rows that follow lost samples (from the
        rig's sequence numbers); without it, a step longer than 1.5 sample periods is a loss."""
        rows = np.vstack([np.atleast_1d(np.asarray(a, float)) for a in (t, u, x, p1, p2)])
        n = rows.shape[1]
        if n == 0:
            return
        if lost_before is not None:
            gap = np.atleast_1d(np.asarray(lost_before, bool))
        else:
            t_before = np.r_[self._last_row[0] if self._last_row else np.inf, rows[0, :-1]]
            gap = rows[0] - t_before > 1.5 * self.dt
        out = []  # the rows to append, with a row for the start of each bridged gap
        for j in range(n):
            i = self._seen + len(out)
            if gap[j] and self._open is not None:
                t_prev, u_prev = self._last_row
                length = rows[0, j] - t_prev
                if self._gap_link(i, length) == _BRIDGED:
                    # the sample before the gap held its command for one period (known); the lost
                    # ticks latched commands nobody saw: a row with nothing measured marks where
                    # they begin, and the step from it across the gap carries an estimated command
                    lost = max(1, int(round(length / self.dt)) - 1)
                    out.append((t_prev + length / (lost + 1), u_prev, np.nan, np.nan, np.nan))
                    self._virtual.append(i)
                    self._open[1] += 1
                    self._close_open()
                    self._open = [i + 1, 0, _BRIDGED]
                    i += 1
                elif self._open[1]:
                    self._close_open()
                    self._open = [i, 0, _NEW_PIECE]
                else:
                    self._open[2] = _NEW_PIECE
            elif self._last_row is not None and rows[0, j] - self._last_row[0] > 1.5 * self.dt:
                # a stretched tick with nothing lost (the rig's numbers run on: its firmware
                # overran): the valve held the last command all along, so it is known. Rows with
                # nothing measured keep the steps at about a period; one step of 28 ms is beyond
                # what the integrator refines (32 substeps) and wrecked a live estimate
                t_prev, u_prev = self._last_row
                k = int(round((rows[0, j] - t_prev) / self.dt))
                for m in range(1, k):
                    self._push(out, (t_prev + m * (rows[0, j] - t_prev) / k, u_prev, np.nan, np.nan, np.nan))
            self._push(out, rows[:, j])
        self._buf = np.hstack([self._buf, np.array(out).T])
        self._seen += len(out)
        self._ended = False

    def _push(self, out: list, row) -> None:
        """Append one row to `out` (the rows of this add) and count it into its interval."""
        i = self._seen + len(out)
        if self._open is None:
            self._open = [i, 0, _NEW_PIECE]
        out.append(row)
        self._last_row = (float(row[0]), float(row[1]))
        self._open[1] += 1
        if self._open[1] == self.M:
            self._close_open()
            self._open = [i + 1, 0, _JOINED]

    def _gap_link(self, row: int, length: float) -> int:
        """How the interval after a gap of `length` seconds before `row` joins the one before."""
        recent = self._bridged_rows
        while recent and recent[0] <= row - self.N:
            recent.pop(0)
        if length > self.options.bridge_s + 0.5 * self.dt or len(recent) >= self.options.max_bridged:
            self.gaps_cut += 1
            return _NEW_PIECE
        recent.append(row)
        self.gaps_bridged += 1
        return _BRIDGED

    def flush(self) -> None:
        """The stream has ended: the interval being filled is complete as it is."""
        if self._open is not None and self._open[1]:
            self._close_open()
            self._open = [self._seen, 0, _JOINED]
        self._ended = True

    def _close_open(self) -> None:
        start, rows, link = self._open
        self._iv_start.append(start)
        self._iv_rows.append(rows)
        self._iv_link.append(link)

    def _rows(self, g0: int, g1: int) -> int:
        """Samples in the complete intervals g0 .. g1 - 1 (global indices)."""
        a, b = g0 - self._iv_base, g1 - self._iv_base
        return sum(self._iv_rows[a:b])

    @property
    def _complete(self) -> int:
        """One past the newest complete interval."""
        return self._iv_base + len(self._iv_rows)

    @property
    def backlog(self) -> int:
        """Samples in complete intervals that no window has taken in yet."""
        end = self._prev["k0"] + self._prev["Kw"] if self._prev else self._w
        return self._rows(end, self._complete)

    @property
    def started(self) -> bool:
        return self._prev is not None

    def ready(self) -> bool:
        if self._prev is None:  # (after a step: as soon as a block is there)
            return self.backlog >= (self.SUB * self.M if self._restarting else self.N)
        # intervals end early at gaps, so the data come in uneven steps: slide as soon as the
        # nearest whole-interval amount to update_s is there, so updates keep their rate
        return self.backlog >= self.slide_min - self.M // 2 or (self._ended and self.backlog > 0)

    # ------------------------------------------------------------ the window
    def _next_window(self) -> tuple[int, int, int]:
        """(first interval, intervals, intervals that leave) of the next window: it ends at the
        newest complete interval, holds at most N samples, and starts no later than right after
        the previous window (so every sample enters some window)."""
        k1 = self._complete
        if self._prev is None:
            k0 = self._w
            while self._rows(k0, k1) > self.N:
                k1 -= 1
            return k0, k1 - k0, 0
        old0, old_end = self._prev["k0"], self._prev["k0"] + self._prev["Kw"]
        k0 = old0
        # (a window may grow to hold_s before its oldest data leave it, a window's worth at once)
        hold = max(self.N, int(round(self.options.hold_s / self.dt)))
        if self._rows(k0, k1) > hold:
            while self._rows(k0, k1) > self.N and k0 < old_end:
                k0 += 1
        while self._rows(k0, k1) > max(hold if k0 == old0 else self.N, self.N):
            k1 -= 1  # fallen behind by more than a window: catch up over the next updates
        return k0, k1 - k0, k0 - old0

    def _is_virtual(self, row: int) -> bool:
        """Whether stream row `row` marks where a bridged gap begins (nothing measured there)."""
        i = bisect.bisect_left(self._virtual, row)
        return i < len(self._virtual) and self._virtual[i] == row

    def _layout(self, k0: int, Kw: int):
        """Inputs (the held commands, without the offsets over bridged gaps), step lengths,
        measurements, masks and the joints of intervals k0 .. k0 + Kw - 1."""
        M, a = self.M, k0 - self._iv_base
        starts = np.array(self._iv_start[a:a + Kw]) - self._base
        lens = np.array(self._iv_rows[a:a + Kw])
        link = np.array(self._iv_link[a:a + Kw])
        link[0] = _NEW_PIECE  # the window's first node is free
        has_next = np.r_[link[1:] != _NEW_PIECE, False]
        j = np.arange(M + 1)
        # an interval's steps reach the next one's first sample only when they are joined (the
        # last step then runs across a bridged gap)
        last = starts + np.where(has_next, lens, lens - 1)
        idx = np.minimum(starts[:, None] + j[None, :], last[:, None])  # (Kw, M+1); repeats = padding
        b = self._buf
        W = b[1][idx].reshape(1, -1)
        H = np.diff(b[0][idx], axis=1).reshape(1, -1)
        iy = np.minimum(starts[:, None] + j[None, :M], (starts + lens - 1)[:, None])
        inside = j[None, :M] < lens[:, None]
        out_rows = {"x": 2, "p1": 3, "p2": 4}
        Y = np.stack([b[out_rows[o]][iy] for o in self.plant.output_names], axis=-1)  # (Kw, M, ny)
        mask = np.isfinite(Y) & inside[:, :, None]
        Y = np.where(mask, Y, 0.0)
        pieces, piece_of = [], np.empty(Kw, int)
        for k in range(Kw):
            if link[k] == _NEW_PIECE:
                pieces.append([k, 0])
            pieces[-1][1] += 1
            piece_of[k] = len(pieces) - 1
        after_gap = np.flatnonzero(link == _BRIDGED)  # intervals that follow a bridged gap
        before = after_gap - 1
        return dict(W=W, H=H, Y=Y, mask=mask.astype(float), has_next=has_next, starts=starts, lens=lens,
                    pieces=[_Piece(k, n) for k, n in pieces], piece_of=piece_of, after_gap=after_gap,
                    gap_w=before * (M + 1) + lens[before] - 1, gap_h=before * M + lens[before] - 1)

    def _node_guesses(self, lay: dict, which: np.ndarray) -> np.ndarray:
        """Node states from the measured state (nearest measured values) and a smoothed velocity."""
        r0, r1 = lay["starts"][0], lay["starts"][-1] + lay["lens"][-1]
        t, _, x, p1, p2 = self._buf[:, r0:r1]
        x, p1, p2 = (fill_missing(t, c) for c in (x, p1, p2))
        v = velocity_estimate(t, x)
        S = np.zeros((self.plant.nx, len(lay["starts"])))
        for k in np.flatnonzero(which):
            i = lay["starts"][k] - r0
            S[:, k] = self.plant.initial_state(self.cyl, x[i], p1[i], p2[i], v[i])
        return S

    def _problem(self, lay: dict) -> "_PaddedProblem":
        """The shooting problem for this window (built once, again only for a larger window)."""
        Kw = len(lay["starts"])
        if self._prob is None or self._prob.capacity < Kw:
            self._prob = _PaddedProblem(self.sf, Kw + self.K, self.options.threads, self.wts, self.sscale,
                                        self.plant.possible_states(self.cyl))
        self._prob.set(lay)
        return self._prob

    # ------------------------------------------------------------ one update
    def update(self) -> OnlineEstimate | None:
        if not self.ready():
            return None
        t_wall = time.perf_counter()
        prev = self._prev
        w = self._window()
        self._carry_over(prev, w)
        u = self._unknowns(w)
        S, first_ev, keep = self._warm_start(prev, w, u)
        solved = self._solve(w, u, S, first_ev, self._iterations(prev, w, keep))
        r_acc, t0, seen = self._keep(w, solved)
        return self._estimate(w, solved, r_acc, t0, seen, t_wall)

    def _window(self) -> "_Window":
        """The next window: its intervals, layout and problem, and its last real sample (the
        estimate is of that one, not of a row that marks a gap)."""
        k0, Kw, left = self._next_window()
        lay = self._layout(k0, Kw)
        r_first = lay["starts"][0]
        r_last = lay["starts"][-1] + lay["lens"][-1] - 1
        last_k, last_row = Kw - 1, lay["lens"][-1] - 1
        if self._is_virtual(self._base + r_last):
            r_last -= 1
            last_k, last_row = (last_k, last_row - 1) if last_row else (Kw - 2, lay["lens"][-2] - 1)
        return _Window(k0, Kw, left, lay, self._problem(lay), len(self.p), r_first, r_last, last_k, last_row,
                       float(self._buf[0, r_first]), float(self._buf[0, r_last]))

    def _carry_over(self, prev: dict | None, w: "_Window") -> None:
        """What the last update leaves this one: the intervals that left the window into the
        arrival cost (and a drift's prior); the first window starts from the equation-error fit."""
        if prev is not None:
            self._absorb(prev, w.left)
            if self._drift is not None:
                self._drift_prior(0.5 * (w.t_first + w.t_last))
        elif self.options.prefit and not self._fitted and {"Fc", "Fv", "kp"} & set(self.names):
            b = self._buf[:, w.r_first:w.r_last + 1]
            start = equation_error_friction(self.cyl, [Run(t=b[0], u=b[1], x=b[2], p1=b[3], p2=b[4])])
            for n, v in start.items():
                if n in self.names:
                    self.theta[self.names.index(n)] = v
            self.theta = np.clip(self.theta, self.lower, self.upper)
            self.prior_mean = self.theta.copy()

    def _unknowns(self, w: "_Window") -> "_Unknowns":
        """The parameters, then the command offsets over the bridged gaps, which reach the plant
        through the held commands (p: the plant's parameters, then the offsets). A new gap's
        offset starts from the command reported after it: a host that answers in time has that
        one latched while the samples are lost, since it sent nothing newer."""
        lay, G, nth, npar = w.lay, w.G, len(self.free), len(self.p)
        W0 = lay["W"][0]
        jump = W0[lay["after_gap"] * (self.M + 1)] - W0[lay["gap_w"]]
        du = np.array([self._du.get(w.k0 + k, d) for k, d in zip(lay["after_gap"], jump)])
        theta = np.r_[self.theta, du]
        lower, upper = np.r_[self.lower, np.full(G, -_DU_RANGE)], np.r_[self.upper, np.full(G, _DU_RANGE)]
        free = list(self.free) + list(range(npar, npar + G))
        p = np.r_[self.p, du]
        p[self.free] = self.theta
        info = np.zeros((nth + G, nth + G))
        info[:nth, :nth] = self.info
        info[nth:, nth:] = np.eye(G) / _DU_RANGE**2  # weak: an offset the data after its gap do not fix stays small
        return _Unknowns(theta, lower, upper, free, p, info, np.r_[self.prior_mean, np.zeros(G)])

    def _warm_start(self, prev: dict | None, w: "_Window", u: "_Unknowns"):
        """(node states, the first iteration's evaluation or None, intervals shared with the last
        window): the previous nodes and trajectories where the windows overlap (shift and
        forward-simulate); new intervals run on from the one before, or start from the measured
        state where a new piece begins."""
        M, nx, nth, Kw, lay, p = self.M, self.plant.nx, len(self.free), w.Kw, w.lay, u.p
        keep = prev["Kw"] - w.left if prev is not None else 0
        S = self._node_guesses(lay, np.arange(Kw) >= keep)
        if keep <= 0:
            return S, None, keep  # the first iteration's evaluation is the first simulation of these nodes
        X = np.empty((nx, Kw, M))
        S[:, :keep] = prev["S"][:, w.left:]
        X[:, :keep] = prev["X"][:, w.left:]
        W = w.commands(p)
        # when the last update took no step, its linearisation holds where this window starts:
        # the intervals both windows share are not simulated again (an update that takes no
        # step then costs the new intervals, not the window)
        Sens = None
        if prev["Sens"] is not None:
            Sens = np.empty((nx, Kw, M, nx + nth))
            Sens[:, :keep] = prev["Sens"][:, w.left:]
        for k in range(keep - 1, Kw):  # the old last interval may have a successor now
            if k >= keep and lay["has_next"][k - 1]:
                S[:, k] = X[:, k - 1, M - 1]
            args = (S[:, k], W[:, k * (M + 1):(k + 1) * (M + 1)], p[:w.npar], lay["H"][:, k * M:(k + 1) * M])
            if Sens is None:
                X[:, k] = np.asarray(self.sf.interval(*args))
            else:
                X[:, k], sens_k = self._sens_one(*args)
                Sens[:, k] = sens_k.reshape(nx, M, nx + nth)
        first_ev = None
        if Sens is not None and w.prob.allows(S) and np.all(np.isfinite(X)):
            first_ev = (*w.prob.residuals(S, X), X, Sens)
        return S, first_ev, keep

    def _iterations(self, prev: dict | None, w: "_Window", keep: int) -> int:
        """Gauss-Newton iterations this update may take: the first window starts cold; a piece
        that starts in the new data (after an outage) gets a few more than a warm start, and so
        does a window mostly of new data (an estimator that fell behind slides far)."""
        n_iter = self.options.first_iterations if prev is None else self.options.max_iterations
        if prev is not None and (any(pc.node0 >= keep for pc in w.pieces) or keep < w.Kw // 2):
            n_iter = max(n_iter, min(3, self.options.first_iterations))
        return n_iter

    def _solve(self, w: "_Window", u: "_Unknowns", S: np.ndarray, first_ev, n_iter: int) -> "_Solved":
        """Up to n_iter Gauss-Newton iterations (gauss_newton.damped_step) until _update_end."""
        nx, R = self.plant.nx, w.R
        node_scale = np.tile(self.sscale, R)  # the free node states' defect scales (the damping's bound)
        theta, p = u.theta, u.p
        lam, mu, it = 0.0, 0.0, 0
        for it in range(1, n_iter + 1):
            # Jacobians are taken fresh every iteration: reusing those of the overlap (taken
            # before the last step) fails at reversals, where stick and slip switch
            ev = first_ev if it == 1 and first_ev is not None else w.evaluate(S, p, True)
            if ev is None:
                raise RuntimeError(f"online estimate: the simulation of the window at t = {w.t_first:.3f} s "
                                   "is not finite; check the cylinder file against the rig")
            E, X = ev[0], ev[2]
            model = self._step_model(w, u, ev, S, theta, p)
            out = damped_step(model.Nm, model.g, theta, u.lower, u.upper, node_scale, lam, mu, model,
                              ONLINE_DAMPING)
            lam, mu, step_taken = out.lam, out.mu, None
            why = _update_end(out, it, self.options.iterations, model.cost)
            if out.found is not None:
                lam = lam / 10 if lam > 1e-6 else 0.0
                alpha, S, th_try, p, ev_try = out.found
                step_taken = (alpha * out.step[:R * nx].reshape(R, nx)[w.piece_of], th_try - theta)
                theta, E, X = th_try, ev_try[0], ev_try[2]
            if why is not None:
                break
        return _Solved(it, S, X, E, theta, p, model.red, model.Nm, ev[3], step_taken)

    def _step_model(self, w: "_Window", u: "_Unknowns", ev, S: np.ndarray, theta: np.ndarray,
                    p: np.ndarray) -> "_OnlineStep":
        """The window linearised at (S, theta, p), evaluated in `ev`: its reduced normal
        equations with the arrival cost (and the gap offsets' prior) added."""
        M, nx, nth, lay = self.M, self.plant.nx, len(self.free), w.lay
        E, D, X = ev[0], ev[1], ev[2]
        lin = linearize(ev, w.prob.out_idx, self.wts, lay["mask"], M, nx, len(self.wts), nth)
        if w.G:
            lin = self._with_gap_offsets(lin, S, X, p, w.commands(p), lay, w.k0)
        red = _ReducedWindow(lin, E, D * self.sscale[:, None], lay["has_next"], nx, nth)
        Nm, g = red.normal_equations(w.pieces)
        dev = theta - u.mean
        Nm = Nm.with_parameters(u.info)
        g[w.R * nx:] += u.info @ dev
        cost = 0.5 * float(np.sum(E * E)) + 0.5 * float(dev @ u.info @ dev)
        return _OnlineStep(w, u, red, Nm, g, S, theta, p, dev, cost, float(np.sum(np.abs(D))), nth + w.G)

    def _keep(self, w: "_Window", solved: "_Solved"):
        """Keep this update's solution and linearisation for the next one, and drop the rows and
        intervals no later window can need: (residuals at the accepted point as the last
        linearisation predicts them, the intervals' start times, samples seen so far)."""
        nth, lay, red = len(self.free), w.lay, solved.red
        self.theta, self.p = solved.theta[:nth].copy(), solved.p[:w.npar].copy()
        self._du = {w.k0 + k: float(v) for k, v in zip(lay["after_gap"], solved.theta[nth:])}
        self._fitted = True
        r_acc = red.r0 if solved.step_taken is None else red.r0 + red.apply(*solved.step_taken)
        t0 = self._buf[0, lay["starts"]]
        t1 = self._buf[0, lay["starts"] + lay["lens"] - 1]
        self._prev = {"k0": w.k0, "Kw": w.Kw, "S": solved.S, "X": solved.X, "red": red, "r": r_acc,
                      "theta": self.theta, "piece_of": w.piece_of, "mask": lay["mask"], "t0": t0, "t1": t1,
                      "after_gap": lay["after_gap"], "Sens": solved.sens if solved.step_taken is None else None}
        r_last = w.r_last
        seen = self._base + r_last + 1 - self._virtual_gone - bisect.bisect_right(self._virtual, self._base + r_last)
        if w.r_first > 0:  # (buffer positions)
            self._buf = self._buf[:, w.r_first:]
            self._base += w.r_first
            gone_rows = bisect.bisect_left(self._virtual, self._base)
            del self._virtual[:gone_rows]
            self._virtual_gone += gone_rows
        gone = w.k0 - self._iv_base
        if gone > 0:
            del self._iv_start[:gone], self._iv_rows[:gone], self._iv_link[:gone]
            self._iv_base = w.k0
        return r_acc, t0, seen

    def _estimate(self, w: "_Window", solved: "_Solved", r_acc: np.ndarray, t0: np.ndarray, seen: int,
                  t_wall: float) -> OnlineEstimate:
        """The update's estimate: the parameters with the whole session's std (or a followed
        drift's value now), a change this refit reports, the window's fit, the model state at
        its last sample. A change found here restarts the window from the change on."""
        lay, R, E, t_last = w.lay, w.R, solved.E, w.t_last
        nres = float(lay["mask"].sum())
        sigma = math.sqrt(float(np.sum(E * E)) / max(1.0, nres - R * self.plant.nx - (len(self.free) + w.G)))
        value = self.theta
        std = self._std(solved.Nm, R, w.piece_of, solved.red, r_acc, lay["mask"], t0, self.theta)
        if self.options.track:
            followed = self._track(self._prev, t_last, sigma)
            if followed == "restart":
                again = self.update()  # the window again, from the change on
                if again is not None:
                    return again
            elif followed is not None:  # a drift: the trend's value now
                value, std = followed
        change, self._change = self._change, None
        if change is not None:  # after the step: as this refit of the data after it finds it
            change = replace(change, after=dict(zip(self.names, value.tolist())),
                             std_after=dict(zip(self.names, std.tolist())),
                             std={n: math.hypot(change.std_before[n], s_) for n, s_ in zip(self.names, std.tolist())})
        wts = self.wts
        rmse = {f"rmse_{n}": float(np.sqrt(np.sum(E[..., j] ** 2) / max(lay["mask"][..., j].sum(), 1))) / wts[j]
                for j, n in enumerate(self.plant.output_names)}
        state = solved.S[:, w.last_k] if w.last_row == 0 else solved.X[:, w.last_k, w.last_row - 1]
        return OnlineEstimate(
            t=t_last, values=dict(zip(self.names, value.tolist())), std=dict(zip(self.names, std.tolist())),
            units=self.units, window=(w.t_first, t_last), samples_seen=int(seen), sigma=sigma, rmse=rmse,
            iterations=solved.iterations, wall_s=time.perf_counter() - t_wall, pieces=R, gaps=w.G,
            state=state.copy(), params=self.p.copy(), change=change, drift=self._drift,
            step_pending=bool(self.analysis is not None and self.analysis.pending >= self.options.change_z
                              and self._t_tested == t_last))

    # ------------------------------------------------------------ a rig that changes
    def _block_ranges(self, k0: int, end: int, piece_of: np.ndarray) -> list[tuple[int, int]]:
        """The window's intervals 0 .. end - 1 (window k0) in blocks: (first, one past the
        last), cut where a piece begins and at the global multiples of SUB (so that the same
        intervals make the same blocks in every window)."""
        out, a = [], 0
        for k in range(1, end):
            if piece_of[k] != piece_of[k - 1] or (k0 + k) % self.SUB == 0:
                out.append((a, k))
                a = k
        if end > a:
            out.append((a, end))
        return out

    def _blocks(self, w: dict, ranges: list[tuple[int, int]]) -> Blocks:
        """What each block of window `w` (an update's _prev) alone says about the parameters."""
        s, A = w["red"].block_stats(ranges, w["r"], w["after_gap"])
        a = np.array([x for x, _ in ranges], int)
        b = np.array([y for _, y in ranges], int)
        return Blocks(len(self.free), w["t0"][a], w["t1"][b - 1], w["k0"] + a,
                      np.repeat(w["theta"][None, :], len(a), axis=0), s, A)

    def _track(self, w: dict, t_last: float, sigma: float):
        """The tests over the history and this window (w: its _prev). A step restarts the
        estimate at the change ("restart"); a drift is followed (its value and std now); else None."""
        opts = self.options
        self._history = self._history.since(t_last - opts.history_s)
        self._sigmas = [(t, s_) for t, s_ in self._sigmas if t >= t_last - opts.history_s] + [(t_last, sigma)]
        if self._restarting:  # the refit after a step: its blocks are tested from the next update on
            self._restarting = False
            return None
        if w["Sens"] is None:  # a step was taken: no block of the last window holds as it was
            self._block_cache = None
        if self._drift is None and t_last - self._t_tested < opts.block_s - 0.5 * self.dt:
            return None  # less than a block since the last tests: nothing new to test
        w["ranges"] = ranges = self._block_ranges(w["k0"], w["Kw"], w["piece_of"])
        # where neither this update nor the last took a step, the intervals both windows hold
        # are linearised alike, and so are the blocks they make (a block's own start state is
        # profiled out, whichever node the window starts from)
        kept = self._block_cache if w["Sens"] is not None else None
        keys = [(w["k0"] + a, w["k0"] + b) for a, b in ranges]
        todo = [r for r, key in zip(ranges, keys) if not kept or key not in kept]
        fresh = iter(self._blocks(w, todo).rows() if todo else ())
        rows = [kept[key] if kept and key in kept else next(fresh) for key in keys]
        w["blocks"] = Blocks.of_rows(len(self.free), rows)
        self._block_cache = dict(zip(keys, rows)) if w["Sens"] is not None else None
        data = self._history.extend(w["blocks"])
        slide, self._t_tested = t_last - self._t_tested, t_last
        self._regime_slide += slide
        if self._regime_slide >= 1.0 or self._regime_recent is None:  # a slow quantity: once a second of data
            self._update_regime(t_last, self._regime_slide)
            self._regime_slide = 0.0
        if len(data) < 2:
            return None
        # the residual of the rig as it was: the windows before the data tested for a step
        steady = self._sigma_before(t_last - opts.recent_s)
        noise = max(1.0, min(steady if steady is not None else 1.0, MISMATCH)) ** 2
        # until the history has shown the rig's regimes for a while, a step must be larger
        settled = float(np.sum((self._history.t1 - self._history.t0)[self._history.t1 < t_last - opts.regime_s]))
        regime = self._regime_now()
        young = regime if settled >= opts.settle_s else self._regime_now(opts.young_floor)
        an = self.analysis = analyse(data, self.theta, t_last, young, noise, cluster_s=opts.cluster_s,
                                     min_after_s=opts.min_after_s, recent_s=opts.recent_s, drift_regime=regime)
        chi2 = an.dispersion
        # a model that did not explain the rig before a step says nothing of it; one that left
        # sigma times the noise left it systematically, with a regime dependence that the
        # history need not have shown in full: a step must be sigma times as large
        before = self._sigma_before(an.t_change) if an.z_step else None
        if (before is not None and before <= MISMATCH and an.z_step >= opts.change_z * max(1.0, before)
                and (an.z_drift < opts.drift_z or chi2["step_chi2"] <= chi2["drift_chi2"])):
            self._restart(an, data, w["k0"], t_last)
            return "restart"
        if self._drift is None:
            # (a rig that drifts away from its estimate leaves a growing residual: judged by the
            # session's typical recent window rather than the last one)
            typical = float(np.median([s_ for _, s_ in self._sigmas[-10:]])) <= MISMATCH
            # (nor while a step may be on its way: a fresh step looks like a steep trend)
            if typical and math.isinf(opts.memory_s) and an.z_drift >= opts.drift_z and an.pending < opts.change_z:
                self._drift = self._drift_of(an, t_last)
                self._drift_quiet = 0.0
        else:
            self._drift_quiet = 0.0 if an.z_drift >= 2.0 else self._drift_quiet + min(slide, opts.update_s)
            if self._drift_quiet >= 5.0:  # the drift has stopped: constant again
                self._constant_prior(data.since(t_last - 5.0))
                self._drift = None
            else:
                self._drift = self._drift_of(an, self._drift.since)
        if self._drift is None:
            return None
        tr = an.trend
        return np.clip(tr.value, self.lower, self.upper), np.sqrt(np.maximum(np.diag(tr.cov), 0.0))

    def _sigma_before(self, t: float) -> float | None:
        """The typical residual sigma of the windows that ended by t (the median of the last ten
        of them), or None when none did."""
        past = [s_ for t_, s_ in self._sigmas if t_ <= t]
        return float(np.median(past[-10:])) if past else None

    def _update_regime(self, t_last: float, slide: float) -> None:
        """The rig's regime variance (identify/tracking.regime_variances) from the history but its
        last regime_s (where a change may be under way), averaged over the session with a
        time constant of regime_memory_s of data; a step does not reset it (the model lacks
        what it lacked before)."""
        opts = self.options
        old = self._history.select(self._history.t1 < t_last - opts.regime_s)
        est = regime_variances(old, self.theta, self._scales)
        for i in range(1, len(est)):  # a scale the history is too short for: that of the one below
            if est[i] is None:
                est[i] = est[i - 1]
        if est[0] is None:
            self._regime_recent = None
            return
        est = np.array(est)
        self._regime_recent = est
        if self._regime is None:
            self._regime = est
        else:
            a = min(1.0, max(slide, 0.0) / opts.regime_memory_s)
            self._regime = (1 - a) * self._regime + a * est

    def _regime_now(self, floor_factor: float = 1.0) -> Regime:
        """The regime covariance to count at each scale: the session's, or the recent
        history's where larger (the session's average is slow to learn), and at least the
        floor on the diagonal: regime_floor of each value, and for kp of the friction force
        Fc + Fv 0.1 m/s + kp 2 bar over 2 bar (the seal's pressure term is the least determined
        and moves with the regime more than the others)."""
        f = self.options.regime_floor * floor_factor
        floor = f * np.abs(self.theta)
        names = list(self.names)
        if "kp" in names:
            terms = {"Fc": 1.0, "Fv": 0.1, "kp": 2e5}  # each term's regressor at a typical state
            level = sum(abs(self.theta[names.index(n)]) * x for n, x in terms.items() if n in names)
            floor[names.index("kp")] = max(floor[names.index("kp")], f * level / 2e5)
        var = np.tile(floor ** 2, (len(self._scales), 1))
        for v in (self._regime, self._regime_recent):  # (diagonal: regime_variances')
            if v is not None:
                var = np.maximum(var, np.diagonal(v, axis1=1, axis2=2))
        return Regime(self._scales, var[:, :, None] * np.eye(len(floor)))

    def _drift_of(self, an, since: float) -> Drift:
        tr = an.trend
        rate_std = np.sqrt(np.maximum(np.diag(tr.rate_cov), 0.0))
        return Drift(rate=dict(zip(self.names, tr.rate.tolist())), rate_std=dict(zip(self.names, rate_std.tolist())),
                     z=an.z_drift, since=since)

    def _drift_prior(self, t_c: float) -> None:
        """While a drift is followed: the window's prior is the history's trend at the window's
        centre (what the data before the window say of it)."""
        if len(self._history) < 2:
            return
        steady = self._sigma_before(t_c)
        noise = max(1.0, min(steady if steady is not None else 1.0, MISMATCH)) ** 2
        fit = trend_fit(self._history, self.theta, t_c, self._regime_now(), noise)
        self.info = pinv(fit.cov)[0] + self._weak
        self.prior_mean = np.clip(fit.value, self.lower, self.upper)

    def _constant_prior(self, blocks: Blocks) -> None:
        """The prior from what `blocks` say of constant parameters (and the weak prior)."""
        if not len(blocks):
            return
        G, A = blocks.at(self.theta)[0].sum(axis=0), blocks.A.sum(axis=0)
        self.info, mean = _merged_prior(self._weak, self.theta, A, self.theta, G)
        self.prior_mean = np.clip(mean, self.lower, self.upper)

    def _restart(self, an, data: Blocks, k0: int, t_last: float) -> None:
        """After a step at the located boundary: the data before it lose their weight. The
        prior becomes the estimate before the step, widened to cover the step (and what the
        history after it says); the window restarts at the step when the step lies in it; the
        session's residual statistics start anew."""
        b = an.boundary
        before, after = an.before, an.after
        sb = np.sqrt(np.maximum(np.diag(before.cov), 0.0))
        sa = np.sqrt(np.maximum(np.diag(after.cov), 0.0))
        jump = np.abs(after.value - before.value)
        width = np.maximum.reduce([2 * jump + 3 * np.hypot(sb, sa), 0.1 * np.abs(before.value),
                                   1e-3 * (self.upper - self.lower)])
        self.info = np.diag(1.0 / width ** 2) + self._weak
        self.prior_mean = np.clip(before.value, self.lower, self.upper)
        self._history = self._history.since(float(data.t0[b]))
        self.theta = np.clip(after.value, self.lower, self.upper)
        if len(self._history):  # the history after the step (it lies before the window) is information
            G, A = self._history.at(self.theta)[0].sum(axis=0), self._history.A.sum(axis=0)
            self.info, mean = _merged_prior(self.info, self.prior_mean, A, self.theta, G)
            self.prior_mean = np.clip(mean, self.lower, self.upper)
        self.p[self.free] = self.theta
        self._prev, self._w, self._restarting = None, max(int(data.k[b]), k0), True
        self._ssr = self._nres = self._nstates = 0.0
        self._clusters = _Clusters(len(self.free))
        self._drift = None
        n = self.names
        self._change = Change(t=an.t_change, t_std=an.t_change_std, z=an.z_step, t_detected=t_last,
                              before=dict(zip(n, before.value.tolist())), after=dict(zip(n, after.value.tolist())),
                              std_before=dict(zip(n, sb.tolist())), std_after=dict(zip(n, sa.tolist())),
                              std=dict(zip(n, np.hypot(sb, sa).tolist())))

    def _with_gap_offsets(self, lin, S, X, p, W, lay, k0: int):
        """The linearisation with the command offsets over the bridged gaps as further
        parameters of the transitions (B): each moves the end state of the interval before its
        gap (the step across the gap) along the derivative of that step by the command (central
        differences). No residual depends on an offset directly (Hth keeps the parameters)."""
        G_, Hth, A, B = lin
        npar = len(self.p)
        after = lay["after_gap"]
        Gn = len(after)
        before = after - 1
        n = lay["lens"][before]
        xb = X[:, before, np.maximum(n - 2, 0)]  # the state at the last sample before each gap
        xb[:, n == 1] = S[:, before[n == 1]]
        u, h = W[0, lay["gap_w"]], lay["H"][0, lay["gap_h"]]
        # a gap whose step starts where it did in the last evaluation has the same slope (most
        # updates take no step: only the new gaps are differenced)
        at = np.vstack([xb, u, h, np.repeat(p[:npar, None], Gn, axis=1)])
        keys = [(int(k), at[:, i].tobytes()) for i, k in enumerate(k0 + after)]
        dxdu = np.empty((xb.shape[0], Gn))
        new = []
        for i, key in enumerate(keys):
            if (kept := self._gap_slopes.get(key)) is None:
                new.append(i)
            else:
                dxdu[:, i] = kept
        if new:
            eps, cols = 1e-4, -(-len(new) // 8) * 8  # the unused columns take zero-length steps
            if cols not in self._gap_steps:
                self._gap_steps[cols] = NumpyCall(self.sf.step.map(2 * cols))
            xs, us, hs = np.zeros((xb.shape[0], 2 * cols)), np.zeros(2 * cols), np.zeros(2 * cols)
            for side, d in enumerate((eps, -eps)):
                at = slice(side * cols, side * cols + len(new))
                xs[:, at], us[at], hs[at] = xb[:, new], u[new] + d, h[new]
            xn = self._gap_steps[cols](xs, us[None], us[None], p[:npar, None], hs[None])[0]
            dxdu[:, new] = (xn[:, :len(new)] - xn[:, cols:cols + len(new)]) / (2 * eps)
        self._gap_slopes = {key: dxdu[:, i].copy() for i, key in enumerate(keys)}
        nth = Hth.shape[-1]
        B = np.concatenate([B, np.zeros(B.shape[:-1] + (Gn,))], axis=-1)
        B[before, :, nth + np.arange(Gn)] = dxdu.T
        return G_, Hth, A, B

    # ------------------------------------------------------------ arrival cost
    def _absorb(self, prev: dict, left: int) -> None:
        """Merge the intervals leaving the window into the arrival cost: their Gauss-Newton
        model around the previous estimate, with the start state of each piece they belong to
        and the command offsets of their gaps marginalised out, updates the prior's
        information and mean (a Kalman update)."""
        decay = 1.0
        if math.isfinite(self.options.memory_s):
            decay = math.exp(-self._rows(prev["k0"], prev["k0"] + left) * self.dt / self.options.memory_s)
            self._clusters.scale(decay)
            self._ssr, self._nres, self._nstates = (v * decay for v in (self._ssr, self._nres, self._nstates))
        info_old = self.info * decay
        if left <= 0:
            self.info = info_old
            return
        nth = len(self.free)
        A, b = np.zeros((nth, nth)), np.zeros(nth)
        theta = prev["theta"]
        leaving = np.arange(left)
        for part in np.unique(prev["piece_of"][:left]):
            ks = leaving[prev["piece_of"][:left] == part]
            s_k, A_k, r = prev["red"].profiled_scores(ks, prev["r"])
            A += A_k.sum(axis=0)
            b += s_k.sum(axis=0)
            self._clusters.add((prev["t0"][ks] // self.options.cluster_s).astype(int), s_k, A_k, theta)
            self._ssr += float(np.sum(r * r))
            self._nstates += self.plant.nx
        self._nres += float(prev["mask"][:left].sum())
        if self.options.track:  # the leaving blocks, as the last tests saw them where they can
            ranges = self._block_ranges(prev["k0"], left, prev["piece_of"])
            seen, n = prev.get("ranges", []), 0
            while n < len(ranges) and n < len(seen) and ranges[n] == seen[n]:
                n += 1
            if n:
                self._history = self._history.extend(prev["blocks"].select(slice(0, n)))
            if n < len(ranges):
                self._history = self._history.extend(self._blocks(prev, ranges[n:]))
        # the leaving data's cost around theta, 0.5 d'A d + b'd, merged with the prior
        self.info, self.prior_mean = _merged_prior(info_old, self.prior_mean, A, theta, b)

    def _std(self, Nm, R, piece_of, red: _ReducedWindow, r, mask, t0, theta) -> np.ndarray:
        """Standard deviations of the whole-session estimate: the larger of the Gauss-Newton one
        (scaled by the session's residual variance) and the cluster-robust one. Nm holds the
        window's normal equations with the arrival cost; its node states and gap offsets are
        profiled out."""
        nx, nth = self.plant.nx, len(self.free)
        E = Nm.schur(keep=nth)
        try:
            Hinv = E.parameter_inverse()
        except np.linalg.LinAlgError:
            return np.full(nth, np.nan)
        # the session's residual variance: what left the window and the window itself
        ssr = self._ssr + float(np.sum(r * r))
        dof = self._nres + float(mask.sum()) - self._nstates - R * nx - red.nu
        var = np.diag(Hinv) * (ssr / dof if dof > 0 else np.nan)
        # each window interval's parameter gradient, with the window's nuisances profiled out,
        # joins the clusters of what has left
        g_state, g_par = red.scores(r)
        s_k = E.profiled(g_state, piece_of, g_par)
        scores = self._clusters.at(theta, (t0 // self.options.cluster_s).astype(int), s_k)
        if len(scores) >= 5:
            meat = scores.T @ scores * len(scores) / (len(scores) - 1)
            var = np.maximum(var, np.diag(Hinv @ meat @ Hinv))
        return np.sqrt(np.maximum(var, 0.0))


class _Clusters:
    """Parameter gradient contributions of the data that left the window, summed by cluster
    (of cluster_s seconds) with their information: a cluster taken in at theta_k contributes
    sum s_k + sum A_k (theta - theta_k) at theta."""

    def __init__(self, nth: int):
        self.rows: dict[int, int] = {}
        self.s, self.A, self.c = np.zeros((0, nth)), np.zeros((0, nth, nth)), np.zeros((0, nth))

    def add(self, index: np.ndarray, s_k: np.ndarray, A_k: np.ndarray, theta: np.ndarray) -> None:
        rows = np.array([self._row(int(i)) for i in index], int)
        np.add.at(self.s, rows, s_k)
        np.add.at(self.A, rows, A_k)
        np.add.at(self.c, rows, A_k @ theta)

    def scale(self, factor: float) -> None:
        self.s *= factor
        self.A *= factor
        self.c *= factor

    def at(self, theta: np.ndarray, index: np.ndarray, s_k: np.ndarray) -> np.ndarray:
        """Every cluster's contribution at theta, with those of the window (s_k by cluster index) added."""
        out = self.s + self.A @ theta - self.c
        extra = {}
        for i, s in zip(index.tolist(), s_k):
            if i in self.rows:
                out[self.rows[i]] += s
            else:
                extra[i] = extra.get(i, 0.0) + s
        return np.vstack([out, *extra.values()]) if extra else out

    def _row(self, i: int) -> int:
        if i not in self.rows:
            self.rows[i] = len(self.rows)
            self.s = np.vstack([self.s, np.zeros((1, self.s.shape[1]))])
            self.A = np.concatenate([self.A, np.zeros((1,) + self.A.shape[1:])])
            self.c = np.vstack([self.c, np.zeros((1, self.c.shape[1]))])
        return self.rows[i]


def _noise_gain(nu: int) -> float:
    """The decrease of 0.5 |r|^2 that fitting nu unknowns to pure noise exceeds in about one
    window of ten: its mean nu / 2 plus 1.28 of its standard deviations, sqrt(nu / 2) (chi2
    with nu degrees of freedom, halved; 3.07 at nu = 3, 15.8 at nu = 23, where the exact 90th
    percentiles are 3.13 and 16.0). The threshold of a step worth taking: the mean alone is
    crossed by four windows in ten, so a window with twenty gap offsets took a step for noise
    that often, while the parameters alone (nu = 3, mean 1.5) were held to about this level by
    the threshold's other term, a thousandth of the cost."""
    return 0.5 * nu + 1.2816 * math.sqrt(0.5 * nu)


def _merit(ev, theta: np.ndarray, mean: np.ndarray, info: np.ndarray, mu: float) -> float:
    """Data cost, arrival cost (and the gap offsets' prior) and the l1 penalty on the defects."""
    d = theta - mean
    return 0.5 * float(np.sum(ev[0] ** 2)) + 0.5 * float(d @ info @ d) + mu * float(np.sum(np.abs(ev[1])))


class _ReducedWindow:
    """The window's residuals linearised in the reduced unknowns: the start state of each
    piece, the parameters and the command offsets over the bridged gaps.

    An offset reaches the residuals only through the node states after its gap, so its
    columns are Gf_k Qg_k (Gf_k: an interval's residuals by its node state, Qg_k: the node
    state by the offsets) and are never formed: every product with them is taken through
    the small nx-by-nx blocks Gf_k' Gf_k (the normal equations of a 2 s window with twenty
    gaps: 1.4 ms, against 2.3 ms with dense columns and 1.1-1.2 ms without gaps)."""

    @np.errstate(over="ignore", invalid="ignore")  # see shooting.node_transitions
    def __init__(self, lin, E, Draw, has_next, nx: int, nth: int):
        G, Hth, A, B = lin  # B: by the parameters, then by the offsets
        K = G.shape[0]
        self.P, self.Q, self.q = node_transitions(A, B, Draw, has_next)
        self.nx, self.nth, self.nu = nx, nth, B.shape[-1]
        self.Gf = G.reshape(K, -1, nx)
        self.Qg = self.Q[..., nth:]
        self.Js = (self.Gf @ self.P).reshape(G.shape[:3] + (nx,))
        self.Jth = (self.Gf @ self.Q[..., :nth]).reshape(G.shape[:3] + (nth,)) + Hth
        self.r0 = E + (self.Gf @ self.q[:, :, None]).reshape(E.shape)

    def _Gt(self, v):
        """Gf_k' v_k for per-interval residual blocks v (K, M, ny, ...)."""
        K = v.shape[0]
        return self.Gf.transpose(0, 2, 1) @ v.reshape(K, self.Gf.shape[1], -1)

    def normal_equations(self, pieces: Sequence[_Piece]):
        """(N, g) in (the pieces' start states, the parameters, the offsets) at r0."""
        nx, nth, nu = self.nx, self.nth, self.nu
        Nt, gt, _ = normal_equations(self.Js, self.Jth, self.r0, pieces, nx, nth)
        if nu == nth:
            return Nt, gt
        K, ng = self.Qg.shape[0], nu - nth
        Qg = self.Qg.reshape(K * nx, ng)  # the sums over intervals and states as one product each
        CQ = (self.Gf.transpose(0, 2, 1) @ self.Gf) @ self.Qg
        starts = [pc.node0 for pc in pieces]
        C = np.concatenate([Nt.C, np.add.reduceat(self.P.transpose(0, 2, 1) @ CQ, starts, axis=0)], axis=2)
        T = np.zeros((nu, nu))
        T[:nth, :nth] = Nt.T
        T[:nth, nth:] = self._Gt(self.Jth).transpose(2, 0, 1).reshape(nth, K * nx) @ Qg
        T[nth:, :nth] = T[:nth, nth:].T
        T[nth:, nth:] = Qg.T @ CQ.reshape(K * nx, ng)
        g = np.concatenate([gt, Qg.T @ self._Gt(self.r0).reshape(K * nx)])
        return ReducedNormal(Nt.S, C, T), g

    def apply(self, ds0_k, dth):
        """The change of the residuals for node increments ds0_k (per interval) and dth."""
        shape = self.r0.shape
        dx = self.P @ ds0_k[:, :, None] + self.Qg @ dth[self.nth:, None]
        return (self.Gf @ dx).reshape(shape) + self.Jth @ dth[:self.nth]

    def scores(self, r):
        """Per interval, the gradient of 0.5 |r|^2: by the start state of its piece, and by
        the parameters and the offsets."""
        K = self.Js.shape[0]
        rr = r.reshape(K, -1, 1)
        gt_r = self._Gt(r)
        g_th = (self.Jth.reshape(K, rr.shape[1], -1).transpose(0, 2, 1) @ rr)[..., 0]
        g_gap = (self.Qg.transpose(0, 2, 1) @ gt_r)[..., 0]
        return (self.P.transpose(0, 2, 1) @ gt_r)[..., 0], np.concatenate([g_th, g_gap], axis=1)

    def profiled_scores(self, ks, r):
        """Per interval ks of one piece: the gradient contributions and information of the
        parameters with the piece's start state and the gap offsets profiled out (they sum
        to the reduced gradient and the Schur complement), and the residuals r[ks]."""
        nth, k = self.nth, len(ks)
        Nk = np.concatenate([self.P[ks], self.Qg[ks]], axis=-1)  # nuisances = Gf_k Nk
        Gf, Jth = self.Gf[ks], self.Jth[ks].reshape(k, -1, nth)
        F = Gf.transpose(0, 2, 1) @ Jth
        NtCN = np.einsum("kai,kab,kbj->ij", Nk, Gf.transpose(0, 2, 1) @ Gf, Nk)
        proj = pinv(NtCN, rcond=_NUISANCE_RCOND)[0] @ np.einsum("kai,kaj->ij", Nk, F)
        par = Jth - Gf @ (Nk @ proj)
        rr = r[ks].reshape(k, -1)
        return (par.transpose(0, 2, 1) @ rr[:, :, None])[..., 0], par.transpose(0, 2, 1) @ par, rr

    def block_stats(self, ranges, r, after_gap):
        """Per block (a, b) of a piece's intervals a .. b - 1: the gradient of 0.5 |r|^2 by the
        parameters and its Gauss-Newton information, with the block's own start state (and
        the command offsets over gaps inside it) profiled out: what the block alone says."""
        nth = self.nth
        S, A = np.empty((len(ranges), nth)), np.empty((len(ranges), nth, nth))
        inner = [[j for j, kk in enumerate(after_gap) if a < kk < b] for a, b in ranges]
        plain = np.array([not g for g in inner])
        if plain.any():  # blocks without a gap inside: their sums over intervals at once
            ks = np.concatenate([np.arange(a, b) for (a, b), p in zip(ranges, plain) if p])
            firsts = np.cumsum([0] + [b - a for (a, b), p in zip(ranges, plain) if p][:-1])
            K = len(ks)
            Gf, P = self.Gf[ks], self.P[ks]
            Gt = Gf.transpose(0, 2, 1)
            Jth = self.Jth[ks].reshape(K, -1, nth)
            rr = r[ks].reshape(K, -1, 1)
            Pt = P.transpose(0, 2, 1)
            per = [Pt @ (Gt @ Gf) @ P, Pt @ (Gt @ Jth), (Pt @ (Gt @ rr))[..., 0],
                   Jth.transpose(0, 2, 1) @ Jth, (Jth.transpose(0, 2, 1) @ rr)[..., 0]]
            NtCN, NtF, Ntr, JJ, Jr = (np.add.reduceat(x, firsts, axis=0) for x in per)
            proj = pinv(NtCN)[0] @ NtF
            A[plain] = JJ - NtF.transpose(0, 2, 1) @ proj
            S[plain] = Jr - (proj.transpose(0, 2, 1) @ Ntr[..., None])[..., 0]
        for i in np.flatnonzero(~plain):  # a block with gaps: their command offsets too
            (a, b), gaps = ranges[i], inner[i]
            k = b - a
            Nk = np.concatenate([self.P[a:b], self.Qg[a:b][:, :, gaps]], axis=-1)
            Gf, Jth = self.Gf[a:b], self.Jth[a:b].reshape(k, -1, nth)
            rr = r[a:b].reshape(k, -1)
            Gt = Gf.transpose(0, 2, 1)
            NtCN = np.einsum("kai,kab,kbj->ij", Nk, Gt @ Gf, Nk)
            NtF = np.einsum("kai,kaj->ij", Nk, Gt @ Jth)
            Ntr = np.einsum("kai,ka->i", Nk, (Gt @ rr[:, :, None])[..., 0])
            proj = pinv(NtCN, rcond=_NUISANCE_RCOND)[0] @ NtF
            A[i] = np.einsum("kma,kmb->ab", Jth, Jth) - NtF.T @ proj
            S[i] = np.einsum("kma,km->a", Jth, rr) - proj.T @ Ntr
        return S, A


def _merged_prior(info: np.ndarray, mean: np.ndarray, A: np.ndarray, theta: np.ndarray, G: np.ndarray):
    """(information, mean) of the prior 0.5 (x - mean)' info (x - mean) plus data whose cost
    around theta is 0.5 d'A d + G'd (d = x - theta)."""
    merged = info + A
    return merged, _solve_scaled(merged, info @ mean + A @ theta - G)


def _solve_scaled(N: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """N^-1 rhs on the unit-diagonal scaling of N (parameters differ by 10 decades)."""
    s = np.sqrt(np.maximum(np.diag(N), 1e-300))
    return np.linalg.solve(N / np.outer(s, s), rhs / s) / s
