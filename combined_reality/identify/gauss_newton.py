"""One Gauss-Newton iteration of a shooting fit, written once for the offline identifier
(offline.py) and the moving-horizon estimator (online.py), and the named ends of a fit.

An iteration solves the damped, bounded normal equations (solve_bounded), asks the problem
what decrease its linear model promises, ends the fit when that is nothing worth taking,
raises the l1 penalty on the defects as far as the step needs and searches along the step
(shooting.line_search). A failed search raises the damping (Levenberg-Marquardt) and tries
again; from the first failure on, the damping bounds the free node states too. What differs
between the problems (the decrease their model predicts, what is worth a step, the penalty
rule, the merit and the search) is a `StepModel`; how often and how hard the damping is
raised is a `Damping`.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Callable, NamedTuple, Protocol

import numpy as np

from .shooting import ReducedNormal, solve_bounded, step_matrix

__all__ = ["Exit", "Damping", "Prediction", "StepModel", "StepOutcome", "damped_step"]


class Exit(Enum):
    """Why a fit stopped iterating; `status` is what the solver reports for it."""

    NOTHING_TO_GAIN = "converged"  # the step promises less than the noise would, defects closed
    AT_NOISE_FLOOR = "converged"  # no step could be taken, and none would change what the data say
    SMALL_STEP = "converged"  # a full step that moved no parameter by 1e-3 of its std, defects closed
    PARAMETERS_SETTLED = "converged"  # steps that only polish node states (offline.parameters_settled)
    STATES_SETTLED = "converged"  # a fit of initial states alone stopped gaining (offline.states_settled)
    START_SETTLED = "converged"  # a fit that only starts another has done its part (offline.start_settled)
    COST_UNCHANGED = "converged"  # the step left the cost as it was, defects closed
    WARM_START_ENOUGH = "converged"  # online: a full step with little left to gain after the real-time iteration
    LINE_SEARCH_FAILED = "line_search_failed"  # no damping made a step the merit accepts
    TIME_LIMIT = "time_limit"  # the caller's wall-clock guard
    ABOVE_REFERENCE = "above_reference"  # the cost stayed above the reference (IdentifyOptions.give_up_above)
    MAX_ITERATIONS = "max_iterations"

    def __new__(cls, status: str):
        obj = object.__new__(cls)
        obj._value_ = len(cls.__members__)  # members with the same status stay distinct
        obj.status = status
        return obj


@dataclass(frozen=True)
class Damping:
    """How an iteration retries a step its line search could not take."""

    attempts: int  # steps tried per iteration at most
    floor: float  # the damping after a failure: max(floor, 10 x the damping before)
    # whether every retry bounds the free node states (else only those after a failed search)
    bound_states_on_retry: bool = False
    # a retry whose step lies within this (relative, in the scaled variables) of the step that
    # just failed is not searched again: the damping is raised further first (0: searched)
    same_step: float = 0.0


class Prediction(NamedTuple):
    decrease: float  # of the cost, as the problem's linear model predicts it for the full step
    gdir: float = 0.0  # the model's directional derivative of the cost (offline's search slope)


class StepModel(Protocol):
    """What an iteration needs of its problem besides the normal equations."""

    def predict(self, step: np.ndarray) -> Prediction: ...

    def nothing_to_gain(self, pred: Prediction) -> bool: ...

    def penalty(self, mu: float, pred: Prediction) -> float: ...

    def search(self, step: np.ndarray, pred: Prediction, mu: float) -> tuple | None: ...


@dataclass
class StepOutcome:
    """What one iteration did: `found` the accepted trial (alpha, S, theta, p, evaluation) of
    shooting.line_search, or `converged` (nothing left to gain), or neither (no step taken)."""

    lam: float  # the damping as the iteration left it
    mu: float  # the defects' penalty as the iteration left it
    found: tuple | None = None
    converged: bool = False
    step: np.ndarray | None = None  # the last step solved (None if its system was singular)
    first_step: np.ndarray | None = None  # the least damped step: what the model still expects to gain
    prediction: Prediction | None = None  # the last step's

    @property
    def predicted(self) -> float:
        return self.prediction.decrease if self.prediction is not None else float("inf")


def damped_step(N: ReducedNormal, g: np.ndarray, theta: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                node_scale: np.ndarray, lam: float, mu: float, model: StepModel, damping: Damping,
                out_of_time: Callable[[], bool] | None = None) -> StepOutcome:
    """One Gauss-Newton iteration on the normal equations N d = -g of (the free node states,
    theta): steps of growing damping until one is accepted, nothing is left to gain, or
    `damping.attempts` have failed (or `out_of_time()`, asked before each retry)."""
    out = StepOutcome(lam=lam, mu=mu)
    scaled = step_matrix(N)  # scaled once for every damping, and once more when the states are bounded
    scale = scaled.scale
    failed, bounded = None, False
    for attempt in range(damping.attempts):
        if attempt and out_of_time is not None and out_of_time():
            break  # a struggling line search is where the time goes
        # once a step has failed, the damping bounds the free node states too: a state the data
        # cannot see (the velocity of a piston stuck where a piece starts) may have taken it all
        if not bounded and (failed is not None or (damping.bound_states_on_retry and attempt > 0)):
            scaled, bounded = step_matrix(N, node_scale), True
        step = out.step = solve_bounded(scaled, g, theta, lower, upper, out.lam)
        if out.first_step is None:
            out.first_step = step
        if step is None or (damping.same_step and failed is not None and (
                np.linalg.norm((step - failed) * scale) <= damping.same_step * np.linalg.norm(failed * scale))):
            out.lam = max(damping.floor, out.lam * 10)
            continue
        pred = out.prediction = model.predict(step)
        if model.nothing_to_gain(pred):
            out.converged = True
            break
        out.mu = model.penalty(out.mu, pred)
        found = model.search(step, pred, out.mu)
        if found:
            out.found = found
            break
        failed = step
        out.lam = max(damping.floor, out.lam * 10)
    return out
