"""An independent plain-Python transcription of docs/model.md, sharing no code with sim/.

The test oracle for the CasADi plant (tests/test_plant.py) and the model of the scipy
baseline in benchmarks/identify_speed.py, so a disagreement points at one of them.
"""
import math

RHO0, T0, R_LAM, KAPPA, R_AIR, G = 1.185, 293.15, 0.995, 1.4, 287.0, 9.81


class ReferenceModel:
    """The docs/model.md right-hand side in plain Python scalars (math is faster than numpy on scalars)."""

    def __init__(self, cyl):
        g = cyl.geometry
        self.A1 = math.pi * g.bore**2 / 4
        self.A2 = math.pi * (g.bore**2 - g.rod**2) / 4
        self.L, self.V01, self.V02 = g.stroke, g.dead_volume_cap, g.dead_volume_rod
        self.M, self.angle = cyl.mechanics.moving_mass, cyl.mechanics.angle
        self.ps, self.pa, self.T = cyl.supply.pressure, cyl.supply.atmosphere, cyl.supply.temperature
        self.C, self.b = cyl.valve.sonic_conductance, cyl.valve.critical_ratio
        self.vs = cyl.friction.v_smooth
        self.rho = RHO0 * math.sqrt(T0 / self.T)
        self.phi_lam = math.sqrt(1 - ((R_LAM - self.b) / (1 - self.b)) ** 2)  # phi at r = r_lam

    def mdot(self, c: float, p_from: float, p_to: float) -> float:
        """ISO 6358 mass flow p_from -> p_to (negative for back-flow), with the laminar end."""
        if c <= 0.0:
            return 0.0
        pu, pd = (p_from, p_to) if p_from >= p_to else (p_to, p_from)
        r, b = pd / pu, self.b
        if r <= b:
            phi = 1.0
        elif r <= R_LAM:
            phi = math.sqrt(1 - ((r - b) / (1 - b)) ** 2)
        else:
            phi = self.phi_lam * (1 - r) / (1 - R_LAM)
        m = c * pu * self.rho * phi
        return m if p_from >= p_to else -m

    def rhs(self, t, y, u, Fc, Fv, kp):
        p1, p2, x, v = y
        u = min(max(u, -1.0), 1.0)
        c_pos, c_neg = self.C * max(u, 0.0), self.C * max(-u, 0.0)
        m1 = self.mdot(c_pos, self.ps, p1) + self.mdot(c_neg, self.pa, p1)
        m2 = self.mdot(c_neg, self.ps, p2) + self.mdot(c_pos, self.pa, p2)
        A1, A2 = self.A1, self.A2
        V1, V2 = self.V01 + A1 * x, self.V02 + A2 * (self.L - x)
        Ff = (Fc + kp * abs(p1 - p2)) * math.tanh(v / self.vs) + Fv * v
        dv = (p1 * A1 - p2 * A2 - self.pa * (A1 - A2) - Ff - self.M * G * math.sin(self.angle)) / self.M
        return [KAPPA / V1 * (R_AIR * self.T * m1 - p1 * A1 * v),
                KAPPA / V2 * (R_AIR * self.T * m2 + p2 * A2 * v), v, dv]
