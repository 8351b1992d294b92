"""Savitzky-Golay smoothing and derivatives of sampled signals (position -> velocity,
acceleration): one kernel builder for every estimate the tool makes from measured motion."""
from __future__ import annotations

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
    lead, tail = np.empty(h), np.empty(h)  # shrinking windows, sample i from the start / the end
    end_kernel = np.zeros(0)
    for i in range(h):
        w = max(i, edge)
        if w == i:
            k = derivative_kernels(w)[0][::-1]  # convolve's kernel, flipped back for a dot product
            lead[i], tail[i] = k @ x[:2 * w + 1] / dt, k @ x[n - 2 * w - 1:] / dt
        else:  # the end quadratic, evaluated i samples in
            coef = np.linalg.pinv(np.vander(np.arange(-w, w + 1.0), 3, increasing=True))
            k = coef[1] + 2 * (i - w) * coef[2]
            end_kernel = end_kernel if i else k
            lead[i] = k @ x[:2 * w + 1] / dt
            tail[i] = -k[::-1] @ x[n - 2 * w - 1:] / dt
    # the position noise from second differences (robust: motion adds little at these rates)
    d2 = np.diff(x, 2)
    sigma_x = 1.4826 * float(np.median(np.abs(d2 - np.median(d2)))) / np.sqrt(6.0)
    noise = 3.0 * np.linalg.norm(end_kernel) * sigma_x / dt
    if abs(lead[0] - v[h]) > noise:
        v[:h] = lead
    if abs(tail[0] - v[n - h - 1]) > noise:
        v[n - h:] = tail[::-1]
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
