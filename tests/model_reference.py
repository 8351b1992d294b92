"""An independent plain-NumPy transcription of MODEL.md, used only as a test oracle.

Written from the contract text, not from sim/, so that a disagreement points at one of them.
"""
import math

import numpy as np

RHO0, T0, R_LAM, KAPPA, R, G = 1.185, 293.15, 0.995, 1.4, 287.0, 9.81


def phi(r, b):
    if r <= b:
        return 1.0
    if r <= R_LAM:
        return math.sqrt(1 - ((r - b) / (1 - b)) ** 2)
    return math.sqrt(1 - ((R_LAM - b) / (1 - b)) ** 2) * (1 - r) / (1 - R_LAM)


def mdot(C, p_from, p_to, b, T):
    if C == 0:
        return 0.0
    if p_from >= p_to:
        return C * p_from * RHO0 * math.sqrt(T0 / T) * phi(p_to / p_from, b)
    return -C * p_to * RHO0 * math.sqrt(T0 / T) * phi(p_from / p_to, b)


def rhs(state, u, cyl):
    p1, p2, x, v = state
    g, m, s, va, f = cyl.geometry, cyl.mechanics, cyl.supply, cyl.valve, cyl.friction
    A1 = math.pi * g.bore ** 2 / 4
    A2 = math.pi * (g.bore ** 2 - g.rod ** 2) / 4
    V1 = g.dead_volume_cap + A1 * x
    V2 = g.dead_volume_rod + A2 * (g.stroke - x)
    u = min(max(u, -1.0), 1.0)
    C = va.sonic_conductance * abs(u)
    if u >= 0:
        m1 = mdot(C, s.pressure, p1, va.critical_ratio, s.temperature)
        m2 = mdot(C, s.atmosphere, p2, va.critical_ratio, s.temperature)
    else:
        m1 = mdot(C, s.atmosphere, p1, va.critical_ratio, s.temperature)
        m2 = mdot(C, s.pressure, p2, va.critical_ratio, s.temperature)
    T = s.temperature
    dp1 = KAPPA / V1 * (R * T * m1 - p1 * A1 * v)
    dp2 = KAPPA / V2 * (R * T * m2 + p2 * A2 * v)
    Ff = (f.Fc + f.kp * abs(p1 - p2)) * math.tanh(v / f.v_smooth) + f.Fv * v
    dv = (p1 * A1 - p2 * A2 - s.atmosphere * (A1 - A2) - Ff - m.moving_mass * G * math.sin(m.angle)) / m.moving_mass
    return np.array([dp1, dp2, v, dv])
