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

import functools
import math
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

from sim.compiled import ShootingFunctions, shooting_functions
from sim.cylinder import PARAMETERS, Cylinder
from sim.extension import Effect
from sim.integrator import IntegratorOptions
from sim.plant import Plant, plant_for

from ..files import Run, split_at_gaps
from ..progress import Step
from .determined import not_determined as undetermined_among
from .discretisation import corrected, discretisation
from .drives import check_drive
from .gauss_newton import Damping, Exit, Prediction, StepOutcome, damped_step
from .newton import equation_error_friction
from .preflight import check_determinable
from .shooting import (Clusters, IdentificationError, NormalEquations, PriorRow, ReducedNormal, RunLayout,
                       ShootingProblem, at_bounds, concatenated_layouts, correlation, drives_with_measured_inputs,
                       fit_metrics, free_parameters, interval_residual_sigma, line_search, parameter_bounds,
                       parameter_unit, pooled_fit, prior_matrix, reported_covariance, residual_scales, run_layout,
                       simulate_layout, standard_deviations, warm_nodes, with_effect_values)


# a model whose residual is this many times the sensor noise does not explain the run: its
# parameters describe a misfit, not the cylinder
MISMATCH = 3.0

# short steps in a row after which the line search turns non-monotone, and how many past
# iterations it then looks back on
NONMONOTONE = 3

# residual sigma (x noise) up to which a fit whose parameters no longer move has converged
# although its cost still creeps down (node states polished around gaps and end stops); above
# it, a fit that ended is restarted once (IdentifyOptions.restart_misfit)
SETTLED_SIGMA = 1.5
STATES_SETTLED_GAIN = 1e-3  # states_settled


def parameters_steady(history: list[dict], theta: np.ndarray, std: np.ndarray) -> bool:
    """Whether the last 2 NONMONOTONE iterations (and `theta`, where they ended) moved no
    parameter by a quarter of its standard deviation, every parameter determined (std finite)."""
    ok = np.isfinite(std) & (std > 0)
    if len(history) < 2 * NONMONOTONE or not len(theta) or not ok.all():
        return False
    recent = np.array([h["theta"] for h in history[-2 * NONMONOTONE:]] + [np.asarray(theta).tolist()])
    return bool(np.all(np.ptp(recent, axis=0) <= 0.25 * std))


def parameters_settled(history: list[dict], theta: np.ndarray, std: np.ndarray, cost: float, n_res: float,
                       at_noise: Callable[[], bool] | None = None) -> bool:
    """Whether more iterations would only polish node states: the last 2 NONMONOTONE iterations
    moved no parameter by a quarter of its standard deviation (every parameter determined), and
    either the fit is at the sensor noise (residual sigma <= SETTLED_SIGMA, or `at_noise()`: a
    test that knows the drive's noise floor, asked only once the parameters are steady as it
    costs simulations) or the cost stopped falling (those iterations gained less than one unit
    of chi-square at the present residual level). A misfit's standard deviations are inflated
    with its residual, so without the second test a fit still descending far above the noise
    would look settled."""
    if n_res <= 0 or not parameters_steady(history, theta, std):
        return False
    gained = history[-2 * NONMONOTONE]["cost"] - min(cost, history[-1]["cost"])
    return bool(2 * cost <= SETTLED_SIGMA ** 2 * n_res or gained <= cost / n_res
                or (at_noise is not None and at_noise()))


def states_settled(history: list[dict]) -> bool:
    """Whether a fit of initial states alone (a validation segment) has stopped gaining: the last
    2 NONMONOTONE iterations lowered the cost by less than STATES_SETTLED_GAIN of it. Only the
    simulation from the first node counts there, so defects the steps still trade against the
    residual do not matter; a model that misses a segment by far creeps so to the iteration cap
    (a heat-exchange candidate's validation on a leakage case: 50 s, 8 s so, its score within 0.1 %)."""
    if len(history) < 2 * NONMONOTONE:
        return False
    now = history[-1]["cost"]
    return history[-2 * NONMONOTONE]["cost"] - now <= STATES_SETTLED_GAIN * now


def start_settled(history: list[dict], theta: np.ndarray, std: np.ndarray) -> bool:
    """Whether a fit that only starts another (IdentifyOptions.start_only) has done its part:
    the last 2 NONMONOTONE iterations moved no parameter by a quarter of the std it reports and
    gained less than STATES_SETTLED_GAIN of the cost. What it would still do is close defects
    where the node states all but jump (stick-slip, an end stop's contact): a calibration's
    force balance crept so for 38 iterations (and 22 more once restarted) with its parameters
    within 0.3 std of where they were after 12; the fit it starts settles those states itself."""
    return states_settled(history) and parameters_steady(history, theta, std)


@dataclass(frozen=True)
class IdentifyOptions:
    drive: str = "command"
    estimate: tuple[str, ...] = ("Fc", "Fv", "kp")
    interval_s: float = 0.1  # shooting interval length
    max_iter: int = 40
    time_limit_s: float = math.inf  # stop iterating after this long (status "time_limit")
    # stop (status "above_reference") once `give_up_after` iterations in a row stayed above
    # this cost: a candidate model that does not even beat the model it extends (a diagnosis'
    # nominal fit); deterministic, unlike a wall-clock limit
    give_up_above: float = math.inf
    give_up_after: int = 6
    # start Fc, Fv, kp from a linear equation-error fit (friction from Newton's law with the
    # measured pressures: Trentini et al.'s Karnopp/least-squares fit, seed 000) unless a start is given explicitly
    prefit: bool = True
    integrator: IntegratorOptions = IntegratorOptions()
    threads: int = max(1, os.cpu_count() or 1)
    # tell the residual in units of what the inputs' noise leaves (drives with measured inputs;
    # a few extra simulations): see input_noise_floor
    noise_floor: bool = True
    # a fit that ends above the noise (residual sigma > SETTLED_SIGMA) is started once more from
    # where its parameters ended with node states afresh from the data, and the lower cost kept:
    # node states stuck in a wrong basin (a stick-slip branch, a leak's slow pressure) leave a
    # misfit that the right parameters alone would not
    restart_misfit: bool = True
    # the fit only starts another (a calibration's staged fits): it ends once its parameters
    # have settled (start_settled), its defects closed or not
    start_only: bool = False
    # from this much data on (s; inf: never), the estimates are moved by the fit's discretisation
    # error (their shift towards a much finer integration) and the std own what that leaves
    # uncertain (identify.discretisation); below, it was within the statistical std (0.01-0.9 of it)
    discretisation_min_s: float = 30.0


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

    @property
    def explains_run(self) -> bool:
        """Whether the model reproduces the runs to within a few times the sensor noise."""
        return self.solver["residual_sigma"] <= MISMATCH

    @property
    def not_determined(self) -> list[str]:
        """The estimates the data do not determine (identify.not_determined): no estimates."""
        p = self.params
        return undetermined_among({n: e.value for n, e in p.items()}, {n: e.std for n, e in p.items()},
                                  {n for n, e in p.items() if e.at_bound})

    @property
    def status(self) -> str:
        """The status identify reports: the solver's, `not_determined` where it converged with
        an estimate the data do not determine."""
        st = self.solver["status"]
        return "not_determined" if st == "converged" and self.not_determined else st

    def to_json(self) -> dict:
        """The fit as the solver ended it (calibrate and demo write it); `document` is identify's."""
        return {
            "params": {n: {"value": e.value, "std": e.std, "unit": e.unit, "initial": e.initial,
                           **({"at_bound": True} if e.at_bound else {})} for n, e in self.params.items()},
            "fit": self.fit,
            "solver": {**self.solver, "explains_run": self.explains_run},
            "drive": self.drive,
            "runs": self.fit_per_run,
            "correlation": {"names": list(self.params),
                            "matrix": None if self.correlation is None else np.round(self.correlation, 4).tolist()},
        }

    def document(self, config: str | Path | None = None, inputs: Sequence[str | Path] = ()) -> dict:
        """identify's JSON document (docs/formats.md): each estimate says whether it is
        `determined`, a converged fit with an estimate that is not says `not_determined`, then
        the cylinder file (`config`, default the result cylinder's source) and the runs."""
        out = self.to_json()
        unknown = self.not_determined
        for n, entry in out["params"].items():
            entry["determined"] = n not in unknown
        out["solver"]["status"] = self.status
        source = config if config is not None else self.cylinder.source
        out["config"] = None if source is None else str(source)
        out["inputs"] = [str(p) for p in inputs]
        return out


def lower_cost(kept: IdentifyResult | None, other: IdentifyResult) -> IdentifyResult:
    """Of two fits of the same runs, the one of the lower TRAIN cost: `kept` on a tie, `other`
    where none is kept yet (every "started again, the lowest cost kept" goes through here)."""
    return other if kept is None or other.solver["cost"] < kept.solver["cost"] else kept


# ------------------------------------------------------------------ problem layout

# A run longer than this is fitted as pieces of at most this long, each from its own initial state,
# like the stretches between lost samples. A Gauss-Newton step closes every continuity defect of
# a piece at once: over an hour the position integrates the defects of 36 000 intervals into
# node states no cylinder can have, and the first line search failed (a 600 s piece converged).
LONG_PIECE_S = 60.0


def long_run_pieces(run: Run, M: int) -> list[Run]:
    """`run` in equal pieces of whole intervals (M samples), none longer than LONG_PIECE_S."""
    if run.duration <= LONG_PIECE_S:
        return [run]
    intervals = math.ceil(run.n / M)
    n_pieces = math.ceil(run.duration / LONG_PIECE_S)
    per = math.ceil(intervals / n_pieces) * M
    return [run.slice(a, min(a + per, run.n)) for a in range(0, run.n, per) if min(a + per, run.n) - a >= 3]


# ------------------------------------------------------------------ the solver


def identify(cyl: Cylinder, runs: Sequence[Run], options: IdentifyOptions = IdentifyOptions(),
             effects: Sequence[Effect] = (), initial: Mapping[str, float] | None = None,
             nodes: np.ndarray | None = None,
             progress: Callable[[str], None] | None = None, prior: Sequence[PriorRow] = ()) -> IdentifyResult:
    """Identify `options.estimate` from the runs (jointly) by multiple-shooting Gauss-Newton;
    `initial` overrides start values, `nodes` warm-starts the node states (another model's
    solution on the same runs), `prior` adds prior knowledge of the parameters. A fit that ends
    above the noise is restarted once (options.restart_misfit), and the better one returned;
    a parameter the drive cannot estimate is refused (DriveError). An effect's FREED_LAST
    parameters are held at their start until the rest has converged (not restarted), then freed
    from there (restarted if options.restart_misfit)."""
    check_drive(options.drive, options.estimate)
    last = tuple(f"{e.name}.{n}" for e in effects for n in e.PARAMS
                 if n in e.FREED_LAST and f"{e.name}.{n}" in options.estimate)
    if not last:
        return _identify_restarted(cyl, runs, options, effects, initial, nodes, progress, prior)
    t_start = time.perf_counter()
    # the held fit is a start for the freed one, which may restart: restarting both could fit 4 times
    held = _identify_restarted(cyl, runs, replace(options, estimate=tuple(n for n in options.estimate if n not in last),
                                                  restart_misfit=False),
                               effects, initial, nodes, progress, prior)
    if progress:
        progress(f"  residual {held.solver['residual_sigma']:.2f} x the noise with {', '.join(last)} held: "
                 "freed from there")
    left_s = options.time_limit_s - (time.perf_counter() - t_start)
    freed = _identify_restarted(cyl, runs, replace(options, time_limit_s=left_s), effects,
                                {**(initial or {}), **{n: e.value for n, e in held.params.items()}},
                                held.nodes, progress, prior)
    for n, e in freed.params.items():
        if n in held.params:
            e.initial = held.params[n].initial
    freed.solver = {**freed.solver, "iterations": held.solver["iterations"] + freed.solver["iterations"],
                    "wall_s": round(time.perf_counter() - t_start, 4),
                    "held_first": {"parameters": list(last), "status": held.solver["status"],
                                   "residual_sigma": held.solver["residual_sigma"]}}
    return freed


def _identify_restarted(cyl: Cylinder, runs: Sequence[Run], options: IdentifyOptions, effects: Sequence[Effect],
                        initial: Mapping[str, float] | None, nodes: np.ndarray | None,
                        progress: Callable[[str], None] | None, prior: Sequence[PriorRow]) -> IdentifyResult:
    """One fit, restarted once from where it ended if it ends above the noise."""
    t_start = time.perf_counter()
    first = _identify_once(cyl, runs, options, effects, initial, nodes, progress, prior)
    sol = first.solver
    left_s = options.time_limit_s - (time.perf_counter() - t_start)  # the user's guard covers both fits
    if not (options.restart_misfit and first.params and sol["status"] in ("converged", "line_search_failed")
            and sol["residual_sigma"] > SETTLED_SIGMA and left_s > 0):
        return first
    if progress:
        progress(f"  residual {sol['residual_sigma']:.2f} x the noise: started again from these parameters "
                 "with node states afresh from the data")
    ended = {n: e.value for n, e in first.params.items()}
    again = _identify_once(cyl, runs, replace(options, restart_misfit=False, time_limit_s=left_s), effects, ended,
                           None, progress, prior)
    kept = lower_cost(first, again)
    for n, e in kept.params.items():
        e.initial = first.params[n].initial
    kept.solver = {**kept.solver, "iterations": sol["iterations"] + again.solver["iterations"],
                   "wall_s": round(time.perf_counter() - t_start, 4),
                   "restart": {"residual_sigma_before": sol["residual_sigma"],
                               "residual_sigma_after": again.solver["residual_sigma"],
                               "kept": "restart" if kept is again else "first"}}
    if progress:
        progress(f"  restart: residual {again.solver['residual_sigma']:.2f} x the noise, "
                 f"{'kept' if kept is again else 'the first fit kept'}")
    return kept


def _identify_once(cyl: Cylinder, runs: Sequence[Run], options: IdentifyOptions, effects: Sequence[Effect],
                   initial: Mapping[str, float] | None, nodes: np.ndarray | None,
                   progress: Callable[[str], None] | None, prior: Sequence[PriorRow]) -> IdentifyResult:
    t_start = time.perf_counter()
    if not runs:
        raise IdentificationError("no runs to identify from.")
    check_determinable(cyl, runs, options.estimate)  # no "converged" on runs that cannot say
    runs = _gap_free_pieces(runs, options.drive, progress)
    plant = plant_for(cyl, options.drive, effects, options.estimate)
    p, theta_init = _start_values(cyl, runs, plant, options, initial, progress)
    fit = _shooting_fit(cyl, runs, plant, options, nodes, prior, progress)
    ended = _iterate(fit, fit.S0, theta_init.copy(), p, options, progress, t_start)
    return _result(fit, ended, options, effects, theta_init, t_start, progress)


def _gap_free_pieces(runs: Sequence[Run], drive: str, progress: Callable[[str], None] | None) -> Sequence[Run]:
    """The runs cut at lost samples (no simulation bridges a gap). The measured pressures drive
    the pressure-driven plant: where one was not measured, that plant has no input, so the run
    is cut there too."""
    inputs = ("p1", "p2") if drive == "pressure" else ()
    pieces = [piece for r in runs for piece in split_at_gaps(r, channels=inputs)]
    if len(pieces) <= len(runs):
        return runs
    kept = [q for q in pieces if q.n >= 3]
    if not kept:
        raise IdentificationError("the runs have no gap-free stretch of 3 samples or more.")
    if progress:
        progress(f"  {len(pieces) - len(runs)} gap(s) of lost samples: {len(kept)} gap-free pieces "
                 "identified jointly (no simulation bridges a gap)")
    return kept


def _start_values(cyl: Cylinder, runs: Sequence[Run], plant: Plant, options: IdentifyOptions,
                  initial: Mapping[str, float] | None,
                  progress: Callable[[str], None] | None) -> tuple[np.ndarray, np.ndarray]:
    """(the plant's parameter vector, the estimates' start within their bounds): the cylinder
    file's values, `initial` over them, else the equation-error fit of the friction."""
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
    lower, upper = parameter_bounds(plant, estimate)
    theta = np.clip(p[free], lower, upper)
    p[free] = theta
    return p, theta.copy()


@dataclass(frozen=True)
class _Fit:
    """The multiple-shooting problem of some runs: layout, compiled functions, prior, and the
    merit the line search weighs steps by."""

    cyl: Cylinder
    plant: Plant
    sf: ShootingFunctions
    problem: ShootingProblem
    layouts: list[RunLayout]
    S0: np.ndarray  # node states to start from
    estimate: tuple[str, ...]
    free: list[int]
    lower: np.ndarray
    upper: np.ndarray
    M: int
    cluster: int
    node_scale: np.ndarray  # the free node states' defect scales (the damping's bound on them)
    Gp: np.ndarray
    tp: np.ndarray
    nres: float  # residuals (measured samples x outputs)

    @property
    def nx(self) -> int:
        return self.plant.nx

    @property
    def nth(self) -> int:
        return len(self.free)

    @property
    def K(self) -> int:  # shooting intervals in all
        return self.problem.K

    @property
    def n_state(self) -> int:  # free node states: the first of each piece
        return len(self.layouts) * self.nx

    @functools.cached_property
    def piece_of(self) -> np.ndarray:
        """The piece of every interval."""
        return np.repeat(np.arange(len(self.layouts)), [l.K for l in self.layouts])

    def closed(self, viol: float) -> bool:
        """Whether defects summing to `viol` (scaled) are closed."""
        return viol < 1e-2 * max(1, self.K)

    def linearise(self, S: np.ndarray, p: np.ndarray) -> NormalEquations | None:
        pieces = [(l.node0, l.K) for l in self.layouts]
        return self.problem.linearise(S, p, NormalEquations(pieces, self.nx, self.nth, self.cluster))

    def evaluate(self, S: np.ndarray, p: np.ndarray, _with_sens: bool, give_up=None):
        return self.problem.merit_terms(S, p, give_up)

    def prior_cost(self, th: np.ndarray) -> float:
        rp = self.Gp @ th - self.tp
        return 0.5 * float(rp @ rp)

    def merit(self, sq: float, D: np.ndarray, mu: float, th: np.ndarray) -> float:
        # a trial step so far off that its squared residuals overflow has an infinite merit,
        # which the line search rejects: no warning for the user (sq: the residuals' sum of squares)
        with np.errstate(over="ignore"):
            return 0.5 * sq + self.prior_cost(th) + mu * float(np.sum(np.abs(D)))

    @staticmethod
    def merit_part(E: np.ndarray, D: np.ndarray, mu: float) -> float:
        """merit's share of some intervals' residuals and defects (without the prior)"""
        with np.errstate(over="ignore"):
            return 0.5 * float(np.sum(E * E)) + mu * float(np.sum(np.abs(D)))

    def with_prior(self, Nmat: ReducedNormal, g: np.ndarray, th: np.ndarray) -> tuple[ReducedNormal, np.ndarray]:
        if not len(self.tp):
            return Nmat, g
        g = g.copy()
        g[self.n_state:] += self.Gp.T @ (self.Gp @ th - self.tp)
        return Nmat.with_parameters(self.Gp.T @ self.Gp), g

    def residual_sigma(self, S: np.ndarray, p: np.ndarray, ev: NormalEquations) -> tuple[float, float]:
        """(residual sigma, noise floor) of a drive by measured inputs (interval_residual_sigma)."""
        return interval_residual_sigma(self.problem, self.layouts, self.cyl, S, p, ev,
                                       self.nres - self.K * self.nx - self.nth)


def _shooting_fit(cyl: Cylinder, runs: Sequence[Run], plant: Plant, options: IdentifyOptions, nodes: np.ndarray | None,
                  prior: Sequence[PriorRow], progress: Callable[[str], None] | None) -> _Fit:
    """The runs laid out in shooting intervals (long runs in pieces), the compiled functions,
    the node states to start from (`nodes`: warm) and the prior."""
    estimate = tuple(options.estimate)
    free = free_parameters(plant, estimate)
    lower, upper = parameter_bounds(plant, estimate)
    dt0 = runs[0].sample_period
    M = max(5, int(round(options.interval_s / dt0)))
    cluster = max(1, int(round(1.0 / (M * dt0))))  # intervals per second: the robust std's clusters
    sf = shooting_functions(plant, M, free, options.integrator, progress=progress, with_sens=True)
    cut = [part for r in runs for part in long_run_pieces(r, M)]
    if progress and len(cut) > len(runs):
        progress(f"  {len(cut) - len(runs)} cut(s) where a run is longer than {LONG_PIECE_S:g} s: {len(cut)} pieces "
                 "identified jointly, each from its own initial state")
    layouts: list[RunLayout] = []
    node0 = 0
    for r in cut:
        if r.n < 3:
            raise IdentificationError(f"{r.source}: a run needs at least 3 samples.")
        lay = run_layout(r, plant, cyl, M, node0)
        layouts.append(lay)
        node0 += lay.K
    Ktot = node0
    layouts, (W, H, Y, mask, S) = concatenated_layouts(layouts)
    if nodes is not None:
        S = warm_nodes(plant, cyl, S, np.asarray(nodes, float))
    wts, sscale = residual_scales(plant, cyl, dt0)
    # node k is followed by node k+1 within the same run
    has_next = np.ones(Ktot, bool)
    for l in layouts:
        has_next[l.node0 + l.K - 1] = False
    threads = max(1, min(options.threads, Ktot))
    problem = ShootingProblem(sf, Ktot, threads, W, H, Y, mask, wts, sscale, np.flatnonzero(has_next),
                              plant.possible_states(cyl))
    Gp, tp = prior_matrix(prior, estimate)
    return _Fit(cyl, plant, sf, problem, layouts, S, estimate, free, lower, upper, M, cluster,
                np.tile(sscale, len(layouts)), Gp, tp, float(np.sum(mask)))


# how an offline iteration retries a step its line search could not take: eight times at most,
# a step within 1e-2 of the one that just failed not searched again (searching the step that
# just failed again is where a struggling fit spent its time). The node states are bounded only
# after a failed search: the Gauss-Newton path of a fit that works stays undamped (a stiction
# fit went to another local minimum, 1.09 x noise, when always damped so)
OFFLINE_DAMPING = Damping(attempts=8, floor=1e-6, same_step=1e-2)


class _OfflineStep:
    """The step model of one offline iteration at (S, theta, p), linearised in `ev`."""

    def __init__(self, fit: _Fit, ev: NormalEquations, S, theta, p, cost: float, viol: float, recent: list[dict]):
        self.fit, self.ev, self.S, self.theta, self.p = fit, ev, S, theta, p
        self.cost, self.viol = cost, viol
        self.recent = recent  # the iterations a non-monotone search looks back on (none: monotone)

    def predict(self, step: np.ndarray) -> Prediction:
        fit = self.fit
        gdir, quad = self.ev.predicted(step)
        lin_prior = fit.Gp @ step[fit.n_state:]
        gdir += float((fit.Gp @ self.theta - fit.tp) @ lin_prior)
        quad += float(lin_prior @ lin_prior)
        return Prediction(-(gdir + 0.5 * quad), gdir)

    def nothing_to_gain(self, pred: Prediction) -> bool:
        # nothing left to gain, statistically or numerically
        return pred.decrease < max(1e-2, 1e-10 * self.cost) and self.fit.closed(self.viol)

    def penalty(self, mu: float, pred: Prediction) -> float:
        return max(mu, -pred.decrease / (0.5 * self.viol) + 1.0) if self.viol > 0 else mu

    def search(self, step: np.ndarray, pred: Prediction, mu: float):
        fit, ev = self.fit, self.ev
        ds0, dth = step[: fit.n_state].reshape(len(fit.layouts), fit.nx), step[fit.n_state:]
        dS = (ev.P @ ds0[fit.piece_of][:, :, None])[..., 0] + ev.Q @ dth + ev.q
        # a fit that creeps (only short steps accepted, NONMONOTONE times in a row) is in a curved
        # valley: then a step may rise above the current merit as long as it stays below the
        # worst of the last few (Grippo-Lampariello-Lucidi), so it takes full steps along it
        reference = self.cost + mu * self.viol
        if self.recent:
            reference = max([reference] + [h["cost"] + mu * h["defect"] for h in self.recent])
        return line_search(fit.evaluate, lambda tr, th_: fit.merit(tr[0], tr[1], mu, th_), self.S, dS.T,
                           self.theta, dth, self.p, fit.free, fit.lower, fit.upper, reference,
                           min(pred.gdir - mu * self.viol, 0.0), 1.0 / 64,
                           part=lambda E_, D_: fit.merit_part(E_, D_, mu))


@dataclass
class _Ended:
    """Where the iterations left a fit: why, after how many, and its state linearised in `ev`."""

    exit: Exit
    iterations: int
    history: list[dict]
    S: np.ndarray
    theta: np.ndarray
    p: np.ndarray
    ev: NormalEquations


def _iterate(fit: _Fit, S: np.ndarray, theta: np.ndarray, p: np.ndarray, options: IdentifyOptions,
             progress: Callable[[str], None] | None, t_start: float) -> _Ended:
    """Gauss-Newton iterations from (S, theta, p) until an exit of _FitEnd."""
    ev = fit.linearise(S, p)
    if ev is None:
        raise IdentificationError("the simulation from the initial guess is not finite, or starts where this "
                                  "cylinder cannot be (a position beyond a stroke outside its travel, pressures "
                                  "beyond ten times the supply); check the cylinder file "
                                  "(units, dead volumes, supply pressure) against the run.")
    end = _FitEnd(fit, options, t_start)
    lam, mu = 0.0, 0.0
    creeping = 0  # accepted steps in a row that were backtracked to 1/8 or less
    history: list[dict] = []
    it, why = 0, Exit.MAX_ITERATIONS
    for it in range(1, options.max_iter + 1):
        if end.out_of_time():
            why = Exit.TIME_LIMIT
            break
        Nmat, g = fit.with_prior(ev.N, ev.g, theta)
        cost = 0.5 * ev.cost2 + fit.prior_cost(theta)
        viol = float(np.sum(np.abs(ev.D)))
        recent = history[-NONMONOTONE:] if creeping >= NONMONOTONE else []
        model = _OfflineStep(fit, ev, S, theta, p, cost, viol, recent)
        out = damped_step(Nmat, g, theta, fit.lower, fit.upper, fit.node_scale, lam, mu, model,
                          OFFLINE_DAMPING, end.out_of_time)
        lam, mu = out.lam, out.mu
        if out.converged:
            why = Exit.NOTHING_TO_GAIN
            break
        if out.found is None:
            why = end.after_failed_step(out, Nmat, ev, S, theta, p, cost, viol, history)
            break
        alpha, S, theta_new, p, _ = out.found
        dth = out.step[fit.n_state:]
        lam = lam / 10 if lam > 1e-6 else 0.0
        creeping = creeping + 1 if alpha <= 0.125 else 0
        theta, scores = theta_new, ev.clusters
        history.append({"iteration": it, "cost": cost, "defect": viol, "alpha": alpha, "lm": lam,
                        "theta": theta.tolist()})
        if progress:
            values = "  ".join(f"{n}={v:.5g}" for n, v in zip(fit.estimate, theta))
            progress(Step(f"  iteration {it:2d}: cost {cost:.6g}  defects {viol:.3g}  step {alpha:.3g}  {values}",
                          "iterations", it, cost=cost))
        ev = fit.linearise(S, p)
        if ev is None:
            raise IdentificationError(f"the simulation stopped being finite at iteration {it} "
                                      f"({', '.join(f'{n}={v:.4g}' for n, v in zip(fit.estimate, theta))}); "
                                      "check the cylinder file against the run.")
        why = end.after_step(Nmat, scores, ev, theta, alpha, alpha * dth, cost, history)
        if why is not None:
            break
        why = Exit.MAX_ITERATIONS
    return _Ended(why, it, history, S, theta, p, ev)


class _FitEnd:
    """When an offline fit stops: every exit but NOTHING_TO_GAIN (damped_step's) and
    MAX_ITERATIONS, in the order the iterations ask."""

    def __init__(self, fit: _Fit, options: IdentifyOptions, t_start: float):
        self.fit, self.options, self.t_start = fit, options, t_start

    def out_of_time(self) -> bool:
        return time.perf_counter() - self.t_start > self.options.time_limit_s

    def after_step(self, Nmat: ReducedNormal, scores: Clusters, ev: NormalEquations, theta: np.ndarray,
                   alpha: float, moved: np.ndarray, cost: float, history: list[dict]) -> Exit | None:
        """The exit after an accepted step of length `alpha` that moved the parameters by `moved` to `theta`
        (Nmat, scores: of the iteration's start; ev: linearised after the step)."""
        fit, options, nres = self.fit, self.options, self.fit.nres
        std = standard_deviations(Nmat, cost, nres)
        # a step small against what the data determine; an undetermined parameter (std not
        # finite) must itself stop moving
        yardstick = np.where(np.isfinite(std), std, 1e-6 * (fit.upper - fit.lower))
        rel_step = np.max(np.abs(moved) / np.maximum(yardstick, 1e-300)) if fit.nth else 0.0
        closed = fit.closed(float(np.sum(np.abs(ev.D))))
        if rel_step < 1e-3 and closed and alpha == 1.0:
            return Exit.SMALL_STEP
        if closed and parameters_settled(history, theta, std, cost, nres):
            return Exit.PARAMETERS_SETTLED  # short steps that only polish node states (e.g. around gaps)
        if not fit.nth and states_settled(history):
            return Exit.STATES_SETTLED
        if options.start_only and fit.nth and len(history) >= 2 * NONMONOTONE:
            cov_rep = reported_covariance(Nmat, scores, cost, nres)
            if cov_rep is not None and start_settled(history, theta, np.sqrt(np.maximum(np.diag(cov_rep), 0.0))):
                return Exit.START_SETTLED
        if abs(cost - 0.5 * ev.cost2 - fit.prior_cost(theta)) < 1e-12 * cost and closed:
            return Exit.COST_UNCHANGED
        n_last = options.give_up_after
        if (math.isfinite(options.give_up_above) and len(history) >= n_last
                and all(h["cost"] > options.give_up_above for h in history[-n_last:])):
            return Exit.ABOVE_REFERENCE
        return None

    def after_failed_step(self, out: StepOutcome, Nmat: ReducedNormal, ev: NormalEquations, S: np.ndarray,
                          theta: np.ndarray, p: np.ndarray, cost: float, viol: float, history: list[dict]) -> Exit:
        """The exit when no step was accepted: AT_NOISE_FLOOR where nothing can be gained any
        more, else TIME_LIMIT or LINE_SEARCH_FAILED."""
        if self.at_noise_floor(out, Nmat, ev, S, theta, p, cost, viol, history):
            return Exit.AT_NOISE_FLOOR
        return Exit.TIME_LIMIT if self.out_of_time() else Exit.LINE_SEARCH_FAILED

    def at_noise_floor(self, out: StepOutcome, Nmat: ReducedNormal, ev: NormalEquations, S: np.ndarray,
                       theta: np.ndarray, p: np.ndarray, cost: float, viol: float, history: list[dict]) -> bool:
        """Whether a step the line search could not take leaves nothing to gain: at the numerical
        noise floor of the cost; or it moves no parameter by a tenth of what the data determine
        (a noisy rig's cost surface is rough at that scale); or the fit has settled; or, at the
        sensor noise, it moves no parameter by half the std the fit reports."""
        fit, nres = self.fit, self.fit.nres
        closed = fit.closed(viol)
        if out.step is not None and out.predicted < 1.0 and closed:
            return True
        if out.first_step is None or not fit.nth:
            return False
        std_here = standard_deviations(Nmat, cost, nres)
        ok = np.isfinite(std_here) & (std_here > 0)
        if not ok.all():
            return False
        moves = np.abs(out.first_step[fit.n_state:])
        tiny = moves[ok] <= 0.1 * std_here[ok]
        # nor when the last steps (short ones, in a curved valley of the node states) moved no
        # parameter by a quarter of its std and the cost no longer falls: a defect left at an end
        # stop's stiff contact (where the piston leaves the stop is all but discontinuous in the
        # node state) is one the data cannot resolve
        settled = parameters_settled(history, theta, std_here, cost, nres)
        # the raw residual of a drive by measured (noisy) signals stays above the sensor noise
        # however good the model, so it is judged against that drive's floor; and its
        # Gauss-Newton std understates what the data leave open (the std it reports is the
        # cluster-robust one, here ~30 times larger)
        by_floor = not settled and self.options.noise_floor and drives_with_measured_inputs(fit.plant)
        at_noise = 2 * cost <= SETTLED_SIGMA ** 2 * nres
        cov_rep = reported_covariance(Nmat, ev.clusters, cost, nres) if by_floor or at_noise else None
        std_rep = None if cov_rep is None else np.sqrt(np.maximum(np.diag(cov_rep), 0.0))
        if by_floor and std_rep is not None:
            settled = parameters_settled(history, theta, std_rep, cost, nres,
                                         at_noise=lambda: fit.residual_sigma(S, p, ev)[0] <= SETTLED_SIGMA)
        # at the sensor noise, a step that would move no parameter by half the std the fit
        # reports: the data cannot tell the two apart (a lossy recording with its defects not
        # quite closed)
        at_noise_step = bool(at_noise and std_rep is not None and np.all(moves <= 0.5 * std_rep))
        return bool((closed and tiny.all()) or settled or at_noise_step)


def _result(fit: _Fit, ended: _Ended, options: IdentifyOptions, effects: Sequence[Effect],
            theta_init: np.ndarray, t_start: float, progress: Callable[[str], None] | None = None) -> IdentifyResult:
    """The estimates with their standard deviations and correlation at the solution, the fit
    of every run simulated from its identified initial state in one piece, the solver's figures."""
    S, theta, p, ev, plant = ended.S, ended.theta, ended.p, ended.ev, fit.plant
    cost = 0.5 * ev.cost2
    Nfinal, _ = fit.with_prior(ev.N, ev.g, theta)
    cov = reported_covariance(Nfinal, ev.clusters, cost, fit.nres)
    wanted = (fit.nth and cov is not None and not options.start_only
              and not at_bounds(theta, fit.lower, fit.upper).any()
              and sum(l.run.duration for l in fit.layouts) >= options.discretisation_min_s)
    term = (discretisation(fit.problem, fit.sf, options.integrator, fit.layouts, S, p, min(options.threads, fit.K),
                           progress) if wanted else None)
    theta, cov = corrected(theta, cov, term, fit.lower, fit.upper)
    at_bound = at_bounds(theta, fit.lower, fit.upper)
    std = np.sqrt(np.maximum(np.diag(cov), 0.0)) if cov is not None else np.full(fit.nth, np.nan)
    corr = correlation(cov) if cov is not None and fit.nth else None
    params = {n: Estimate(n, float(v), float(s), parameter_unit(plant, n), float(v0), bool(b))
              for n, v, s, v0, b in zip(fit.estimate, theta, std, theta_init, at_bound)}
    sims = [simulate_layout(fit.sf, S[:, l.node0], p, l, fit.M) for l in fit.layouts]
    fit_runs = [fit_metrics(l.run, sim, plant.output_names) for l, sim in zip(fit.layouts, sims)]
    pooled = pooled_fit([l.run for l in fit.layouts], sims, plant.output_names)
    values = {n: params[n].value for n in fit.estimate if n in PARAMETERS}
    eff_values: dict[str, dict[str, float]] = {}
    for n in fit.estimate:
        if "." in n:
            ename, pname = n.split(".", 1)
            eff_values.setdefault(ename, {})[pname] = params[n].value
    new_effects = tuple(with_effect_values(e, eff_values.get(e.name, {})) for e in effects)
    residual_sigma, floor = math.sqrt(2 * cost / max(1.0, fit.nres - fit.n_state - fit.nth)), 1.0
    if options.noise_floor and drives_with_measured_inputs(plant):
        # measured inputs carry noise that drives the model too: the residual is told in units of
        # what that noise alone leaves, so that 1 means a perfect model in every drive
        residual_sigma, floor = fit.residual_sigma(S, p, ev)
    sf = fit.sf
    solver = {"status": ended.exit.status, "iterations": ended.iterations,
              "wall_s": round(time.perf_counter() - t_start, 4),
              "cost": cost, "residual_sigma": residual_sigma, "noise_floor": floor,
              "n_samples": int(sum(l.run.n for l in fit.layouts)), "n_intervals": fit.K, "interval_samples": fit.M,
              "discretisation": None if term is None else term.to_json(fit.estimate),
              "compile": {"cache_hit": sf.stats.cache_hit, "build_s": round(sf.stats.build_s + sf.stats.compile_s, 3)},
              "history": ended.history}
    return IdentifyResult(params=params, fit=pooled, fit_per_run=fit_runs, solver=solver,
                          cylinder=fit.cyl.with_values(values), effects=new_effects, drive=plant.drive,
                          simulated=sims, output_names=plant.output_names, correlation=corr, nodes=S)
