"""Friction from Newton's law with the measured pressures (the Karnopp/least-squares friction fit
of Trentini et al., seed 000): the piston equation of the plant, driven by the measured
pressures with the friction set to zero, against the acceleration of the measured position. The
equation-error fit of Fc, Fv, kp on it is the identifier's start and a regressor of the
diagnosis."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from sim.compiled import plant_columns
from sim.cylinder import Cylinder
from sim.plant import Plant, build_plant

from ..files import Run
from .smoothing import derivative_kernels

__all__ = ["friction_from_newton", "equation_error_friction", "scaled_lstsq"]


def scaled_lstsq(A: np.ndarray, b: np.ndarray) -> np.ndarray | None:
    """The least-squares solution of A x = b with A's columns scaled to a largest entry of 1
    (regressors of different units: N, N/Pa, N s/m, kg, ...); None if it is not finite."""
    scale = np.maximum(np.abs(A).max(axis=0), 1e-300)
    sol = np.linalg.lstsq(A / scale, b, rcond=None)[0] / scale
    return sol if np.all(np.isfinite(sol)) else None


def friction_from_newton(cyl: Cylinder, run: Run, half: int = 15,
                         plant: Plant | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Friction the piston equation implies, with measured pressures (seed 000's method).

    Friction = M (a_without_friction - a): the pressure drive of the plant, evaluated with
    zero friction at the measured pressures, gives the acceleration without friction; a and v
    are Savitzky-Golay derivatives of the position. Returns (index, v, F) for the samples
    away from the ends (index into the run) whose window holds every sample, measured: no
    window with a position or pressure not measured, none across lost samples."""
    if run.n < 4 * half:
        return np.empty(0, int), np.empty(0), np.empty(0)
    plant = plant or build_plant("pressure")
    frictionless = np.array(plant.parameter_vector(cyl.with_values({"Fc": 0.0, "Fv": 0.0, "kp": 0.0})))
    k1, k2 = derivative_kernels(half)
    dt = run.sample_period
    # a position not measured makes every window that holds it NaN (0 * NaN is NaN too)
    v = np.convolve(run.x, k1, mode="same")[half:-half] / dt
    a = np.convolve(run.x, k2, mode="same")[half:-half] / dt**2
    idx = np.arange(half, run.n - half)
    lost = np.r_[0, np.cumsum(np.diff(run.t) > 1.5 * dt)]  # lost-sample gaps before each sample
    whole = (lost[idx + half] == lost[idx - half]) & np.isfinite(v) & np.isfinite(run.p1[idx]) \
        & np.isfinite(run.p2[idx])
    idx, v, a = idx[whole], v[whole], a[whole]
    if not len(idx):
        return idx, v, a
    xdot = plant_columns(plant)(np.vstack([run.x[idx], v]), np.vstack([run.p1[idx], run.p2[idx]]), frictionless)
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
    sol = scaled_lstsq(np.vstack(rows), np.concatenate(rhs))
    if sol is None:
        return {}
    return {"Fc": max(float(sol[0]), 0.0), "kp": max(float(sol[1]), 0.0), "Fv": max(float(sol[2]), 0.0)}
