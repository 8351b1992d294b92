"""The candidates' fits: each re-identified on TRAIN from one start (the first pass in process
pools), validated on VALID where it fits TRAIN better, the best start per candidate kept, the
screen that validates only what fits TRAIN well, and the further starts after the first pass."""
from __future__ import annotations

import copy
import math
import time
from dataclasses import replace
from typing import Callable

import numpy as np

from sim.effects import Effect

from ..files import Run
from ..identify import IdentificationError, IdentifyOptions, Validation, identify, validate
from ..parallel import iter_jobs, runs_in_pool, workers_here
from .candidates import (NESTED_START, Candidate, NominalFit, candidate_starts, closes_gap, explained_share,
                         near_noise, neutral_start, score_candidate)
from .options import DiagnoseOptions


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


# a nested fit that converges within this many iterations without a gain did not move (stiction
# from no break-away force): its defaults are fitted in the same job
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
        # serve mechanical effects better than the nominal trajectory)
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
        # it gained, but stayed above what its caller needs of it (the pair: best_pair)
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
    if base.normalized_rms() <= opts.closed_gap or any(near_noise(c, opts) for c in cands):
        return []
    ranked = sorted((c for c in cands if c.significant), key=lambda c: -c.score)
    leaders = {c.effect for c in ranked[:opts.leaders]}
    retry = leaders | {c.effect for c in cands if not math.isfinite(c.shrink)
                       and c.status not in ("screened_out", "not_validated")}
    if ranked and explained_share(base, ranked[0].validation) >= opts.dominant:
        leaders = retry = {ranked[0].effect}
    return [(n, k) for n in order for k in range(1, len(candidate_starts(n)))
            if (n, k) not in tried and ((k == 1 and n in retry) or (k > 1 and (not leaders or n in leaders)))]
