"""Multiple-shooting least-squares identification of recorded runs.

The runs are cut into shooting intervals; each interval starts from a free node state
and is integrated by the compiled plant with the recorded input. Unknowns are all
node states and the chosen parameters; the continuity defects between intervals are
equality constraints. Each Gauss-Newton step linearises residuals and defects and
eliminates the node-state increments by the forward recursion

    ds_{k+1} = A_k ds_k + B_k dtheta + d_k        (condensing, Bock's method)

leaving a small dense problem in (first node state of each run, parameters). Steps are
globalised with an l1 merit line search and Levenberg-Marquardt damping; parameter
bounds are kept by an active set. At convergence the defects vanish, so the reduced
Jacobian is that of the simulated run, and its Gauss-Newton covariance scaled by the
residual variance gives the standard deviations.
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from typing import Callable, Mapping, Sequence

import numpy as np

from sim.compiled import NumpyCall, ShootingFunctions, shooting_functions
from sim.cylinder import ESTIMABLE, PARAMETERS, Cylinder
from sim.effects import Effect
from sim.integrator import IntegratorOptions
from sim.plant import Plant, build_plant

from .runs import Run, split_at_gaps

UNITS = {name: spec.unit for name, spec in PARAMETERS.items()}


class IdentificationError(RuntimeError):
    """The identification could not be carried out (the message says why)."""


# a damped step closer than this (relative, in the scaled variables) to one whose line search
# just failed is not searched again
_SAME_STEP = 1e-2


@dataclass(frozen=True)
class IdentifyOptions:
    drive: str = "command"
    estimate: tuple[str, ...] = ("Fc", "Fv", "kp")
    interval_s: float = 0.1  # shooting interval length
    max_iter: int = 40
    time_limit_s: float = math.inf  # stop iterating after this long (status "time_limit")
    # start Fc, Fv, kp from a linear equation-error fit (friction from Newton's law with the
    # measured pressures, seed 000's method) unless a start is given explicitly
    prefit: bool = True
    integrator: IntegratorOptions = IntegratorOptions()
    threads: int = max(1, os.cpu_count() or 1)


@dataclass
class Estimate:
    name: str
    value: float
    std: float
    unit: str
    initial: float
    at_bound: bool = False


@dataclass
class IdentifyResult:
    params: dict[str, Estimate]
    fit: dict[str, float]
    fit_per_run: list[dict[str, float]]
    solver: dict
    cylinder: Cylinder
    effects: tuple[Effect, ...]
    drive: str
    simulated: list[np.ndarray] = field(repr=False, default_factory=list)  # per run: (n_outputs, N)
    output_names: tuple[str, ...] = ()
    correlation: np.ndarray | None = field(repr=False, default=None)
    nodes: np.ndarray | None = field(repr=False, default=None)  # final node states (nx, intervals)

    def to_json(self) -> dict:
        return {
            "params": {n: {"value": e.value, "std": e.std, "unit": e.unit, "initial": e.initial,
                           **({"at_bound": True} if e.at_bound else {})} for n, e in self.params.items()},
            "fit": self.fit,
            "solver": self.solver,
            "drive": self.drive,
            "runs": self.fit_per_run,
            "correlation": {"names": list(self.params),
                            "matrix": None if self.correlation is None else np.round(self.correlation, 4).tolist()},
        }


# ------------------------------------------------------------------ problem layout

@dataclass
class _RunLayout:
    run: Run
    K: int  # intervals
    node0: int  # index of its first node among all nodes
    W: np.ndarray  # (nw, K*(M+1)) inputs at both ends of every sample step
    H: np.ndarray  # (1, K*M) step lengths (0 = padding)
    Y: np.ndarray  # (K, M, ny) measured outputs
    mask: np.ndarray  # (K, M) 1 where a sample exists
    S0: np.ndarray  # (nx, K) initial node states


def _velocity_estimate(t: np.ndarray, x: np.ndarray, half: int = 10) -> np.ndarray:
    """Savitzky-Golay slope over +-half samples, held constant at the ends."""
    if len(x) < 2 * half + 1:
        return np.gradient(x, t)
    v = np.convolve(x, _derivative_kernels(half)[0], mode="same") / np.median(np.diff(t))
    v[:half] = v[half]
    v[-half:] = v[-half - 1]
    return v


def _savgol_kernels(half: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Savitzky-Golay kernels (quadratic, window 2*half+1): smoothing, first and second derivative."""
    j = np.arange(-half, half + 1, dtype=float)
    pinv = np.linalg.pinv(np.vander(j, 3, increasing=True))
    return pinv[0][::-1], pinv[1][::-1], 2.0 * pinv[2][::-1]


def _derivative_kernels(half: int) -> tuple[np.ndarray, np.ndarray]:
    """Savitzky-Golay kernels for the first and second derivative."""
    return _savgol_kernels(half)[1:]


def friction_from_newton(cyl: Cylinder, run: Run, half: int = 15,
                         plant: Plant | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Friction the piston equation implies, with measured pressures (seed 000's method).

    Friction = M (a_without_friction - a): the pressure drive of the plant, evaluated with
    zero friction at the measured pressures, gives the acceleration without friction; a and v
    are Savitzky-Golay derivatives of the position. Returns (index, v, F) for the samples
    away from the ends (index into the run)."""
    if run.n < 4 * half:
        return np.empty(0, int), np.empty(0), np.empty(0)
    plant = plant or build_plant("pressure")
    frictionless = np.array(plant.parameter_vector(cyl.with_values({"Fc": 0.0, "Fv": 0.0, "kp": 0.0})))
    k1, k2 = _derivative_kernels(half)
    dt = run.sample_period
    v = np.convolve(run.x, k1, mode="same")[half:-half] / dt
    a = np.convolve(run.x, k2, mode="same")[half:-half] / dt**2
    idx = np.arange(half, run.n - half)
    xdot = np.asarray(plant.rhs.map(len(v))(np.vstack([run.x[idx], v]), np.vstack([run.p1[idx], run.p2[idx]]),
                                            frictionless))
    return idx, v, cyl.mechanics.moving_mass * (xdot[1] - a)


def equation_error_friction(cyl: Cylinder, runs: Sequence[Run], half: int = 15) -> dict[str, float]:
    """Fc, Fv, kp by linear least squares on the friction Newton's law implies.

    Where the piston slides (|v| well above v_smooth) the nominal friction is linear in
    (Fc, kp, Fv). Biased by filtering, but a start from which Gauss-Newton needs few
    iterations. Empty if the runs barely move."""
    rows, rhs = [], []
    for r in runs:
        idx, v, F = friction_from_newton(cyl, r, half)
        if len(idx) == 0:
            continue
        sliding = np.abs(v) > max(20 * cyl.friction.v_smooth, 0.005)
        sgn = np.sign(v[sliding])
        dp = np.abs(r.p1[idx] - r.p2[idx])[sliding]
        rows.append(np.column_stack([sgn, sgn * dp, v[sliding]]))
        rhs.append(F[sliding])
    if not rows or sum(len(x) for x in rhs) < 50:
        return {}
    A, b = np.vstack(rows), np.concatenate(rhs)
    scale = np.maximum(np.abs(A).max(axis=0), 1e-300)
    sol = np.linalg.lstsq(A / scale, b, rcond=None)[0] / scale
    if not np.all(np.isfinite(sol)):
        return {}
    return {"Fc": max(float(sol[0]), 0.0), "kp": max(float(sol[1]), 0.0), "Fv": max(float(sol[2]), 0.0)}


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


def _layout(run: Run, plant: Plant, cyl: Cylinder, M: int, node0: int) -> _RunLayout:
    N = run.n
    K = math.ceil(N / M)
    pad = K * M + 1 - N
    if plant.drive == "command":
        w = run.u[None, :]
    else:
        w = np.vstack([run.p1, run.p2])
    w_pad = np.hstack([w, np.repeat(w[:, -1:], pad, axis=1)])  # (nw, K*M+1)
    idx = (np.arange(K)[:, None] * M + np.arange(M + 1)[None, :]).ravel()
    W = w_pad[:, idx]
    dt = np.diff(run.t)
    H = np.concatenate([dt, np.zeros(K * M - len(dt))])[None, :]
    meas = {"x": run.x, "p1": run.p1, "p2": run.p2}
    ys = np.stack([meas[n] for n in plant.output_names], axis=-1)  # (N, ny)
    ys = np.vstack([ys, np.zeros((K * M - N, ys.shape[1]))])
    mask = (np.arange(K * M) < N).astype(float).reshape(K, M)
    v = _velocity_estimate(run.t, run.x)
    nodes = np.arange(K) * M
    S0 = np.array([plant.initial_state(cyl, run.x[i], run.p1[i], run.p2[i], v[i]) for i in nodes]).T
    return _RunLayout(run, K, node0, W, H, ys.reshape(K, M, -1), mask, S0)


# ------------------------------------------------------------------ the solver

class ShootingProblem:
    """Weighted output residuals and scaled continuity defects of K shooting intervals."""

    def __init__(self, sf: ShootingFunctions, K: int, threads: int, W, H, Y, mask, wts, sscale, nxt):
        plant = sf.plant
        self.f_sens = NumpyCall(sf.sens.map(K, "thread", threads) if threads > 1 else sf.sens.map(K))
        self.f_sim = NumpyCall(sf.interval.map(K, "thread", threads) if threads > 1 else sf.interval.map(K))
        self.W, self.H, self.Y, self.mask, self.wts, self.sscale, self.nxt = W, H, Y, mask, wts, sscale, nxt
        self.K, self.M = K, sf.interval_len
        self.nx, self.nth = plant.nx, len(sf.free)
        self.out_idx = [plant.state_names.index(n) for n in plant.output_names]

    def evaluate(self, S: np.ndarray, p: np.ndarray, with_sens: bool):
        """(E, D, X, Sens) or None when the simulation is not finite."""
        nx, K, M = self.nx, self.K, self.M
        if with_sens:
            Xr, Sr = self.f_sens(S, self.W, p, self.H)
            X = Xr.reshape(nx, K, M)
            Sens = Sr.reshape(nx, K, M, nx + self.nth)
        else:
            X = self.f_sim(S, self.W, p, self.H)[0].reshape(nx, K, M)
            Sens = None
        if not np.all(np.isfinite(X)):
            return None
        E, D = self.residuals(S, X)
        return E, D, X, Sens

    def residuals(self, S: np.ndarray, X: np.ndarray):
        """Weighted output residuals E (K, M, ny) and scaled defects D of trajectories X."""
        M = self.M
        # predicted outputs at the interval's own samples: node state, then the first M-1 steps
        oi = self.out_idx
        Ypred = np.concatenate([S[oi, :, None], X[oi][:, :, : M - 1]], axis=2).transpose(1, 2, 0)
        E = (Ypred - self.Y) * self.wts * self.mask[:, :, None]  # (K, M, ny)
        nxt = self.nxt
        D = (X[:, nxt, M - 1] - S[:, nxt + 1]) / self.sscale[:, None]  # scaled defects (nx, n_links)
        return E, D


def identify(cyl: Cylinder, runs: Sequence[Run], options: IdentifyOptions = IdentifyOptions(),
             effects: Sequence[Effect] = (), initial: Mapping[str, float] | None = None,
             nodes: np.ndarray | None = None,
             progress: Callable[[str], None] | None = None) -> IdentifyResult:
    t_start = time.perf_counter()
    if not runs:
        raise IdentificationError("no runs to identify from.")
    n_runs = len(runs)
    pieces = [piece for r in runs for piece in split_at_gaps(r)]
    if len(pieces) > n_runs:
        runs = [q for q in pieces if q.n >= 3]
        if not runs:
            raise IdentificationError("the runs have no gap-free stretch of 3 samples or more.")
        if progress:
            progress(f"  {len(pieces) - n_runs} gap(s) of lost samples: {len(runs)} gap-free pieces "
                     "identified jointly (no simulation bridges a gap)")
    plant = build_plant(options.drive, effects)
    estimate = tuple(options.estimate)
    free = free_parameters(plant, estimate)
    p = np.array(plant.parameter_vector(cyl), dtype=float)
    for name, val in (initial or {}).items():
        p[plant.param_names.index(name)] = val
    if options.prefit and not initial and {"Fc", "Fv", "kp"} & set(estimate):
        start = equation_error_friction(cyl, runs)
        if start:
            for name, val in start.items():
                if name in estimate:
                    p[plant.param_names.index(name)] = val
            if progress:
                progress("  start from the equation-error fit: " + ", ".join(f"{n}={v:.5g}" for n, v in start.items()))
    lower, upper = _bounds(plant, estimate)
    theta = np.clip(p[free], lower, upper)
    p[free] = theta
    theta_init = theta.copy()

    dt0 = runs[0].sample_period
    M = max(5, int(round(options.interval_s / dt0)))
    sf = shooting_functions(plant, M, free, options.integrator, progress=progress, with_sens=True)
    nx, ny, nth = plant.nx, len(plant.output_names), len(free)
    out_idx = [plant.state_names.index(n) for n in plant.output_names]

    layouts: list[_RunLayout] = []
    node0 = 0
    for r in runs:
        if r.n < 3:
            raise IdentificationError(f"{r.source}: a run needs at least 3 samples.")
        lay = _layout(r, plant, cyl, M, node0)
        layouts.append(lay)
        node0 += lay.K
    Ktot = node0
    W = np.hstack([l.W for l in layouts])
    H = np.hstack([l.H for l in layouts])
    Y = np.concatenate([l.Y for l in layouts])  # (Ktot, M, ny)
    mask = np.concatenate([l.mask for l in layouts])  # (Ktot, M)
    S = np.hstack([l.S0 for l in layouts])  # (nx, Ktot)
    if nodes is not None:
        S = _warm_nodes(plant, cyl, S, np.asarray(nodes, float))
    wts, sscale = residual_scales(plant, cyl, dt0)
    # node k is followed by node k+1 within the same run
    has_next = np.ones(Ktot, bool)
    for l in layouts:
        has_next[l.node0 + l.K - 1] = False
    nxt = np.flatnonzero(has_next)

    threads = max(1, min(options.threads, Ktot))
    problem = ShootingProblem(sf, Ktot, threads, W, H, Y, mask, wts, sscale, nxt)
    evaluate = problem.evaluate

    def out_of_time() -> bool:
        return time.perf_counter() - t_start > options.time_limit_s

    def merit(E, D, mu):
        return 0.5 * float(np.sum(E * E)) + mu * float(np.sum(np.abs(D)))

    ev = evaluate(S, p, True)
    if ev is None:
        raise IdentificationError("the simulation from the initial guess is not finite; check the cylinder file "
                                  "(units, dead volumes, supply pressure) against the run.")
    lam, mu = 0.0, 0.0
    linearized_at = None
    status = "max_iterations"
    history = []
    it = 0
    for it in range(1, options.max_iter + 1):
        if out_of_time():
            status = "time_limit"
            break
        E, D, X, Sens = ev
        lin_ = _linearize(ev, out_idx, wts, mask, M, nx, ny, nth)
        G, Hth = lin_[0], lin_[1]
        Nmat, g, P, Q, q, scores = _condense(lin_, E, D * sscale[:, None], layouts, has_next, nx, nth)
        linearized_at = (ev, Nmat, scores)
        R = len(layouts)
        cost = 0.5 * float(np.sum(E * E))
        viol = float(np.sum(np.abs(D)))

        accepted = converged_here = False
        predicted = math.inf
        failed_step = None
        scale = np.sqrt(np.maximum(np.diag(Nmat), 1e-300))
        for _attempt in range(8):
            if _attempt and out_of_time():
                break  # a struggling line search is where the time goes
            step = _solve_bounded(Nmat, g, theta, lower, upper, R * nx, lam)
            if step is None:
                lam = max(1e-6, lam * 10)
                continue
            if failed_step is not None and (np.linalg.norm((step - failed_step) * scale)
                                            <= _SAME_STEP * np.linalg.norm(failed_step * scale)):
                # damping too weak to change the step: searching the step that just failed again
                # is where a struggling fit spent its time
                lam = max(1e-6, lam * 10)
                continue
            ds0, dth = step[: R * nx].reshape(R, nx), step[R * nx:]
            dS = np.empty((Ktot, nx))
            for ri, l in enumerate(layouts):
                sl = slice(l.node0, l.node0 + l.K)
                dS[sl] = P[sl] @ ds0[ri] + Q[sl] @ dth + q[sl]
            lin = np.einsum("kmoi,ki->kmo", G, dS) + np.einsum("kmoi,i->kmo", Hth, dth)
            gdir = float(np.sum(E * lin))
            quad = float(np.sum(lin * lin))
            predicted = -(gdir + 0.5 * quad)  # decrease of the cost the Gauss-Newton model expects
            if predicted < max(1e-2, 1e-10 * cost) and viol < 1e-2 * max(1, Ktot):
                converged_here = True  # nothing left to gain, statistically or numerically
                break
            if viol > 0:
                mu = max(mu, (gdir + 0.5 * quad) / (0.5 * viol) + 1.0)
            found = line_search(evaluate, lambda ev_, _th: merit(ev_[0], ev_[1], mu), S, dS.T, theta, dth, p,
                                free, lower, upper, cost + mu * viol, min(gdir - mu * viol, 0.0), 1.0 / 64)
            if found:
                alpha, S_try, th_try, p_try, ev_try = found
                accepted = True
                break
            failed_step = step
            lam = max(1e-6, lam * 10)
        if converged_here:
            status = "converged"
            break
        if not accepted:
            # at the numerical noise floor of the cost nothing can be gained any more
            noise_floor = step is not None and predicted < 1.0 and viol < 1e-2 * max(1, Ktot)
            status = "converged" if noise_floor else "time_limit" if out_of_time() else "line_search_failed"
            break
        lam = lam / 10 if lam > 1e-6 else 0.0
        S, theta, p = S_try, th_try, p_try
        std = _std(Nmat, R * nx, cost, mask.sum() * ny)
        rel_step = np.max(np.abs(alpha * dth) / np.maximum(std, 1e-300)) if nth else 0.0
        history.append({"iteration": it, "cost": cost, "defect": viol, "alpha": alpha, "lm": lam,
                        "theta": theta.tolist()})
        if progress:
            progress(f"  iteration {it:2d}: cost {cost:.6g}  defects {viol:.3g}  step {alpha:.3g}  "
                     + "  ".join(f"{n}={v:.5g}" for n, v in zip(estimate, theta)))
        ev = evaluate(S, p, True)
        if ev is None:
            raise IdentificationError(f"the simulation stopped being finite at iteration {it} "
                                      f"({', '.join(f'{n}={v:.4g}' for n, v in zip(estimate, theta))}); "
                                      "check the cylinder file against the run.")
        new_viol = float(np.sum(np.abs(ev[1])))
        if rel_step < 1e-3 and new_viol < 1e-2 * max(1, Ktot) and alpha == 1.0:
            status = "converged"
            break
        if abs(cost - 0.5 * float(np.sum(ev[0] ** 2))) < 1e-12 * cost and new_viol < 1e-2 * max(1, Ktot):
            status = "converged"
            break

    # final statistics at the solution (evaluated with sensitivities in ev)
    E, D, X, Sens = ev
    cost = 0.5 * float(np.sum(E * E))
    nres = float(mask.sum() * ny)
    if linearized_at is not None and linearized_at[0] is ev:  # converged where the loop linearised
        Nfinal, scores = linearized_at[1], linearized_at[2]
    else:
        Nfinal, _, _, _, _, scores = _condense(_linearize(ev, out_idx, wts, mask, M, nx, ny, nth), E,
                                               D * sscale[:, None], layouts, has_next, nx, nth)
    cov_gn = _covariance(Nfinal, len(layouts) * nx, cost, nres)
    cov_robust = _cluster_covariance(Nfinal, scores, layouts, len(layouts) * nx,
                                     max(1, int(round(1.0 / (M * dt0)))))
    # residuals of real rigs (and of the pressure drive, whose inputs are noisy) are not
    # white: report the larger of the Gauss-Newton and the cluster-robust variances
    cov = cov_gn
    if cov_gn is not None and cov_robust is not None:
        scale = np.sqrt(np.maximum(np.diag(cov_robust), 0) / np.maximum(np.diag(cov_gn), 1e-300))
        scale = np.maximum(scale, 1.0)
        cov = cov_gn * np.outer(scale, scale)
    at_bound = at_bounds(theta, lower, upper)
    std = np.sqrt(np.maximum(np.diag(cov), 0.0)) if cov is not None else np.full(nth, np.nan)
    corr = None
    if cov is not None and nth:
        d = np.sqrt(np.maximum(np.diag(cov), 1e-300))
        corr = cov / np.outer(d, d)
    params = {n: Estimate(n, float(v), float(s), _unit(plant, n), float(v0), bool(b))
              for n, v, s, v0, b in zip(estimate, theta, std, theta_init, at_bound)}
    # the fit: simulate every run from its identified initial state in one piece
    sims = [_simulate_run(sf, S[:, l.node0], p, l, M) for l in layouts]
    fit_runs = [_fit_metrics(l.run, sim, plant.output_names) for l, sim in zip(layouts, sims)]
    fit = _pooled_fit([l.run for l in layouts], sims, plant.output_names)
    values = {n: params[n].value for n in estimate if n in PARAMETERS}
    eff_values = {}
    for n in estimate:
        if "." in n:
            ename, pname = n.split(".", 1)
            eff_values.setdefault(ename, {})[pname] = params[n].value
    new_effects = tuple(_replace_effect(e, eff_values.get(e.name, {})) for e in effects)
    solver = {"status": status, "iterations": it, "wall_s": round(time.perf_counter() - t_start, 4),
              "cost": cost, "residual_sigma": math.sqrt(2 * cost / max(1.0, nres - len(layouts) * nx - nth)),
              "n_samples": int(sum(l.run.n for l in layouts)), "n_intervals": Ktot, "interval_samples": M,
              "compile": {"cache_hit": sf.stats.cache_hit, "build_s": round(sf.stats.build_s + sf.stats.compile_s, 3)},
              "history": history}
    return IdentifyResult(params=params, fit=fit, fit_per_run=fit_runs, solver=solver,
                          cylinder=cyl.with_values(values), effects=new_effects, drive=plant.drive,
                          simulated=sims, output_names=plant.output_names, correlation=corr, nodes=S)


def _warm_nodes(plant: Plant, cyl: Cylinder, S: np.ndarray, warm: np.ndarray) -> np.ndarray:
    """Node states of an earlier solution on the same runs and intervals (a warm start, e.g.
    another model's): its drive states are taken, the states this plant adds start from
    their initial values at those nodes."""
    nb = 4 if plant.drive == "command" else 2
    if warm.ndim != 2 or warm.shape[1] != S.shape[1] or warm.shape[0] < nb:
        raise ValueError(f"warm-start nodes of shape {warm.shape} do not fit {S.shape[1]} intervals")
    out = S.copy()
    out[:nb] = warm[:nb]
    if plant.nx > nb:
        names = plant.state_names
        ix, iv = names.index("x"), names.index("v")
        ip1 = names.index("p1") if "p1" in names else None
        for k in range(S.shape[1]):
            p1 = out[ip1, k] if ip1 is not None else 0.0
            p2 = out[ip1 + 1, k] if ip1 is not None else 0.0
            out[nb:, k] = plant.initial_state(cyl, out[ix, k], p1, p2, out[iv, k])[nb:]
    return out


def _replace_effect(e: Effect, values: Mapping[str, float]) -> Effect:
    from dataclasses import replace
    return replace(e, **values) if values else e


def _unit(plant: Plant, name: str) -> str:
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


def _bounds(plant: Plant, names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
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
                min_alpha: float):
    """Backtracking from the full step on an l1 merit (Armijo, or a tie at the numerical noise
    floor): (alpha, S, theta, p, evaluation) of the first accepted trial, or None."""
    alpha = 1.0
    while alpha >= min_alpha:
        th = np.clip(theta + alpha * dth, lower, upper)
        p_try = p.copy()
        p_try[free] = th
        S_try = S + alpha * dS
        ev = evaluate(S_try, p_try, False)
        if ev is not None:
            m1 = merit(ev, th)
            if m1 <= m0 + 1e-4 * alpha * slope or abs(m1 - m0) <= 1e-12 * max(m0, 1.0):
                return alpha, S_try, th, p_try, ev
        alpha *= 0.5
    return None


def scaled_inverse(N: np.ndarray) -> np.ndarray:
    """N^-1 computed on the unit-diagonal scaling of N (parameters differ by 10 decades)."""
    scale = np.sqrt(np.maximum(np.diag(N), 1e-300))
    return np.linalg.inv(N / np.outer(scale, scale)) / np.outer(scale, scale)


def _solve_bounded(N: np.ndarray, g: np.ndarray, theta, lower, upper, n_state: int, lam: float):
    """min 0.5 d'Nd + g'd with theta + d_theta kept in bounds (active set on the parameters)."""
    n = len(g)
    fixed = np.zeros(n, bool)
    d = np.zeros(n)
    for _ in range(len(theta) + 1):
        free = ~fixed
        scale = np.sqrt(np.maximum(np.diag(N), 1e-300))
        Ns = N / np.outer(scale, scale)
        Ns = Ns + lam * np.diag(np.diag(Ns))
        rhs = -(g + N[:, fixed] @ d[fixed]) / scale
        try:
            sol = np.linalg.solve(Ns[np.ix_(free, free)], rhs[free])
        except np.linalg.LinAlgError:
            sol = np.linalg.lstsq(Ns[np.ix_(free, free)], rhs[free], rcond=1e-12)[0]
        d[free] = sol / scale[free]
        th_new = theta + d[n_state:]
        viol = (th_new < lower) | (th_new > upper)
        if not viol.any():
            return d if np.all(np.isfinite(d)) else None
        idx = np.flatnonzero(viol)
        for i in idx:
            d[n_state + i] = (lower[i] if th_new[i] < lower[i] else upper[i]) - theta[i]
            fixed[n_state + i] = True
    return d


def _linearize(ev, out_idx, wts, mask, M, nx, ny, nth):
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
    wm = (wts[None, None, :] * mask[:, :, None])[..., None]
    G *= wm
    Hth *= wm
    A = Sens[:, :, M - 1, :nx].transpose(1, 0, 2)  # (K, nx, nx)
    B = Sens[:, :, M - 1, nx:].transpose(1, 0, 2)  # (K, nx, nth)
    return G, Hth, A, B


def _reduce(lin, E, Draw, has_next, nx, nth):
    """Eliminate the node increments: ds_k = P_k ds0 + Q_k dtheta + q_k within each run.

    Returns P, Q, q and the reduced residual Jacobians Js = dr/ds0, Jt = dr/dtheta and the
    linearised residual r0 (all per interval)."""
    G, Hth, A, B = lin
    Ktot = G.shape[0]
    P = np.empty((Ktot, nx, nx))
    Q = np.empty((Ktot, nx, nth))
    q = np.empty((Ktot, nx))
    eye = np.eye(nx)
    link = 0
    for k in range(Ktot):
        if k == 0 or not has_next[k - 1]:
            P[k], Q[k], q[k] = eye, 0.0, 0.0
        else:
            j = k - 1
            P[k] = A[j] @ P[j]
            Q[k] = A[j] @ Q[j] + B[j]
            q[k] = A[j] @ q[j] + Draw[:, link]
            link += 1
    Js = np.einsum("kmoi,kij->kmoj", G, P)
    Jt = np.einsum("kmoi,kij->kmoj", G, Q) + Hth
    r0 = E + np.einsum("kmoi,ki->kmo", G, q)
    return P, Q, q, Js, Jt, r0


def _condense(lin, E, Draw, layouts, has_next, nx, nth):
    """The reduced normal equations (N, g) in (ds0 per run, dtheta), with P, Q, q of `_reduce`
    and the per-interval gradient contributions."""
    P, Q, q, Js, Jt, r0 = _reduce(lin, E, Draw, has_next, nx, nth)
    Ktot, R = Js.shape[0], len(layouts)
    nred = R * nx + nth
    N = np.zeros((nred, nred))
    g = np.zeros(nred)
    # per-interval gradient contributions ("scores") for the cluster-robust covariance
    scores = np.zeros((Ktot, nred))
    for ri, l in enumerate(layouts):
        sl = slice(l.node0, l.node0 + l.K)
        scores[sl, ri * nx:(ri + 1) * nx] = np.einsum("kmoi,kmo->ki", Js[sl], r0[sl])
    scores[:, R * nx:] = np.einsum("kmoi,kmo->ki", Jt, r0)
    for ri, l in enumerate(layouts):
        sl = slice(l.node0, l.node0 + l.K)
        js = Js[sl].reshape(-1, nx)
        jt = Jt[sl].reshape(js.shape[0], nth)  # explicit rows: nth may be 0 (states only)
        rr = r0[sl].reshape(-1)
        a = slice(ri * nx, (ri + 1) * nx)
        N[a, a] = js.T @ js
        N[a, R * nx:] = js.T @ jt
        N[R * nx:, a] = N[a, R * nx:].T
        N[R * nx:, R * nx:] += jt.T @ jt
        g[a] = js.T @ rr
        g[R * nx:] += jt.T @ rr
    return N, g, P, Q, q, scores


def _covariance(N: np.ndarray, n_state: int, cost: float, nres: float) -> np.ndarray | None:
    sigma2 = 2 * cost / max(1.0, nres - N.shape[0])
    try:
        inv = scaled_inverse(N)
    except np.linalg.LinAlgError:
        return None
    return (sigma2 * inv)[n_state:, n_state:]


def _cluster_covariance(N: np.ndarray, scores: np.ndarray, layouts, n_state: int, block: int) -> np.ndarray | None:
    """Sandwich covariance N^-1 (sum_b s_b s_b') N^-1 with clusters of `block` consecutive
    intervals (about one second): honest when residuals are correlated in time."""
    sums = []
    for l in layouts:
        for k0 in range(l.node0, l.node0 + l.K, block):
            sums.append(scores[k0:min(k0 + block, l.node0 + l.K)].sum(axis=0))
    S = np.array(sums)
    nb = len(S)
    if nb < 5:
        return None
    meat = S.T @ S * nb / (nb - 1)
    try:
        inv = scaled_inverse(N)
    except np.linalg.LinAlgError:
        return None
    return (inv @ meat @ inv)[n_state:, n_state:]


def _std(N, n_state, cost, nres) -> np.ndarray:
    cov = _covariance(N, n_state, cost, nres)
    if cov is None:
        return np.full(N.shape[0] - n_state, np.inf)
    return np.sqrt(np.maximum(np.diag(cov), 0.0))


def _simulate_run(sf: ShootingFunctions, s0: np.ndarray, p: np.ndarray, l: _RunLayout, M: int) -> np.ndarray:
    """Single-shooting simulation of a whole run from its first node state: (n_outputs, N)."""
    plant = sf.plant
    out_idx = [plant.state_names.index(n) for n in plant.output_names]
    nw = l.W.shape[0]
    # the layout holds M+1 inputs per interval (both ends of each step): back to one per sample
    w = np.hstack([l.W.reshape(nw, l.K, M + 1)[:, :, :M].reshape(nw, l.K * M), l.W[:, -1:]])
    return sf.simulate(s0, w, p, l.H[0])[out_idx, : l.run.n]


def _metrics(meas: np.ndarray, sim: np.ndarray) -> tuple[float, float]:
    err = sim - meas
    rmse = float(np.sqrt(np.mean(err * err)))
    sst = float(np.sum((meas - meas.mean()) ** 2))
    r2 = 1.0 - float(np.sum(err * err)) / sst if sst > 0 else float("nan")
    return rmse, r2


def _fit_metrics(run: Run, sim: np.ndarray, outputs: Sequence[str]) -> dict[str, float]:
    meas = {"x": run.x, "p1": run.p1, "p2": run.p2}
    out: dict[str, float] = {"source": str(run.source) if run.source else None}
    for i, n in enumerate(outputs):
        rmse, r2 = _metrics(meas[n], sim[i])
        out[f"rmse_{n}"], out[f"r2_{n}"] = rmse, r2
    return out


def _pooled_fit(runs: Sequence[Run], sims: Sequence[np.ndarray], outputs: Sequence[str]) -> dict[str, float]:
    meas_all = {n: np.concatenate([getattr(r, n) for r in runs]) for n in outputs}
    fit = {}
    for i, n in enumerate(outputs):
        sim = np.concatenate([s[i] for s in sims])
        fit[f"rmse_{n}"], fit[f"r2_{n}"] = _metrics(meas_all[n], sim)
    return fit
