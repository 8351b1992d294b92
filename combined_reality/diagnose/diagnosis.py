"""Diagnose the sim-to-real gap: where it lies, which unmodelled effect causes it, and how
far it shrinks once that effect is added.

The nominal model is identified on TRAIN and scored on VALID, a run the fit never saw.
The score is the simulation error over a fixed horizon: VALID is cut into segments of
about `horizon_s` (cut where the piston moves, so that its state is well determined),
and each segment is simulated open loop with the recorded command from an initial state
fitted to that segment alone (the model's parameters stay fixed: nothing of VALID enters
the model). A correct model then leaves the sensor noise, whatever the horizon.

Each candidate effect extends the one plant, is re-identified on TRAIN (friction and the
effect's own parameters, from the nominal fit and from the effect's alternative starts;
the start with the lowest TRAIN cost is kept) and scored the same way. Candidates are
ranked by the improvement of the noise-weighted validation error of all outputs (x, p1,
p2), less a penalty per added parameter; `shrink` is the position RMSE's, as docs/formats.md
defines it. An improvement is significant when no sensor noise could make the nominal
model look that much worse than the candidate (z above `min_z`, see validation_gain) and
the all-output error shrinks by `min_shrink` at least; the verdict is `none` when no
candidate's is.
"""
from __future__ import annotations

import copy
import math
import os
import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from sim.compiled import plant_columns
from sim.cylinder import Cylinder
from sim.effects import EFFECTS, Effect, make_effect

from ..files import Run
from ..progress import counter, stage_steps
from ..parallel import iter_jobs, run_jobs, runs_in_pool, workers_here
from ..identify import (IdentificationError, IdentifyOptions, Validation, equation_error_friction,
                        friction_from_newton, identify, savgol_kernels, derivative_kernels, validate, validation_gain,
                        validation_segments, velocity_estimate)


@dataclass(frozen=True)
class DiagnoseOptions:
    candidates: tuple[str, ...] = tuple(EFFECTS)
    horizon_s: float = 1.0  # validation simulation horizon
    min_z: float = 3.0  # z statistic of the validation gain a verdict needs (validation_gain)
    min_shrink: float = 0.02  # ... and this shrink of the all-output validation error
    penalty_per_param: float = 0.01  # shrink charged per added parameter when ranking
    pair: bool = True  # try the best pair when one effect leaves a significant gap
    max_iter: int = 20  # Gauss-Newton iterations of a candidate fit; no wall-clock limit: a fit
    # cut by time would make the verdict depend on the machine's load
    closed_gap: float = 1.2  # a candidate leaving at most this x the noise has closed the gap
    explained: float = 0.5  # a verdict must explain this share of the gap (excess error variance)
    # calibrate the cylinder file's guesses on TRAIN with every candidate (diagnose.calibrated): the
    # nominal calibration is the candidate `none`
    calibrate: bool = False
    # with calibrate: a candidate is calibrated as a whole when its screen (in the stage that sees
    # it) removes this share of that stage's excess above the noise, and screen_share of the best
    # screen's; the `leaders` best of them
    screen_min: float = 0.2
    # ... and the calibration without an effect is given up (status above_reference) once it stays
    # above this multiple of the best screened candidate's calibrated TRAIN cost for
    # IdentifyOptions.give_up_after iterations in a row: it cannot become the better model
    nominal_give_up: float = 1.25
    # ... and a significant candidate whose calibration removes this share of what the calibration
    # without an effect leaves on TRAIN above the noise leaves the lower screens uncalibrated
    train_dominant: float = 0.9
    # ... and a candidate that removes train_explains of what the calibration without an effect
    # leaves on TRAIN above the noise, where that is train_gap x the noise or more, counts when it
    # improves VALID significantly (z) by less than min_shrink: VALID holds what the calibrated
    # model extrapolates to beside the effect (diagnose.calibrated.by_train)
    train_explains: float = 0.5
    train_gap: float = 1.1
    leaders: int = 3  # further starts for this many of the best significant candidates
    # a candidate that explains this share of the gap after the first pass leaves nothing for
    # the other effects' further starts: only its own run (they can only improve its figure)
    dominant: float = 0.98
    # a pair is the verdict when it closes the gap, or when the second effect explains this
    # share of what the first leaves (a partner that imitates part of a single effect's misfit
    # takes less; with 0.5, a stiction fit in a local minimum was named stiction+mass)
    pair_rest: float = 0.8
    # a pair fit that explains less than this share of what it needs to change the verdict
    # (pair_need, of the single effect's excess cost on TRAIN) for IdentifyOptions.give_up_after
    # iterations in a row is given up, not validated: the pair of a single-effect case crept for
    # 20 iterations at a ninth of what the single effect left
    pair_give_up: float = 0.5
    min_train_gain: float = 1e-3  # a candidate must cut the TRAIN cost by this share to be validated
    # ... and by this share of the best candidate's cut (the screen): what imitates a sliver
    # of the misfit on TRAIN neither wins on VALID nor partners the winner
    screen_share: float = 0.1
    workers: int = max(1, os.cpu_count() or 1)


def _rmse(r: np.ndarray) -> float:
    r = r[np.isfinite(r)]
    return float(np.sqrt(np.mean(r * r))) if r.size else math.nan


# ------------------------------------------------------------------ where

def operating_regions(cyl: Cylinder, run: Run) -> dict[str, np.ndarray]:
    """Boolean masks of the operating regimes of a run: direction, speed bands, reversals,
    stroke zones, valve near centre, high flow, time spans."""
    v = velocity_estimate(run.t, run.x)
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
        masks[f"time: quarter {q + 1}"] = (t_rel >= q / 4) & ((t_rel < (q + 1) / 4) if q < 3 else (t_rel <= 1))
    return masks


MIN_REGION_FRACTION = 0.01  # a regime with fewer samples is listed, never singled out


def regions(cyl: Cylinder, run: Run, base: Validation, best: Validation | None = None) -> list[dict]:
    """Where the validation position error lies: share of the squared error per operating
    regime, how over-represented it is (share / fraction of samples), and the position RMSE
    there before and (with the verdict's effect) after; most concentrated first, regimes
    with under MIN_REGION_FRACTION of the samples last."""
    r = base.residual[base.outputs.index("x")]
    ok = np.isfinite(r)
    e2 = np.where(ok, r, 0.0) ** 2
    total = float(e2.sum()) or 1.0
    out = []
    for where, m in operating_regions(cyl, run).items():
        m = m & ok
        frac = float(m.sum()) / max(int(ok.sum()), 1)
        if frac == 0:
            continue
        share = float(e2[m].sum()) / total
        row = {"where": where, "share_of_error": share, "fraction_of_samples": frac,
               "concentration": share / frac, "rmse_x": float(np.sqrt(e2[m].mean()))}
        if best is not None:
            row["rmse_x_after"] = best.rmse("x", m)
        out.append(row)
    # a regime of a handful of samples can look concentrated by chance: those last
    return sorted(out, key=lambda r: (r["fraction_of_samples"] < MIN_REGION_FRACTION, -r["concentration"]))


def whiteness(resid: np.ndarray, lags: int = 20, decimate: int = 10) -> dict:
    """Ljung-Box statistic of a residual (decimated, to 10 ms at 1 kHz, where sensor noise no
    longer dominates) and its first autocorrelation; `white` at the 0.1 % level."""
    from scipy.special import chdtrc  # chi2's survival function, without scipy.stats's 0.6 s import

    r = resid[np.isfinite(resid)][::decimate]
    r = r - r.mean()
    n = len(r)
    den = float(r @ r) or 1.0
    acf = np.array([float(r[:-k] @ r[k:]) / den for k in range(1, min(lags, n - 1) + 1)])
    q = n * (n + 2) * float(np.sum(acf ** 2 / (n - np.arange(1, len(acf) + 1))))
    p = float(chdtrc(len(acf), q)) if len(acf) else 1.0
    return {"ljung_box_q": q, "lags": len(acf), "p_value": p, "acf_1": float(acf[0]) if len(acf) else 0.0,
            "white": bool(p > 1e-3)}


# ------------------------------------------------------------------ which

@dataclass
class Candidate:
    effect: str  # a vocabulary word, or "a+b" for a pair
    shrink: float = math.nan
    rmse_x_validation: float = math.nan
    params: dict[str, float] = field(default_factory=dict)
    std: dict[str, float] = field(default_factory=dict)
    score: float = -math.inf
    status: str = "failed"
    shrink_all: float = math.nan
    z: float = math.nan
    significant: bool = False
    friction: dict[str, float] = field(default_factory=dict)
    train_cost: float = math.nan
    iterations: int = 0
    start: int = 0
    wall_s: float = 0.0
    error: str | None = None
    validation: Validation | None = field(default=None, repr=False)
    effects: tuple[Effect, ...] = field(default=(), repr=False)
    nodes: np.ndarray | None = field(default=None, repr=False)  # TRAIN node states of the fit
    cylinder: Cylinder | None = field(default=None, repr=False)  # the fitted model, for its validation
    calibration: dict | None = None  # with DiagnoseOptions.calibrate: how the candidate was calibrated

    @property
    def n_params(self) -> int:
        return len(self.params)

    def to_json(self) -> dict:
        out = {"effect": self.effect, "shrink": self.shrink, "rmse_x_validation": self.rmse_x_validation,
               "params": self.params, "std": self.std, "score": self.score, "significant": self.significant,
               "shrink_all": self.shrink_all, "z": self.z, "status": self.status,
               "friction": self.friction, "iterations": self.iterations, "start": self.start,
               "wall_s": round(self.wall_s, 3)}
        if self.validation is not None:
            out["rmse_p1_validation"] = self.validation.rmse("p1")
            out["rmse_p2_validation"] = self.validation.rmse("p2")
            out["normalized_rms_validation"] = self.validation.normalized_rms()
        if self.error:
            out["error"] = self.error
        if self.calibration is not None:
            out["calibration"] = self.calibration
        return out


NESTED_START = 0  # the start index of "the nominal optimum with the effect at its neutral value"


def neutral_start(name: str) -> Effect:
    """The candidate at its neutral value (the nominal model to rounding; a value below the
    identification range, heat_transfer's h = 0, at that range's bound), shapes at defaults."""
    cls = EFFECTS[name]
    return make_effect(name, {k: min(max(v, cls.PARAMS[k].lower), cls.PARAMS[k].upper)
                              for k, v in cls.NEUTRAL.items()})


def has_nested_start(name: str) -> bool:
    """Whether the candidate's neutral value lies inside its identification range: heat
    exchange's (h = 0) does not, and from the range's bound its fit only creeps."""
    cls = EFFECTS[name]
    return all(cls.PARAMS[k].lower <= v <= cls.PARAMS[k].upper for k, v in cls.NEUTRAL.items())


def candidate_starts(name: str) -> list[Effect]:
    """The identification starts of a candidate: neutral from the nominal optimum (start 0:
    a fit from there can only improve on the nominal model), its defaults from the cylinder
    file (start 1), then its alternatives."""
    cls = EFFECTS[name]
    return [neutral_start(name), make_effect(name)] + [make_effect(name, s) for s in cls.STARTS]


@dataclass
class NominalFit:
    """What every candidate fit starts from and is compared with: the cylinder file (the
    friction start of the default and alternative starts comes from the equation-error
    prefit, as for the nominal fit: a nominal fit distorted by a strong effect is a poor
    start), the nominal optimum (friction and node states: the nested start), the nominal
    fit's TRAIN cost and its validation."""

    config: Cylinder
    optimum: Cylinder
    nodes: np.ndarray | None
    train_cost: float
    validation: Validation
    noise_cost: float = math.nan  # the TRAIN cost of a model at the sensor noise
    # the TRAIN cost a fit from here must get under within IdentifyOptions.give_up_after
    # iterations (NaN: the train cost itself, plus min_train_gain of it)
    give_up_above: float = math.nan


# a first fit that found nothing on TRAIN: no validation; its defaults are tried as well
_NO_GAIN = ("no_gain_on_train", "worse_than_nominal", "failed", "no_better_start", "falls_short")


def fit_candidate(args) -> Candidate:
    """Re-identify on TRAIN with the effects added from one start, then score on VALID when it
    fits TRAIN better than the nominal model. args: (NominalFit, TRAIN, VALID, effects, start
    index of candidate_starts, DiagnoseOptions, validation segments)."""
    nominal, train, valid, effects, start, opts, segments = args
    c = _fit(nominal, train, effects, start, opts)
    return c if c.status in _NO_GAIN else validate_candidate((c, nominal, valid, opts, segments))


def further_fit(args) -> Candidate:
    """A further start's fit on TRAIN alone (further_scored scores it). args: (NominalFit, TRAIN,
    effects, start index of candidate_starts, DiagnoseOptions)."""
    nominal, train, effects, start, opts = args
    return _fit(nominal, train, effects, start, opts)


def further_scored(jobs: list, beat: dict[str, float], nominal: NominalFit, valid: Run, segments,
                   base_rmse_x: float, opts: DiagnoseOptions) -> list[Candidate]:
    """The further starts (`jobs` of further_fit) fitted over `opts.workers` processes and scored on
    VALID in job order as they come, while the pool fits the later ones (a validation then
    takes one process). Only the start with the lowest TRAIN cost is kept (_best_starts): one
    that ends at or above its effect's best scored start (`beat`: the effect's TRAIN cost,
    updated as starts are scored) is not scored, said in words. The results end at the first
    start that closes the gap: the same ones on any number of workers."""
    fits = iter_jobs(further_fit, jobs, opts.workers)
    pooled = runs_in_pool(opts.workers, len(jobs))
    done = []
    try:
        for i, c in enumerate(fits):
            if c.status not in _NO_GAIN:
                if c.train_cost >= beat.get(c.effect, math.inf):
                    c.error = (f"this start fits TRAIN worse than the effect's best start (cost {c.train_cost:.4g} "
                               f"vs {beat[c.effect]:.4g}, {c.status} after {c.iterations} iterations): not validated")
                    c.status = "no_better_start"
                else:
                    busy = pooled and i < len(jobs) - 1  # the pool is gone when the last start comes
                    c = validate_candidate((c, nominal, valid, replace(opts, workers=1) if busy else opts, segments))
                    if c.validation is not None:
                        beat[c.effect] = c.train_cost
            done.append(c)
            if closes_gap(c, nominal.validation, base_rmse_x, opts):
                break
    finally:
        fits.close()  # stops the fits still running
    return done


def _call(job):
    """A job of a process pool: (function, its arguments)."""
    fn, args = job
    return fn(*args)


def fit_first(args) -> list[Candidate]:
    """The first pass of one candidate, on TRAIN only: its first start and, where a gap is to be
    explained and the nested start stalled (no gain on TRAIN, converged within
    `_STALLED_ITERATIONS`), its defaults too, in the same job. From the neutral value at a
    bound some effects never move (stiction without a break-away force); their defaults must
    not wait for a second round. A nested fit that moved and found nothing gets them there,
    if the gap is still open. args: (NominalFit, TRAIN, effect, start index, DiagnoseOptions,
    whether the nominal model leaves a gap on VALID)."""
    nominal, train, effect, start, opts, gap = args
    out = [_fit(nominal, train, (candidate_starts(effect)[start],), start, opts)]
    first = out[0]
    if gap and start == NESTED_START and first.status == "no_gain_on_train" \
            and first.iterations <= _STALLED_ITERATIONS:
        out.append(_fit(nominal, train, (candidate_starts(effect)[1],), 1, opts))
    return out


# a nested fit that converges within this many iterations without a gain did not move: stiction
# from no break-away force, 1 iteration on cylinder A's stiction run; found from its defaults
_STALLED_ITERATIONS = 2


def _fit(nominal: NominalFit, train: Run, effects: tuple[Effect, ...], start: int, opts: DiagnoseOptions) -> Candidate:
    t0 = time.perf_counter()
    label = "+".join(e.name for e in effects)
    try:
        with np.errstate(all="ignore"):  # a diverging candidate is caught by its costs, not by warnings
            c = _fit_on_train(nominal, train, effects, start, opts, label)
    except (IdentificationError, ValueError, np.linalg.LinAlgError, RuntimeError) as e:
        # one candidate failing must not end the diagnosis
        c = Candidate(effect=label, status="failed", start=start,
                      error=f"the fit could not be computed ({type(e).__name__}: {e})")
    c.wall_s = time.perf_counter() - t0
    return c


def validate_candidate(args) -> Candidate:
    """A fitted candidate with its validation on VALID (the nominal model's validation as the
    segments' fallback start). args: (Candidate, NominalFit, VALID, DiagnoseOptions, segments)."""
    c, nominal, valid, opts, segments = args
    t0 = time.perf_counter()
    c = copy.copy(c)
    try:
        with np.errstate(all="ignore"):
            c.validation = validate(c.cylinder, c.effects, valid, opts.horizon_s, segments=segments,
                                    fallback=nominal.validation, workers=workers_here(opts.workers))
        c.rmse_x_validation = c.validation.rmse("x")
    except (IdentificationError, ValueError, np.linalg.LinAlgError, RuntimeError) as e:
        c.status, c.error = "failed", f"the validation could not be computed ({type(e).__name__}: {e})"
    c.wall_s += time.perf_counter() - t0
    return c


def _fit_on_train(nominal, train, effects, start, opts, label) -> Candidate:
    names = ("Fc", "Fv", "kp") + tuple(e.key(k) for e in effects for k in e.PARAMS)
    # candidates have further starts of their own (further_starts); the nominal model was fitted
    # without a restart too, so that every candidate is measured against the same baseline
    # the model's threads: one in a pool's process, all of them where a fit runs alone (the pair)
    reference = (nominal.train_cost * (1 + opts.min_train_gain) if math.isnan(nominal.give_up_above)
                 else nominal.give_up_above)
    options = IdentifyOptions(estimate=names, threads=workers_here(opts.workers), max_iter=opts.max_iter,
                              restart_misfit=False, give_up_above=reference)
    if start == NESTED_START:
        # from the nominal optimum, node states included: the fit starts at the nominal
        # model's TRAIN cost and a descent can only lower it. A single effect gets half the
        # iterations: it converges fast when the effect is absent or its basin is there; one
        # that creeps gets its defaults next (diagnose)
        iters = max(1, opts.max_iter // 2) if len(effects) == 1 else opts.max_iter
        res = identify(nominal.optimum, [train], replace(options, prefit=False, max_iter=iters),
                       effects=effects, nodes=nominal.nodes)
    else:
        # friction from the equation-error prefit, node states from the measurements (they
        # served better than the nominal trajectory for mechanical effects)
        res = identify(nominal.config, [train], options, effects=effects)
    keyed = {e.key(k): (e.name, k) for e in effects for k in e.PARAMS}
    pname = (lambda n: keyed[n][1]) if len(effects) == 1 else (lambda n: n)
    c = Candidate(effect=label, params={pname(n): res.params[n].value for n in keyed},
                  std={pname(n): res.params[n].std for n in keyed},
                  status=res.solver["status"], friction={n: res.params[n].value for n in ("Fc", "Fv", "kp")},
                  train_cost=res.solver["cost"], iterations=res.solver["iterations"], start=start,
                  effects=res.effects, nodes=res.nodes, cylinder=res.cylinder)
    gain = 1.0 - c.train_cost / nominal.train_cost
    if gain < -1e-3:
        # kept only if no start does better (_best_starts); then _nested_floor replaces it
        c.status = "worse_than_nominal"
        c.error = (f"this start ended worse on TRAIN than the nominal model it contains (cost "
                   f"{c.train_cost:.4g} vs {nominal.train_cost:.4g}, {res.solver['status']} after "
                   f"{res.solver['iterations']} iterations)")
    elif gain < opts.min_train_gain:
        # the fast screen: what does not fit TRAIN better cannot explain the gap
        c.status = "no_gain_on_train"
        c.error = f"fits TRAIN no better than the nominal model ({gain:+.2%} of its cost): not validated"
    elif res.solver["status"] == "above_reference" and c.train_cost > reference:
        # it gained, but stayed above what its caller needs of it (the pair: _best_pair)
        c.status = "falls_short"
        c.error = (f"stayed above the TRAIN cost it had to reach ({c.train_cost:.4g} vs {reference:.4g}) for "
                   f"{options.give_up_after} iterations in a row: given up, not validated")
    return c


def _nested_floor(c: Candidate, nominal: NominalFit) -> Candidate:
    """A candidate contains the nominal model (at its neutral value): when no start fitted TRAIN
    better, it is that model, never worse. Said in words; its parameters are the neutral ones
    and no friction was re-identified."""
    if c.status not in ("worse_than_nominal", "failed") or "+" in c.effect:
        return c
    why = c.error or c.status
    neutral = neutral_start(c.effect)
    return Candidate(effect=c.effect, status="no_gain_on_train", params=neutral.as_dict(),
                     std={k: math.nan for k in neutral.PARAMS}, train_cost=nominal.train_cost,
                     iterations=c.iterations, start=NESTED_START, wall_s=c.wall_s, effects=(neutral,),
                     error=f"no start fitted TRAIN better than the nominal model ({why}); the candidate "
                           "is reported at its neutral value, i.e. the nominal model: not validated")


def best_of_starts(results: list[Candidate], nominal: NominalFit) -> list[Candidate]:
    """Per candidate, the start that fitted TRAIN best (VALID never chooses); never worse than
    the nominal model it contains (_nested_floor)."""
    return [_nested_floor(c, nominal) for c in _best_starts(results)]


def _best_starts(results: list[Candidate]) -> list[Candidate]:
    best: dict[str, Candidate] = {}
    for c in results:
        old = best.get(c.effect)
        ok, old_ok = c.validation is not None, old is not None and old.validation is not None
        better = old is None or (ok and not old_ok) or (ok == old_ok and c.train_cost < old.train_cost)
        if better:
            if old is not None:
                c.wall_s += old.wall_s
            best[c.effect] = c
        else:
            old.wall_s += c.wall_s
    return list(best.values())


def validate_screened(cands: list[Candidate], nominal: NominalFit, valid: Run, segments, base_rmse_x: float,
                      opts: DiagnoseOptions, say: Callable[[str], None] = lambda _m: None) -> list[Candidate]:
    """The first pass's candidates scored on VALID, in the order of their TRAIN cost, the best
    fit first; in that order the validations end at the first candidate that closes the gap
    (closes_gap: whatever fits TRAIN less well can at best tie with it). Not validated either:
    a candidate whose TRAIN gain is under `screen_share` of the best one's (the screen). Those
    rows say why in words."""
    base = nominal.validation
    # one candidate per effect (best_of_starts)
    gain = {c.effect: 1.0 - c.train_cost / nominal.train_cost for c in cands if c.status not in _NO_GAIN}
    top = max(gain.values(), default=0.0)
    leader = next((n for n, g in gain.items() if g == top), "")
    keep = sorted((c for c in cands if gain.get(c.effect, -math.inf) >= opts.screen_share * top),
                  key=lambda c: c.train_cost)
    for c in cands:
        if c.effect in gain and gain[c.effect] < opts.screen_share * top:
            c.status = "screened_out"
            c.error = (f"fits TRAIN {gain[c.effect]:.2%} better than the nominal model, under {opts.screen_share:.0%} "
                       f"of the best candidate's gain ({leader}: {top:.2%}): not validated (the screen)")
    if keep:
        say(f"  validating {len(keep)} of them on VALID, the best fit on TRAIN first ...")
    # one candidate after the other, its segments over all processes: a candidate's validation
    # is done before the next one starts (the first that closes the gap ends them), and no
    # process idles while the last candidate's segments are fitted
    done = []
    for c in keep:
        done.append(validate_candidate((c, nominal, valid, opts, segments)))
        if closes_gap(done[-1], base, base_rmse_x, opts):
            break
    closer = done[-1] if len(done) < len(keep) else None
    for c in keep[len(done):]:
        c.status = "not_validated"
        c.error = (f"not validated: {closer.effect}, which fits TRAIN better, closed the gap on VALID to near the "
                   "noise first")
    scored = {d.effect: d for d in done}
    out = [scored.get(c.effect, c) for c in cands]
    for c in out:
        score_candidate(c, base, base_rmse_x, opts)
    return out


def score_candidate(c: Candidate, base: Validation, base_rmse_x: float, opts: DiagnoseOptions) -> None:
    """A validated candidate's figures against the baseline `base` (shrink, z, significance,
    score), in place; one whose simulation of VALID diverges is marked so."""
    if c.validation is None or not c.validation.normalized_rms() < 1e6 * base.normalized_rms():
        if c.validation is not None:
            c.status, c.error = "diverged", ("the re-identified model's simulation of VALID diverges (not finite, "
                                             "or a million times the nominal model's error)")
        return
    c.shrink = 1.0 - c.rmse_x_validation / base_rmse_x
    c.shrink_all, c.z = validation_gain(base, c.validation)
    c.significant = bool(c.z >= opts.min_z and c.shrink_all >= opts.min_shrink)
    c.score = c.shrink_all - opts.penalty_per_param * c.n_params


# ------------------------------------------------------------------ the diagnosis

@dataclass
class Diagnosis:
    """Everything a diagnosis found; `to_json()` is the docs/formats.md document, the arrays feed
    the report and Rerun."""

    cylinder: Cylinder  # with the nominal friction identified on TRAIN
    train: Run
    valid: Run
    options: DiagnoseOptions
    baseline: dict
    verdict: str
    ranking: list[Candidate]
    pair: Candidate | None
    regions: list[dict]
    subsystems: list[dict]
    whiteness: dict
    correlations: list[dict]
    base_validation: Validation
    wall_s: float = 0.0
    verdict_note: str = ""  # why the verdict is a pair or `unexplained`
    calibration: dict | None = None  # with DiagnoseOptions.calibrate: the file's mis-set quantities

    @property
    def best(self) -> Candidate | None:
        """The candidate the verdict names (a single effect or the pair); None for `none` and
        `unexplained`."""
        if self.pair is not None and self.verdict == self.pair.effect:
            return self.pair
        return next((c for c in self.ranking if c.effect == self.verdict), None)

    @property
    def runner(self) -> Candidate | None:
        """The best significant candidate, also when the verdict is `unexplained`."""
        return next((c for c in self.ranking if c.significant), None)

    @property
    def velocity(self) -> np.ndarray:
        return velocity_estimate(self.valid.t, self.valid.x)

    def to_json(self) -> dict:
        return {
            "baseline": self.baseline,
            "verdict": self.verdict,
            "verdict_note": self.verdict_note,
            "calibration": self.calibration,
            "ranking": [c.to_json() for c in self.ranking],
            "pair": self.pair.to_json() if self.pair is not None else None,
            "regions": self.regions,
            "subsystems": self.subsystems,
            "whiteness": self.whiteness,
            "correlations": self.correlations,
            "options": {"horizon_s": self.options.horizon_s, "min_z": self.options.min_z,
                        "min_shrink": self.options.min_shrink, "penalty_per_param": self.options.penalty_per_param,
                        "candidates": list(self.options.candidates)},
            "segments": len(self.base_validation.segments),
            "wall_s": round(self.wall_s, 3),
        }


# how far a calibrated quantity must be from the file's value to count as mis-set (beyond 3 std)
_MIS_SET_ABSOLUTE = {"offset_p1": 1000.0, "offset_p2": 1000.0, "external_force": 1.0}  # Pa, Pa, N
_MIS_SET_RELATIVE = 0.02


def mis_set_quantities(file_cyl: Cylinder, params: dict) -> list[dict]:
    """The cylinder file's quantities that a calibration on TRAIN found off (beyond 3 std and
    2 %, offsets 1 kPa, a constant force 1 N), from its estimates (`params`: name -> Estimate):
    name, file and calibrated value, std, unit. The valve characteristic is one row: its largest
    departure over the knots of both directions."""
    from sim.cylinder import FLOW_CHARACTERISTIC

    out, flow = [], []
    for n, e in params.items():
        if n in ("Fc", "Fv", "kp") or "." in n:
            continue
        f = file_cyl.value(n)
        d = e.value - f
        limit = _MIS_SET_ABSOLUTE.get(n, _MIS_SET_RELATIVE * abs(f))
        off = abs(d) > max(limit, 3 * e.std if math.isfinite(e.std) else 0.0)
        if n in FLOW_CHARACTERISTIC:
            if n.startswith("flow_") and off:
                flow.append((abs(d) / max(abs(f), 1e-12), n, f, e))
            continue
        if off:
            out.append({"quantity": n, "file": f, "calibrated": e.value, "std": e.std, "unit": e.unit,
                        "change": d / f if f else math.nan})
    if flow:
        rel, n, f, e = max(flow)
        out.append({"quantity": "valve characteristic", "file": f, "calibrated": e.value, "std": e.std,
                    "unit": e.unit, "change": (e.value - f) / f if f else math.nan, "at": n})
    return out


def diagnose_as_filed(cyl: Cylinder, train: Run, valid: Run, options: DiagnoseOptions = DiagnoseOptions(),
                      progress: Callable[[str], None] | None = None) -> Diagnosis:
    """The diagnosis with the cylinder file's values as they are: the nominal model's friction
    identified on TRAIN, every candidate nested from it (module docstring)."""
    t_start = time.perf_counter()
    say = progress or (lambda _m: None)
    opts = options
    say("identifying the nominal model on TRAIN ...")
    base = identify(cyl, [train], IdentifyOptions(restart_misfit=False), progress=stage_steps(progress, "nominal"))
    nominal = base.cylinder
    segments = validation_segments(valid, opts.horizon_s)
    base_val = validate(nominal, (), valid, opts.horizon_s, segments=segments, workers=opts.workers)
    sigma = base.solver["residual_sigma"]
    start = NominalFit(cyl, nominal, base.nodes, base.solver["cost"], base_val,
                       noise_cost=base.solver["cost"] / sigma ** 2 if sigma > 0 else math.nan)
    base_rmse = base_val.rmse("x")
    say(f"  validation RMSE of x: {base_rmse * 1e6:.2f} um, all outputs {base_val.normalized_rms():.2f} x the "
        f"sensor noise ({len(segments)} segments of about {opts.horizon_s:g} s)")

    correlations = regressor_correlations(nominal, valid)
    # the slowest fits first (added states, then parameters) so that the processes finish together
    order = sorted(opts.candidates, key=lambda n: (-len(EFFECTS[n].STATES), -len(EFFECTS[n].PARAMS)))
    # first from the nominal optimum (the defaults where the neutral value is out of range)
    first_start = {n: NESTED_START if has_nested_start(n) else 1 for n in order}
    gap = base_val.normalized_rms() > opts.closed_gap
    first = [(fit_first, ((start, train, n, k, opts, gap),)) for n, k in first_start.items()]
    # the subsystem split needs no candidate: last, it fills the process that finishes first
    first.append((subsystem_split, (cyl, nominal, train, valid, base_val, opts, segments)))
    say(f"re-identifying {len(order)} candidate effects on TRAIN from the nominal optimum "
        f"({min(opts.workers, len(first))} processes) ...")
    done_first = run_jobs(_call, first, opts.workers, on_result=counter(progress, "first-pass fits", len(first)))
    subsystems = done_first.pop()
    fitted = [c for cs in done_first for c in cs]
    tried = {(c.effect, c.start) for c in fitted}
    cands = validate_screened(best_of_starts(fitted, start), start, valid, segments, base_rmse, opts, say)
    # the cheapest first: they end at the first start that closes the gap (closes_gap). Each is
    # scored as soon as it and those before it are fitted, while the pool fits the next ones
    more = [(start, train, (candidate_starts(n)[k],), k, opts)
            for n, k in further_starts(cands, base_val, order[::-1], tried, opts)]
    if more:
        say(f"  trying {len(more)} further starts (the effects' defaults and alternatives) ...")
        done = further_scored(more, {c.effect: c.train_cost for c in cands if c.validation is not None}, start,
                              valid, segments, base_rmse, opts)
        if len(done) < len(more):
            say(f"  {done[-1].effect} (start {done[-1].start}) closed the gap: the {len(more) - len(done)} "
                "further starts after it were not needed")
        cands = best_of_starts(cands + done, start)
        for c in cands:
            score_candidate(c, base_val, base_rmse, opts)
    ranking, best = ranked(cands, say)

    pair = None
    if opts.pair and best is not None:
        pair = _best_pair(start, train, valid, ranking, base_val, base_rmse, segments, opts, say)
    verdict, verdict_note = decide(base_val, best, pair, opts)
    if verdict_note:
        say(f"  verdict {verdict}: {verdict_note}")
    shown = pair if pair is not None and verdict == pair.effect else best if verdict != "unexplained" else None

    x_idx = base_val.outputs.index("x")
    return Diagnosis(
        cylinder=nominal, train=train, valid=valid, options=opts,
        baseline={"rmse_x_validation": base_rmse, "rmse_p1_validation": base_val.rmse("p1"),
                  "rmse_p2_validation": base_val.rmse("p2"), "normalized_rms": base_val.normalized_rms(),
                  "friction": {n: e.value for n, e in base.params.items()},
                  "friction_std": {n: e.std for n, e in base.params.items()},
                  "rmse_x_train": base.fit["rmse_x"], "train_cost": base.solver["cost"],
                  "horizon_s": opts.horizon_s,
                  "noise": {"x": float(base_val.noise[0]), "p": float(cyl.sensors.pressure_noise)}},
        verdict=verdict, verdict_note=verdict_note, ranking=ranking, pair=pair,
        regions=regions(nominal, valid, base_val, shown.validation if shown is not None else None),
        subsystems=subsystems, whiteness=whiteness(base_val.residual[x_idx]),
        correlations=correlations, base_validation=base_val, wall_s=time.perf_counter() - t_start)


def ranked(cands: list[Candidate], say: Callable[[str], None]) -> tuple[list[Candidate], Candidate | None]:
    """The scored candidates, each said in a line; ranked, the significant ones first by score; and
    the best one when it is significant."""
    for c in cands:
        say(f"  {c.effect:20s} " + (f"shrink {c.shrink:7.1%}  all outputs {c.shrink_all:7.1%}  z {c.z:6.1f}"
                                     if math.isfinite(c.shrink) else f"not scored: {c.error or c.status}"))
    ranking = sorted(cands, key=lambda c: (not c.significant, -c.score))
    return ranking, ranking[0] if ranking and ranking[0].significant else None


def further_starts(cands: list[Candidate], base: Validation, order: list[str], tried: set[tuple[str, int]],
                   opts: DiagnoseOptions) -> list[tuple[str, int]]:
    """The (effect, start index into candidate_starts) fits to run after the first pass, none of
    those it `tried` already.

    None where no gap is left to explain: the nominal model already fits VALID or a candidate
    closed the gap (to near the noise). Otherwise the defaults of the candidates whose first
    fit found nothing on TRAIN (from the neutral value some effects never move) and of the
    leading ones (a better basin may exist), and the alternative starts of the leading ones
    (of all when none explains anything yet). Leading: the `leaders` significant candidates of
    the best score; the rest only imitate part of the gap. When the best explains `dominant`
    of the gap, only its own further starts run: no other effect's would change the verdict."""
    if base.normalized_rms() <= opts.closed_gap or any(_near_noise(c, opts) for c in cands):
        return []
    ranked = sorted((c for c in cands if c.significant), key=lambda c: -c.score)
    leaders = {c.effect for c in ranked[:opts.leaders]}
    retry = leaders | {c.effect for c in cands if not math.isfinite(c.shrink)
                       and c.status not in ("screened_out", "not_validated")}
    if ranked and explained_share(base, ranked[0].validation) >= opts.dominant:
        leaders = retry = {ranked[0].effect}
    return [(n, k) for n in order for k in range(1, len(candidate_starts(n)))
            if (n, k) not in tried and ((k == 1 and n in retry) or (k > 1 and (not leaders or n in leaders)))]


def closes_gap(c: Candidate, base: Validation, base_rmse_x: float, opts: DiagnoseOptions) -> bool:
    """Whether one fit (of one start) leaves VALID significantly better and near the noise
    (`closed_gap`): then no further start can change the verdict much. Scored on a copy."""
    c = copy.copy(c)
    score_candidate(c, base, base_rmse_x, opts)
    return _near_noise(c, opts)


def _near_noise(c: Candidate, opts: DiagnoseOptions) -> bool:
    """A scored candidate that is significant and leaves VALID within `closed_gap` x the noise."""
    return bool(c.significant and c.validation.normalized_rms() < opts.closed_gap)


def explained_share(base: Validation, cand: Validation | None) -> float:
    """The share of the nominal model's excess error variance (above the sensor noise, over all
    outputs) that a candidate removes on VALID: 1 = down to the noise, 0 = nothing."""
    if cand is None:
        return math.nan
    b2, c2 = base.normalized_rms() ** 2, cand.normalized_rms() ** 2
    return (b2 - c2) / (b2 - 1.0) if b2 > 1.0 else math.nan


def decide(base: Validation, best: Candidate | None, pair: Candidate | None,
           opts: DiagnoseOptions) -> tuple[str, str]:
    """The verdict and, where it is not simply the best single effect, why.

    - `none`: no candidate improves VALID significantly and the nominal model fits it to near
      the noise (`closed_gap`);
    - `unexplained` also when no candidate improves VALID significantly but a gap above
      `closed_gap` remains;
    - the pair `a+b`: it is significantly better than the best single effect, which alone
      leaves a gap above `closed_gap`, and it closes the gap (to `closed_gap`) or together they
      explain `explained` of the gap and the second effect `pair_rest` of what the first leaves;
    - `unexplained`: the best candidate (or pair) improves VALID significantly but leaves most
      of a gap that is well above the noise (a weak winner is no diagnosis);
    - otherwise the best single effect."""
    nb = base.normalized_rms()
    if best is None:
        if nb > opts.closed_gap:  # a gap well above the noise that nothing in the vocabulary touches
            return "unexplained", (f"the nominal model misses VALID by {nb:.2f} x the sensor noise over all "
                                   "outputs and no candidate improves it significantly: the gap's cause is not "
                                   "in the vocabulary")
        return "none", ""
    share = explained_share(base, best.validation)
    left = best.validation.normalized_rms()
    if pair is not None and pair.significant and left > opts.closed_gap:
        pshare = explained_share(base, pair.validation)
        # the second effect must itself explain most of what the first leaves, not a sliver
        # of it (a wrong partner imitates part of any remaining error)
        rest = explained_share(best.validation, pair.validation)
        if (pshare >= opts.explained and rest >= opts.pair_rest) or pair.validation.normalized_rms() <= opts.closed_gap:
            return pair.effect, (f"{best.effect} alone explains {share:.0%} of the gap, together with "
                                 f"{pair.effect.split('+')[1]} {pshare:.0%}: both effects are likely present")
        share = max(share, pshare)
    if share < opts.explained and left > opts.closed_gap:
        return "unexplained", (f"the best candidate, {best.effect}, explains only {share:.0%} of the gap (the "
                               f"nominal model misses VALID by {nb:.2f} x the sensor noise over all outputs, "
                               f"{best.effect} by {left:.2f} x): the gap's cause is not in the vocabulary, or "
                               "several effects combine")
    return best.effect, ""


def _best_pair(nominal: NominalFit, train, valid, ranking, base_val, base_rmse, segments, opts,
               say) -> Candidate | None:
    """The verdict's effect with the runner-up, when the verdict alone leaves a significant
    gap that the runner-up also addresses. Nested: from the best single fit with the
    runner-up at its neutral value, so never worse than the single effect."""
    best = ranking[0]
    second = next((c for c in ranking[1:] if c.significant), None)
    if second is None or best.validation is None:
        return None
    # a pair can be the verdict only where the best candidate leaves a gap (decide)
    if best.validation.normalized_rms() <= opts.closed_gap:
        return None
    say(f"trying the pair {best.effect} + {second.effect} ...")
    # a fit that stays under pair_give_up of what the pair needs to matter (as a share of the
    # first effect's excess cost on TRAIN) gives up, unvalidated
    need = pair_need(base_val, best.validation, opts)
    excess = best.train_cost - nominal.noise_cost
    give_up = best.train_cost - opts.pair_give_up * need * excess if excess > 0 else math.nan
    inner = NominalFit(nominal.config, nominal.config.with_values(best.friction), best.nodes, best.train_cost,
                       best.validation, nominal.noise_cost, give_up)
    c = fit_candidate((inner, train, valid, (best.effects[0], neutral_start(second.effect)), NESTED_START, opts,
                       segments))
    if c.status == "falls_short":
        c.error = (f"together they explain {(best.train_cost - c.train_cost) / excess:.0%} of what {best.effect} "
                   f"leaves on TRAIN above the sensor noise; to change the verdict the pair needs {need:.0%} of "
                   f"it, and its fit stayed under {opts.pair_give_up * need:.0%} for {IdentifyOptions.give_up_after} "
                   "iterations in a row: given up, not validated")
    score_candidate(c, base_val, base_rmse, opts)
    c.significant = c.significant and gain_over(best.validation, c.validation, opts)
    if math.isfinite(c.shrink):
        say(f"  {c.effect}: shrink {c.shrink:.1%}, all outputs {c.shrink_all:.1%}"
            + ("" if c.significant else " (not significantly better than the verdict alone)"))
    else:
        say(f"  {c.effect}: not scored ({c.error or c.status})")
    return c


def pair_need(base: Validation, best: Validation, opts: DiagnoseOptions) -> float:
    """The share of what the best single effect leaves on VALID (its error variance above the
    noise) that the runner-up must explain for the pair to change the verdict (decide): the
    pair is the verdict where it explains `pair_rest` of it or closes the gap (`closed_gap`),
    and a single effect that explains under `explained` of the gap is named, instead of
    `unexplained`, where the pair lifts that to `explained`. The least of these."""
    b2 = best.normalized_rms() ** 2
    need = min(opts.pair_rest, (b2 - opts.closed_gap ** 2) / (b2 - 1.0))
    share = explained_share(base, best)
    if share < opts.explained:
        need = min(need, (opts.explained - share) / (1.0 - share))
    return max(need, 0.0)


def gain_over(ref: Validation, cand: Validation | None, opts: DiagnoseOptions) -> bool:
    """Whether `cand` improves VALID significantly over `ref` (min_z and min_shrink)."""
    if cand is None:
        return False
    shrink, z = validation_gain(ref, cand)
    return z >= opts.min_z and shrink >= opts.min_shrink


# ------------------------------------------------------------------ subsystems and regressors

def equation_errors(nominal: Cylinder, run: Run, half: int = 15) -> dict[str, np.ndarray]:
    """Equation errors of the nominal model at the measured signals (seed 000's method), each
    subsystem on its own:

    force  friction implied by Newton's law with the measured pressures minus the nominal
           friction law refitted to it by linear least squares (so a dynamic fit distorted
           by an unmodelled pneumatic effect does not blame the friction law) (N);
    p1, p2 the measured pressure derivatives minus the nominal chamber equations (valve and
           chambers) evaluated at the smoothed measured state and the command (Pa/s).
    Derivatives and smoothing are Savitzky-Golay over +-`half` samples; the model's chamber
    rates, which follow the command sample by sample, are smoothed by the same filter."""
    from sim.plant import plant_for


    idx, v, F = friction_from_newton(nominal, run, half)
    if len(idx) == 0:
        return {}
    fitted = equation_error_friction(nominal, [run], half)
    fr = nominal.with_values(fitted).friction if fitted else nominal.friction
    dp = np.abs(run.p1[idx] - run.p2[idx])
    eF = F - ((fr.Fc + fr.kp * dp) * np.tanh(v / fr.v_smooth) + fr.Fv * v)
    k0, k1, _ = savgol_kernels(half)
    full = {n: np.convolve(getattr(run, n), k0, mode="same") for n in ("x", "p1", "p2")}
    v_full = np.convolve(run.x, k1, mode="same") / run.sample_period
    dt = run.sample_period
    plant = plant_for(nominal, "command")
    p = np.array(plant.parameter_vector(nominal))
    # the command changes every sample: smooth the model's rates with the same filter as the
    # measured derivative, so both see the same bandwidth
    states = np.vstack([full["p1"], full["p2"], full["x"], v_full])
    rhs_full = plant_columns(plant)(states, run.u[None, :], p)
    rhs = np.vstack([np.convolve(rhs_full[i], k0, mode="same")[idx] for i in range(2)])
    out = {"index": idx, "v": v, "force": eF}
    for i, name in enumerate(("p1", "p2")):
        out[name] = np.convolve(getattr(run, name), k1, mode="same")[idx] / dt - rhs[i]  # (idx: whole windows)
    return out


def subsystem_split(cyl: Cylinder, nominal: Cylinder, train: Run, valid: Run, base_val: Validation,
                    opts: DiagnoseOptions, segments, seed: int = 0) -> list[dict]:
    """Which part of the model carries the gap.

    - the piston force balance (friction, mass) alone: the pressure drive, driven by the
      MEASURED pressures, identified on TRAIN and scored on VALID like the whole model. Its
      floor is not the sensor noise (the noisy measured pressures drive it), so the same
      score on the nominal model's own simulation of VALID with sensor noise added (a
      parametric bootstrap) gives it;
    - the chamber pressures (valve and chambers) in the whole model's validation, with the
      valve near centre (chambers: leakage, heat; a valve that should be shut) and open
      (valve characteristic, timing, supply); their floor is the pressure sensor noise.
    `excess` is (rmse / floor)^2 - 1, the error variance above the floor in units of it;
    `share_of_error` divides the summed excess among the parts."""
    rows = []
    label = "piston force balance (friction, mass), driven by the measured pressures"
    try:
        # one thread: diagnose runs it in a process beside the candidate fits
        mech = identify(cyl, [train], IdentifyOptions(drive="pressure", threads=1, restart_misfit=False))
        mval = validate(mech.cylinder, (), valid, opts.horizon_s, drive="pressure", segments=segments)
        rng = np.random.default_rng(seed)
        sen, sim = cyl.sensors, base_val.simulated
        fake = replace(valid, x=sim[0] + rng.normal(0, sen.position_noise, valid.n),
                       p1=sim[1] + rng.normal(0, sen.pressure_noise, valid.n),
                       p2=sim[2] + rng.normal(0, sen.pressure_noise, valid.n))
        floor = validate(nominal, (), fake, opts.horizon_s, drive="pressure", segments=segments).rmse("x")
        rows.append({"subsystem": label, "output": "x", "rmse": mval.rmse("x"), "floor": floor, "unit": "m",
                     "fraction_of_samples": 1.0})
    except IdentificationError as e:
        rows.append({"subsystem": label, "error": str(e)})
    centre = np.abs(valid.u) < 0.05
    for label, m in (("chamber pressures, valve near centre (chambers, leakage, heat)", centre),
                     ("chamber pressures, valve open (valve characteristic, timing, supply)", ~centre)):
        if m.any():
            r = np.concatenate([base_val.residual[base_val.outputs.index(o)][m] for o in ("p1", "p2")])
            rows.append({"subsystem": label, "output": "p1, p2", "rmse": _rmse(r),
                         "floor": float(cyl.sensors.pressure_noise), "unit": "Pa",
                         "fraction_of_samples": float(m.mean())})
    for r in rows:
        ok = "rmse" in r and math.isfinite(r["rmse"]) and r["floor"] > 0
        r["excess"] = max(0.0, (r["rmse"] / r["floor"]) ** 2 - 1) if ok else 0.0
        r["within_noise"] = bool(r["excess"] < 0.1)
    total = sum(r["excess"] for r in rows)
    for r in rows:
        r["share_of_error"] = r["excess"] / total if total > 0 else 0.0
    return rows


# regressors that each candidate's physics would add to the force or pressure equations
_REGRESSOR_EFFECTS = {
    "stribeck (sign(v) exp(-(v/10 mm/s)^2))": "stiction",
    "direction (sign(v))": "friction_asymmetry",
    "position along the stroke": "friction_position",
    "pressure difference (p1 - p2)": "leakage",
    "command rate (du/dt)": "valve_delay",
    "valve near centre (u, |u| < 0.1)": "valve_deadzone",
    "supply draw (|u| ps)": "supply_droop",
}


def regressor_correlations(nominal: Cylinder, run: Run) -> list[dict]:
    """Fast screen: correlation of the nominal model's equation errors (equation_errors, with
    the friction refitted by equation error on this run so that a distorted dynamic fit
    does not leak into the force error) with regressors the candidates' physics would add.
    Reported, never deciding. There is no regressor for `mass` or the effects with their own
    states: the acceleration correlated with the force error at about -0.5 on every run,
    clean ones too (the derivative filter's lag), so it hinted at nothing."""
    ee = equation_errors(nominal, run)
    if not ee or len(ee["index"]) < 100:
        return []
    idx, v = ee["index"], ee["v"]
    half = 15
    k1, _ = derivative_kernels(half)
    dt = run.sample_period
    g = nominal.geometry
    V1 = g.dead_volume_cap + g.area_cap * run.x[idx]
    V2 = g.dead_volume_rod + g.area_rod * (g.stroke - run.x[idx])
    # chamber errors as volume-weighted rates (mass flow equivalents), net into chamber 1
    e12 = ee["p1"] * V1 - ee["p2"] * V2
    u = run.u[idx]
    du = np.convolve(run.u, k1, mode="same")[idx] / dt
    moving = np.abs(v) > 0.005
    xi = run.x[idx] / g.stroke
    eF = ee["force"]
    regs = {
        "stribeck (sign(v) exp(-(v/10 mm/s)^2))": (eF, np.sign(v) * np.exp(-(v / 0.01) ** 2)),
        "direction (sign(v))": (eF, np.sign(v) * moving),
        "position along the stroke": (eF, np.sign(v) * (xi - 0.5) * moving),
        "pressure difference (p1 - p2)": (e12, -(run.p1[idx] - run.p2[idx])),
        "command rate (du/dt)": (e12, -du),
        "valve near centre (u, |u| < 0.1)": (e12, -u * (np.abs(u) < 0.1)),
        "supply draw (|u| ps)": (ee["p1"] * V1 + ee["p2"] * V2, -np.abs(u)),
    }
    out = []
    step = max(1, int(round(0.005 / dt)))  # decimate: neighbouring samples share the filter
    for name, (e, r_) in regs.items():
        e, r_ = e[::step], r_[::step]
        ok = np.isfinite(e) & np.isfinite(r_)
        e, r_ = e[ok] - e[ok].mean(), r_[ok] - r_[ok].mean()
        den = math.sqrt(float(e @ e) * float(r_ @ r_))
        r = float(e @ r_) / den if den > 0 else 0.0
        out.append({"regressor": name, "hints": _REGRESSOR_EFFECTS[name], "r": r, "n": int(len(e))})
    return sorted(out, key=lambda d: -abs(d["r"]))
