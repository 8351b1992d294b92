"""Fits of the friction models to one direction's points of the map.

The linear least squares of Trentini et al.'s Karnopp/least-squares friction fit (seed 000:
F = Fc + B v, R^2), and the static curve of every model of sim.friction_models (nonlinear
least squares, scipy), each with standard deviations and 95 % intervals of its parameters
from the Jacobian at the solution (as scipy's curve_fit), RMSE, R^2, the mean absolute error
(the "mean error" of Romeo et al.'s pneumatic-gripper friction models, seed 003) and flags on
the parameters the points cannot determine. Breakaway rows are left out: every fit is of the
sliding points (so that RMSE, R^2 and AICc of all models refer to the same points).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from sim.friction_models import DIRECTIONS, FRICTION_MODELS, FrictionModel

from ..identify import too_uncertain
from .points import MapPoint
from .specs import FIT_SPECS, FitSpec, FrictionMapError, TooFewPointsError

__all__ = ["LinearFit", "ModelFit", "linear_fit", "fit_model", "predicted", "fit_curve"]


_CONDITION_HELP = {"dp": "dp (|p1 - p2|, Pa)", "pc": "pc (counter pressure, Pa gauge)", "load": "load (N)"}
_STRONG_CORRELATION = 0.999
_REACH = 0.05  # a static force of which less reaches any point is extrapolated, not measured


@dataclass(frozen=True)
class LinearFit:
    """Seed 000: F = Fc s + B v by linear least squares (s = sign v), one direction."""

    direction: str
    Fc: float
    B: float
    std: Mapping[str, float]
    r2: float
    rmse: float
    mae: float
    n_points: int

    def to_json(self) -> dict:
        return {"params": {"Fc": self.Fc, "B": self.B}, "std": dict(self.std), "r2": self.r2, "rmse": self.rmse,
                "mae": self.mae, "n_points": self.n_points}


@dataclass(frozen=True)
class ModelFit:
    """One model fitted to one direction's points. Parameters under their base names (Fc,
    not Fc_pos), magnitudes; None where the points cannot give a value."""

    model: str
    family: str
    direction: str
    params: Mapping[str, float | None]
    std: Mapping[str, float | None]
    ci95: Mapping[str, tuple[float, float] | None]
    fixed: Mapping[str, str]  # base parameter -> why it was not fitted
    start: Mapping[str, float]  # the start of the best least-squares run (free parameters)
    r2: float
    rmse: float
    mae: float
    n_points: int
    dof: int
    aicc: float | None  # corrected Akaike criterion: lower is better, penalises parameters
    flags: tuple[Mapping[str, str], ...]
    status: str
    nfev: int
    not_determined: tuple[str, ...] = ()  # parameters whose value the points do not pin down
    problems: tuple[str, ...] = ()  # what is wrong with the fitted curve as a whole (shape, order of levels)

    @property
    def free(self) -> tuple[str, ...]:
        return tuple(self.start)

    @property
    def preferable(self) -> bool:
        """May be ranked (by AICc) and preferred: converged, every parameter determined, a
        curve within the data's range with the static level not below the Coulomb level."""
        return self.status == "converged" and not self.not_determined and not self.problems

    def model_values(self) -> dict[str, float]:
        """The fitted values under the model's parameter names (Fc_pos / Fc_neg)."""
        suffix = DIRECTIONS[self.direction][0]
        return {f"{k}_{suffix}": v for k, v in self.params.items()
                if v is not None and f"{k}_{suffix}" in FRICTION_MODELS[self.family].PARAMS}

    def to_json(self) -> dict:
        return {"family": self.family, "params": dict(self.params), "std": dict(self.std),
                "ci95": {k: (list(v) if v is not None else None) for k, v in self.ci95.items()},
                "fixed": dict(self.fixed), "start": dict(self.start), "r2": self.r2, "rmse": self.rmse,
                "mae": self.mae, "n_points": self.n_points, "dof": self.dof, "aicc": self.aicc,
                "flags": [dict(f) for f in self.flags], "status": self.status, "nfev": self.nfev,
                "not_determined": list(self.not_determined), "problems": list(self.problems),
                "preferable": self.preferable}


def _metrics(F: np.ndarray, pred: np.ndarray) -> tuple[float, float, float]:
    """R^2 (seed 000 Eq. 10), RMSE, mean absolute error (seed 003's 'mean error')."""
    r = F - pred
    sst = float(np.sum((F - F.mean()) ** 2))
    r2 = 1.0 - float(np.sum(r * r)) / sst if sst > 0 else math.nan
    return r2, float(np.sqrt(np.mean(r * r))), float(np.mean(np.abs(r)))


def _direction_of(points: Sequence[MapPoint]) -> str:
    dirs = {p.direction for p in points}
    if len(dirs) != 1:
        raise FrictionMapError("a fit takes the points of one direction (all v > 0 or all v < 0).")
    return dirs.pop()


def linear_fit(points: Sequence[MapPoint]) -> LinearFit:
    """Seed 000's least squares, Eq. (8): Theta = (X^T X)^-1 X^T Y with X = [sign v, v], on the
    sliding points (breakaway rows are left out)."""
    direction = _direction_of(points)
    points = [p for p in points if not p.breakaway]
    v = np.array([p.v for p in points])
    F = np.array([p.F for p in points])
    n = len(v)
    if n < 3:
        raise TooFewPointsError(f"the {direction} direction has {n} sliding points, too few for the linear fit "
                                f"(2 parameters, at least 3 points).")
    X = np.column_stack([np.sign(v), v])
    theta, *_ = np.linalg.lstsq(X, F, rcond=None)
    pred = X @ theta
    s2 = float(np.sum((F - pred) ** 2)) / (n - 2)
    cov = np.linalg.pinv(X.T @ X) * s2
    r2, rmse, mae = _metrics(F, pred)
    return LinearFit(direction=direction, Fc=float(theta[0]), B=float(theta[1]),
                     std={"Fc": float(np.sqrt(cov[0, 0])), "B": float(np.sqrt(cov[1, 1]))},
                     r2=r2, rmse=rmse, mae=mae, n_points=n)


def _conditions(spec: FitSpec, points: Sequence[MapPoint], direction: str) -> dict[str, np.ndarray]:
    cond = {}
    for key in spec.needs():
        vals = np.array([getattr(p, key) for p in points], float)
        if not np.all(np.isfinite(vals)):
            raise FrictionMapError(f"model {spec.name} needs {_CONDITION_HELP[key]} for every point, and the "
                                   f"{direction} points lack it (tables: add a column '{key}').")
        cond[key] = vals
    for key in FRICTION_MODELS[spec.family].CONDITIONS:
        cond.setdefault(key, np.zeros(len(points)))  # left out of this fit: its terms are held at 0
    return cond


def _starts(cls: type[FrictionModel], free: Sequence[str], v: np.ndarray, F: np.ndarray,
            cond: Mapping[str, np.ndarray]) -> list[dict[str, float]]:
    """Starting points for the least squares: linear fits where the model is linear, a few
    decades of the velocity scale where it is not."""
    a, f = np.abs(v), np.abs(F)
    order = np.argsort(a)
    fast = order[len(order) // 2:] if len(order) >= 4 else order  # away from a Stribeck hump

    def lin(cols: Sequence[np.ndarray], rows) -> np.ndarray:
        X = np.column_stack([c[rows] for c in cols])
        return np.maximum(np.linalg.lstsq(X, f[rows], rcond=None)[0], 0.0)

    one = np.ones_like(a)
    Fc, B = lin([one, a], fast)
    guess = {"Fc": Fc, "B": B, "delta": 2.0, "mu": 0.0, "mu_s": 0.0, "mu_v": 0.0,
             "Fs": max(float(f[order[0]] - B * a[order[0]]), Fc), "K1": 0.0, "alpha": 1.0, "K2": 0.0, "K3": 0.0}
    guess["FA"] = guess["Fc"]
    if "load" in cond:
        L = cond["load"]
        guess["Fc"], guess["mu"], guess["B"], guess["mu_v"] = lin([one, L, a, a * L], fast)
        guess["Fs"], guess["mu_s"] = max(float(f[order[0]] - guess["B"] * a[order[0]]), guess["Fc"]), guess["mu"]
    if "dp" in cond and "pc" in cond:
        guess["FA"], guess["K2"], guess["K3"] = lin([one, cond["dp"], cond["pc"]], order)
    if "dp" in cond:
        if "kp" in cls.BASE:  # cv_dp, efficiency: linear in their parameters
            cols = {"Fc": one, "kp": cond["dp"], "Fv": a}
            guess.update(zip(cls.BASE, lin([cols[b] for b in cls.BASE], order)))
    scales = [n for n in free if n in cls.SCALES]
    if not scales:
        return [{n: float(guess[n]) for n in free}]
    lo, hi = float(a.min()), float(a.max())
    # first the velocity scale the slow points suggest, then a few decades around the data
    candidates = [_scale_from_points(scales[0], a, f, guess), *np.geomspace(lo / 3, max(hi / 3, lo), 5)]
    out = []
    for vs in candidates:
        if vs is not None:
            g = {**guess, **{n: float(vs) for n in scales}}
            out.append({n: float(g[n]) for n in free})
    return out


def _scale_from_points(name: str, a: np.ndarray, f: np.ndarray, guess: Mapping[str, float]) -> float | None:
    """The velocity scale the points suggest: where the excess over the Coulomb-viscous line
    has decayed (Stribeck: excess = (Fs - Fc) exp(-(v/vs)^2)), or where the rise to it is
    done (Threlfall: F = Fc (1 - exp(-3 v / ve)) / 0.95)."""
    Fc, B = guess["Fc"], guess["B"]
    line = Fc + B * a
    with np.errstate(divide="ignore", invalid="ignore"):
        if name == "vs":
            excess = f - line
            E0 = float(excess[np.argmin(a)])
            ok = (excess > 0.05 * E0) & (excess < 0.95 * E0) if E0 > 0 else np.zeros_like(a, bool)
            est = a[ok] / np.sqrt(np.log(E0 / excess[ok]))
        elif name == "ve" and Fc > 0:
            rise = 0.95 * (f - B * a) / Fc
            ok = (rise > 0.05) & (rise < 0.9)
            est = -3 * a[ok] / np.log(1 - rise[ok])
        else:
            return None
    est = est[np.isfinite(est) & (est > 0)]
    return float(np.median(est)) if est.size else None


def _flags(cls, free, values, std, ci, lower, upper, corr, v, J_full, suffix) -> list[dict[str, str]]:
    """Parameters the points cannot determine, with the reason."""
    flags = []
    a = np.abs(v)
    slowest, fastest = float(a.min()), float(a.max())
    for i, n in enumerate(free):
        x, s = values[n], std[n]
        if not math.isfinite(s):
            flags.append({"param": n, "reason": "not determined by the points (the Jacobian is singular there)"})
            continue
        if n in cls.SCALES and x < slowest:
            flags.append({"param": n, "reason": f"{n} = {x:.3g} m/s lies below the slowest tested speed "
                                                 f"{slowest:.3g} m/s: the curve changes where there are no points "
                                                 f"(its shape there is the model's assumption)"})
        elif n in cls.SCALES and x > fastest:
            flags.append({"param": n, "reason": f"{n} = {x:.3g} m/s lies above the fastest tested speed "
                                                 f"{fastest:.3g} m/s: the curve is still changing at the last point"})
        if abs(x - lower[i]) <= 1e-6 * max(1.0, abs(lower[i])) or abs(x - upper[i]) <= 1e-6 * max(1.0, abs(upper[i])):
            bound = lower[i] if abs(x - lower[i]) <= abs(x - upper[i]) else upper[i]
            flags.append({"param": n, "reason": f"at its bound {bound:g}: the least squares wanted to go beyond"})
        elif ci[n] is not None and ci[n][0] <= 0.0 <= ci[n][1] and x != 0.0:
            flags.append({"param": n, "reason": f"the 95 % interval [{ci[n][0]:.3g}, {ci[n][1]:.3g}] includes 0"})
        elif x != 0.0 and s > abs(x):
            flags.append({"param": n, "reason": f"the standard deviation {s:.3g} exceeds the value {x:.3g}"})
        # how much of the parameter reaches the points at all (e.g. Fs behind a tiny Stribeck velocity)
        col = J_full[:, cls.param_index(f"{n}_{suffix}")]
        if n in ("Fs", "mu_s") and float(np.max(np.abs(col))) < _REACH:
            flags.append({"param": n, "reason": f"at most {100 * float(np.max(np.abs(col))):.2g} % of {n} reaches "
                                                 f"the points: it is extrapolated below the slowest speed"})
    if corr is not None:
        for i in range(len(free)):
            for j in range(i + 1, len(free)):
                if abs(corr[i, j]) > _STRONG_CORRELATION:
                    flags.append({"param": free[j], "reason": f"correlated with {free[i]} (r = {corr[i, j]:.4f}): "
                                                              f"the points cannot separate the two"})
    return flags


# the part of the points' force spread within which a parameter's effect must be pinned
_DETERMINED_SHARE = 0.5  # by effect, not value: a parameter near 0 with a small effect is pinned (small)


def _not_determined(cls, free, values, std, lower, upper, corr, J_full, suffix, F) -> set[str]:
    """Free parameters the points do not pin down: no finite standard deviation, stuck at a
    bound other than zero (the fit wanted beyond), inseparable from another (|r| > 0.999), a
    static force that hardly reaches the points, or an uncertainty whose effect on the curve
    (std x largest sensitivity) is as large as half the spread of the points' forces. A parameter
    near 0 with a small effect is determined: the points say it is small."""
    spread = float(np.ptp(np.abs(F))) or float(np.mean(np.abs(F))) or 1.0
    out = set()
    for n in free:
        x, s = values[n], std[n]
        i = cls.param_index(f"{n}_{suffix}")
        lo, hi = lower[free.index(n)], upper[free.index(n)]
        at_bound = (abs(x - hi) <= 1e-6 * max(1.0, abs(hi))) or (lo != 0 and abs(x - lo) <= 1e-6 * max(1.0, abs(lo)))
        reach = float(np.max(np.abs(J_full[:, i])))
        if too_uncertain(s, spread, share=_DETERMINED_SHARE, sensitivity=reach) or at_bound or \
                (n in ("Fs", "mu_s") and reach < _REACH):
            out.add(n)
    if corr is not None:
        for i in range(len(free)):
            for j in range(i + 1, len(free)):
                if abs(corr[i, j]) > _STRONG_CORRELATION:
                    out.update((free[i], free[j]))
    return out


def fit_model(points: Sequence[MapPoint], spec: FitSpec | str, fixed: Mapping[str, float] | None = None,
              fixed_reason: Mapping[str, str] | None = None) -> ModelFit:
    """Fit one model's static curve to one direction's points by nonlinear least squares
    (scipy.optimize.least_squares, bounds from the model's PARAMS, exact Jacobian from the
    model's CasADi expression, a few starts). `fixed` holds base parameters at values (a
    NaN value: not determined, reported as None). Standard deviations as scipy's curve_fit
    (unweighted: the residual variance scales (J^T J)^-1), 95 % intervals with Student's t.
    Breakaway rows are left out: the fit is of the sliding points (build_map fixes Fs from them)."""
    from scipy.stats import t as student_t

    spec = FIT_SPECS[spec] if isinstance(spec, str) else spec
    cls = FRICTION_MODELS[spec.family]
    direction = _direction_of(points)
    points = [p for p in points if not p.breakaway]
    suffix = DIRECTIONS[direction][0]
    fixed_all = {**spec.fixed, **(fixed or {})}
    reasons = {n: "held fixed by the fit" for n in spec.fixed}
    reasons.update(fixed_reason or {})
    free = [n for n in cls.BASE if n not in fixed_all]
    n, k = len(points), len(free)
    if n < k + 1:
        raise TooFewPointsError(f"the {direction} direction has {n} points, too few to fit {spec.name} with {k} "
                                f"parameters (at least {k + 1} points).")
    v = np.array([p.v for p in points])
    F = np.array([p.F for p in points])
    cond = _conditions(spec, points, direction)
    names = list(cls.PARAMS)
    p_full = np.array([cls.defaults()[m] for m in names])
    for b, val in fixed_all.items():
        if math.isfinite(val):
            p_full[names.index(f"{b}_{suffix}")] = val
    idx = [names.index(f"{b}_{suffix}") for b in free]
    lower = np.array([cls.PARAMS[names[i]].lower for i in idx])
    upper = np.array([cls.PARAMS[names[i]].upper for i in idx])
    kw = {"dp": cond.get("dp"), "pc": cond.get("pc"), "load": cond.get("load")}
    full, residual, jacobian = _static_curve(cls, v, F, p_full, idx, kw)
    best, best_start = _least_squares(residual, jacobian, _starts(cls, free, v, F, cond), free, lower, upper)
    theta = best.x
    pred = F + residual(theta)
    r2, rmse, mae = _metrics(F, pred)
    dof = n - k
    std_v, corr = _covariance(jacobian(theta), 2 * best.cost, dof)
    values, std, ci = _estimates(free, theta, std_v, float(student_t.ppf(0.975, dof)))
    J_all = cls.static_jacobian(v, full(theta), **kw)
    flags = _flags(cls, free, values, std, ci, lower, upper, corr, v, J_all, suffix)
    undetermined = _not_determined(cls, free, values, std, lower, upper, corr, J_all, suffix, F)
    for b, val in fixed_all.items():
        values[b] = float(val) if math.isfinite(val) else None
        std.setdefault(b, None)
        ci.setdefault(b, None)
    for b in sorted(cls.DYNAMIC):
        values[b], std[b], ci[b] = None, None, None
        reasons[b] = "dynamic: a static map does not determine it"
        flags.append({"param": b, "reason": "dynamic parameter: a static friction-velocity map does not "
                                            "determine it (identify it from runs)"})
    # the order of the model's parameters
    order = [b for b in (*cls.BASE, *sorted(cls.DYNAMIC)) if b in values]
    return ModelFit(model=spec.name, family=spec.family, direction=direction,
                    params={b: values[b] for b in order}, std={b: std[b] for b in order},
                    ci95={b: ci[b] for b in order}, fixed={b: reasons.get(b, "held fixed") for b in order
                                                           if b not in free},
                    start=best_start, r2=r2, rmse=rmse, mae=mae, n_points=n, dof=dof, aicc=_aicc(2 * best.cost, n, k),
                    flags=tuple(flags),
                    status="converged" if best.status > 0 else f"not converged ({best.message})", nfev=int(best.nfev),
                    not_determined=tuple(b for b in order if b in undetermined or (b in fixed_all and values[b] is None
                                                                                   and b not in cls.DYNAMIC)))


def _static_curve(cls: type[FrictionModel], v: np.ndarray, F: np.ndarray, p_full: np.ndarray, idx: list[int],
                  kw: Mapping[str, np.ndarray | None]):
    """The least-squares problem of a static curve, as functions of the free parameters (at
    `idx` of the model's parameters; the others at their values in p_full): the full parameter
    vector, the residuals at the points and their Jacobian."""

    def full(theta: np.ndarray) -> np.ndarray:
        p = p_full.copy()
        p[idx] = theta
        return p

    def residual(theta):
        return cls.static_force(v, full(theta), **kw) - F

    def jacobian(theta):
        return cls.static_jacobian(v, full(theta), **kw)[:, idx]

    return full, residual, jacobian


def _least_squares(residual, jacobian, starts: Sequence[Mapping[str, float]], free: Sequence[str],
                   lower: np.ndarray, upper: np.ndarray):
    """The bounded least squares (scipy, trust region reflective) from every start: the solution
    of the lowest cost and its start (free parameters by name, clipped to the bounds)."""
    from scipy.optimize import least_squares

    best, best_start = None, None
    for start in starts:
        x0 = np.clip(np.array([start[b] for b in free]), lower, upper)
        sol = least_squares(residual, x0, jac=jacobian, bounds=(lower, upper), method="trf", x_scale="jac",
                            xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=2000)
        # the earliest start (the best informed) that reaches the lowest cost is the one reported
        if best is None or sol.cost < best.cost * (1 - 1e-9):
            best, best_start = sol, dict(zip(free, x0.tolist()))
    return best, best_start


def _estimates(free: Sequence[str], theta: np.ndarray, std_v: np.ndarray, tq: float):
    """The free parameters' values, standard deviations and intervals (value -+ tq std; None
    where the std is not finite), by name."""
    values: dict[str, float | None] = {}
    std: dict[str, float | None] = {}
    ci: dict[str, tuple[float, float] | None] = {}
    for i, b in enumerate(free):
        values[b], std[b] = float(theta[i]), float(std_v[i])
        ci[b] = (values[b] - tq * std[b], values[b] + tq * std[b]) if math.isfinite(std[b]) else None
    return values, std, ci


def _aicc(ssr: float, n: int, k: int) -> float | None:
    """AICc of a least-squares fit with Gaussian residuals: n ln(SSR/n) + 2k + 2k(k+1)/(n-k-1)."""
    if n - k - 1 <= 0 or ssr <= 0:
        return None
    return float(n * math.log(ssr / n) + 2 * k + 2 * k * (k + 1) / (n - k - 1))


def _covariance(J: np.ndarray, ssr: float, dof: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Standard deviations (inf where the Jacobian is rank deficient) and the correlation
    matrix, as scipy's curve_fit: pcov = (J^T J)^+ * ssr / dof by SVD."""
    _, s, VT = np.linalg.svd(J, full_matrices=False)
    k = J.shape[1]
    keep = s > np.finfo(float).eps * max(J.shape) * (s[0] if s.size else 0.0)
    pcov = (VT[keep].T / s[keep] ** 2) @ VT[keep] * (ssr / dof)
    std = np.sqrt(np.clip(np.diag(pcov), 0.0, None))
    if not keep.all():  # parameters touched by the null space are not determined
        null = VT[~keep]
        std[np.max(np.abs(null), axis=0) > 1e-8] = math.inf
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = pcov / np.outer(std, std) if np.all(np.isfinite(std)) and np.all(std > 0) else None
    return std, corr if k > 1 else None


def predicted(fit: ModelFit, points: Sequence[MapPoint]) -> np.ndarray:
    """The fitted model at each point (with the point's own conditions)."""
    cls = FRICTION_MODELS[fit.family]
    p = cls.defaults()
    p.update(fit.model_values())
    needs = FIT_SPECS[fit.model].needs()
    cond = {k: np.array([getattr(q, k) if k in needs else 0.0 for q in points], float) for k in cls.CONDITIONS}
    return cls.static_force(np.array([q.v for q in points]), [p[k] for k in cls.PARAMS], **cond)


def fit_curve(fit: ModelFit, points: Sequence[MapPoint]) -> tuple[np.ndarray, np.ndarray] | None:
    """The fitted curve over the direction's speeds (conditions at their mean over the points)."""
    cls = FRICTION_MODELS[fit.family]
    if not points:
        return None
    s = DIRECTIONS[fit.direction][1]
    a = np.abs([p.v for p in points])
    vv = s * np.linspace(max(a.min() * 0.05, 1e-5), a.max() * 1.05, 300)
    p = cls.defaults()
    p.update(fit.model_values())
    needs = FIT_SPECS[fit.model].needs() if fit.model in FIT_SPECS else cls.CONDITIONS
    cond = {k: float(np.nanmean([getattr(q, k) for q in points])) if k in needs else 0.0 for k in cls.CONDITIONS}
    return vv, cls.static_force(vv, [p[k] for k in cls.PARAMS], **cond)
