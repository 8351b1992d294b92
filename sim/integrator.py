"""One sample of the plant: an L-stable Rosenbrock step with local refinement, in CasADi.

Why this scheme: with v_smooth = 1 mm/s the friction term has time constants near
0.05 ms and the valve's laminar end makes the pressures stiff as well, so explicit
methods would need ~50 substeps per 1 ms sample. RA34PW2 (Rang & Angermann 2005, the
PETSc default Rosenbrock-W method: order 3, L-stable, stiffly accurate, embedded
order-2 error estimate) is linearly implicit, so a step is a fixed sequence of
expressions that CasADi differentiates and compiles. Sub-sample events (velocity
reversals, breakaway) are refined by step doubling behind a short-circuiting
`Function.conditional`: only the ~2 % of samples that need it pay for it. The switch
is a deterministic function of state and input, so simulator and identifier see the
very same trajectory.

Inputs are either held (the valve command, zero-order hold, docs/model.md)
or linearly interpolated across the sample (measured pressures in the pressure drive,
measured position and velocity in the chambers drive); the latter are carried as
auxiliary states with constant slope so the step stays autonomous and keeps its order.
"""
from __future__ import annotations

from dataclasses import astuple, dataclass, fields, replace
from typing import Sequence

import casadi as ca
import numpy as np

from .plant import Plant

# RA34PW2 in the (A, Gamma, b) form: k_i = h f(y + sum a_ij k_j) + h J sum_{j<=i} gamma_ij k_j
_A = np.array([[0, 0, 0, 0],
               [8.7173304301691801e-01, 0, 0, 0],
               [8.4457060015369423e-01, -1.1299064236484185e-01, 0, 0],
               [0, 0, 1.0, 0]])
_GAMMA = np.array([[4.3586652150845900e-01, 0, 0, 0],
                   [-8.7173304301691801e-01, 4.3586652150845900e-01, 0, 0],
                   [-9.0338057013044082e-01, 5.4180672388095326e-02, 4.3586652150845900e-01, 0],
                   [2.4212380706095346e-01, -1.2232505839045147e+00, 5.4526025533510214e-01, 4.3586652150845900e-01]])
_B = np.array([2.4212380706095346e-01, -1.2232505839045147e+00, 1.5452602553351020e+00, 4.3586652150845900e-01])
_B_EMBEDDED = np.array([3.7810903145819369e-01, -9.6042292212423178e-02, 5.0e-01, 2.1793326075422950e-01])


@dataclass(frozen=True)
class IntegratorOptions:
    """Local error tolerance per state (absolute, SI) and the deepest refinement.

    Defaults keep a 20 s closed-loop trajectory within a small fraction of the sensor
    noise of a reference solution (tests/test_integrator.py). They are 10x tighter than
    that alone needs: looser tolerances still fit to the noise but bias the viscous
    coefficient by ~2 reported standard deviations (measured over seeds).
    """

    tol_pressure: float = 1.0  # Pa
    tol_position: float = 1e-8  # m
    tol_velocity: float = 1e-5  # m/s
    tol_other: float = 1e-5  # effect states
    max_depth: int = 5  # up to 2**5 = 32 substeps in one sample

    def scaled(self, factor: float) -> "IntegratorOptions":
        """Every tolerance times factor."""
        tols = [f.name for f in fields(self) if f.name.startswith("tol_")]
        return replace(self, **{n: getattr(self, n) * factor for n in tols})

    def key(self) -> tuple:
        return astuple(self)


# Accurate enough to serve as truth for the identifier's own discretisation.
TRUTH_OPTIONS = IntegratorOptions().scaled(0.05)


def _state_tolerances(plant: Plant, opts: IntegratorOptions) -> np.ndarray:
    tol = {"p1": opts.tol_pressure, "p2": opts.tol_pressure, "x": opts.tol_position, "v": opts.tol_velocity}
    return np.array([tol.get(n, opts.tol_other) for n in plant.state_names])


def _lu_solver(M: ca.SX):
    """Factor a small symbolic matrix once (no pivoting: I - h*gamma*J is dominated by its
    diagonal for this plant) and return a solve(b) that reuses the factors, skipping
    structural zeros."""
    n = M.shape[0]
    U = [[M[i, j] for j in range(n)] for i in range(n)]
    L = [[None] * n for _ in range(n)]
    for k in range(n):
        for i in range(k + 1, n):
            if ca.SX(U[i][k]).is_zero():
                continue
            L[i][k] = U[i][k] / U[k][k]
            for j in range(k, n):
                U[i][j] = U[i][j] - L[i][k] * U[k][j]

    def solve(b: ca.SX) -> ca.SX:
        y = [b[i] for i in range(n)]
        for i in range(n):
            for k in range(i):
                if L[i][k] is not None:
                    y[i] = y[i] - L[i][k] * y[k]
        x = [None] * n
        for i in reversed(range(n)):
            s = y[i]
            for j in range(i + 1, n):
                if not ca.SX(U[i][j]).is_zero():
                    s = s - U[i][j] * x[j]
            x[i] = s / U[i][i]
        return ca.vertcat(*x)

    return solve


class StepBuilder:
    """Builds the one-sample step functions of a plant.

    Signature of every step function: (x, w0, w1, p, h) -> x_next, where w0 is the
    input at the start of the sample and w1 at its end (w1 is ignored for held inputs).
    """

    def __init__(self, plant: Plant, opts: IntegratorOptions = IntegratorOptions()):
        self.plant = plant
        self.opts = opts
        # measured signals vary continuously; the valve command is held (zero-order hold)
        self.held = np.array([n == "u" for n in plant.input_names])
        self.interpolate = not self.held.all()
        self.nx = plant.nx
        self.nw = len(plant.input_names)
        self.npar = len(plant.param_names)
        self._inv_tol = 1.0 / _state_tolerances(plant, opts)

    # ---------------------------------------------------------------- symbolic pieces
    def _symbols(self):
        return (ca.SX.sym("x", self.nx), ca.SX.sym("w0", self.nw), ca.SX.sym("w1", self.nw),
                ca.SX.sym("p", self.npar), ca.SX.sym("h"))

    def rosenbrock(self, x, w0, w1, p, h) -> tuple[ca.SX, ca.SX]:
        """One RA34PW2 step over h (SX): (x_next, scaled error estimate)."""
        rhs = self.plant.rhs
        if self.interpolate:
            # augmented autonomous system z = (x, w) with dw/dt = (w1 - w0)/h over the step
            slope = ca.if_else(h > 0, (w1 - w0) / ca.fmax(h, 1e-300), 0 * w0) * ca.DM(1.0 - self.held)
            z = ca.vertcat(x, w0)

            def f(zz):
                return ca.vertcat(rhs(zz[: self.nx], zz[self.nx:], p), slope)
        else:
            z = x

            def f(zz):
                return rhs(zz, w0, p)
        nz = z.shape[0]
        J = ca.jacobian(f(z), z)  # z is a vector of pure symbols here
        solve = _lu_solver(ca.SX.eye(nz) - h * _GAMMA[0, 0] * J)
        ks: list[ca.SX] = []
        for i in range(4):
            zi = z
            for j in range(i):
                if _A[i, j]:
                    zi = zi + _A[i, j] * ks[j]
            r = h * f(zi)
            corr = None
            for j in range(i):
                if _GAMMA[i, j]:
                    corr = _GAMMA[i, j] * ks[j] if corr is None else corr + _GAMMA[i, j] * ks[j]
            if corr is not None:
                r = r + h * ca.mtimes(J, corr)
            ks.append(solve(r))
        z_next = z + sum(_B[i] * ks[i] for i in range(4))
        err = sum((_B[i] - _B_EMBEDDED[i]) * ks[i] for i in range(4))[: self.nx]
        return z_next[: self.nx], ca.mmax(ca.fabs(err * ca.DM(self._inv_tol)))

    def step(self) -> ca.Function:
        """The adaptive one-sample step (x, w0, w1, p, h) -> x_next."""
        x, w0, w1, p, h = self._symbols()
        xn, err = self.rosenbrock(x, w0, w1, p, h)
        xn, err = ca.cse([xn, err])
        coarse = ca.Function("rb_step", [x, w0, w1, p, h], [xn, err], ["x", "w0", "w1", "p", "h"], ["xn", "err"])
        return self._refine(coarse, self.opts.max_depth, "step")

    def _refine(self, coarse: ca.Function, depth: int, name: str) -> ca.Function:
        """coarse: (x, w0, w1, p, h, *carried) -> (*outputs, err). The result keeps the
        coarse outputs when err <= 1, else takes two refined half steps (recursively); the
        coarse step is evaluated once and only the refinement sits behind the switch.
        The switch depends only on the state's error estimate, so a variant that also carries
        sensitivities (inputs after h) takes exactly the same path."""
        n_out = coarse.n_out() - 1
        sym = [ca.MX.sym(n, *coarse.sparsity_in(i).shape) for i, n in enumerate(coarse.name_in())]
        res = coarse.call(sym)
        outs, err = res[:n_out], res[n_out]
        names_out = coarse.name_out()[:n_out]
        if depth == 0:
            return ca.Function(f"{name}_d0", sym, outs, coarse.name_in(), names_out)
        half = self._refine(coarse, depth - 1, name)
        x, w0, w1, p, h = sym[:5]
        # interpolated inputs split at the midpoint; a held input stays held in both halves
        wm = w0 + 0.5 * (w1 - w0) * ca.DM(1.0 - self.held) if self.interpolate else w0
        first = half.call([x, w0, wm, p, h / 2, *sym[5:]])
        second = half.call([first[0], wm, w1, p, h / 2, *first[1:]])
        held = [ca.MX.sym(f"coarse_{n}", *coarse.sparsity_out(i).shape) for i, n in enumerate(names_out)]
        keep = ca.Function(f"{name}_keep{depth}", held + sym, held)
        fine = ca.Function(f"{name}_fine{depth}", held + sym, second)
        switch = ca.Function.conditional(f"{name}_sw{depth}", [keep], fine)
        out = switch.call([err > 1, *outs, *sym])
        return ca.Function(f"{name}_d{depth}", sym, out, coarse.name_in(), names_out)

    def sensitivity_step(self, free: Sequence[int]) -> ca.Function:
        """(x, w0, w1, p, h, S) -> (x_next, S_next), S = d x / d (x_start, p[free])."""
        free = list(free)
        nz = self.nx + len(free)

        x, w0, w1, p, h = self._symbols()
        S = ca.SX.sym("S", self.nx, nz)
        xn, err = self.rosenbrock(x, w0, w1, p, h)
        Fx = ca.jacobian(xn, x)
        Fp = ca.jacobian(xn, ca.vertcat(*[p[i] for i in free]))
        Sn = ca.mtimes(Fx, S) + ca.horzcat(ca.SX.zeros(self.nx, self.nx), Fp)
        xn, Sn, err = ca.cse([xn, Sn, err])
        coarse = ca.Function("rb_sens", [x, w0, w1, p, h, S], [xn, Sn, err],
                             ["x", "w0", "w1", "p", "h", "S"], ["xn", "Sn", "err"])
        return self._refine(coarse, self.opts.max_depth, "sens")
