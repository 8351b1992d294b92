"""Online estimation: moving-horizon multiple shooting over the last seconds of a stream.

Each update solves the identification problem of `identify` (same plant, same condensed
Gauss-Newton, same compiled functions) on a window of the latest `window_s` of data,
warm-started from the previous solution. An arrival cost carries what the data that left
the window said about the parameters: when intervals leave, their Gauss-Newton information
(their unknown start state marginalised out) is added to the prior. So the estimate keeps
using the whole stream while every update costs one fixed-size window. A finite
`memory_s` discounts old information, to follow slowly drifting friction (a warming seal).

Windows slide by whole shooting intervals and never by more than a window, so no sample is
skipped when the estimator falls behind (it then slides further per update instead).
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from sim.compiled import shooting_functions
from sim.cylinder import Cylinder
from sim.extension import Effect
from sim.integrator import IntegratorOptions
from sim.plant import build_plant

from ..files import Run
from .newton import equation_error_friction
from .shooting import (ShootingProblem, free_parameters, line_search, linearize, parameter_bounds, parameter_unit,
                       reduce_nodes, residual_scales, run_layout, scaled_inverse, solve_bounded)


@dataclass(frozen=True)
class OnlineOptions:
    window_s: float = 2.0  # moving horizon
    update_s: float = 0.2  # slide between updates when keeping up (rounded to whole intervals)
    interval_s: float = 0.1  # shooting interval
    # Gauss-Newton iterations per update: one usually suffices once warm-started on
    # overlapping windows (the real-time iteration of Diehl et al.); more are taken, up to
    # `max_iterations`, only while the step still promises a real decrease (a reversal in
    # the new data); the first window may take `first_iterations`
    iterations: int = 1
    max_iterations: int = 3
    first_iterations: int = 6
    max_missing: int = 0  # lost samples a window may bridge (see `add`)
    estimate: tuple[str, ...] = ("Fc", "Fv", "kp")
    memory_s: float = math.inf  # forgetting time constant of the arrival cost
    prefit: bool = True  # first window: start from the equation-error fit
    integrator: IntegratorOptions = IntegratorOptions()
    threads: int = max(1, os.cpu_count() or 1)  # the estimator process runs niced


@dataclass
class OnlineEstimate:
    t: float  # rig time of the window's last sample
    values: dict[str, float]
    std: dict[str, float]
    units: dict[str, str]
    window: tuple[float, float]
    samples_seen: int  # samples that have entered the estimate so far
    sigma: float  # RMS of the weighted residuals (1 = at sensor noise)
    rmse: dict[str, float]  # over the window, per output
    iterations: int
    wall_s: float
    state: np.ndarray = field(repr=False)  # model state at t, to resynchronise a simulation
    params: np.ndarray = field(repr=False)  # the full plant parameter vector


class MovingHorizonEstimator:
    """Feed complete rows with `add`, call `update` when `ready`; each update returns an estimate."""

    def __init__(self, cyl: Cylinder, sample_period: float, options: OnlineOptions = OnlineOptions(),
                 effects: Sequence[Effect] = (), progress: Callable[[str], None] | None = None):
        self.cyl, self.options, self.dt = cyl, options, float(sample_period)
        self.plant = plant = build_plant("command", effects)
        self.names = tuple(options.estimate)
        self.free = free_parameters(plant, self.names)
        self.M = M = max(5, int(round(options.interval_s / self.dt)))
        self.K = K = max(2, int(round(options.window_s / (M * self.dt))))
        self.N = K * M
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
        self.nxt = np.arange(K - 1)
        self.has_next = np.r_[np.ones(K - 1, bool), False]
        self._problem: ShootingProblem | None = None
        self._threads = max(1, min(options.threads, K))
        self._buf = np.empty((5, 0))  # rows t, u, x, p1, p2
        self._base = 0  # stream index of _buf[:, 0]
        self._seg0 = 0  # stream index where the current gap-free segment starts
        self._breaks: list[int] = []  # stream indices of the first rows after gaps
        self._fitted = False
        self._seen = 0  # stream index one past the newest row
        self._prev: dict | None = None  # the last update's window start, nodes, trajectory, Jacobians
        self.units = {n: parameter_unit(plant, n) for n in self.names}

    # ------------------------------------------------------------ data
    def add(self, t, u, x, p1, p2, lost_before=None) -> None:
        """Append complete rows (u is the command held from t until the next sample).

        `lost_before` flags rows that follow lost samples (from the rig's sequence numbers);
        without it, a step longer than 1.9 sample periods is taken for a loss."""
        rows = np.vstack([np.atleast_1d(np.asarray(a, float)) for a in (t, u, x, p1, p2)])
        if rows.shape[1] == 0:
            return
        # a gap in the stream starts a new segment that no window bridges: the command held
        # during a lost sample is unknown, and one sample of a wrong command moves a chamber
        # pressure by kilopascals, ten times the sensor noise
        if lost_before is not None:
            flagged = np.flatnonzero(np.asarray(lost_before, bool))
            self._breaks.extend(int(self._seen + j) for j in flagged if self._seen + j > 0)
        else:
            t_all = rows[0] if self._buf.shape[1] == 0 else np.concatenate([self._buf[0, -1:], rows[0]])
            off = self._seen - (len(t_all) - rows.shape[1])
            limit = (self.options.max_missing + 1.9) * self.dt
            for j in np.flatnonzero(np.diff(t_all) > limit):
                self._breaks.append(off + j + 1)
        self._buf = np.hstack([self._buf, rows])
        self._seen += rows.shape[1]

    @property
    def backlog(self) -> int:
        """Samples received, not yet inside any window, and before the next gap."""
        end = self._prev["i0"] + self.N if self._prev else self._seg0
        limit = min(self._seen, self._breaks[0]) if self._breaks else self._seen
        return limit - end

    @property
    def started(self) -> bool:
        return self._prev is not None

    def ready(self) -> bool:
        self._skip_gaps()
        if self._prev is None:
            return self.backlog >= self.N
        return self.backlog >= self.slide_min

    def _skip_gaps(self) -> None:
        """No window bridges a gap. When too little is left before the next gap for another
        slide, what the current window taught goes into the arrival cost and estimation
        starts again after the gap, as soon as a whole window has arrived there."""
        while self._breaks and self._seen >= self._breaks[0]:
            b = self._breaks[0]
            if self._prev is not None and self.backlog >= self.slide_min:
                return  # data before the gap still to use
            if self._prev is None and self.backlog >= self.N:
                return  # a whole window fits before the gap
            if self._prev is not None:
                self._absorb_leaving(self._prev, self.K)
                self.prior_mean = self.theta.copy()
                self._prev = None
            self._seg0 = b
            self._breaks.pop(0)

    # ------------------------------------------------------------ one update
    def update(self) -> OnlineEstimate | None:
        if not self.ready():
            return None
        t_wall = time.perf_counter()
        M, K, N, nx, nth = self.M, self.K, self.N, self.plant.nx, len(self.free)
        prev = self._prev
        if prev is None:
            i0, left = self._seg0, K
        else:
            left = min(self.backlog // M, K)  # the backlog stops at the next gap
            i0 = prev["i0"] + left * M
        rows = self._buf[:, i0 - self._base: i0 - self._base + N]
        run = Run(t=rows[0], u=rows[1], x=rows[2], p1=rows[3], p2=rows[4])
        lay = run_layout(run, self.plant, self.cyl, M, 0)
        if self._problem is None:
            self._problem = ShootingProblem(self.sf, K, self._threads, lay.W, lay.H, lay.Y, lay.mask,
                                            self.wts, self.sscale, self.nxt)
        prob = self._problem
        prob.W, prob.H, prob.Y, prob.mask = lay.W, lay.H, lay.Y, lay.mask

        if prev is not None:
            self._absorb_leaving(prev, left)
            self.prior_mean = self.theta.copy()
        elif self.options.prefit and not self._fitted and {"Fc", "Fv", "kp"} & set(self.names):
            start = equation_error_friction(self.cyl, [run])
            for n, v in start.items():
                if n in self.names:
                    self.theta[self.names.index(n)] = v
            self.theta = np.clip(self.theta, self.lower, self.upper)
            self.prior_mean = self.theta.copy()
        drop = i0 - self._base  # keep only what later windows can still need
        if drop > 0:
            self._buf = self._buf[:, drop:]
            self._base = i0

        theta, p = self.theta.copy(), self.p.copy()
        p[self.free] = theta
        # warm start (shift and forward-simulate): the previous nodes and trajectories where
        # the windows overlap; the new intervals run forward from the previous window's end
        keep = K - left
        S = lay.S0.copy()
        if keep > 0:
            X = np.empty((nx, K, M))
            S[:, :keep] = prev["S"][:, left:]
            X[:, :keep] = prev["X"][:, left:]
            # the old last interval ended on a zero-length padding step; it now has a successor
            for k in range(keep - 1, K):
                if k >= keep:
                    S[:, k] = X[:, k - 1, M - 1]
                X[:, k] = np.asarray(self.sf.interval(S[:, k], lay.W[:, k * (M + 1):(k + 1) * (M + 1)], p,
                                                      lay.H[:, k * M:(k + 1) * M]))
        else:
            ev0 = prob.evaluate(S, p, False)
            if ev0 is None:
                raise RuntimeError(f"online estimate: the simulation of the window at t = {run.t[0]:.3f} s "
                                   "is not finite; check the cylinder file against the rig")
            X = ev0[2]
        E, D = prob.residuals(S, X)
        lam, mu, it = 0.0, 0.0, 0
        Nm = None
        n_iter = self.options.first_iterations if prev is None else self.options.max_iterations
        for it in range(1, n_iter + 1):
            # Jacobians are taken fresh every iteration: reusing those of the overlap (taken
            # before the last step) fails at reversals, where stick and slip switch
            ev = prob.evaluate(S, p, True)
            if ev is None:
                raise RuntimeError(f"online estimate: the simulation of the window at t = {run.t[0]:.3f} s "
                                   "is not finite; check the cylinder file against the rig")
            E, D, X = ev[0], ev[1], ev[2]
            P, Q, q, Js, Jt, r0 = reduce_nodes(linearize(ev, prob.out_idx, self.wts, lay.mask, M, nx, len(self.wts), nth),
                                          E, D * self.sscale[:, None], self.has_next, nx, nth)
            js, jt, r = Js.reshape(-1, nx), Jt.reshape(-1, nth), r0.reshape(-1)
            dev = theta - self.prior_mean
            Nm = np.block([[js.T @ js, js.T @ jt], [jt.T @ js, jt.T @ jt + self.info]])
            g = np.concatenate([js.T @ r, jt.T @ r + self.info @ dev])
            lin_J = (Js, Jt)
            cost = 0.5 * float(np.sum(E * E)) + 0.5 * float(dev @ self.info @ dev)
            viol = float(np.sum(np.abs(D)))
            accepted = converged = False
            # a bounded line search: an update that cannot improve keeps the previous
            # estimate and tries again with the next data, instead of stalling the stream
            for lam in (lam, max(1e-2, 10 * lam)):
                step = solve_bounded(Nm, g, theta, self.lower, self.upper, nx, lam)
                if step is None:
                    continue
                ds0, dth = step[:nx], step[nx:]
                dS = (P @ ds0 + Q @ dth + q).T
                # the decrease the linear model promises, closing the defects included
                r_lin = r + js @ ds0 + jt @ dth
                d_lin = dev + dth
                pred = cost - 0.5 * float(r_lin @ r_lin) - 0.5 * float(d_lin @ self.info @ d_lin)
                if pred < max(0.5 * nth, 1e-3 * cost) and viol < 1e-2 * K:
                    converged = True  # less to gain than a fraction of a standard deviation
                    break
                if viol > 0:
                    mu = max(mu, 2 * abs(pred) / viol + 1.0)
                found = line_search(prob.evaluate, lambda ev_, th: self._merit(ev_, th, mu), S, dS, theta, dth, p,
                                    self.free, self.lower, self.upper, cost + mu * viol, -max(pred, 0.0), 1 / 4)
                if found:
                    alpha, S_try, th_try, p_try, ev_try = found
                    accepted = True
                    break
            if converged or not accepted:
                break
            lam = lam / 10 if lam > 1e-6 else 0.0
            S, theta, p = S_try, th_try, p_try
            E, D, X = ev_try[0], ev_try[1], ev_try[2]
            if it >= self.options.iterations and alpha == 1.0 and (pred < 1e-3 * cost or pred < 1.0):
                break  # the warm start was good: the real-time iteration was enough
        self.theta, self.p = theta, p
        self._fitted = True
        nres = E.size
        sigma2 = float(np.sum(E * E)) / max(1.0, nres - nx - nth)
        std = np.full(nth, np.nan)
        if Nm is not None:
            try:
                cov = scaled_inverse(Nm)
                std = np.sqrt(np.maximum(np.diag(cov)[nx:], 0.0) * max(sigma2, 1e-12))
            except np.linalg.LinAlgError:
                pass
        self._prev = {"i0": i0, "S": S, "X": X, "J": lin_J if Nm is not None else None}
        w = self.wts
        rmse = {f"rmse_{n}": float(np.sqrt(np.sum(E[..., j] ** 2) / lay.mask.sum())) / w[j]
                for j, n in enumerate(self.plant.output_names)}
        return OnlineEstimate(
            t=float(run.t[-1]), values=dict(zip(self.names, theta.tolist())), std=dict(zip(self.names, std.tolist())),
            units=self.units, window=(float(run.t[0]), float(run.t[-1])), samples_seen=i0 + N,
            sigma=math.sqrt(sigma2), rmse=rmse, iterations=it, wall_s=time.perf_counter() - t_wall,
            state=X[:, K - 1, M - 2].copy(), params=p.copy())

    def _merit(self, ev, theta: np.ndarray, mu: float) -> float:
        """Data cost, arrival cost and the l1 penalty on the continuity defects."""
        d = theta - self.prior_mean
        return 0.5 * float(np.sum(ev[0] ** 2)) + 0.5 * float(d @ self.info @ d) + mu * float(np.sum(np.abs(ev[1])))

    def _absorb_leaving(self, prev: dict, left: int) -> None:
        """Move the information of the intervals leaving the window into the arrival cost."""
        nx = self.plant.nx
        decay = math.exp(-left * self.M * self.dt / self.options.memory_s) if math.isfinite(self.options.memory_s) else 1.0
        self.info = self.info * decay
        if prev["J"] is None or left <= 0:
            return
        js = prev["J"][0][:left].reshape(-1, nx)
        jt = prev["J"][1][:left].reshape(-1, len(self.free))
        Nss, Nst, Ntt = js.T @ js, js.T @ jt, jt.T @ jt
        # Schur complement: the leaving data's start state is unknown, marginalise it out
        self.info = self.info + Ntt - Nst.T @ np.linalg.pinv(Nss, rcond=1e-12) @ Nst
