"""Calibration and diagnosis together (`diagnose --calibrate`): the cylinder file's values are
off AND an effect the model lacks may be at work.

A calibration alone bends what it calibrates (the valve, the volumes, the offsets, the friction
law) to imitate an effect it lacks, and a diagnosis that starts from that bent model finds
nothing (a leak: critical ratio 0.66 for 0.38, every candidate without gain). Here each
candidate effect is calibrated WITH the file's quantities, and the calibrated models are compared
on VALID; the nominal calibration is one of them (`none`), not the ground the others stand on.

1. The calibration's first stages, as `calibrate` runs them: the force balance (pressure drive),
   the valve and chambers (chambers drive, driven by the measured motion), and the force
   balance once more through the command-driven model with that valve.
2. Every candidate is screened in the stage that sees it, where it is cheap to fit and cannot be
   imitated by what the other subsystem would bend:
   - pneumatic effects (leakage, heat transfer, valve delay, supply droop) in the valve and
     chambers, with the effect's parameters and the stage's own (the flow characteristic, the
     critical ratio, the dead volumes, the offsets) free, nested from stage 2: the motion is
     measured, so no friction law can imitate them. (With the characteristic held as stage 2 had
     bent it, a leak removed 10 % of that stage's excess above the noise; with it free, 85 %.)
   - mechanical effects (stiction, friction asymmetry, friction along the stroke, friction
     with memory) in the whole command-driven model with the valve and chambers fixed as stage
     2 left them, with the friction, the mass and the constant force free: the force balance
     seen through the pressures the model itself computes. (The pressure drive's own cost is
     dominated by the random walk its noisy input pressures drive: a leak case's friction
     asymmetry "gained" 54 % there with its parameters at 3 % and its interval residual up.)
3. The candidates that remove a clear share of their stage's excess above the noise (choose)
   are calibrated as a whole (every calibrated quantity and the effect, command drive) from
   their staged start (the screen's values and node states, the other subsystem's from its
   stage), the best screen first. Then the whole model without an effect (the nominal
   calibration, `none`), given up once it stays well above the best candidate on TRAIN (it
   cannot become the better model). Where a candidate ends above the nominal calibration's
   TRAIN cost, it is fitted once more nested from it with the effect neutral: a candidate never
   fits TRAIN worse than `none`.
4. The calibrated models are scored on VALID, the best screen first, ending at the first that
   closes the gap or removes nearly all of what `none` leaves on TRAIN; the verdict by the
   rules of the diagnosis (verdict.decide): significance against the nominal calibration, the
   share of the gap explained, the pair. Where no candidate improves VALID and the nominal
   calibration fits TRAIN to the noise, the verdict is `none` (no effect shows in TRAIN).

Two effects of the vocabulary are quantities the calibration estimates under another name
(ABSORBED: the moving mass, the valve's overlap): they are not fitted, and a mis-set mass or
overlap says so. A form of one that the calibrated quantities cannot take (Absorption.form: a
valve that opens to the full command beyond its overlap, a hard dead zone) is screened and
calibrated like any candidate, in that form. Its screen may not see it: with the motion measured,
the calibrated overlap imitates it. So where no candidate explains the gap and the calibration
without an effect stays above the misfit level on TRAIN, that form is calibrated as a whole once
more from that calibration, with the overlap handed over to it (handed_over). What a run cannot
separate beyond that is read from the calibrated candidates' correlations (an effect parameter
that trades off against a calibrated quantity) and from the runs themselves
(calibrate.separability: the motion that tells an effect from what it imitates).
"""
from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Iterable, Mapping, Sequence

import numpy as np

from sim.cylinder import Cylinder
from sim.effects import EFFECTS, Effect

from ..calibrate import (CALIBRATED, DATA_STARTS, MECHANICAL, PNEUMATIC, CalibrateOptions, Calibration, finish,
                         first_stages, force_balance_in_model, misfit_note, model_start, run_stage, separability,
                         stage_summaries, whole_model)
from ..files import Run
from ..identify import IdentificationError, IdentifyResult, Validation, regions, validate, validation_segments
from ..parallel import run_jobs, workers_here
from .candidates import (NESTED_START, Candidate, NominalFit, candidate_starts, closes_gap, departure_z, gain_over,
                         has_nested_start, held_shapes, score_candidate, shapes_label)
from .diagnosis import Diagnosis, mis_set_quantities
from .fits import validate_candidate
from .options import DiagnoseOptions
from .subsystems import regressor_correlations, subsystem_split
from .verdict import decide, fold_absent_partner, pair_need, ranked, with_fold_note
from .where import whiteness

__all__ = ["ABSORBED", "Absorption", "Screen", "WholeFit", "absorbed_note",
           "calibrated_candidates", "choose", "confounded", "diagnose_calibrated", "handed_over", "nested",
           "trade_offs", "unfinished"]

@dataclass(frozen=True)
class Absorption:
    """An effect that is a calibrated quantity under another name: not fitted beside the
    calibration. `form`: the shape values of its form that the calibrated quantities cannot take
    (screened as a candidate in that form); `handed_to`: that form's parameter that takes over
    what the calibration absorbed (handed_over)."""

    quantities: tuple[str, ...]
    form: Mapping[str, float] | None = None
    handed_to: str | None = None


# a gate opens to the full command beyond its overlap, the calibrated characteristic from zero there
# (a reference-plant hard dead zone of 0.004 left the calibrated model at 1.50 x the noise on
# VALID); the gate's overlap takes over the calibrated characteristic's overlaps
ABSORBED = {"mass": Absorption(("mass",)),
            "valve_deadzone": Absorption(("overlap_extend", "overlap_retract"), {"gate": 1.0}, "overlap")}
SCREEN_ITER = 10  # Gauss-Newton iterations of a screen at most
# a screen must remove this share of its stage's cost to be calibrated as a whole: a stage's
# residual near the noise says little of a weak effect (a project-plant leak of 2.3e-5 of the
# valve's conductance: the valve and chambers at 1.009 x, the leak's screen -3.1 % of the cost, its
# conductance within 0.4 %; VALID at 1.71 x without it); the spurious gains of other effects there
# were 0.8 % and less
SCREEN_MIN_GAIN = 0.005
# a screen that has not removed a tenth of its stage's excess above the noise, or half of
# SCREEN_MIN_GAIN of its cost, within SCREEN_GIVE_UP_AFTER iterations is given up (a screen only
# ranks: a fit that leads somewhere gains that much in its first iterations)
SCREEN_GIVE_UP = 0.1
SCREEN_GIVE_UP_AFTER = 4
DATA_START_ITER = 20  # iterations per step of a screen from the data (calibrate.DATA_STARTS)
STALLED = 2  # a nested screen that ends within this many iterations without a gain did not move
# a pneumatic screen whose nested and default starts removed less than this share of its stage's
# excess, where the stage stays above ALTERNATIVES_ABOVE x the noise, tries the effect's other
# starts (Effect.STARTS: a valve's dead time lies in another basin than its lag)
ALTERNATIVES_BELOW = 0.5
ALTERNATIVES_ABOVE = 1.1
STRONG_CORRELATION = 0.95  # |r| above which an effect parameter and a calibrated quantity trade off


def absorbed_note(name: str) -> str:
    qs, form = ABSORBED[name].quantities, ABSORBED[name].form
    return (f"{EFFECTS[name].description}: the calibration estimates this itself ({', '.join(qs)}); "
            "a departure shows as a mis-set quantity, not as an effect" + (
                f" (but for its form {', '.join(f'{k} = {v:g}' for k, v in form.items())}, screened as a candidate)"
                if form else ""))


def calibrated_starts(name: str) -> list[Effect]:
    """A candidate's starts beside the calibration (candidate_starts); an absorbed effect's only in
    the form the calibration cannot take (Absorption.form), at its neutral value first."""
    form = ABSORBED[name].form if name in ABSORBED else None
    starts = candidate_starts(name)
    if form is None:
        return starts
    return [replace(starts[0], **form)] + [e for e in starts[1:] if all(getattr(e, k) == v for k, v in form.items())]


def screened_names(names: Iterable[str]) -> list[str]:
    """The candidates screened beside the calibration: all but the absorbed ones, whose forms that
    the calibration cannot take are screened all the same."""
    return [n for n in names if n not in ABSORBED or ABSORBED[n].form]


@dataclass
class Screen:
    """A candidate fitted in the stage that sees it: `gain` is the share of that stage's nominal
    cost it removes, `share` the share of the nominal's excess above the sensor noise."""

    effect: str
    stage: str
    gain: float = math.nan
    share: float = math.nan
    status: str = "failed"
    iterations: int = 0
    start: int | str = 0  # the candidate's start index (candidate_starts), or "data"
    wall_s: float = 0.0
    params: dict[str, float] = field(default_factory=dict)
    error: str | None = None
    result: IdentifyResult | None = field(default=None, repr=False)

    def to_json(self) -> dict:
        out = {"effect": self.effect, "stage": self.stage, "gain": self.gain, "share": self.share,
               "status": self.status, "iterations": self.iterations, "start": self.start,
               "wall_s": round(self.wall_s, 3), "params": self.params}
        if self.error:
            out["error"] = self.error
        return out


def _options(workers: int) -> CalibrateOptions:
    return CalibrateOptions(threads=workers_here(workers))


def _quiet(_msg: str) -> None:
    pass


def _excess(base: IdentifyResult) -> float:
    """A fit's cost above what the sensor noise alone leaves (its cost / residual sigma^2)."""
    sigma = base.solver["residual_sigma"]
    return base.solver["cost"] * (1.0 - 1.0 / sigma ** 2) if sigma > 1.0 else 0.0


def _excess_share(base: IdentifyResult, cost: float) -> float:
    """The share of `base`'s excess above the noise (its cost less what the noise alone leaves,
    base cost / residual sigma^2) that a fit of cost `cost` removes (capped at 1)."""
    b, excess = base.solver["cost"], _excess(base)
    if excess <= 0:
        return 0.0 if cost >= b else 1.0
    return min(1.0, (b - cost) / excess)


def _screen_fit(base: IdentifyResult, runs: Sequence[Run], drive: str, estimate: tuple[str, ...], effect: Effect,
                start: int | str, workers: int) -> Screen:
    opts = replace(_options(workers), max_iter=SCREEN_ITER)
    give_up = base.solver["cost"] - max(SCREEN_GIVE_UP * _excess(base), 0.5 * SCREEN_MIN_GAIN * base.solver["cost"])
    return _screened(base, drive, effect, start, lambda: run_stage(
        f"screen {effect.name}", base.cylinder, runs, drive, estimate, opts, _quiet, base.nodes, (effect,),
        start_only=False, restart=False, give_up_after=SCREEN_GIVE_UP_AFTER, give_up_above=give_up))


def _screened(base: IdentifyResult, drive: str, effect: Effect, start: int | str,
              fit: Callable[[], IdentifyResult | None]) -> Screen:
    """A screen of `effect` by `fit`, measured against its stage's nominal fit `base`."""
    stage = "valve and chambers" if drive == "chambers" else "force balance in the whole model"
    sc = Screen(effect=effect.name, stage=stage, start=start)
    t0 = time.perf_counter()
    try:
        with np.errstate(all="ignore"):
            res = fit()
    except (IdentificationError, ValueError, np.linalg.LinAlgError, RuntimeError) as e:
        sc.error = f"the fit could not be computed ({type(e).__name__}: {e})"
        sc.wall_s = time.perf_counter() - t0
        return sc
    if res is None:
        sc.error, sc.wall_s = "the runs give no start of this kind", time.perf_counter() - t0
        return sc
    sc.result, sc.status, sc.iterations = res, res.solver["status"], res.solver["iterations"]
    fitted = next(e for e in res.effects if e.name == effect.name)  # estimated, or held where a fit held it
    sc.params = {k: float(getattr(fitted, k)) for k in effect.PARAMS}
    sc.gain = 1.0 - res.solver["cost"] / base.solver["cost"]
    sc.share = _excess_share(base, res.solver["cost"])
    sc.wall_s = time.perf_counter() - t0
    return sc


def _went_nowhere(s: Screen) -> bool:
    """A nested screen that failed, did not move, or ended above its own start (a position-dependent
    friction from neutral: +157 % of the stage's cost, given up): the defaults are tried too."""
    return s.result is None or s.gain < 0 or (s.gain < 1e-3 and s.iterations <= STALLED)


def screen_candidate(args) -> list[Screen]:
    """One candidate in the stage that sees it, nested from that stage's nominal fit (`base`), and
    from the effect's defaults where the nested fit did not move (some effects never leave
    their neutral value, stiction without a break-away force), ended above the stage's cost or
    has none (heat exchange); a pneumatic one from its alternative starts too where these leave
    most of the stage's excess (ALTERNATIVES_BELOW); the nested start and the one from the data
    also with each alternative's held shapes (held_shapes). The screen of the lowest TRAIN cost
    is kept.
    args: (name, base fit, runs, workers)."""
    name, base, runs, workers, file_cyl = args
    mechanical = EFFECTS[name].subsystem == "mechanical"
    drive = "command" if mechanical else "chambers"
    estimate = MECHANICAL if mechanical else PNEUMATIC
    starts = calibrated_starts(name)
    held = held_shapes(name)
    out = []
    if has_nested_start(name):
        out.append(_screen_fit(base, runs, drive, estimate, starts[0], 0, workers))
        out += [_screen_fit(base, runs, drive, estimate, replace(starts[0], **h), f"0, {shapes_label(h)}", workers)
                for h in held]
    if not out or _went_nowhere(out[0]):
        out.append(_screen_fit(base, runs, drive, estimate, starts[1], 1, workers))
    if not mechanical and base.solver["residual_sigma"] > ALTERNATIVES_ABOVE \
            and max((s.share for s in out if s.result is not None), default=0.0) < ALTERNATIVES_BELOW:
        out += [_screen_fit(base, runs, drive, estimate, starts[k], k, workers) for k in range(2, len(starts))]
    from_data = DATA_STARTS.get(name) if mechanical else None
    if from_data is not None:
        opts = replace(_options(workers), max_iter=DATA_START_ITER)
        for label, e in [("data", starts[1])] + [(f"data, {shapes_label(h)}", replace(starts[1], **h)) for h in held]:
            out.append(_screened(base, drive, e, label, lambda e=e: from_data(base.cylinder, runs, e, opts, _quiet,
                                                                            file_cyl)))
    ok = [s for s in out if s.result is not None]
    if not ok:
        return out[:1]
    best = min(ok, key=lambda s: s.result.solver["cost"])
    best.wall_s = sum(s.wall_s for s in out)
    return [best]


def mechanical_base(args) -> IdentifyResult:
    """The force balance through the whole model (calibrate's stage between 2 and 3), fitted to
    convergence: the base of the mechanical screens and the nominal calibration's start.
    args: (file cylinder, runs, stage 1, stage 2, workers)."""
    cyl, runs, mech, pneu, workers = args
    with np.errstate(all="ignore"):
        return force_balance_in_model(cyl, runs, replace(_options(workers), max_iter=SCREEN_ITER), _quiet, mech, pneu,
                                      start_only=False)


def nominal_whole(cyl: Cylinder, runs: Sequence[Run], start: Cylinder, nodes: np.ndarray | None, workers: int,
                  give_up: float = math.inf) -> tuple[IdentifyResult, list[dict]]:
    """The nominal calibration's whole model (the candidate `none`), given up where it stays
    above `give_up` (IdentifyOptions.give_up_after iterations in a row)."""
    with np.errstate(all="ignore"):
        return whole_model(cyl, runs, _options(workers), _quiet, start, nodes, give_up_above=give_up)


@dataclass
class WholeFit:
    """A model calibrated as a whole: the kept fit, which start it came from (`staged`, `nested`:
    from the nominal calibration with the effect neutral), every start's stage summaries, and
    what failed."""

    result: IdentifyResult | None = None
    start: str = ""
    stages: list[dict] = field(default_factory=list)
    error: str | None = None
    wall_s: float = 0.0

    def add(self, fit: Callable[[], tuple[IdentifyResult, list[dict]]], start: str) -> None:
        """One more start: its fit kept where it ends lower on TRAIN; a failure said in words."""
        t0 = time.perf_counter()
        try:
            with np.errstate(all="ignore"):
                res, stages = fit()
        except _FAILS as e:
            self.error = "; ".join(filter(None, (self.error, f"from the {start} start: {type(e).__name__}: {e}")))
        else:
            self.stages += [{**st, "start": start} for st in stages]
            if self.result is None or res.solver["cost"] < self.result.solver["cost"]:
                self.result, self.start = res, start
        self.wall_s += time.perf_counter() - t0


_FAILS = (IdentificationError, ValueError, np.linalg.LinAlgError, RuntimeError)


def calibrate_staged(cyl: Cylinder, runs: Sequence[Run], staged: tuple, workers: int,
                     give_up: float = math.inf) -> WholeFit:
    """A candidate calibrated as a whole from its staged start (cylinder, nodes, effects)."""
    w = WholeFit()
    w.add(lambda: whole_model(cyl, runs, _options(workers), _quiet, *staged, give_up_above=give_up), "staged")
    return w


def unfinished(res: IdentifyResult) -> bool:
    """A whole-model fit that did not converge (it ran out of iterations, its line search failed)
    and stays above the misfit level (CalibrateOptions.misfit x the noise): a crawl in a wrong
    basin (a friction with memory from its screen's start: 6.3 x after 40 iterations, its restart
    without the effect at 1.46 x), not the candidate's optimum."""
    return res.solver["status"] != "converged" and res.solver["residual_sigma"] > CalibrateOptions.misfit


def nested(w: WholeFit, cyl: Cylinder, runs: Sequence[Run], nominal: IdentifyResult, neutral: Sequence[Effect],
           workers: int, give_up: float = math.inf) -> WholeFit:
    """Where the candidate's fit failed or ended above the nominal calibration's TRAIN cost, once
    more from the nominal calibration (node states included) with the effects `neutral`: a
    descent from there ends at or below it, so the candidate never fits TRAIN worse than `none`.
    Also where it did not converge and stays above the noise (unfinished): its staged start had
    left it in a wrong basin, and the effect's own start from the nominal calibration is the
    other one (the lower cost kept)."""
    if w.result is None or w.result.solver["cost"] > nominal.solver["cost"] or unfinished(w.result):
        w.add(lambda: whole_model(cyl, runs, _options(workers), _quiet, nominal.cylinder, nominal.nodes,
                                  tuple(nominal.effects) + tuple(neutral), give_up_above=give_up), "nested")
    return w


def handed_over(name: str, nominal: IdentifyResult) -> tuple[Cylinder, np.ndarray | None, tuple[Effect, ...]] | None:
    """An absorbed effect's unabsorbed form started from the nominal calibration with what that
    calibration absorbed handed to it (Absorption.handed_to): a gate's overlap at the larger of the
    calibrated overlaps, the characteristic's overlaps lowered by as much (to zero). None where
    the calibration absorbed nothing (no overlap)."""
    quantities, param = ABSORBED[name].quantities, ABSORBED[name].handed_to
    values = {q: nominal.cylinder.value(q) for q in quantities}
    d = max(values.values())
    if not d > 0:
        return None
    start = nominal.cylinder.with_values({q: max(v - d, 0.0) for q, v in values.items()})
    effect = replace(_neutral(name), **{param: d})
    return start, nominal.nodes, tuple(nominal.effects) + (effect,)


def _call(job):
    fn, args = job
    return fn(args)


def staged_start(screen: Screen, base: IdentifyResult) -> tuple[Cylinder, np.ndarray | None, tuple[Effect, ...]]:
    """A candidate's start for the whole model: its screen's values, effect and node states for the
    subsystem it belongs to; the other subsystem's from the force balance through the model
    (which holds stage 2's valve and chambers)."""
    res = screen.result
    if res.drive == "chambers":
        start = base.cylinder.with_values({n: res.cylinder.value(n) for n in PNEUMATIC})
        return start, np.vstack([res.nodes[:2], base.nodes[2:4]]), tuple(res.effects)
    return res.cylinder, res.nodes, tuple(res.effects)


def confounded(res: IdentifyResult, effect: str) -> list[dict]:
    """The effect's parameters that trade off against a calibrated quantity in a fit (|r| above
    STRONG_CORRELATION): the run cannot separate them."""
    if res.correlation is None:
        return []
    names = list(res.params)
    out = []
    for i, a in enumerate(names):
        if not a.startswith(effect + "."):
            continue
        for j, b in enumerate(names):
            if b in CALIBRATED and b not in ("Fc", "Fv", "kp"):
                r = float(res.correlation[i, j])
                if math.isfinite(r) and abs(r) > STRONG_CORRELATION:
                    out.append({"effect": effect, "parameter": a.split(".", 1)[1], "quantity": b, "r": r})
    return sorted(out, key=lambda d: -abs(d["r"]))


def calibrated_candidates(cyl: Cylinder, runs: Sequence[Run], names: Sequence[str], workers: int,
                          say: Callable[[str], None]) -> dict:
    """Steps 1 and 2 of the module docstring: the calibration's first stages and every candidate's
    screen. Returns a dict with `stages` (stage 1 and 2), `base` (the force balance through the
    model), `screens` (list of Screen), `absorbed` ({effect: note}), `t0` and `wall_s` per step."""
    t0 = time.perf_counter()
    # the critical ratio's other starts are left to the screens: where the valve and chambers stay
    # above the noise, a pneumatic candidate is screened there from the same fit
    opts = CalibrateOptions(threads=max(1, workers), other_starts=("overlap",))
    say("calibrating the cylinder file's valve, volumes, mass and offsets on TRAIN: the first two stages ...")
    mech, pneu = first_stages(cyl, runs, opts, say)
    if mech is None or pneu is None:
        raise IdentificationError("diagnose --calibrate needs both stages of the calibration")
    absorbed = {n: absorbed_note(n) for n in names if n in ABSORBED}
    fitted = screened_names(names)
    pneumatic = [n for n in fitted if EFFECTS[n].subsystem != "mechanical"]
    mechanical = [n for n in fitted if EFFECTS[n].subsystem == "mechanical"]
    t1 = time.perf_counter()
    say(f"the force balance through the whole model, and {len(pneumatic)} pneumatic candidates screened in the valve "
        f"and chambers ({min(workers, 1 + len(pneumatic))} processes) ...")
    done = run_jobs(_call, [(mechanical_base, (cyl, runs, mech, pneu, workers))]
                    + [(screen_candidate, (n, pneu, runs, workers, cyl)) for n in pneumatic], workers)
    base = done[0]
    screens: list[Screen] = [s for ss in done[1:] for s in ss]
    say(f"  the force balance through the whole model (the valve and chambers as calibrated): residual "
        f"{base.solver['residual_sigma']:.3g} x noise")
    t2 = time.perf_counter()
    if mechanical:
        say(f"screening {len(mechanical)} mechanical candidates through the whole model "
            f"({min(workers, len(mechanical))} processes) ...")
        done = run_jobs(_call, [(screen_candidate, (n, base, runs, workers, cyl)) for n in mechanical], workers)
        screens += [s for ss in done for s in ss]
    for s in screens:
        say(f"  screen {s.effect:20s} ({s.stage}): " + (
            f"{max(s.share, 0.0):.0%} of the excess above the noise, cost {-s.gain:+.2%}" if s.result is not None
            else s.error or s.status))
    return {"stages": (mech, pneu), "base": base, "screens": screens, "absorbed": absorbed, "t0": t0,
            "wall_s": {"first_stages": round(t1 - t0, 3), "pneumatic_screens": round(t2 - t1, 3),
                       "mechanical_screens": round(time.perf_counter() - t2, 3)}}


def _neutral(name: str) -> Effect:
    return calibrated_starts(name)[0]


def choose(screens: list[Screen], screen_min: float, screen_share: float, leaders: int) -> list[Screen]:
    """The screened candidates calibrated as a whole: those that remove at least `screen_min` of
    their stage's excess above the noise (and SCREEN_MIN_GAIN of its cost) and `screen_share` of
    the best one's, the `leaders` that remove most of their stage's cost, that one first, and the
    best of the other stage last where the leaders all come from one."""
    ok = [s for s in screens if s.result is not None and s.gain >= SCREEN_MIN_GAIN and s.share >= screen_min]
    top = max((s.share for s in ok), default=0.0)
    # best first by the share of its stage's cost it removes: the share of the excess compares badly
    # across stages (a weak friction asymmetry: 42 % of the force balance's excess, -14.3 % of its
    # cost; supply droop 49 % of the valve and chambers' small excess, -1.2 % of its cost)
    ok = sorted((s for s in ok if s.share >= screen_share * top), key=lambda s: (-s.gain, -s.share))
    chosen = ok[:leaders]
    # where the leaders all come from one stage, the other stage's best comes last: a stage's
    # misfit that the other stage causes gains there too (a hard dead zone took all the valve and
    # chambers' excess, 4.4 % of its cost, while three friction screens took 7-15 % of the force
    # balance's, driven by the valve's misfit through the model)
    stages = {s.stage for s in chosen}
    other = [s for s in ok[leaders:] if s.stage not in stages]
    return chosen + other[:1] if len(stages) == 1 else chosen


# ------------------------------------------------------------------ the verdict among calibrated models


def _candidate(name: str, fit: WholeFit, screen: Screen | None, nominal_cost: float) -> Candidate:
    res = fit.result
    effects = [e for e in res.effects if e.name in name.split("+")]
    keyed = {e.key(k): (k if len(effects) == 1 else e.key(k)) for e in effects for k in e.PARAMS}
    return Candidate(
        effect=name, params={keyed[n]: res.params[n].value for n in keyed},
        std={keyed[n]: res.params[n].std for n in keyed}, status=res.solver["status"],
        friction={n: res.params[n].value for n in ("Fc", "Fv", "kp") if n in res.params},
        train_cost=res.solver["cost"], iterations=res.solver["iterations"],
        start=NESTED_START if fit.start == "nested" else 1, effects=res.effects, nodes=res.nodes,
        cylinder=res.cylinder, wall_s=fit.wall_s,
        calibration={"start": fit.start, "residual_sigma": res.solver["residual_sigma"],
                     "train_gain": 1.0 - res.solver["cost"] / nominal_cost,
                     "screen": screen.to_json() if screen is not None else None,
                     "confounded": [c for e in effects for c in confounded(res, e.name)],
                     "stages": fit.stages})


def train_share(nominal: IdentifyResult, res: IdentifyResult) -> float:
    """The share of what the nominal calibration leaves on TRAIN above the noise (residual sigma^2
    - 1) that a calibrated candidate removes."""
    b, c = nominal.solver["residual_sigma"] ** 2, res.solver["residual_sigma"] ** 2
    return (b - c) / (b - 1.0) if b > 1.0 else 0.0


def by_train(c: Candidate, nominal: IdentifyResult, opts: DiagnoseOptions, shrink: bool = False) -> bool:
    """Whether a validated candidate counts by what it explains on TRAIN: the calibration without
    an effect leaves TRAIN at `train_gap` x the noise or more, the candidate's calibration removes
    `train_explains` of that excess, and it improves VALID beyond what the noise could (z), if by
    less than min_shrink (with `shrink`: whatever share of VALID's gap it explains). VALID holds
    what a calibrated model extrapolates to beside the effect: a weak friction memory (Dahl, 0.4 N)
    calibrated TRAIN from 1.16 to 1.03 x the noise while VALID stayed at 1.45 x (z 5.5, 0.8 %)."""
    cal = c.calibration or {}
    if c.validation is None or not math.isfinite(c.z) or c.z < opts.min_z or "residual_sigma" not in cal:
        return False
    b, r = nominal.solver["residual_sigma"], cal["residual_sigma"]
    explains = (b * b - r * r) / (b * b - 1.0) if b > 1.0 else 0.0
    return b >= opts.train_gap and explains >= opts.train_explains and (shrink or c.shrink_all > 0)


def shows_itself(c: Candidate, base_val: Validation, opts: DiagnoseOptions) -> bool:
    """Whether a candidate's gain can be its effect's: always where the calibration without an
    effect leaves a gap on VALID above `small_gap`; within it, only if the effect lies `min_z`
    standard deviations from the nominal plant in one of its parameters (or cannot be told)."""
    if base_val.normalized_rms() > opts.small_gap:
        return True
    z = departure_z(c)
    return not z < opts.min_z


def _at_nominal_words(c: Candidate, base_val: Validation, opts: DiagnoseOptions) -> str:
    return (f"the calibration without an effect already fits VALID to {base_val.normalized_rms():.2f} x the noise "
            f"(within {opts.small_gap:g}), and {c.effect} stays within {departure_z(c):.1f} standard deviations of "
            f"the nominal plant (under {opts.min_z:g}): the gain on VALID is the calibration's, not the effect's")


def _significant(c: Candidate, base_val, base_rmse: float, opts: DiagnoseOptions) -> bool:
    c = copy.copy(c)
    score_candidate(c, base_val, base_rmse, opts)
    return c.significant


def _unfitted(name: str, status: str, error: str, screen: Screen | None = None) -> Candidate:
    return Candidate(effect=name, status=status, error=error,
                     calibration={"screen": screen.to_json()} if screen is not None else None)


def _screen_words(s: Screen, opts: DiagnoseOptions, top: float) -> str:
    if s.result is None:
        return f"its screen in the {s.stage} failed ({s.error or s.status}): not calibrated"
    if s.gain < SCREEN_MIN_GAIN:
        return (f"screened in the {s.stage}: it removes {max(s.gain, 0.0):.2%} of that stage's cost (under "
                f"{SCREEN_MIN_GAIN:.1%}): not calibrated as a whole")
    why = (f"under {opts.screen_min:.0%}" if s.share < opts.screen_min
           else f"under {opts.screen_share:.0%} of the best screen's {top:.0%}" if s.share < opts.screen_share * top
           else f"not among the {opts.leaders} best screens")
    return (f"screened in the {s.stage}: it removes {max(s.share, 0.0):.0%} of what the calibration leaves there above "
            f"the noise ({why}): not calibrated as a whole")


def diagnose_calibrated(cyl: Cylinder, runs: Sequence[Run], valid: Run, opts: DiagnoseOptions,
                        progress: Callable[[str], None] | None = None) -> Diagnosis:
    """The diagnosis among calibrated models (module docstring); `runs` are TRAIN (a calibration
    run and an ordinary one are calibrated together)."""
    t_start = time.perf_counter()
    say = progress or (lambda _m: None)
    found = calibrated_candidates(cyl, runs, opts.candidates, opts.workers, say)
    screens = {s.effect: s for s in found["screens"]}
    chosen = choose(found["screens"], opts.screen_min, opts.screen_share, opts.leaders)
    segments = validation_segments(valid, opts.horizon_s)
    fits: dict[str, WholeFit] = {}
    t3 = time.perf_counter()
    first = chosen[0] if chosen else None
    give_up = _calibrate_first(cyl, runs, first, found["base"], fits, opts, say)
    say("calibrating the whole model without an effect ...")
    t4 = time.perf_counter()
    joint, stages = _nominal_joint(cyl, runs, found, first, fits, give_up, opts.workers, say)
    t5 = time.perf_counter()
    nom = _nominal_validated(cyl, runs, valid, found, joint, stages, first, segments, opts, say)
    scored, closer, why = _score_chosen(cyl, runs, valid, chosen, found["base"], fits, nom, segments, opts, say)
    if closer is None and not any(_judged(copy.copy(c), nom.val, nom.rmse, nom.base, opts).significant
                                  for c in scored.values()):
        _score_handed_over(cyl, runs, valid, screens, scored, fits, nom, segments, opts, say)
    t6 = time.perf_counter()
    cands = _every_candidate(opts, found, screens, chosen, scored, closer, why, nom.base, nom.val, nom.rmse)
    ranking, best = ranked(cands, say)

    pair, folded = None, ""
    if opts.pair and best is not None:
        pair = _calibrated_pair(cyl, runs, valid, ranking, nom.fitting, nom.val, nom.rmse, segments, opts, say, fits)
        ranking, pair, folded = fold_absent_partner(ranking, pair)
        best = ranking[0]
    verdict, verdict_note = _calibrated_verdict(nom, best, pair, fits, opts)
    verdict_note = with_fold_note(verdict, verdict_note, best, folded)
    if verdict_note:
        say(f"  verdict {verdict}: {verdict_note}")
    shown = pair if pair is not None and verdict == pair.effect else best if verdict != "unexplained" else None
    found["wall_s"].update({"first_candidate": round(t4 - t3, 3), "nominal_whole": round(t5 - t4, 3),
                            "candidates_and_validation": round(t6 - t5, 3)})
    calibration = _calibration_section(cyl, runs, nom.nominal, found, fits, verdict, opts, say)
    base_val, nominal = nom.val, nom.nominal
    x_idx = base_val.outputs.index("x")
    t7 = time.perf_counter()
    subsystems = subsystem_split(nominal.cylinder, nominal.cylinder, runs[0], valid, base_val, opts, segments)
    found["wall_s"]["pair_and_subsystems"] = round(time.perf_counter() - t6, 3)
    found["wall_s"]["subsystems"] = round(time.perf_counter() - t7, 3)
    return Diagnosis(
        cylinder=nominal.cylinder, train=runs[0], train_runs=tuple(runs), valid=valid, options=opts,
        baseline=_baseline_doc(cyl, nom, opts),
        verdict=verdict, verdict_note=verdict_note, calibration=calibration, ranking=ranking, pair=pair,
        regions=regions(nominal.cylinder, valid, base_val, shown.validation if shown is not None else None),
        subsystems=subsystems, whiteness=whiteness(base_val.residual[x_idx]),
        correlations=regressor_correlations(nominal.cylinder, valid), base_validation=base_val,
        wall_s=time.perf_counter() - t_start)


@dataclass(frozen=True)
class _Nominal:
    """The calibration without an effect and its score on VALID: what every candidate is measured
    against."""
    nominal: Calibration
    base: IdentifyResult  # nominal.result
    val: Validation
    rmse: float  # val's position RMSE
    sigma: float  # base's residual on TRAIN, in noise units
    fitting: NominalFit


def _calibrate_first(cyl: Cylinder, runs: Sequence[Run], first: Screen | None, base_fit: IdentifyResult,
                     fits: dict[str, WholeFit], opts: DiagnoseOptions, say: Callable[[str], None]) -> float:
    """Step 3: the best screened candidate calibrated as a whole first (into `fits`); the calibration
    without an effect then needs to go on only while it might still come near it on TRAIN: the
    TRAIN cost above which it is given up."""
    if first is not None:
        say(f"calibrating the whole model with {first.effect} (the best screen) ...")
        fits[first.effect] = calibrate_staged(cyl, runs, staged_start(first, base_fit), opts.workers)
    reach = fits[first.effect].result.solver["cost"] if first is not None and fits[first.effect].result else math.nan
    return opts.nominal_give_up * reach if math.isfinite(reach) else math.inf


def _nominal_joint(cyl: Cylinder, runs: Sequence[Run], found: dict, first: Screen | None,
                   fits: dict[str, WholeFit], give_up: float, workers: int,
                   say: Callable[[str], None]) -> tuple[IdentifyResult, list[dict]]:
    """The whole model calibrated without an effect, from the stages' start and, where the first
    candidate's calibration fits TRAIN better, once more from the quantities it calibrated."""
    mech, pneu = found["stages"]
    joint, stages = nominal_whole(cyl, runs, *model_start(cyl, mech, pneu, found["base"])[:2], workers, give_up)
    first_fit = fits[first.effect].result if first is not None else None
    if first_fit is not None and first_fit.solver["cost"] < joint.solver["cost"]:
        # the first candidate may have calibrated the file's quantities better than the nominal fit
        # found them (from its own start), also where that fit was given up: the nominal model from
        # those quantities, the effect left out, so that what the candidate gains is its effect's
        given_up = joint.solver["status"] == "above_reference"
        again, more = nominal_whole(cyl, runs, first_fit.cylinder, first_fit.nodes, workers,
                                    give_up if given_up else joint.solver["cost"])
        stages += [{**st, "start": f"the quantities calibrated with {first.effect}"} for st in more]
        if again.solver["cost"] < joint.solver["cost"]:
            say(f"  the calibration without an effect, from the quantities calibrated with {first.effect}: cost "
                f"{again.solver['cost'] / joint.solver['cost'] - 1:+.1%}")
            joint = again
    return joint, stages


def _nominal_validated(cyl: Cylinder, runs: Sequence[Run], valid: Run, found: dict, joint: IdentifyResult,
                       stages: list[dict], first: Screen | None, segments, opts: DiagnoseOptions,
                       say: Callable[[str], None]) -> _Nominal:
    """The calibration without an effect finished (the friction's std, the stages) and scored on VALID."""
    mech, pneu = found["stages"]
    nominal = finish(cyl, runs, CalibrateOptions(threads=opts.workers), joint, mech, pneu,
                     stage_summaries(mech, pneu, found["base"]) + stages, found["t0"])
    base = nominal.result
    given_up = base.solver["status"] == "above_reference"
    say(f"  the calibration without an effect: {base.solver['status']} after {base.solver['iterations']} iterations, "
        f"residual {base.solver['residual_sigma']:.3g} x noise" + (
            f" (stayed above {opts.nominal_give_up:g} x the TRAIN cost of the calibration with {first.effect}: given "
            "up)" if given_up else ""))
    base_val = validate(nominal.cylinder, nominal.effects, valid, opts.horizon_s, segments=segments,
                        workers=opts.workers)
    base_rmse = base_val.rmse("x")
    say(f"  the calibration without an effect on VALID: position RMSE {base_rmse * 1e6:.2f} um, all outputs "
        f"{base_val.normalized_rms():.2f} x the sensor noise ({len(segments)} segments of about {opts.horizon_s:g} s)")
    sigma = base.solver["residual_sigma"]
    fitting = NominalFit(cyl, nominal.cylinder, base.nodes, base.solver["cost"], base_val,
                         noise_cost=base.solver["cost"] / sigma ** 2 if sigma > 0 else math.nan)
    return _Nominal(nominal, base, base_val, base_rmse, sigma, fitting)


def _score_chosen(cyl: Cylinder, runs: Sequence[Run], valid: Run, chosen: list[Screen], base_fit: IdentifyResult,
                  fits: dict[str, WholeFit], nom: _Nominal, segments, opts: DiagnoseOptions,
                  say: Callable[[str], None]) -> tuple[dict[str, Candidate], Candidate | None, str]:
    """Each chosen candidate calibrated as a whole and scored on VALID, the best screen first; the
    first that closes the gap, or that explains nearly all the calibration without an effect leaves
    on TRAIN and improves VALID significantly, ends them: (the scored candidates, that one or None,
    why)."""
    scored: dict[str, Candidate] = {}
    for s in chosen:
        if s.effect not in fits:
            say(f"calibrating the whole model with {s.effect} ...")
            fits[s.effect] = calibrate_staged(cyl, runs, staged_start(s, base_fit), opts.workers)
        w = nested(fits[s.effect], cyl, runs, nom.base, (_neutral(s.effect),), opts.workers)
        c = scored[s.effect] = _validated_fit(s.effect, w, s, nom, valid, segments, opts, say)
        why = _ends_scoring(c, w, nom, opts)
        if why:
            return scored, c, why
    return scored, None, ""


def _validated_fit(name: str, w: WholeFit, screen: Screen | None, nom: _Nominal, valid: Run, segments,
            opts: DiagnoseOptions, say: Callable[[str], None]) -> Candidate:
    """A candidate calibrated as a whole, validated where it fits TRAIN better than `none`."""
    if w.result is None:
        return _unfitted(name, "failed", f"the calibration with it could not be computed ({w.error})", screen)
    c = _candidate(name, w, screen, nom.base.solver["cost"])
    say(f"  {name}: residual {w.result.solver['residual_sigma']:.3g} x noise on TRAIN "
        f"({w.result.solver['status']}, from the {w.start} start, cost {-c.calibration['train_gain']:+.1%} against "
        "the calibration without it)")
    if c.calibration["train_gain"] < opts.min_train_gain:
        c.status, c.error = "no_gain_on_train", (
            f"calibrated with it, TRAIN is fitted no better than without it ({-c.calibration['train_gain']:+.2%} "
            "of the cost): not validated")
        return c
    return validate_candidate((c, nom.fitting, valid, opts, segments))


def _ends_scoring(c: Candidate, w: WholeFit, nom: _Nominal, opts: DiagnoseOptions) -> str:
    """Why a scored candidate ends the scoring ('' where it does not): it closes the gap on VALID,
    or explains nearly all the calibration without an effect leaves on TRAIN and improves VALID
    significantly."""
    if c.validation is None or not shows_itself(c, nom.val, opts):
        return ""
    if closes_gap(c, nom.val, nom.rmse, opts):
        return "closed the gap on VALID to near the noise first"
    share = train_share(nom.base, w.result)
    if _significant(c, nom.val, nom.rmse, opts) and share >= opts.train_dominant:
        return (f"explains {share:.0%} of what the calibration without an effect leaves on TRAIN above the noise, and "
                "significantly improves VALID")
    return ""


def _score_handed_over(cyl: Cylinder, runs: Sequence[Run], valid: Run, screens: dict[str, Screen],
                       scored: dict[str, Candidate], fits: dict[str, WholeFit], nom: _Nominal, segments,
                       opts: DiagnoseOptions, say: Callable[[str], None]) -> None:
    """Where no scored candidate counts (_judged significant) and the calibration without an effect
    stays above the misfit level on TRAIN (CalibrateOptions.misfit x the noise): each absorbed
    effect's unabsorbed form calibrated as a whole from that calibration with what it absorbed handed over
    (handed_over), and scored (into `scored` and `fits`). Its screen cannot see such a form: with
    the motion measured, the calibrated characteristic imitates it (a reference-plant gate of
    0.0199: the valve and chambers at 1.02 x the noise, the gate's screen without gain; the whole
    model at 1.44 x, 1.09 x with the overlap handed to the gate)."""
    if nom.sigma <= CalibrateOptions.misfit:
        return
    for name in (n for n, a in ABSORBED.items() if a.handed_to):
        start = handed_over(name, nom.base) if name in opts.candidates else None
        if start is None:
            continue
        form = ", ".join(f"{k} = {v:g}" for k, v in ABSORBED[name].form.items())
        say(f"calibrating the whole model with {name} in the form the calibration cannot take ({form}), what it "
            "absorbed handed over ...")
        w = fits.get(name) or WholeFit()  # a chosen screen's fit keeps its starts, the lowest cost kept
        w.add(lambda: whole_model(cyl, runs, _options(opts.workers), _quiet, *start), "handed-over")
        if not any(st.get("start") == "nested" for st in w.stages):
            w = nested(w, cyl, runs, nom.base, (_neutral(name),), opts.workers)
        fits[name] = w
        scored[name] = _validated_fit(name, fits[name], screens.get(name), nom, valid, segments, opts, say)


def _every_candidate(opts: DiagnoseOptions, found: dict, screens: dict[str, Screen], chosen: list[Screen],
                     scored: dict[str, Candidate], closer: Candidate | None, why: str, base: IdentifyResult,
                     base_val: Validation, base_rmse: float) -> list[Candidate]:
    """Every candidate of the options, in their order, with its status and score: absorbed, scored,
    not validated (a higher screen ended the scoring) or screened out."""
    top = max((s.share for s in screens.values() if s.result is not None), default=0.0)
    cands: list[Candidate] = []
    for name in opts.candidates:
        if name in found["absorbed"] and name not in scored:
            c = _unfitted(name, "absorbed", found["absorbed"][name], screens.get(name))
        elif name in scored:
            c = scored[name]
        elif closer is not None and any(s.effect == name for s in chosen):
            c = _unfitted(name, "not_validated", f"not calibrated as a whole: {closer.effect}, whose screen ranked "
                          f"higher, {why}", screens[name])
        else:
            sc = screens.get(name)
            c = _unfitted(name, "screened_out", _screen_words(sc, opts, top) if sc is not None else "not screened", sc)
        cands.append(_judged(c, base_val, base_rmse, base, opts))
    return cands


def _judged(c: Candidate, base_val: Validation, base_rmse: float, base: IdentifyResult,
            opts: DiagnoseOptions) -> Candidate:
    """`c` scored against the calibration without an effect (`base`, `base_val`), in place:
    significant by VALID or by TRAIN (by_train), and only where the gain can be its effect's
    (shows_itself)."""
    score_candidate(c, base_val, base_rmse, opts)
    if by_train(c, base, opts):
        c.significant = True
    if c.significant and not shows_itself(c, base_val, opts):
        c.significant, c.error = False, _at_nominal_words(c, base_val, opts)
    return c


def _calibrated_verdict(nom: _Nominal, best: Candidate | None, pair: Candidate | None, fits: dict[str, WholeFit],
                        opts: DiagnoseOptions) -> tuple[str, str]:
    """The verdict by the diagnosis' rules (verdict.decide), then by TRAIN: an effect that explains
    nearly all the calibration without it leaves on TRAIN, or none where that calibration fits TRAIN
    to the noise and no candidate improves VALID."""
    base, base_val, sigma = nom.base, nom.val, nom.sigma
    verdict, verdict_note = decide(base_val, best, pair, opts)
    if verdict == "unexplained" and best is not None and by_train(best, base, opts, shrink=True):
        share = train_share(base, fits[best.effect].result)
        verdict, verdict_note = best.effect, (
            f"{best.effect} explains {share:.0%} of what the calibration without an effect leaves on TRAIN above the "
            f"noise ({sigma:.2f} -> {fits[best.effect].result.solver['residual_sigma']:.2f} x) and improves VALID "
            f"significantly (z {best.z:.1f}); VALID keeps {best.validation.normalized_rms():.2f} x where the "
            "calibrated model leaves what TRAIN covers (see where the gap lies)")
    if verdict == "unexplained" and best is None and sigma <= CalibrateOptions.misfit:
        # the calibration fits TRAIN to the noise and no candidate improves VALID: no effect shows in
        # TRAIN; what VALID keeps is where the calibrated model extrapolates
        verdict, verdict_note = "none", (
            f"the calibration without an effect fits TRAIN to {sigma:.2f} x the sensor noise and no candidate improves "
            f"VALID significantly; VALID keeps {base_val.normalized_rms():.2f} x where it leaves what TRAIN covers "
            "(see where the gap lies)")
    return verdict, verdict_note


def _calibration_section(cyl: Cylinder, runs: Sequence[Run], nominal: Calibration, found: dict,
                         fits: dict[str, WholeFit], verdict: str, opts: DiagnoseOptions,
                         say: Callable[[str], None]) -> dict:
    """The document's calibration: the calibrated models, what the runs cannot separate; the mis-set
    quantities and the trade-offs said."""
    calibration = _calibration_doc(cyl, nominal, found, fits, [n for n in fits if "+" not in n], verdict)
    calibration["not_separated"] = separability(nominal.cylinder, runs,
                                                [n for n in opts.candidates if n not in ABSORBED])
    for m in calibration["mis_set"]:
        say(f"  mis-set in the cylinder file: {m['quantity']} {m['file']:.4g} -> {m['calibrated']:.4g} {m['unit']}"
            + (f" ({m['change']:+.1%})" if math.isfinite(m["change"]) else ""))
    for c in calibration["confounded"]:
        say(f"  on these runs {c['effect']}.{c['parameter']} trades off against {c['quantity']} (r = {c['r']:+.3f})")
    return calibration


def _baseline_doc(cyl: Cylinder, nom: _Nominal, opts: DiagnoseOptions) -> dict:
    """The document's baseline: the calibration without an effect on VALID and TRAIN."""
    base, base_val = nom.base, nom.val
    return {"rmse_x_validation": nom.rmse, "rmse_p1_validation": base_val.rmse("p1"),
            "rmse_p2_validation": base_val.rmse("p2"), "normalized_rms": base_val.normalized_rms(),
            "friction": {n: base.params[n].value for n in ("Fc", "Fv", "kp")},
            "friction_std": {n: base.params[n].std for n in ("Fc", "Fv", "kp")},
            "rmse_x_train": base.fit["rmse_x"], "train_cost": base.solver["cost"],
            "residual_sigma_train": nom.sigma, "horizon_s": opts.horizon_s,
            "noise": {"x": float(base_val.noise[0]), "p": float(cyl.sensors.pressure_noise)}}


def _calibrated_pair(cyl, runs, valid, ranking, fitting: NominalFit, base_val, base_rmse, segments, opts, say,
                     fits: dict) -> Candidate | None:
    """The verdict's effect with the runner-up, calibrated as a whole nested from the best
    candidate's calibration (the runner-up neutral), when the best alone leaves a gap that the
    runner-up also addresses; given up, unvalidated, when it stays under pair_give_up of what
    it needs on TRAIN to change the verdict (verdict.best_pair's rule)."""
    best = ranking[0]
    second = next((c for c in ranking[1:] if c.significant), None)
    if second is None or best.validation is None or best.validation.normalized_rms() <= opts.closed_gap:
        return None
    say(f"calibrating the pair {best.effect} + {second.effect} ...")
    need = pair_need(base_val, best.validation, opts)
    excess = best.train_cost - fitting.noise_cost
    give_up = best.train_cost - opts.pair_give_up * need * excess if excess > 0 else math.inf
    w = nested(WholeFit(), cyl, runs, fits[best.effect].result, (_neutral(second.effect),), opts.workers, give_up)
    name = f"{best.effect}+{second.effect}"
    fits[name] = w
    if w.result is None:
        return _unfitted(name, "failed", f"the calibration with both could not be computed ({w.error})")
    c = _candidate(name, w, None, fitting.train_cost)
    if w.result.solver["status"] == "above_reference" and c.train_cost > give_up:
        c.status = "falls_short"
        c.error = (f"together they explain {(best.train_cost - c.train_cost) / excess:.0%} of what {best.effect} "
                   f"leaves on TRAIN above the sensor noise; to change the verdict the pair needs {need:.0%} of it: "
                   "given up, not validated")
    else:
        c = validate_candidate((c, fitting, valid, opts, segments))
    score_candidate(c, base_val, base_rmse, opts)
    c.significant = c.significant and gain_over(best.validation, c.validation, opts)
    say(f"  {c.effect}: " + (f"shrink {c.shrink:.1%}, all outputs {c.shrink_all:.1%}"
                             + ("" if c.significant else " (not significantly better than the verdict alone)")
                             if math.isfinite(c.shrink) else f"not scored ({c.error or c.status})"))
    return c


def trade_offs(fits: Iterable[WholeFit], screens: Iterable[Screen]) -> list[dict]:
    """The effect parameters that trade off against a calibrated quantity (confounded), each pair
    once: from the calibrations as a whole, then from the screens that remove SCREEN_MIN_GAIN of
    their stage's cost (a screened-out candidate may still be one the runs cannot tell from a
    calibrated quantity: a Coulomb friction that differs by direction is a constant force while
    the piston slides, r = 0.976 with the external force on a held-out rig)."""
    out: list[dict] = []
    seen: set[tuple[str, str, str]] = set()
    results = [w.result for w in fits if w.result is not None]
    results += [s.result for s in screens if s.result is not None and s.gain >= SCREEN_MIN_GAIN]
    for res in results:
        for e in res.effects:
            for c in confounded(res, e.name):
                if (c["effect"], c["parameter"], c["quantity"]) not in seen:
                    seen.add((c["effect"], c["parameter"], c["quantity"]))
                    out.append(c)
    return out


def _calibration_doc(file_cyl: Cylinder, nominal, found: dict, fits: dict, chosen: list[str], verdict: str) -> dict:
    """The diagnosis's `calibration`: the file's mis-set quantities as the model the verdict names
    calibrated them (the nominal calibration for none and unexplained), its TRAIN residual and
    what that says, the screens, the effects absorbed by calibrated quantities, and what the runs
    cannot separate (an effect parameter that trades off against a calibrated quantity: in a
    calibration as a whole, else in a screen that removes SCREEN_MIN_GAIN of its stage's cost)."""
    fit = fits.get(verdict)
    named = fit.result if fit is not None and fit.result is not None else nominal.result
    confounds = trade_offs(fits.values(), found["screens"])
    return {
        "mis_set": mis_set_quantities(file_cyl, named.params),
        "model": verdict if named is not nominal.result else "none",
        "status": named.solver["status"], "residual_sigma": named.solver["residual_sigma"],
        "misfit": misfit_note(named) or None,
        "nominal": {"status": nominal.result.solver["status"],
                    "residual_sigma": nominal.result.solver["residual_sigma"],
                    "iterations": nominal.result.solver["iterations"], "misfit": nominal.misfit or None,
                    "given_up": nominal.result.solver["status"] == "above_reference"},
        "screens": [s.to_json() for s in found["screens"]],
        "calibrated_with": chosen,
        "absorbed": [{"effect": n, "quantities": list(ABSORBED[n].quantities), "note": t} for n, t in found["absorbed"].items()],
        "confounded": confounds,
        "wall_s": round(nominal.wall_s, 3), "steps_s": found["wall_s"],
    }
