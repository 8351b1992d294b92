"""The gas and flow laws of the model contract: constants and the ISO 6358 valve flow.

Shared by the plant (valve paths), the effects (leak paths, supply draw) and the
application's closed-form estimates (test procedures, excitation), so that every one of
them uses the same law.
"""
from __future__ import annotations

import casadi as ca

# model contract constants
RHO0 = 1.185  # kg/m^3, ISO 6358 reference density
T0 = 293.15  # K, ISO 6358 reference temperature
R_LAM = 0.995  # start of the laminar end of the flow function
KAPPA = 1.4
R_AIR = 287.0  # J/(kg K)
G = 9.81


def flow_function(r, b):
    """ISO 6358 flow function phi(r) with the short laminar end of docs/model.md (0 <= r <= 1)."""
    a = (r - b) / (1 - b)
    phi_turb = ca.sqrt(ca.fmax(1 - a * a, 1e-300))
    a_lam = (R_LAM - b) / (1 - b)
    phi_lam = ca.sqrt(1 - a_lam * a_lam) * (1 - r) / (1 - R_LAM)
    return ca.if_else(r <= b, 1.0, ca.if_else(r <= R_LAM, phi_turb, phi_lam))


def choked_flow(conductance, p_up, temperature):
    """ISO 6358 mass flow through a path at the upstream pressure p_up when choked (phi = 1)."""
    return conductance * p_up * RHO0 * ca.sqrt(T0 / temperature)


def mass_flow(conductance, p_from, p_to, b, temperature):
    """Signed mass flow p_from -> p_to through one valve path (negative when p_to > p_from)."""
    pu = ca.fmax(p_from, p_to)
    pd = ca.fmin(p_from, p_to)
    m = choked_flow(conductance, pu, temperature) * flow_function(pd / pu, b)
    return ca.if_else(p_from >= p_to, m, -m)


def _pchip_slopes(rises, widths):
    """Knot slopes of the monotone piecewise-cubic interpolant (Fritsch and Carlson, with the
    weighted harmonic mean of Fritsch and Butland; as scipy's PchipInterpolator) through the
    levels whose rises over segments of `widths` are given (rises >= 0: a monotone curve)."""
    d = [r / h for r, h in zip(rises, widths)]  # secants
    slopes = []
    for k in range(len(d) + 1):
        if k == 0 or k == len(d):  # an end: the one-sided three-point estimate, kept monotone
            if len(d) == 1:
                slopes.append(d[0])
                continue
            i, j = (0, 1) if k == 0 else (len(d) - 1, len(d) - 2)
            h0, h1 = widths[i], widths[j]
            m = ((2 * h0 + h1) * d[i] - h0 * d[j]) / (h0 + h1)
            m = ca.if_else(m <= 0, 0.0, ca.if_else((d[j] <= 0) * (m > 3 * d[i]), 3 * d[i], m))
            slopes.append(ca.if_else(d[i] <= 0, 0.0, m))
            continue
        h0, h1 = widths[k - 1], widths[k]
        w1, w2 = 2 * h1 + h0, h1 + 2 * h0
        harmonic = (w1 + w2) / (w1 / ca.fmax(d[k - 1], 1e-300) + w2 / ca.fmax(d[k], 1e-300))
        slopes.append(ca.if_else(d[k - 1] * d[k] <= 0, 0.0, harmonic))
    return slopes


def flow_characteristic(s, rises, grid):
    """The valve's flow characteristic at the opening s in [0, 1] beyond the overlap: the
    monotone piecewise-cubic (PCHIP) curve through (0, 0) and the levels its `rises` reach at
    the openings `grid` (ending at 1). Symbolic or numeric (casadi DM: elementwise over a
    column of openings)."""
    widths = [hi - lo for lo, hi in zip((0.0, *grid[:-1]), grid)]
    m = _pchip_slopes(rises, widths)
    g, lo = 0.0, 0.0
    for k, (rise, hi, h) in enumerate(zip(rises, grid, widths)):
        t = ca.fmin(ca.fmax((s - lo) / h, 0.0), 1.0)  # 0 before the segment, 1 beyond it
        # the Hermite cubic's rise within the segment: 0 at t = 0, the whole rise at t = 1
        g = g + rise * t * t * (3 - 2 * t) + h * (m[k] * t * (1 - t) ** 2 - m[k + 1] * t * t * (1 - t))
        lo = hi
    return g
