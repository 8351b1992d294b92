"""Savitzky-Golay smoothing and derivatives of sampled signals (position -> velocity,
acceleration): one kernel builder for every estimate the tool makes from measured motion."""
from __future__ import annotations

import numpy as np

__all__ = ["savgol_kernels", "derivative_kernels", "velocity_estimate", "fill_missing"]


def velocity_estimate(t: np.ndarray, x: np.ndarray, half: int = 10) -> np.ndarray:
    """Savitzky-Golay slope over +-half samples, held constant at the ends. Positions not
    measured (NaN) are interpolated first: an estimate for starting guesses and for sorting
    samples into regimes, not a measurement."""
    x = fill_missing(t, x)
    if len(x) < 2 * half + 1:
        return np.gradient(x, t)
    v = np.convolve(x, derivative_kernels(half)[0], mode="same") / np.median(np.diff(t))
    v[:half] = v[half]
    v[-half:] = v[-half - 1]
    return v


def fill_missing(t: np.ndarray, values: np.ndarray) -> np.ndarray:
    """`values` with the samples not measured (NaN) interpolated linearly in time, held at
    the ends: for starting guesses and estimates, never in place of a measurement."""
    ok = np.isfinite(values)
    if ok.all() or not ok.any():
        return values
    return np.interp(t, t[ok], values[ok])


def savgol_kernels(half: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Savitzky-Golay kernels (quadratic, window 2*half+1): smoothing, first and second derivative."""
    j = np.arange(-half, half + 1, dtype=float)
    pinv = np.linalg.pinv(np.vander(j, 3, increasing=True))
    return pinv[0][::-1], pinv[1][::-1], 2.0 * pinv[2][::-1]


def derivative_kernels(half: int) -> tuple[np.ndarray, np.ndarray]:
    """Savitzky-Golay kernels for the first and second derivative."""
    return savgol_kernels(half)[1:]
