"""Diagnose the sim-to-real gap: where it lies, which unmodelled effect causes it, and how
far it shrinks once that effect is added.

The nominal model is identified on TRAIN and scored on VALID, a run the fit never saw.
The score is the simulation error over a fixed horizon: VALID is cut into segments of
`horizon_s`, each simulated open loop from the measured state at its start (velocity
from a central Savitzky-Golay derivative) with the recorded command. Each candidate
effect extends the one plant, is re-identified on TRAIN (friction and the effect's own
parameters) and scored the same way; candidates are ranked by the shrink of the
validation position RMSE, less a penalty per added parameter. The verdict is `none` when
no candidate shrinks the gap by a significant amount.
"""
from __future__ import annotations

import math
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from sim.compiled import shooting_functions
from sim.cylinder import Cylinder
from sim.effects import EFFECTS, Effect, make_effect
from sim.plant import build_plant

from .identify import IdentifyOptions, _velocity_estimate, identify
from .runs import Run


@dataclass(frozen=True)
class DiagnoseOptions:
    candidates: tuple[str, ...] = tuple(EFFECTS)
    horizon_s: float = 1.0  # validation simulation horizon
    min_shrink: float = 0.10  # below this no candidate explains the gap
    penalty_per_param: float = 0.01  # shrink charged per added parameter when ranking
    workers: int = max(1, os.cpu_count() or 1)


@dataclass
class Candidate:
    effect: str
    shrink: float
    rmse_x_validation: float
    params: dict[str, float]
    std: dict[str, float]
    score: float
    status: str
    friction: dict[str, float] = field(default_factory=dict)
    error: str | None = None

    def to_json(self) -> dict:
        out = {"effect": self.effect, "shrink": self.shrink, "rmse_x_validation": self.rmse_x_validation,
               "params": self.params, "std": self.std, "score": self.score, "status": self.status,
               "friction": self.friction}
        if self.error:
            out["error"] = self.error
        return out


def validation_residuals(cyl: Cylinder, effects: Sequence[Effect], run: Run, horizon_s: float = 1.0) -> np.ndarray:
    """Measured minus simulated (x, p1, p2), shape (3, n): `run` simulated in segments of
    `horizon_s`, each from the measured state at its start, with the recorded command."""
    plant = build_plant("command", effects)
    M = max(5, int(round(0.1 / run.sample_period)))
    sf = shooting_functions(plant, M, ())
    p = np.array(plant.parameter_vector(cyl), float)
    v = _velocity_estimate(run.t, run.x)  # over the whole run: no end effects at segment starts
    seg = max(M, int(round(horizon_s / run.sample_period)))
    out_idx = [plant.state_names.index(n) for n in ("x", "p1", "p2")]
    sim = np.empty((3, run.n))
    for a in range(0, run.n, seg):
        b = min(run.n, a + seg)
        s0 = plant.initial_state(cyl, run.x[a], run.p1[a], run.p2[a], v[a])
        sim[:, a:b] = sf.simulate(s0, run.u[a:b], p, np.diff(run.t[a:b]))[out_idx]
    return np.vstack([run.x, run.p1, run.p2]) - sim


def _rmse(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(r * r)))


def regions(cyl: Cylinder, run: Run, resid_x: np.ndarray) -> list[dict]:
    """Where the validation position error lies: share of the squared error per operating
    regime, and how over-represented it is (share / fraction of samples)."""
    v = _velocity_estimate(run.t, run.x)
    L = cyl.geometry.stroke
    moving = np.abs(v) > 0.005
    sgn = np.sign(np.where(moving, v, 0.0))
    nz = np.flatnonzero(sgn)
    rev = np.zeros(run.n, bool)
    if len(nz) > 1:
        flips = nz[1:][sgn[nz[1:]] != sgn[nz[:-1]]]
        w = max(1, int(round(0.02 / run.sample_period)))
        for i in flips:
            rev[max(0, i - w):i + w] = True
    t_rel = (run.t - run.t[0]) / max(run.duration, 1e-12)
    masks = {
        "extension (v > 5 mm/s)": v > 0.005,
        "retraction (v < -5 mm/s)": v < -0.005,
        "near-zero speed (|v| < 5 mm/s)": ~moving,
        "slow (5-50 mm/s)": moving & (np.abs(v) < 0.05),
        "fast (> 50 mm/s)": np.abs(v) >= 0.05,
        "reversals (within 20 ms)": rev,
        "stroke: first third": run.x < L / 3,
        "stroke: middle third": (run.x >= L / 3) & (run.x < 2 * L / 3),
        "stroke: last third": run.x >= 2 * L / 3,
        "valve near centre (|u| < 0.05)": np.abs(run.u) < 0.05,
        "high flow (|u| > 0.5)": np.abs(run.u) > 0.5,
    }
    for q in range(4):
        masks[f"time: quarter {q + 1}"] = (t_rel >= q / 4) & (t_rel < (q + 1) / 4 if q < 3 else t_rel <= 1)
    e2 = resid_x ** 2
    total = float(e2.sum()) or 1.0
    out = []
    for where, m in masks.items():
        frac = float(m.mean())
        if frac == 0:
            continue
        share = float(e2[m].sum()) / total
        out.append({"where": where, "share_of_error": share, "fraction_of_samples": frac,
                    "concentration": share / frac, "rmse_x": float(np.sqrt(e2[m].mean()))})
    return sorted(out, key=lambda r: -r["concentration"])


def whiteness(resid: np.ndarray, lags: int = 20) -> dict:
    """Ljung-Box statistic of the position residual (decimated to 10 ms, where sensor noise
    no longer dominates) and its first autocorrelations."""
    r = resid[::10] - resid[::10].mean()
    n = len(r)
    den = float(r @ r) or 1.0
    acf = np.array([float(r[:-k] @ r[k:]) / den for k in range(1, min(lags, n - 1) + 1)])
    q = n * (n + 2) * float(np.sum(acf ** 2 / (n - np.arange(1, len(acf) + 1))))
    return {"ljung_box_q": q, "lags": len(acf), "acf_1": float(acf[0]) if len(acf) else 0.0,
            "white": bool(q < len(acf) + 3 * math.sqrt(2 * len(acf)))}


def _fit_candidate(args) -> Candidate:
    cyl, train, valid, name, opts = args
    try:
        eff = make_effect(name)
        names = ("Fc", "Fv", "kp") + tuple(f"{name}.{k}" for k in eff.PARAMS)
        res = identify(cyl, [train], IdentifyOptions(estimate=names, threads=1), effects=[eff])
        r = validation_residuals(res.cylinder, res.effects, valid, opts.horizon_s)
        return Candidate(effect=name, shrink=math.nan, rmse_x_validation=_rmse(r[0]),
                         params={k: res.params[f"{name}.{k}"].value for k in eff.PARAMS},
                         std={k: res.params[f"{name}.{k}"].std for k in eff.PARAMS}, score=math.nan,
                         status=res.solver["status"],
                         friction={n: res.params[n].value for n in ("Fc", "Fv", "kp")})
    except Exception as e:  # one candidate failing must not end the diagnosis
        return Candidate(effect=name, shrink=math.nan, rmse_x_validation=math.nan, params={}, std={},
                         score=-math.inf, status="failed", error=f"{type(e).__name__}: {e}")


def diagnose(cyl: Cylinder, train: Run, valid: Run, options: DiagnoseOptions = DiagnoseOptions(),
             progress: Callable[[str], None] | None = None) -> dict:
    say = progress or (lambda _m: None)
    say("identifying the nominal model on TRAIN ...")
    base = identify(cyl, [train], IdentifyOptions())
    r0 = validation_residuals(base.cylinder, (), valid, options.horizon_s)
    base_rmse = _rmse(r0[0])
    say(f"  validation RMSE of x: {base_rmse * 1e6:.2f} um ({options.horizon_s:g} s horizon)")
    say(f"re-identifying {len(options.candidates)} candidate effects on TRAIN ({options.workers} processes) ...")
    jobs = [(cyl, train, valid, name, options) for name in options.candidates]
    if options.workers > 1:
        with ProcessPoolExecutor(options.workers) as pool:
            cands = list(pool.map(_fit_candidate, jobs))
    else:
        cands = [_fit_candidate(j) for j in jobs]
    for c in cands:
        if math.isfinite(c.rmse_x_validation):
            c.shrink = 1.0 - c.rmse_x_validation / base_rmse
            c.score = c.shrink - options.penalty_per_param * len(c.params)
        say(f"  {c.effect:20s} shrink {c.shrink:7.1%}" + (f"  ({c.error})" if c.error else ""))
    ranking = sorted(cands, key=lambda c: -c.score)
    best = ranking[0] if ranking else None
    verdict = best.effect if best is not None and best.shrink >= options.min_shrink else "none"
    return {
        "baseline": {"rmse_x_validation": base_rmse, "rmse_p1_validation": _rmse(r0[1]),
                     "rmse_p2_validation": _rmse(r0[2]), "friction": {n: e.value for n, e in base.params.items()},
                     "rmse_x_train": base.fit["rmse_x"], "horizon_s": options.horizon_s},
        "verdict": verdict,
        "ranking": [c.to_json() for c in ranking],
        "regions": regions(base.cylinder, valid, r0[0]),
        "whiteness": whiteness(r0[0]),
    }
