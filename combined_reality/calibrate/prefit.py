"""Linear starts for calibration, from the measured signals alone (equation error).

The piston's force balance with the measured pressures is linear in the friction, the moving
mass and a constant force; so least squares on it gives their start without any simulation (the
Newton's-law least-squares friction fit of Trentini et al., seed 000, with the mass and a
constant force added). Its constant force also absorbs the pressure sensors' offsets (o1 A1 - o2
A2), which the force balance alone cannot tell from an external force."""
from __future__ import annotations

from typing import Sequence

import casadi as ca
import numpy as np
from scipy.optimize import lsq_linear

from sim.compiled import compiled_columns
from sim.cylinder import OPENING_GRID, Cylinder
from sim.flow import G, KAPPA, R_AIR, mass_flow
from sim.plant import MODEL_REVISION

from ..files import Run
from ..identify import savgol_kernels, scaled_lstsq

__all__ = ["force_balance_prefit", "breakaway_forces", "stiction_prefit", "settled_offsets", "chamber_prefit",
           "unit_flows", "opening_basis"]

_P_FROM, _P_TO, _B, _T = (ca.SX.sym(n) for n in ("p_from", "p_to", "b", "T"))
SMOOTH = 0.02  # weight of the slope-continuity rows of the flow characteristic, relative to the data
OVERLAP_MAX = 0.2  # the largest overlap the linear start considers
OVERLAP_TIE = 0.002  # overlaps whose cost is within this share of the searched costs' span count as a tie
# the chambers' least squares is formed this many rows at a time (a row per chamber and block of
# samples: 327 s of data at 1 kHz), so that its memory does not grow with the runs beyond their rows
ROWS_AT_ONCE = 1 << 16


def force_balance_prefit(cyl: Cylinder, runs: Sequence[Run], half: int = 15) -> dict[str, float]:
    """Fc, Fv, kp, mass and external_force by linear least squares on Newton's law with the
    measured pressures, from the samples where the piston slides freely (away from the end
    stops, |v| well above the friction smoothing). Empty if the runs barely move."""
    g = cyl.geometry
    A1, A2, pa = g.area_cap, g.area_rod, cyl.supply.atmosphere
    _, k1, k2 = savgol_kernels(half)
    rows, rhs = [], []
    for r in runs:
        if r.n < 4 * half:
            continue
        dt = r.sample_period
        idx = np.arange(half, r.n - half)
        v = np.convolve(r.x, k1, mode="same")[idx] / dt
        a = np.convolve(r.x, k2, mode="same")[idx] / dt**2
        x, p1, p2 = r.x[idx], r.p1[idx], r.p2[idx]
        margin = 0.01 * g.stroke  # the end stops' force is not in this balance
        free = (np.abs(v) > max(20 * cyl.friction.v_smooth, 0.005)) & (x > margin) & (x < g.stroke - margin)
        if not free.any():
            continue
        sgn = np.sign(v[free])
        force = (p1 * A1 - p2 * A2 - pa * (A1 - A2))[free]
        # force = M (a + g sin(angle)) + Fc sgn + kp sgn |p1 - p2| + Fv v - F_ext
        rows.append(np.column_stack([a[free] + G * np.sin(cyl.mechanics.angle), sgn,
                                     sgn * np.abs(p1 - p2)[free], v[free], -np.ones(free.sum())]))
        rhs.append(force)
    if not rows or sum(len(b) for b in rhs) < 100:
        return {}
    sol = scaled_lstsq(np.vstack(rows), np.concatenate(rhs))
    if sol is None:
        return {}
    M, Fc, kp, Fv, F_ext = (float(s) for s in sol)
    out = {"Fc": max(Fc, 0.0), "kp": max(kp, 0.0), "Fv": max(Fv, 0.0), "external_force": F_ext}
    if M > 0.2 * cyl.mechanics.moving_mass:  # accelerations too weak to weigh it: keep the file's
        out["mass"] = M
    return out


# a break-away: the piston still (|v| under STILL) for STUCK_S at least, then sliding beyond SLIDING
# within ONSET_S; its force is the largest pressure force towards the motion in the last PEAK_S
# before the onset. Velocities of a short Savitzky-Golay window (11 ms): a slip lasts some 30 ms
STILL, SLIDING = 2e-3, 5e-3  # m/s
STUCK_S, ONSET_S, PEAK_S = 0.02, 0.05, 0.03
# a start where the piston sticks and slips: this many break-aways per direction at least (a rig
# without stiction gives its ordinary starts from rest, 1-14 per direction on the gauntlet's 20 s
# calibration runs, a stick-slip one 10-55), and static friction STICK_SLIP above the seal level
BREAKAWAYS_MIN = 10
STICK_SLIP = 0.1


def breakaway_forces(cyl: Cylinder, runs: Sequence[Run], half: int = 5) -> list[tuple[float, float, float]]:
    """(direction +1/-1, pressure force at break-away, |p1 - p2| there) of every break-away from
    rest away from the end stops: the pressure force (p1 A1 - p2 A2 - pa (A1 - A2), the pressures
    less `cyl`'s offsets) then holds the external force plus the static friction towards the motion."""
    g = cyl.geometry
    A1, A2, pa, margin = g.area_cap, g.area_rod, cyl.supply.atmosphere, 0.01 * g.stroke
    _, k1, _ = savgol_kernels(half)
    out = []
    for r in runs:
        if r.n < 4 * half:
            continue
        dt = r.sample_period
        v = np.convolve(r.x, k1, mode="same") / dt
        v[:half] = v[-half:] = np.nan  # no derivative at the ends
        p1, p2 = r.p1 - cyl.sensors.offset_p1, r.p2 - cyl.sensors.offset_p2
        force = p1 * A1 - p2 * A2 - pa * (A1 - A2)
        edges = np.diff(np.r_[0, (np.abs(v) < STILL).astype(np.int8), 0])
        ahead, peak = int(round(ONSET_S / dt)), int(round(PEAK_S / dt))
        for i0, i1 in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)):
            if (i1 - i0) * dt < STUCK_S or i1 + ahead > r.n or not margin < r.x[i1] < g.stroke - margin:
                continue
            moving = np.abs(v[i1:i1 + ahead]) > SLIDING
            if not moving.any():
                continue
            k = i1 + int(np.argmax(moving))
            d = float(np.sign(v[k]))
            w = slice(max(i0, i1 - peak), k + 1)
            j = w.start + int(np.argmax(d * force[w]))
            out.append((d, float(force[j]), float(abs(p1[j] - p2[j]))))
    return out


def stiction_prefit(cyl: Cylinder, runs: Sequence[Run]) -> dict[str, float]:
    """The break-away force above the seal level (Fs_excess) and the external force from the
    break-aways of both directions (breakaway_forces): the median force of each direction less
    `cyl`'s pressure friction (kp |p1 - p2|) is (Fc + Fs) - F_ext extending and -(Fc + Fs) - F_ext
    retracting (`cyl`'s Fc). Empty where either direction breaks away fewer than BREAKAWAYS_MIN
    times or the static friction exceeds the seal level by less than STICK_SLIP of the break-away
    force: no stick-slip to start from."""
    kp, Fc = cyl.friction.kp, cyl.friction.Fc
    found = {d: [f - d * kp * dp for e, f, dp in breakaway_forces(cyl, runs) if e == d] for d in (1.0, -1.0)}
    if min(len(f) for f in found.values()) < BREAKAWAYS_MIN:
        return {}
    up, down = float(np.median(found[1.0])), float(np.median(found[-1.0]))
    excess = 0.5 * (up - down) - Fc
    if excess < STICK_SLIP * (excess + Fc):
        return {}
    return {"Fs_excess": excess, "external_force": -0.5 * (up + down)}


def settled_offsets(cyl: Cylinder, runs: Sequence[Run], half: int = 10) -> dict[str, float]:
    """The pressure sensors' offsets from where the truth is known: at rest against an end
    stop with the valve open, the filling chamber settles at the supply pressure and the
    exhausting one at atmosphere. Medians over the settled samples; empty when no run holds
    against an end long enough (the valve's law then ties the offsets down in the fit)."""
    L, ps, pa = cyl.geometry.stroke, cyl.supply.pressure, cyl.supply.atmosphere
    k0, k1, _ = savgol_kernels(half)
    found: dict[str, list[np.ndarray]] = {"offset_p1": [], "offset_p2": []}
    for r in runs:
        if r.n < 4 * half:
            continue
        dt = r.sample_period
        v = np.convolve(r.x, k1, mode="same") / dt
        d1, d2 = (np.abs(np.convolve(p, k1, mode="same")) / dt for p in (r.p1, r.p2))
        inner = np.zeros(r.n, bool)
        inner[half:-half] = True
        # at rest against an end, pushed there by an open valve, pressures no longer moving
        calm = inner & (np.abs(v) < 1e-3) & (np.abs(r.u) > 0.05) & (d1 < 2e4) & (d2 < 2e4)
        out_end = calm & (r.x > L - 2e-4) & (r.u > 0)
        in_end = calm & (r.x < 2e-4) & (r.u < 0)
        found["offset_p1"] += [r.p1[out_end] - ps, r.p1[in_end] - pa]
        found["offset_p2"] += [r.p2[out_end] - pa, r.p2[in_end] - ps]
    out = {}
    for name, parts in found.items():
        vals = np.concatenate(parts) if parts else np.empty(0)
        if vals.size >= 100:
            out[name] = float(np.median(vals))
    return out


def unit_flows(cyl: Cylinder, p_from, p_to, critical_ratio: float) -> np.ndarray:
    """Mass flow per unit sonic conductance from p_from to p_to (the valve's law of sim.flow,
    evaluated on arrays)."""
    fn = ca.Function("unit_flow", [_P_FROM, _P_TO, _B, _T], [mass_flow(1.0, _P_FROM, _P_TO, _B, _T)])
    flows = compiled_columns(fn, "unit_flow_cols", ("unit_flow", MODEL_REVISION), 2)  # the law is the plant's
    return flows(np.ravel(p_from), np.ravel(p_to), critical_ratio, cyl.supply.temperature).ravel()


def opening_basis(a: np.ndarray, overlap: float) -> np.ndarray:
    """The flow characteristic's value at |u| = a as a linear function of its rises, (n, grid):
    straight between the grid points (the plant's monotone cubic is not linear in the rises;
    for a start, the straight segments through the same levels serve)."""
    s = np.maximum(a - overlap, 0.0) / (1.0 - overlap)
    lo = np.r_[0.0, OPENING_GRID[:-1]]
    hi = np.asarray(OPENING_GRID)
    return np.clip((s[:, None] - lo) / (hi - lo), 0.0, 1.0)


def chamber_prefit(cyl: Cylinder, runs: Sequence[Run], offsets: dict[str, float] | None = None,
                   block: int = 10) -> dict[str, float]:
    """The flow characteristic (overlap and rises per direction) and both dead volumes by
    linear least squares on the chambers' mass balance with the measured signals, summed over
    blocks of `block` samples so that every sample's own held command counts:

        sum_j (V0 + A x_j) (p_j+1 - p_j) / kappa = sum_j dt (C(u_j) q_j R T - p_j A (x_j+1 - x_j)/dt)

    (chamber 1; chamber 2 with its own volume and the sign of its work), q the mass flow per
    unit conductance of the open path at the sample's mean pressure (the valve's law, at the
    file's critical ratio). Linear in the rises and V0 for a given overlap; the overlap of each
    direction is searched on a grid. Rows are weighted by kappa / V (pressure units). Empty if
    the runs do not open the valve."""
    rows = _chamber_rows(cyl, runs, offsets, block)
    if rows is None:
        return {}
    K = len(OPENING_GRID)
    fit = _ChamberFit(*(rows[k] for k in ("ch", "u", "q", "v0", "rhs", "w")))
    overlaps = _search_overlaps(fit)
    _, sol = fit.solve((overlaps[0], overlaps[1]))
    out = {"overlap_extend": overlaps[0], "overlap_retract": overlaps[1],
           "dead_volume_cap": float(sol[2 * K]), "dead_volume_rod": float(sol[2 * K + 1])}
    for d, name in enumerate(("extend", "retract")):
        for k in range(K):
            out[f"flow_{name}_{k + 1}"] = float(sol[d * K + k])
    return out


def _blocksum(y: np.ndarray, nb: int, block: int) -> np.ndarray:
    return y.reshape(nb, block).sum(axis=1)


def _chamber_rows(cyl: Cylinder, runs: Sequence[Run], offsets: dict[str, float] | None,
                  block: int) -> dict[str, np.ndarray] | None:
    """The mass balance's rows of both chambers of every run, one per block of samples: the chamber,
    each sample's command and unit flow, the dead volume's column, the right-hand side and the
    row weight. None if no run holds a whole block."""
    off = {"offset_p1": cyl.sensors.offset_p1, "offset_p2": cyl.sensors.offset_p2, **(offsets or {})}
    g, T, b = cyl.geometry, cyl.supply.temperature, cyl.valve.critical_ratio
    ps, pa, L = cyl.supply.pressure, cyl.supply.atmosphere, g.stroke
    C = cyl.valve.sonic_conductance
    parts: list[dict[str, np.ndarray]] = []
    for r in runs:
        nb = (r.n - 1) // block
        if nb < 1:
            continue
        n = nb * block + 1
        dt, x, u = np.diff(r.t[:n]), r.x[:n], r.u[:n - 1]
        dx = np.diff(x)
        for ch, pm, area in ((0, r.p1[:n], g.area_cap), (1, r.p2[:n], g.area_rod)):
            p = pm - off[f"offset_p{ch + 1}"]
            pmid = 0.5 * (p[1:] + p[:-1])
            sources = (ps, pa) if ch == 0 else (pa, ps)  # the open path's other side: extend, retract
            q = np.where(u > 0, unit_flows(cyl, np.full(n - 1, sources[0]), pmid, b),
                         unit_flows(cyl, np.full(n - 1, sources[1]), pmid, b)) * C * R_AIR * T * dt
            sign = 1.0 if ch == 0 else -1.0
            vol = (g.dead_volume_cap + area * x[:-1]) if ch == 0 else (g.dead_volume_rod + area * (L - x[:-1]))
            v0 = g.dead_volume_cap if ch == 0 else g.dead_volume_rod
            dp = np.diff(p)
            parts.append({"ch": np.full(nb, ch), "u": u.reshape(nb, block), "q": q.reshape(nb, block),
                          "v0": _blocksum(dp, nb, block) / KAPPA,
                          "rhs": _blocksum((vol - v0) * dp, nb, block) / KAPPA
                          + _blocksum(pmid * sign * area * dx, nb, block),
                          "w": KAPPA / vol.reshape(nb, block).mean(axis=1)})
    if not parts:
        return None
    return {k: np.concatenate([part[k] for part in parts]) for k in parts[0]}


class _ChamberFit:
    """The bounded least squares of the chambers' rows for given overlaps: the rises of both
    directions (tied weakly by slope continuity, so that segments the runs hardly open still get
    a value: rows SMOOTH * (rise_k/w_k - rise_k-1/w_k-1)) and both dead volumes."""

    def __init__(self, chamber: np.ndarray, ub: np.ndarray, qb: np.ndarray, v0col: np.ndarray, rhs: np.ndarray,
                 w: np.ndarray):
        self.chamber, self.ub, self.qb, self.v0col, self.rhs, self.w = chamber, ub, qb, v0col, rhs, w
        self.widths = np.diff(np.r_[0.0, OPENING_GRID])
        self.weight = np.sqrt(np.mean((rhs * w) ** 2))  # the data rows' typical size
        self.opens = (ub > 0, ub < 0)  # per direction, the samples that open it
        # per direction, the overlap last asked for and its rises: the search asks for the other
        # direction's again and again (more would hold K numbers a row for every overlap searched)
        self.columns: dict[int, tuple[float, np.ndarray]] = {}

    def rises(self, d: int, overlap: float) -> np.ndarray:
        """Each sample's rises of direction d summed in its block's row, (rows, K)."""
        if d not in self.columns or self.columns[d][0] != overlap:
            out = np.empty((len(self.ub), len(OPENING_GRID)))
            step = max(1, ROWS_AT_ONCE // self.ub.shape[1])  # rows of every sample's rises at a time
            for a in range(0, len(self.ub), step):
                ub, qb, sel = (v[a:a + step] for v in (self.ub, self.qb, self.opens[d]))
                per_sample = np.zeros(ub.shape + (len(OPENING_GRID),))
                per_sample[sel] = opening_basis(np.abs(ub[sel]), overlap) * qb[sel][:, None]
                out[a:a + step] = per_sample.sum(axis=1)
            self.columns[d] = (overlap, out)
        return self.columns[d][1]

    def _rows(self, overlaps: tuple[float, float], a: int) -> tuple[np.ndarray, np.ndarray]:
        """(Aw, bw): the weighted rows a..a+ROWS_AT_ONCE of the least squares and their right-hand side."""
        K = len(OPENING_GRID)
        b = min(a + ROWS_AT_ONCE, len(self.rhs))
        A = np.zeros((b - a, 2 * K + 2))
        for d in (0, 1):
            A[:, d * K:(d + 1) * K] = self.rises(d, overlaps[d])[a:b]
        chamber, v0col = self.chamber[a:b], self.v0col[a:b]
        A[chamber == 0, 2 * K] = -v0col[chamber == 0]
        A[chamber == 1, 2 * K + 1] = -v0col[chamber == 1]
        w = self.w[a:b]
        return A * w[:, None], self.rhs[a:b] * w

    def solve(self, overlaps: tuple[float, float]) -> tuple[float, np.ndarray]:
        """(the residual cost, the rises of both directions and the two dead volumes)."""
        K, widths = len(OPENING_GRID), self.widths
        smooth = np.zeros((2 * (K - 1), 2 * K + 2))
        for d in (0, 1):
            for k in range(1, K):
                smooth[d * (K - 1) + k - 1, d * K + k] = 1.0 / widths[k]
                smooth[d * (K - 1) + k - 1, d * K + k - 1] = -1.0 / widths[k - 1]
        # the bounded problem on the Cholesky factor of the normal equations of [Aw; smooth] (scaled
        # columns): as small as the number of unknowns, whatever the number of samples; the rows'
        # sums are taken ROWS_AT_ONCE rows at a time
        starts = range(0, len(self.rhs), ROWS_AT_ONCE)
        norms = np.sqrt(sum(np.sum(self._rows(overlaps, a)[0] ** 2, axis=0) for a in starts))
        scale = np.maximum(norms, 1e-6 * norms.max())  # a segment no sample opens: its prior decides
        Ss = SMOOTH * self.weight * smooth / scale
        normal, rhs = 0.0, 0.0
        for a in starts:
            Aw, bw = self._rows(overlaps, a)
            As = Aw / scale
            normal, rhs = normal + As.T @ As, rhs + As.T @ bw
        normal = normal + Ss.T @ Ss
        R = np.linalg.cholesky(normal + 1e-12 * np.eye(len(normal))).T
        target = np.linalg.solve(R.T, rhs)
        bw = self.rhs * self.w
        lo = np.r_[np.zeros(2 * K), np.full(2, 1e-8)] * scale
        hi = np.r_[np.full(2 * K, 5.0), np.full(2, 1e-2)] * scale
        fit = lsq_linear(R, target, bounds=(lo, hi), method="bvls")
        residual = float(np.sum(bw**2) - np.sum(target**2)) + 2 * fit.cost
        return residual, fit.x / scale


def _search_overlaps(fit: _ChamberFit) -> list[float]:
    """Both directions' overlaps. They share only the dead volumes: each is searched in turn. Closed
    up to an overlap and flat segments from zero fit the data alike, but a curve flat at zero leaves
    the overlap without a gradient for the fits that follow: of the overlaps that fit about as well
    as the best, the largest is taken. Searched on a coarse grid, then at the fine step around the
    coarse choice (18 solves instead of 41)."""
    overlaps = [0.0, 0.0]
    coarse = np.linspace(0.0, OVERLAP_MAX, 11)
    step = OVERLAP_MAX / 40
    for _ in range(2):
        for d in (0, 1):
            def cost(c: float) -> float:
                return fit.solve(tuple(c if i == d else overlaps[i] for i in (0, 1)))[0]

            costs = np.array([cost(c) for c in coarse])
            tie = OVERLAP_TIE * (costs.max() - costs.min())
            top = coarse[np.flatnonzero(costs <= costs.min() + tie)[-1]]
            fine = np.unique(np.clip(top + step * np.arange(-3, 4), 0.0, OVERLAP_MAX))  # holds top itself
            fine_costs = np.array([cost(c) for c in fine])
            best = min(costs.min(), fine_costs.min())
            overlaps[d] = float(fine[np.flatnonzero(fine_costs <= best + tie)[-1]])
    return overlaps
