"""Dynamic identification of a friction model of the family (sim.friction_models) by
multiple shooting, and the comparison of the family on a validation run.

A friction model replaces the nominal friction (Fc + Fv v + kp |dp|) of the plant; it is
identified as an effect of the one plant, on the cylinder with the nominal friction zeroed.
Its start comes from a static map of the run itself: the friction Newton's law implies at
every sample (seed 000's method), averaged in velocity bins per direction and fitted with
the map's least squares (friction_map.fit_model). Gauss-Newton then only polishes.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np

from sim.cylinder import Cylinder
from sim.friction_models import DIRECTIONS, FRICTION_MODELS, FrictionModel, make_friction_model, \
    without_nominal_friction

from .friction_map import FIT_SPECS, FitSpec, FrictionMapError, MapPoint, fit_model
from .identify import IdentificationError, IdentifyOptions, IdentifyResult, friction_from_newton, identify
from .runs import Run

# models whose dynamic identification is offered (the map's "cvs_delta" is cvs with a free exponent)
DYNAMIC_SPECS: tuple[str, ...] = ("cv", "karnopp", "threlfall", "cvs", "cvs_delta", "lugre", "cv_load",
                                  "cvs_load", "belforte")
_BINS_PER_DIRECTION = 24


def fit_spec(name: str) -> FitSpec:
    try:
        return FIT_SPECS[name]
    except KeyError:
        raise ValueError(f"unknown friction model '{name}' (available: nominal, {', '.join(DYNAMIC_SPECS)})") from None


def estimated_parameters(spec: FitSpec) -> tuple[str, ...]:
    """The model's parameters a dynamic fit estimates: all per-direction ones except those the
    spec holds fixed (cvs: the exponent); shared conditions (the normal load) are inputs."""
    cls = FRICTION_MODELS[spec.family]
    return tuple(n for n in cls.PARAMS if n not in cls.SHARED
                 and not any(n == f"{b}_{DIRECTIONS[d][0]}" for b in spec.fixed for d in DIRECTIONS))


def map_points_from_runs(cyl: Cylinder, runs: Sequence[Run], bins: int = _BINS_PER_DIRECTION) -> list[MapPoint]:
    """Sliding friction points from dynamic runs: Newton's-law friction at every sample,
    averaged in velocity bins of equal count per direction (the acceleration noise averages
    out; filtering bias remains, which is why this is only a start)."""
    v_all, F_all, dp_all, pc_all = [], [], [], []
    pa = cyl.supply.atmosphere
    for r in runs:
        idx, v, F = friction_from_newton(cyl, r)
        if len(idx) == 0:
            continue
        v_all.append(v)
        F_all.append(F)
        dp_all.append(np.abs(r.p1[idx] - r.p2[idx]))
        pc_all.append(np.where(v > 0, r.p2[idx] - pa, r.p1[idx] - pa))
    if not v_all:
        return []
    v, F, dp, pc = (np.concatenate(a) for a in (v_all, F_all, dp_all, pc_all))
    moving = np.abs(v) > 2 * cyl.friction.v_smooth
    points = []
    for sign in (1.0, -1.0):
        sel = np.flatnonzero(moving & (np.sign(v) == sign))
        if len(sel) < 2 * bins:
            continue
        sel = sel[np.argsort(np.abs(v[sel]))]
        for chunk in np.array_split(sel, bins):
            points.append(MapPoint(v=float(v[chunk].mean()), F=float(F[chunk].mean()), F_std=float(F[chunk].std()),
                                   v_std=float(v[chunk].std()), count=len(chunk), dp=float(dp[chunk].mean()),
                                   pc=float(pc[chunk].mean()), load=0.0, source="equation error"))
    return points


def map_start(cyl: Cylinder, runs: Sequence[Run], spec: FitSpec) -> dict[str, float]:
    """Start values of the model's parameters from the equation-error map of the runs (per
    direction; the model's defaults where a direction cannot be fitted)."""
    points = map_points_from_runs(cyl, runs)
    cls = FRICTION_MODELS[spec.family]
    start: dict[str, float] = {}
    for direction in DIRECTIONS:
        sign = 1.0 if direction == "extension" else -1.0
        pts = [p for p in points if np.sign(p.v) == sign]
        try:
            fit = fit_model(pts, spec)
        except (FrictionMapError, ValueError, np.linalg.LinAlgError):
            continue
        for k, val in fit.model_values().items():
            info = cls.PARAMS[k]
            if math.isfinite(val):
                # a start on a bound would freeze the parameter in the bounded Gauss-Newton step
                span = info.upper - info.lower
                start[k] = float(np.clip(val, info.lower + 1e-6 * span, info.upper - 1e-6 * span))
    for suffix in ("pos", "neg"):
        # the slowest samples of a dynamic run sit in reversals, where the filtered acceleration
        # smears the breakaway: the map then shows a dip where the cylinder has a hump, and
        # Gauss-Newton started in the dip can collapse the Stribeck term (vs -> 0)
        fs, fc = f"Fs_{suffix}", f"Fc_{suffix}"
        if fs in start and fc in start and start[fs] < 1.2 * start[fc]:
            start[fs] = 1.3 * start[fc]
    return start


def identify_friction_model(cyl: Cylinder, runs: Sequence[Run], model: str | FitSpec,
                            options: IdentifyOptions = IdentifyOptions(),
                            start: dict[str, float] | None = None,
                            progress: Callable[[str], None] | None = None) -> IdentifyResult:
    """Identify a friction model of the family on the runs by multiple shooting (all of the
    model's parameters; the cylinder file's nominal friction is replaced, not used)."""
    spec = fit_spec(model) if isinstance(model, str) else model
    values = dict(start) if start is not None else map_start(cyl, runs, spec)
    values.update({f"{b}_{DIRECTIONS[d][0]}": v for b, v in spec.fixed.items() for d in DIRECTIONS})
    if progress:
        progress(f"  {spec.name}: start from the equation-error map: "
                 + ", ".join(f"{k}={v:.4g}" for k, v in values.items()))
    effect = make_friction_model(spec.family, values)
    estimate = tuple(effect.key(k) for k in estimated_parameters(spec))
    return identify(without_nominal_friction(cyl), runs, replace(options, estimate=estimate, prefit=False),
                    effects=[effect], progress=progress)


def friction_model_of(result: IdentifyResult) -> FrictionModel | None:
    return next((e for e in result.effects if isinstance(e, FrictionModel)), None)


def model_parameters(result: IdentifyResult) -> tuple[dict[str, float], dict[str, float]]:
    """The identified friction parameters (values, standard deviations) under the model's own
    names (Fc_pos, ...; Fc, Fv, kp for the nominal model)."""
    model = friction_model_of(result)
    if model is None:
        return ({n: e.value for n, e in result.params.items()}, {n: e.std for n, e in result.params.items()})
    values = dict(zip(model.param_names(), model.values()))
    std = {n: math.nan for n in values}
    for key, e in result.params.items():
        name = key.split(".", 1)[1] if key.startswith(model.name + ".") else key
        if name in values:
            values[name], std[name] = e.value, e.std
    return values, std


# ------------------------------------------------------------------ comparison on VALID

@dataclass
class ModelComparison:
    """One model of the family identified on TRAIN and scored on VALID."""

    model: str
    n_params: int
    params: dict[str, float] = field(default_factory=dict)
    std: dict[str, float] = field(default_factory=dict)
    status: str = ""
    iterations: int = 0
    rmse_x_train: float = math.nan
    rmse_x_validation: float = math.nan
    normalized_rms: float = math.nan  # all outputs on VALID, in units of the sensor noise
    score: float = math.nan  # normalized_rms with a penalty per parameter (lower is better)
    wall_s: float = 0.0
    error: str = ""

    def to_json(self) -> dict:
        def num(x):
            return None if x is None or not math.isfinite(x) else float(x)

        out = {"model": self.model, "n_params": self.n_params, "status": self.status,
               "iterations": self.iterations, "params": {k: num(v) for k, v in self.params.items()},
               "std": {k: num(v) for k, v in self.std.items()}, "rmse_x_train": num(self.rmse_x_train),
               "rmse_x_validation": num(self.rmse_x_validation), "normalized_rms": num(self.normalized_rms),
               "score": num(self.score), "wall_s": round(self.wall_s, 3)}
        if self.error:
            out["error"] = self.error
        return out


def _compare_one(args) -> ModelComparison:
    import time

    from .diagnose import validate

    cyl, train, valid, name, opts, horizon, penalty = args
    t0 = time.perf_counter()
    try:
        with np.errstate(all="ignore"):
            if name == "nominal":
                res = identify(cyl, [train], opts)
            else:
                res = identify_friction_model(cyl, [train], name, opts)
            val = validate(res.cylinder, res.effects, valid, horizon)
    except (IdentificationError, ValueError, np.linalg.LinAlgError, RuntimeError) as e:
        return ModelComparison(model=name, n_params=0, status="failed", error=f"{type(e).__name__}: {e}",
                               wall_s=time.perf_counter() - t0)
    values, std = model_parameters(res)
    k = len(res.params)
    nrms = val.normalized_rms()
    return ModelComparison(model=name, n_params=k, params=values, std=std, status=res.solver["status"],
                           iterations=res.solver["iterations"], rmse_x_train=res.fit["rmse_x"],
                           rmse_x_validation=val.rmse("x"), normalized_rms=nrms,
                           score=nrms * (1 + penalty * k) if math.isfinite(nrms) else math.inf,
                           wall_s=time.perf_counter() - t0)


def compare_friction_models(cyl: Cylinder, train: Run, valid: Run, models: Sequence[str],
                            horizon_s: float = 1.0, workers: int = 1, penalty_per_param: float = 0.01,
                            options: IdentifyOptions = IdentifyOptions(max_iter=40, time_limit_s=60.0),
                            progress: Callable[[str], None] | None = None) -> list[ModelComparison]:
    """Each model identified on TRAIN by multiple shooting, simulated on VALID segment by
    segment (diagnose.validate: parameters never see VALID), ranked by the noise-weighted
    validation error with 1 % per parameter added. 'nominal' is the cylinder file's model."""
    for m in models:
        if m != "nominal":
            fit_spec(m)
    opts = replace(options, threads=1) if workers > 1 else options
    jobs = [(cyl, train, valid, m, opts, horizon_s, penalty_per_param) for m in models]
    if workers > 1 and len(jobs) > 1:
        with ProcessPoolExecutor(min(workers, len(jobs))) as pool:
            rows = []
            for row in pool.map(_compare_one, jobs):
                rows.append(row)
                if progress:
                    progress(f"  {row.model:10s} done ({row.wall_s:.1f} s, {row.status})")
    else:
        rows = []
        for j in jobs:
            rows.append(_compare_one(j))
            if progress:
                progress(f"  {rows[-1].model:10s} done ({rows[-1].wall_s:.1f} s, {rows[-1].status})")
    return sorted(rows, key=lambda r: (r.status == "failed", r.score))
