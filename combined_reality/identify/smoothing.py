"""Savitzky-Golay smoothing and derivatives of sampled signals (position -> velocity,
acceleration): one kernel builder for every estimate the tool makes from measured motion."""
from __future__ import annotations

import functools

import numpy as np

__all__ = ["savgol_kernels", "derivative_kernels", "velocity_estimate", "fill_missing"]


def velocity_estimate(t: np.ndarray, x: np.ndarray, half: int = 10, edge: int = 3) -> np.ndarray:
    """Savitzky-Golay slope over +-half samples. Within `half` samples of an end the slope
    held from `half` samples in is kept, unless the motion at the end says otherwise beyond
    its noise: then the window shrinks to what the samples allow, down to a quadratic through
    the last 2*edge+1 samples evaluated at the end. (A run cut at lost samples often starts
    braking: the held slope called a piston at 80 mm/s resting, and its fit started in a wrong
    stick-slip basin; a piston at rest must stay at rest, or a stiction fit starts sliding.)
    Positions not measured (NaN) are interpolated first: an estimate for starting guesses and
    for sorting samples into regimes, not a measurement."""
    x = fill_missing(t, x)
    n = len(x)
    if n < 2 * edge + 1:
        return np.gradient(x, t)
    dt = np.median(np.diff(t))
    v = np.empty(n)
    h = min(half, (n - 1) // 2)
    v[h:n - h] = np.convolve(x, derivative_kernels(h)[0], mode="valid") / dt
    v[:h], v[n - h:] = v[h], v[n - h - 1]
    if h <= edge:
        return v
    kernels = _end_slope_kernels(h, edge)  # shrinking windows: sample i from the start
    k0 = kernels[0]
    # the position noise from second differences (robust: motion adds little at these rates)
    d2 = np.diff(x, 2)
    sigma_x = 1.4826 * float(np.median(np.abs(d2 - np.median(d2)))) / np.sqrt(6.0)
    noise = 3.0 * np.linalg.norm(k0) * sigma_x / dt
    if abs(k0 @ x[:len(k0)] / dt - v[h]) > noise:
        v[:h] = [k @ x[:len(k)] / dt for k in kernels]
    if abs(-k0[::-1] @ x[n - len(k0):] / dt - v[n - h - 1]) > noise:  # mirrored: slope sign flips
        v[n - h:] = [-k[::-1] @ x[n - len(k):] / dt for k in reversed(kernels)]
    return v


def fill_missing(t: np.ndarray, values: np.ndarray) -> np.ndarray:
    """`values` with the samples not measured (NaN) interpolated linearly in time, held at
    the ends: for starting guesses and estimates, never in place of a measurement."""
    ok = np.isfinite(values)
    if ok.all() or not ok.any():
        return values
    return np.interp(t, t[ok], values[ok])


@functools.lru_cache(maxsize=64)
def _quadratic_fit(half: int) -> np.ndarray:
    """Least-squares coefficients (rows: c0, c1, c2 of c0 + c1 j + c2 j^2) of samples j = -half..half."""
    pinv = np.linalg.pinv(np.vander(np.arange(-half, half + 1, dtype=float), 3, increasing=True))
    pinv.flags.writeable = False  # shared by every caller
    return pinv


@functools.lru_cache(maxsize=16)
def _end_slope_kernels(half: int, edge: int) -> tuple[np.ndarray, ...]:
    """For sample i = 0..half-1 of a signal: the kernel on its first len(kernel) samples that
    gives the slope there per sample (velocity_estimate's shrinking windows)."""
    out = []
    for i in range(half):
        w = max(i, edge)
        c = _quadratic_fit(w)
        k = c[1] + 2 * (i - w) * c[2]  # the quadratic's slope i samples in (i == w: centred)
        k.flags.writeable = False
        out.append(k)
    return tuple(out)


def savgol_kernels(half: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Savitzky-Golay kernels (quadratic, window 2*half+1): smoothing, first and second derivative."""
    pinv = _quadratic_fit(half)
    return pinv[0][::-1], pinv[1][::-1], 2.0 * pinv[2][::-1]


def derivative_kernels(half: int) -> tuple[np.ndarray, np.ndarray]:
    """Savitzky-Golay kernels for the first and second derivative."""
    return savgol_kernels(half)[1:]
