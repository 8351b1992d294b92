"""The Gauss-Newton iteration shared by the offline identifier and the online estimator
(identify/gauss_newton.py), on a small linear least-squares problem with a scripted search."""
from __future__ import annotations

import numpy as np

from combined_reality.identify.gauss_newton import Damping, Exit, Prediction, damped_step
from combined_reality.identify.shooting import ReducedNormal

# min 0.5 |J d + r|^2 over (one node state, two parameters)
J = np.array([[2.0, 0.0, 1.0], [0.0, 1.0, 0.0], [1.0, 1.0, 3.0], [0.0, 0.0, 1.0]])
r = np.array([1.0, -2.0, 0.5, 0.3])
N, g = J.T @ J, J.T @ r
NR = ReducedNormal(N[None, :1, :1], N[None, :1, 1:], N[1:, 1:])  # (one node state, two parameters)
LOWER, UPPER = np.full(2, -10.0), np.full(2, 10.0)


class Scripted:
    """A step model whose search accepts from the `accept_from`-th search on."""

    def __init__(self, accept_from: int, gain: float = 5.0):
        self.accept_from, self.gain, self.searched, self.mus = accept_from, gain, [], []

    def predict(self, step):
        return Prediction(-(g @ step + 0.5 * step @ N @ step), float(g @ step))

    def nothing_to_gain(self, pred):
        return pred.decrease < 1e-12

    def penalty(self, mu, pred):
        return mu + 1.0

    def search(self, step, pred, mu):
        self.searched.append(step.copy())
        self.mus.append(mu)
        return ("trial", len(self.searched)) if len(self.searched) >= self.accept_from else None


def test_the_undamped_step_is_the_least_squares_solution_and_taken_first():
    model = Scripted(accept_from=1)
    out = damped_step(NR, g, np.zeros(2), LOWER, UPPER, np.ones(1), 0.0, 0.0, model, Damping(8, 1e-6))
    d = np.linalg.lstsq(J, -r, rcond=None)[0]
    assert out.found == ("trial", 1) and not out.converged
    np.testing.assert_allclose(out.step, d, rtol=1e-10)
    np.testing.assert_allclose(out.predicted, 0.5 * (r @ r - np.sum((J @ d + r) ** 2)), rtol=1e-10)
    assert out.lam == 0.0 and out.mu == 1.0


def test_failed_searches_raise_the_damping_shorten_the_step_and_end_after_the_attempts():
    model = Scripted(accept_from=99)
    out = damped_step(NR, g, np.zeros(2), LOWER, UPPER, np.ones(1), 0.0, 0.0, model, Damping(3, 1e-2))
    assert out.found is None and not out.converged and len(model.searched) == 3
    assert out.lam == 1.0  # 0 -> 1e-2 -> 0.1 -> 1 (raised after the last failure too)
    norms = [np.linalg.norm(s) for s in model.searched]
    assert norms[0] > norms[1] > norms[2]
    np.testing.assert_array_equal(out.first_step, model.searched[0])
    assert model.mus == [1.0, 2.0, 3.0]


def test_a_step_as_good_as_nothing_ends_the_fit_without_a_search():
    out = damped_step(NR, np.zeros(3), np.zeros(2), LOWER, UPPER, np.ones(1), 0.0, 0.0, Scripted(1), Damping(8, 1e-6))
    assert out.converged and out.found is None and out.mu == 0.0


def test_a_retry_that_would_search_the_failed_step_again_is_damped_further_first():
    """With a tiny damping floor the second step is all but the first: it is skipped, and the
    damping raised until the step differs by more than `same_step`."""
    model = Scripted(accept_from=2)
    out = damped_step(NR, g, np.zeros(2), LOWER, UPPER, np.ones(1), 0.0, 0.0, model,
                      Damping(12, 1e-9, same_step=1e-2))
    # the scaled damping changes the step by about itself: 1e-9 ... 1e-3 were skipped, unsearched
    assert out.found == ("trial", 2) and len(model.searched) == 2 and out.lam >= 1e-2
    first, second = model.searched
    scale = np.sqrt(np.diag(N))
    assert np.linalg.norm((second - first) * scale) > 1e-2 * np.linalg.norm(first * scale)


def test_bounds_hold_and_every_exit_reports_its_status():
    model = Scripted(accept_from=1)
    out = damped_step(NR, g, np.zeros(2), np.full(2, -0.05), np.full(2, 0.05), np.ones(1), 0.0, 0.0, model,
                      Damping(8, 1e-6))
    assert np.all(np.abs(out.step[1:]) <= 0.05 + 1e-15)
    assert {e.status for e in Exit} == {"converged", "line_search_failed", "time_limit", "above_reference",
                                        "max_iterations"}
    assert len(set(Exit)) == len(Exit.__members__)  # exits with the same status stay distinct
