"""Dynamic identification of a friction model of the family (sim.friction_models) by
multiple shooting, and the comparison of the family on a validation run.

A friction model replaces the nominal friction (Fc + Fv v + kp |dp|) of the plant; it is
identified as an effect of the one plant, on the cylinder with the nominal friction zeroed.
Its start comes from a static map of the run itself: the friction Newton's law implies at
every sample (Trentini et al.'s Karnopp/least-squares fit, seed 000), averaged in velocity bins
per direction and fitted with the map's least squares (friction_map.fit_model). Gauss-Newton then only polishes. The map's
slow end is biased (filtering smears reversals and breakaways), so its fit can put a model's
velocity scale (vs, ve, dv) far above the speeds where it could act, or Belforte's pressure
terms on their bound; from there Gauss-Newton stalls in a local minimum. Such a start is
accompanied by a second one shaped from the map's faster half and its slowest speed, and
the start that reaches the lower TRAIN cost is kept (`solver["start"]` says which).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field, replace

import numpy as np

from sim.cylinder import Cylinder
from sim.friction_models import DIRECTIONS, FRICTION_MODELS, FrictionModel, make_friction_model, \
    without_nominal_friction

from ..files import Run
from ..identify import (IdentificationError, IdentifyOptions, IdentifyResult, friction_from_newton, identify,
                        lower_cost, not_determined, validate)
from .fits import fit_model
from .points import MapPoint
from .specs import DYNAMIC_SPECS, FIT_SPECS, FitSpec, FrictionMapError

_BINS_PER_DIRECTION = 24
# a condition of a static curve that the plant, which has no such signal, holds as a constant
# parameter: an input of the dynamic fit, not an estimate
_CONDITION_PARAMETERS = {"load": "Fn"}


def fit_spec(name: str) -> FitSpec:
    try:
        return FIT_SPECS[name]
    except KeyError:
        raise ValueError(f"unknown friction model '{name}' (available: nominal, {', '.join(DYNAMIC_SPECS)})") from None


def estimated_parameters(spec: FitSpec) -> tuple[str, ...]:
    """The model's parameters a dynamic fit estimates: all of them except those the spec holds
    fixed (cvs: the exponent) and the conditions the plant holds constant (the normal load Fn
    of the load models: an input). LuGre's shared sigma0, sigma1 are estimated: the static map
    cannot determine them, runs can."""
    cls = FRICTION_MODELS[spec.family]
    inputs = {_CONDITION_PARAMETERS[c] for c in cls.CONDITIONS if c in _CONDITION_PARAMETERS}
    fixed = {f"{b}_{DIRECTIONS[d][0]}" for b in spec.fixed for d in DIRECTIONS}
    return tuple(n for n in cls.PARAMS if n not in inputs and n not in fixed)


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
    return _map_start(map_points_from_runs(cyl, runs), spec)


def _inside(info, value: float) -> float:
    """A start value kept just inside its range: on a bound, the bounded Gauss-Newton step
    would freeze the parameter."""
    span = info.upper - info.lower
    return float(np.clip(value, info.lower + 1e-6 * span, info.upper - 1e-6 * span))


def _map_start(points: Sequence[MapPoint], spec: FitSpec) -> dict[str, float]:
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
            if math.isfinite(val):
                start[k] = _inside(cls.PARAMS[k], val)
    for suffix in ("pos", "neg"):
        # the slowest samples of a dynamic run sit in reversals, where the filtered acceleration
        # smears the breakaway: the map then shows a dip where the cylinder has a hump, and
        # Gauss-Newton started in the dip can collapse the Stribeck term (vs -> 0)
        fs, fc = f"Fs_{suffix}", f"Fc_{suffix}"
        if fs in start and fc in start and start[fs] < 1.2 * start[fc]:
            start[fs] = 1.3 * start[fc]
    return start


def _shaped_start(points: Sequence[MapPoint], spec: FitSpec, start: dict[str, float]) -> dict[str, float] | None:
    """A second start for the directions where the map start is implausible, else None.

    Implausible: a velocity scale (vs, ve, dv) not within a factor 2 of twice the slowest
    speed of the direction's points (the slow end is where the map is biased: a scale the
    fit put far above it bent the fast end, and one a few times above it already leads
    Gauss-Newton into a local minimum on some runs), or Belforte's pressure terms carrying
    less than 1 % of the friction at the median speed (K2, K3 on their bound, K1 huge).
    Shaped: Fc, B from a line through the faster half of the points, Fs = 1.5 Fc (at least
    Fc + 5 % of the friction at the median speed), the scale twice the slowest speed,
    Belforte's pressure terms as a share of that line (alpha = 1); load terms at 0."""
    cls = FRICTION_MODELS[spec.family]
    out = dict(start)
    changed = False
    for direction, (suffix, sign) in DIRECTIONS.items():
        pts = [p for p in points if np.sign(p.v) == sign]
        if len(pts) < 4:
            continue
        a = np.abs([p.v for p in pts])
        f = np.abs([p.F for p in pts])
        order = np.argsort(a)
        fast = order[len(order) // 2:]
        Fc, B = np.maximum(np.linalg.lstsq(np.column_stack([np.ones(len(fast)), a[fast]]), f[fast], rcond=None)[0], 0)
        v_lo, v_med = float(a.min()), float(np.median(a))
        F_med = float(Fc + B * v_med)
        get = lambda base: start.get(f"{base}_{suffix}", getattr(cls, f"{base}_{suffix}", math.nan))  # noqa: E731
        scales = [b for b in cls.BASE if b in cls.SCALES]
        bad = any(not v_lo <= get(b) <= 4 * v_lo for b in scales)
        if spec.family == "belforte":
            dp, pc = float(np.median([p.dp for p in pts])), float(np.median([p.pc for p in pts]))
            bad = bad or not get("K2") * dp + get("K3") * pc >= 0.01 * F_med
        if not bad:
            continue
        changed = True
        P = max(0.5 * Fc, 0.05 * F_med)  # Belforte: the pressure terms at rest
        shaped = {"Fc": Fc, "B": B, "Fs": max(1.5 * Fc, Fc + 0.05 * F_med), "delta": 2.0, "mu": 0.0, "mu_s": 0.0,
                  "mu_v": 0.0, "FA": max(Fc - P, 0.0), "alpha": 1.0, "K1": B / P if P > 0 else 0.0}
        if spec.family == "belforte":
            shaped.update(K2=0.5 * P / max(dp, 1.0), K3=0.5 * P / max(pc, 1.0))
        shaped.update({b: 2 * v_lo for b in scales})
        for b in cls.BASE:
            name = f"{b}_{suffix}"
            if b in shaped and b not in spec.fixed:
                out[name] = _inside(cls.PARAMS[name], shaped[b])
    return out if changed else None


def identify_friction_model(cyl: Cylinder, runs: Sequence[Run], model: str | FitSpec,
                            options: IdentifyOptions = IdentifyOptions(),
                            start: dict[str, float] | None = None,
                            progress: Callable[[str], None] | None = None, *,
                            load: float | None = None) -> IdentifyResult:
    """Identify a friction model of the family on the runs by multiple shooting (all of the
    model's parameters but the normal load; the cylinder file's nominal friction is replaced,
    not used). Without `start`, from the equation-error map and, where that start is
    implausible, also from a shaped one (module docstring): the lower TRAIN cost wins.
    `load`: the constant normal load Fn of the load models (their default 0 otherwise, at
    which the load terms have no effect); at one load they are not separable from Fc, Fs, B."""
    spec = fit_spec(model) if isinstance(model, str) else model
    cls = FRICTION_MODELS[spec.family]
    if start is not None:
        starts = [("given", dict(start))]
    else:
        points = map_points_from_runs(cyl, runs)
        first = _map_start(points, spec)
        starts = [("equation-error map", first)]
        shaped = _shaped_start(points, spec, first)
        if shaped is not None:
            starts.append(("shaped (the map's start is implausible)", shaped))
    fixed = {f"{b}_{DIRECTIONS[d][0]}": v for b, v in spec.fixed.items() for d in DIRECTIONS}
    if load is not None:
        if "Fn" not in cls.PARAMS:
            raise ValueError(f"friction model {spec.name} has no normal load (Fn); only the load models take one")
        fixed["Fn"] = float(load)
    best, failure = None, None
    for what, values in starts:
        values = {**values, **fixed}
        if progress:
            progress(f"  {spec.name}: start from the {what}: " + ", ".join(f"{k}={v:.4g}" for k, v in values.items()))
        effect = make_friction_model(spec.family, values)
        estimate = tuple(effect.key(k) for k in estimated_parameters(spec))
        try:
            res = identify(without_nominal_friction(cyl), runs, replace(options, estimate=estimate, prefit=False),
                           effects=[effect], progress=progress)
        except IdentificationError as e:
            failure = e
            continue
        res.solver["start"] = what
        best = lower_cost(best, res)
    if best is None:
        raise failure
    if progress and len(starts) > 1:
        progress(f"  {spec.name}: kept the start from the {best.solver['start']} (lowest TRAIN cost)")
    return best


def check_model(name: str) -> None:
    """Refuse (ValueError) a name that is neither 'nominal' nor a model of the family."""
    if name != "nominal":
        fit_spec(name)


def identify_model(cyl: Cylinder, runs: Sequence[Run], model: str, options: IdentifyOptions = IdentifyOptions(),
                   load: float | None = None) -> IdentifyResult:
    """'nominal' (the cylinder file's Fc + Fv v + kp |dp|, from the equation-error prefit) or a
    friction model of the family; `load` goes to the models that have a normal load."""
    if model == "nominal":
        return identify(cyl, runs, options)
    has_load = "Fn" in FRICTION_MODELS[fit_spec(model).family].PARAMS
    return identify_friction_model(cyl, runs, model, options, load=load if has_load else None)


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
    start: str = ""  # the start the kept fit came from (identify_friction_model)
    not_determined: tuple[str, ...] = ()  # parameters TRAIN does not determine (identify.not_determined): no estimate

    def to_json(self) -> dict:
        def num(x):
            return None if x is None or not math.isfinite(x) else float(x)

        out = {"model": self.model, "n_params": self.n_params, "status": self.status,
               "iterations": self.iterations, "params": {k: num(v) for k, v in self.params.items()},
               "std": {k: num(v) for k, v in self.std.items()}, "rmse_x_train": num(self.rmse_x_train),
               "rmse_x_validation": num(self.rmse_x_validation), "normalized_rms": num(self.normalized_rms),
               "score": num(self.score), "wall_s": round(self.wall_s, 3)}
        if self.start:
            out["start"] = self.start
        if self.not_determined:
            out["not_determined"] = list(self.not_determined)
        if self.error:
            out["error"] = self.error
        return out


def _compare_one(args) -> ModelComparison:
    cyl, train, valid, name, opts, horizon, penalty, load = args
    t0 = time.perf_counter()
    try:
        with np.errstate(all="ignore"):
            res = identify_model(cyl, [train], name, opts, load)
            val = validate(res.cylinder, res.effects, valid, horizon)
    except Exception as e:  # noqa: BLE001  one model's failure must not lose the others' results
        return ModelComparison(model=name, n_params=0, status="failed", error=f"{type(e).__name__}: {e}",
                               wall_s=time.perf_counter() - t0)
    values, std = model_parameters(res)
    k = len(res.params)
    nrms = val.normalized_rms()
    unknown = tuple(n.split(".", 1)[1] if "." in n else n for n in not_determined(
        {n: e.value for n, e in res.params.items()}, {n: e.std for n, e in res.params.items()},
        {n for n, e in res.params.items() if e.at_bound}))
    status = "not_determined" if unknown and res.solver["status"] == "converged" else res.solver["status"]
    return ModelComparison(model=name, n_params=k, params=values, std=std, status=status, not_determined=unknown,
                           iterations=res.solver["iterations"], rmse_x_train=res.fit["rmse_x"],
                           rmse_x_validation=val.rmse("x"), normalized_rms=nrms,
                           score=nrms * (1 + penalty * k) if math.isfinite(nrms) else math.inf,
                           wall_s=time.perf_counter() - t0, start=res.solver.get("start", ""))


def _expected_cost(model: str) -> int:
    """Estimated parameters: a proxy of a model's fitting time (the slowest start first)."""
    return 3 if model == "nominal" else len(estimated_parameters(fit_spec(model)))


def compare_friction_models(cyl: Cylinder, train: Run, valid: Run, models: Sequence[str],
                            horizon_s: float = 1.0, workers: int = 1, penalty_per_param: float = 0.01,
                            options: IdentifyOptions = IdentifyOptions(max_iter=40),
                            progress: Callable[[str], None] | None = None,
                            load: float | None = None) -> list[ModelComparison]:
    """Each model identified on TRAIN by multiple shooting, simulated on VALID segment by
    segment (diagnose.validate: parameters never see VALID), ranked by the noise-weighted
    validation error of all outputs times (1 + penalty_per_param x estimated parameters);
    failed models last. 'nominal' is the cylinder file's model (Fc, Fv, kp). `load` is the
    normal load Fn the load models are identified at (else their default, 0). `progress`
    gets one line per model as it finishes, with its own and the total elapsed time."""
    for m in models:
        check_model(m)
    t0 = time.perf_counter()
    opts = replace(options, threads=1) if workers > 1 else options
    order = sorted(models, key=_expected_cost, reverse=True) if workers > 1 else list(models)
    jobs = [(cyl, train, valid, m, opts, horizon_s, penalty_per_param, load) for m in order]
    rows: list[ModelComparison] = []

    def done(row: ModelComparison) -> None:
        rows.append(row)
        if progress:
            what = f"failed: {row.error}" if row.status == "failed" else \
                f"{row.status}, VALID {row.normalized_rms:.3g} x noise"
            progress(f"  [{len(rows)}/{len(jobs)}] {row.model:10s} {row.wall_s:6.1f} s ({what}); "
                     f"{time.perf_counter() - t0:.0f} s elapsed")

    if workers > 1 and len(jobs) > 1:
        with ProcessPoolExecutor(min(workers, len(jobs))) as pool:
            for fut in as_completed([pool.submit(_compare_one, j) for j in jobs]):
                done(fut.result())
    else:
        for j in jobs:
            done(_compare_one(j))
    return sorted(rows, key=lambda r: (r.status == "failed", r.score))
