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
