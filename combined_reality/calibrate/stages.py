"""Calibration of what a cylinder file only guesses, staged the way the physics separates it.

1. The piston's force balance, driven by the measured pressures (the pressure drive):
   friction (Fc, Fv, kp), the moving mass and a constant force. Its constant force holds the
   external force and the pressure sensors' offsets together (o1 A1 - o2 A2): the balance
   alone cannot tell them apart.
2. The valve and the chambers, driven by the measured motion (the chambers drive): the flow
   characteristic per direction (overlap and rises), the critical ratio, both dead volumes
   and the pressure sensors' offsets (at an end stop with the valve open, one chamber
   settles at supply and the other at atmosphere; between, the valve's law ties them down).
3. The whole command-driven model from those starts, every parameter at once: what the
   stages left to each other (the offsets inside the constant force, the friction's share
   of the pressure term) is settled where the model must reproduce position and pressures
   from the command alone. Its node states start from the stages' (motion from 1, pressures
   from 2): its continuity gaps start small, and it converges in fewer iterations.

Stages 1 and 2 need nothing from each other and run side by side.

Runs of more than START_S in all are calibrated on a share of them first (start_share): the
stages and the whole model see START_S of the data, in stretches of START_STRETCH_S spread
evenly over the runs; the whole model is then fitted to all the data from there (every estimate,
its std and the identifiability from all of it). The stages only start the whole model, and on a
long run they cost the most and gain nothing: a 600 s force balance ran into a failed line
search far above the noise, and the whole model crawled 13 iterations from its start.

Each stage is the one identifier (multiple-shooting Gauss-Newton) on the one plant with
another drive, so nothing of the physics is written twice.
"""
from __future__ import annotations

import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import numpy as np
from threadpoolctl import threadpool_limits

from sim.cylinder import FLOW_CHARACTERISTIC, OPENING_GRID, VALVE_DIRECTIONS, Cylinder
from sim.extension import Effect

from ..files import Run
from ..identify import (TRUSTED_VALID, Estimate, IdentificationError, IdentifyOptions, IdentifyResult, PriorRow,
                        identify, lower_cost, misses_valid, untaught_regions, validate)
from ..progress import stage_steps
from .dead_band import dead_band_in_overlap, overlap_as_dead_band
from .identifiability import Identifiability, assess
from .prefit import chamber_prefit, force_balance_prefit, settled_offsets, stiction_prefit

__all__ = ["MECHANICAL", "PNEUMATIC", "CALIBRATED", "OTHER_STARTS_ABOVE", "START_S", "START_STRETCH_S",
           "CalibrateOptions", "Calibration", "applies", "DATA_STARTS", "breakaway_fit", "calibrate", "start_share",
           "effect_names", "finish", "first_stages", "force_balance", "force_balance_in_model", "from_data", "joint_start",
           "misfit_note", "model_start", "run_stage", "smooth_valve_prior", "stage_summaries", "validation_figures",
           "valve_and_chambers", "whole_model", "with_model_error"]

# what each stage estimates
MECHANICAL = ("Fc", "Fv", "kp", "mass", "external_force")
PNEUMATIC = ("critical_ratio", "dead_volume_cap", "dead_volume_rod", "offset_p1", "offset_p2", *FLOW_CHARACTERISTIC)
CALIBRATED = (*MECHANICAL, *PNEUMATIC)


# a valve-and-chambers fit that ends above this (x the noise, which that drive's residual tells well:
# 1.005-1.03 on the benchmark's effect-free runs) is started again from other_chamber_starts. On a
# held-out Norgren case (a logistic retract curve, no overlap) it had taken an overlap of 0.042 at
# 1.12 x, and the whole model crawled 40 iterations to 7.8 x with kp doubled; from the overlaps at
# zero it ended at 1.01 x, the whole model at 1.08 x with the friction within 1.5 %
OTHER_STARTS_ABOVE = 1.05
OTHER_CRITICAL_RATIOS = (0.2, 0.45)
# a whole-model fit that runs out of iterations above this (x the noise) crawled in a wrong basin:
# started once more (as identify restarts a fit that converged above it)
CRAWLING = 1.5  # the critical ratio's other starts (its realistic span 0.15-0.5)

# the flow characteristic's slope may change from one grid segment to the next by about this much
# (in units of the linear law's slope) without cost: a smooth valve; what the runs do not open
# follows its neighbours instead of staying undetermined. Where the runs open the valve, the
# data outweigh it. At 0.3, a clean 12 s run whose commands stopped at 0.295 left the curve
# beyond at 0.83 of the true slope (a rise the data barely reach, pulled by the cubic's knot
# slopes), and VALID, which went to 0.45, was missed by 1.26 x the noise; at 0.05, 1.02 x.
SLOPE_CHANGE = 0.05

# runs of more than this much data in all (s) are calibrated on START_S of it first, in stretches
# of START_STRETCH_S spread evenly, then the whole model on all of it (module docstring)
START_S = 120.0
START_STRETCH_S = 60.0


def smooth_valve_prior() -> tuple[PriorRow, ...]:
    """Slope continuity of each direction's flow characteristic between neighbouring segments."""
    widths = [b - a for a, b in zip((0.0, *OPENING_GRID[:-1]), OPENING_GRID)]
    return tuple(PriorRow({f"flow_{d}_{k + 1}": 1.0 / widths[k], f"flow_{d}_{k}": -1.0 / widths[k - 1]}, 0.0,
                          SLOPE_CHANGE)
                 for d in VALVE_DIRECTIONS for k in range(1, len(OPENING_GRID)))


@dataclass(frozen=True)
class CalibrateOptions:
    estimate: tuple[str, ...] = CALIBRATED  # what to calibrate (the others keep the file's values)
    interval_s: float = 0.1  # shooting interval of every stage
    max_iter: int = 40  # Gauss-Newton iterations per stage at most
    threads: int = IdentifyOptions.threads
    # a calibration whose TRAIN residual stays above this (x the sensor noise) says that the model
    # lacks something (an unmodelled effect, most likely) instead of merely "converged"
    misfit: float = 1.3
    # the valve and chambers' other starts where that fit ends above the noise (other_chamber_starts):
    # "overlap" (the overlaps at zero), "critical_ratio" (from both ends of its span)
    other_starts: tuple[str, ...] = ("overlap", "critical_ratio")


@dataclass
class Calibration:
    """The calibrated cylinder, the final (joint) fit, what each stage found and what the runs
    determine."""

    cylinder: Cylinder
    result: IdentifyResult
    identifiability: Identifiability
    stages: list[dict] = field(default_factory=list)
    wall_s: float = 0.0
    misfit_above: float = CalibrateOptions.misfit
    # (seconds of data the stages started from, seconds in all) where that was a share (start_share)
    start_share: tuple[float, float] | None = None

    @property
    def effects(self) -> tuple[Effect, ...]:
        """The effects calibrated with the file's quantities, at their estimates (none: the nominal model)."""
        return self.result.effects

    @property
    def misfit(self) -> str:
        """What a TRAIN residual well above the sensor noise means, in words ("" when it does not)."""
        return misfit_note(self.result, self.misfit_above)

    def to_json(self, start: Cylinder | None = None) -> dict:
        """The identify format (params, fit, solver) plus the stages, the valve characteristic
        and the identifiability; with `start` (the cylinder file), each parameter's file value."""
        out = self.result.to_json()
        if start is not None:
            for n, d in out["params"].items():
                d["file"] = start.value(n)
        out["solver"] = {**out["solver"], "wall_s": round(self.wall_s, 3), "stages": self.stages,
                         "start_share": None if self.start_share is None else
                         {"seconds": round(self.start_share[0], 3), "of": round(self.start_share[1], 3)}}
        v = self.cylinder.valve
        out["valve"] = {"opening": list(OPENING_GRID), **{
            d: {"overlap": getattr(v, f"overlap_{d}"), "flow": list(getattr(v, f"flow_{d}")),
                "conductance": [x * v.sonic_conductance for x in getattr(v, f"flow_{d}")]}
            for d in VALVE_DIRECTIONS}}
        out["identifiability"] = self.identifiability.to_json()
        out["misfit"] = ({"residual_sigma": self.result.solver["residual_sigma"], "above": self.misfit_above,
                          "message": self.misfit} if self.misfit else None)
        return out


def misfit_note(result: IdentifyResult, above: float = CalibrateOptions.misfit) -> str:
    """A calibrated model that leaves TRAIN at more than `above` x the sensor noise, said plainly:
    what the valve, the volumes, the mass, the offsets and the friction law can bend to, they have;
    what is left is most likely an effect the model lacks. Empty where the residual is at the noise."""
    sigma = result.solver["residual_sigma"]
    if not sigma > above:
        return ""
    with_effect = [e.name for e in result.effects]
    lacks = (f"the model with {' and '.join(with_effect)} still lacks something" if with_effect
             else "an effect the model lacks (leakage, stiction, friction that differs by direction or has memory, "
                  "heat exchange, a valve delay, ...) is the likely cause")
    return (f"the calibrated model leaves the run at {sigma:.3g} x the sensor noise (above {above:g}): {lacks}, and "
            "the quantities calibrated beside it may have been bent to imitate it; run `combined-reality diagnose "
            "--calibrate` on this run and another one to find the effect and calibrate with it")


def validation_figures(cyl: Cylinder, valid: Run, horizon_s: float = 1.0, val=None,
                       effects: Sequence[Effect] = (), train: Sequence[Run] = ()) -> dict:
    """The calibrated model (with `effects`, where it was calibrated with some) scored on a run no
    fit saw: open-loop segments of about `horizon_s` from initial states fitted per segment (as
    the diagnosis scores); `val`: that validation, where it was made already. Beyond
    TRUSTED_VALID x the noise, `caveat` says that its predictions are no match and, given the
    calibration's runs (`train`), where its error gathers (`regions`: untaught_regions)."""
    val = val if val is not None else validate(cyl, tuple(effects), valid, horizon_s)
    nrms = val.normalized_rms()
    where = untaught_regions(cyl, train, valid, val) if train and nrms > TRUSTED_VALID else None
    return {"rmse_x": val.rmse("x"), "rmse_p1": val.rmse("p1"), "rmse_p2": val.rmse("p2"),
            "normalized_rms": nrms, "horizon_s": horizon_s, "segments": len(val.segments),
            "status": val.status, "trusted_within": TRUSTED_VALID, "regions": where or [],
            "caveat": misses_valid("the calibrated model", nrms, where) if nrms > TRUSTED_VALID else ""}


def applies(effect: Effect, drive: str) -> bool:
    """Whether a stage of this drive sees the effect: the force balance (pressure drive) the
    mechanical ones, the valve and chambers (chambers drive) the pneumatic ones, the whole model all."""
    return drive == "command" or (effect.subsystem == "mechanical") == (drive == "pressure")


def effect_names(effects: Sequence[Effect], drive: str = "command") -> tuple[str, ...]:
    """The estimated names of the effects' parameters that a stage of this drive sees."""
    return tuple(e.key(k) for e in effects if applies(e, drive) for k in e.PARAMS)


def run_stage(name: str, cyl: Cylinder, runs: Sequence[Run], drive: str, estimate: Sequence[str],
              opts: CalibrateOptions, say: Callable[[str], None], nodes: np.ndarray | None = None,
              effects: Sequence[Effect] = (), start_only: bool | None = None,
              give_up_above: float = math.inf, held: Sequence[str] = (), restart: bool | None = None,
              give_up_after: int = IdentifyOptions.give_up_after) -> IdentifyResult | None:
    """One stage: the one identifier on the plant of `drive` with the effects that stage sees,
    their parameters estimated too (but for the effects named in `held`). The first two stages
    only start the whole model's fit (`start_only` by default), which settles their node states
    and escapes a wrong basin itself (`restart`, by default in the command drive: a fit that ends
    above the noise is started again)."""
    effects = tuple(e for e in effects if applies(e, drive))
    estimate = tuple(estimate) + effect_names([e for e in effects if e.name not in held], drive)
    if not estimate:
        return None
    t0 = time.perf_counter()
    start_only = drive != "command" if start_only is None else start_only
    res = identify(cyl, runs, IdentifyOptions(drive=drive, estimate=estimate, interval_s=opts.interval_s,
                                              max_iter=opts.max_iter, prefit=False, threads=opts.threads,
                                              start_only=start_only,
                                              restart_misfit=drive == "command" if restart is None else restart,
                                              give_up_above=give_up_above, give_up_after=give_up_after),
                   effects=effects, prior=smooth_valve_prior(), nodes=nodes, progress=stage_steps(say, name))
    say(f"  {name}: {res.solver['status']} after {res.solver['iterations']} iterations, "
        f"{time.perf_counter() - t0:.1f} s, residual {res.solver['residual_sigma']:.3g} x noise")
    return res


def calibrate(cyl: Cylinder, runs: Sequence[Run], options: CalibrateOptions = CalibrateOptions(),
              progress: Callable[[str], None] | None = None, effects: Sequence[Effect] = ()) -> Calibration:
    """Estimate `options.estimate` from the runs in three stages (module docstring); with
    `effects`, their parameters too, each in the stages that see it (a mechanical effect in the
    force balance, a pneumatic one in the valve and chambers, both in the whole model). Runs of
    more than START_S start on a share of them (start_share), the whole model then on all.

    One BLAS thread: the compiled evaluations take the cores, and OpenBLAS's own threads spin
    beside them (the normal equations' products of a chunk took 20 x as long so on a busy
    2-core machine)."""
    t0 = time.perf_counter()
    say = progress or (lambda _msg: None)
    with threadpool_limits(1, user_api="blas"):
        share = start_share(runs)
        staged = runs if share is None else share
        if share is not None:
            say(f"  the stages start from {_seconds(share):.0f} s of the {_seconds(runs):.0f} s of data (stretches of "
                f"{START_STRETCH_S:g} s spread over it), the whole model then fitted to all of it")
        mech, pneu = first_stages(cyl, staged, options, say, effects)
        through = force_balance_in_model(cyl, staged, options, say, mech, pneu)
        through = from_data(cyl, staged, options, say, mech, pneu, through, effects)
        joint, stages = whole_model(cyl, staged, options, say, *model_start(cyl, mech, pneu, through))
        stages = stage_summaries(mech, pneu, through) + stages
        if share is not None:
            # the whole model on all the data, from the share's estimates, its node states fitted
            # first with them held (sensitivities to the states alone: a tenth of the cost)
            nodes = identify(joint.cylinder, runs, IdentifyOptions(
                drive="command", estimate=(), interval_s=options.interval_s, max_iter=options.max_iter,
                prefit=False, threads=options.threads, restart_misfit=False), effects=joint.effects,
                progress=stage_steps(say, "3/3 on all the data: the node states")).nodes
            joint, more = whole_model(cyl, runs, options, say, joint.cylinder, nodes, joint.effects,
                                      name="3/3 on all the data:")
            stages = ([{**s, "data_s": round(_seconds(share), 3)} for s in stages]
                      + [{**s, "data_s": round(_seconds(runs), 3)} for s in more])
        return finish(cyl, runs, options, joint, mech, pneu, stages, t0,
                      None if share is None else (_seconds(share), _seconds(runs)))


def _seconds(runs: Sequence[Run]) -> float:
    return sum(r.duration for r in runs)


def start_share(runs: Sequence[Run], share_s: float = START_S, stretch_s: float = START_STRETCH_S) -> list[Run] | None:
    """The data the stages start from where the runs hold more than `share_s` in all (None where
    they hold less, or where the share would be all of them): the runs cut into equal pieces of
    at most `stretch_s`, and about `share_s / stretch_s` of them taken at equal spacing over all
    (a 600 s run: 120-180 s and 420-480 s), so that the start sees what the whole recording
    holds rather than its beginning."""
    total = _seconds(runs)
    if total <= share_s * (1 + 1e-9):
        return None
    pieces = []
    for r in runs:
        n = max(1, math.ceil(r.duration / stretch_s - 1e-9))
        per = math.ceil(r.n / n)
        pieces += [r.slice(a, min(a + per, r.n)) for a in range(0, r.n, per) if min(a + per, r.n) - a >= 3]
    k = max(1, round(share_s / (total / len(pieces))))
    if k >= len(pieces):  # the share would be all of it
        return None
    return [pieces[int((i + 0.5) * len(pieces) / k)] for i in range(k)]


def first_stages(cyl: Cylinder, runs: Sequence[Run], options: CalibrateOptions, say: Callable[[str], None],
                 effects: Sequence[Effect] = ()) -> tuple[IdentifyResult | None, IdentifyResult | None]:
    """Stages 1 and 2. They need nothing from each other: the force balance runs in a thread
    beside the valve and chambers (the compiled evaluations release the GIL), on one thread of
    its own."""
    want = set(options.estimate)
    if options.threads > 1:
        with ThreadPoolExecutor(1) as pool:
            mech_job = pool.submit(force_balance, cyl, runs, want, replace(options, threads=1), say, effects)
            pneu = valve_and_chambers(cyl, runs, want, options, say, effects)
            mech = mech_job.result()
    else:
        mech = force_balance(cyl, runs, want, options, say, effects)
        pneu = valve_and_chambers(cyl, runs, want, options, say, effects)
    return mech, pneu


def joint_start(cyl: Cylinder, mech: IdentifyResult | None, pneu: IdentifyResult | None
                ) -> tuple[Cylinder, np.ndarray | None, tuple[Effect, ...]]:
    """The command-driven model's start from the first two stages: their values (the force
    balance's constant force less what the offsets of the valve and chambers put into it), node
    states (motion from the force balance, pressures from the chambers) and effects as they found them."""
    values: dict[str, float] = {}
    effects: list[Effect] = []
    if pneu is not None:
        values.update({n: e.value for n, e in pneu.params.items() if "." not in n})
        effects += pneu.effects
    if mech is not None:
        values.update({n: e.value for n, e in mech.params.items() if "." not in n})
        effects += mech.effects
        if "external_force" in values:
            # stage 1 measured F_ext - o1 A1 + o2 A2 (offsets taken as zero there)
            g = cyl.geometry
            o1 = values.get("offset_p1", cyl.sensors.offset_p1) - cyl.sensors.offset_p1
            o2 = values.get("offset_p2", cyl.sensors.offset_p2) - cyl.sensors.offset_p2
            values["external_force"] += o1 * g.area_cap - o2 * g.area_rod
    nodes = None
    if mech is not None and pneu is not None:
        # a force balance that does not explain the run hands on its values, not its motion: its
        # node states describe the misfit (velocities of 100 m/s at 223 x the noise on a
        # reference-plant case); the measured motion instead (NaN: warm_nodes takes the data's)
        motion = mech.nodes[:2] if mech.explains_run else np.full_like(mech.nodes[:2], np.nan)
        nodes = np.vstack([pneu.nodes[:2], motion])
    return cyl.with_values(values), nodes, tuple(effects)


def force_balance_in_model(cyl: Cylinder, runs: Sequence[Run], options: CalibrateOptions, say: Callable[[str], None],
                           mech: IdentifyResult | None, pneu: IdentifyResult | None,
                           start_only: bool = True) -> IdentifyResult | None:
    """Between stages 2 and 3: the force balance once more, now through the command-driven model
    with the valve and chambers as stage 2 left them (its mechanical quantities and mechanical
    effects estimated, from stage 1's). The pressure drive's cost is dominated by the random walk
    its noisy input pressures drive, and an effect it lacks can leave it far off (a friction
    asymmetry case: 48 x the noise there, 2.7 x here); the whole model then starts from this
    continuation instead."""
    want = set(options.estimate)
    estimate = [n for n in MECHANICAL if n in want]
    if mech is None or pneu is None or not estimate:
        return None
    start, nodes, effects = joint_start(cyl, mech, pneu)
    # fitted to the end (the diagnosis's base), it is started once more from its ending values with
    # node states from the data where it ends above the noise: stage 1's motion nodes can be far
    # off (a supply droop case: stage 1 at 406 x, this fit from them 940 x, from the data 1.58 x)
    return run_stage("2/3 the force balance through the whole model (the valve and chambers as found)", start, runs,
                     "command", estimate, replace(options, max_iter=min(options.max_iter, 20)), say, nodes, effects,
                     start_only=start_only, held=[e.name for e in effects if e.subsystem != "mechanical"],
                     restart=not start_only)


def from_data(cyl: Cylinder, runs: Sequence[Run], options: CalibrateOptions, say: Callable[[str], None],
              mech: IdentifyResult | None, pneu: IdentifyResult | None, through: IdentifyResult | None,
              effects: Sequence[Effect]) -> IdentifyResult | None:
    """The force balance through the model once more from the data's start of the one effect
    calibrated that has one (DATA_STARTS), kept where it ends lower: `through` otherwise."""
    if len(effects) != 1 or effects[0].name not in DATA_STARTS or mech is None or pneu is None:
        return through
    try:
        res = DATA_STARTS[effects[0].name](joint_start(cyl, mech, pneu)[0], runs, effects[0],
                                           replace(options, max_iter=min(options.max_iter, 20)), say, cyl)
    except IdentificationError as e:
        say(f"  that start failed ({e})")
        return through
    if res is None or (through is not None and res.solver["cost"] >= through.solver["cost"]):
        return through
    return res


def model_start(cyl: Cylinder, mech: IdentifyResult | None, pneu: IdentifyResult | None,
                through: IdentifyResult | None) -> tuple[Cylinder, np.ndarray | None, tuple[Effect, ...]]:
    """The whole model's start: the first two stages' values, the mechanical ones (and the node
    states) from the force balance through the model where it ran."""
    if through is None:
        return joint_start(cyl, mech, pneu)
    return through.cylinder, through.nodes, tuple(through.effects)


def stage_summaries(mech: IdentifyResult | None, pneu: IdentifyResult | None,
                    through: IdentifyResult | None = None) -> list[dict]:
    out = []
    for res, name, drive in ((mech, "force balance", "pressure"), (pneu, "valve and chambers", "chambers"),
                             (through, "force balance through the model", "command")):
        if res is not None:
            out.append({"stage": name, "drive": drive, **_summary(res)})
    return out


def whole_model(cyl: Cylinder, runs: Sequence[Run], options: CalibrateOptions, say: Callable[[str], None],
                start: Cylinder, nodes: np.ndarray | None, effects: Sequence[Effect] = (),
                give_up_above: float = math.inf, name: str = "3/3") -> tuple[IdentifyResult, list[dict]]:
    """Stage 3: everything together, driven by the command, from `start` (values, node states
    and effects of the stages or of another fit), with the dead band moved into the overlap
    before it and, where the fit closed one itself, once more after it (kept where it ends
    lower). Returns the fit and its stages' summaries."""
    want = set(options.estimate)
    stages: list[dict] = []
    effects = tuple(effects)
    start = start.with_values(_dead_band_moved(start, want, say))
    estimate = [n for n in CALIBRATED if n in want]
    if not estimate and not effects:
        raise IdentificationError("nothing to calibrate: the estimate list is empty.")
    joint = run_stage(f"{name} the whole model (driven by the command)", start, runs, "command", estimate, options, say,
                      nodes, effects, give_up_above=give_up_above)
    stages.append({"stage": "whole model", "drive": "command", **_summary(joint)})
    status = joint.solver["status"]
    if status == "line_search_failed" or (status == "max_iterations"
                                          and joint.solver["residual_sigma"] > CRAWLING):
        # a failed line search is no result, nor a fit that ran out of iterations far above the noise
        # (a crawl in a wrong basin): once more from where it ended, node states afresh from the data
        # (as identify restarts a misfit that converged), given up where it stays above the first;
        # the lower cost kept
        why = "a failed line search" if status == "line_search_failed" else "running out of iterations"
        try:
            again = run_stage(f"{name} again after {why}", joint.cylinder, runs, "command", estimate, options, say,
                              None, joint.effects, give_up_above=min(give_up_above, joint.solver["cost"]))
        except IdentificationError as e:
            say(f"  that start failed ({e})")
        else:
            stages.append({"stage": f"whole model, again after {why}", "drive": "command", **_summary(again)})
            # the converged one where the two end alike (within 0.1 % of the cost)
            bound = joint.solver["cost"] * (1 + 1e-3 if again.solver["status"] == "converged" else 1)
            if again.solver["cost"] < bound:
                joint = again
    moved = _dead_band_moved(joint.cylinder, want, say, start)
    if moved:  # the whole model closed a dead band of its own: once more, from the same curve said so
        try:
            again = run_stage(f"{name} again, the dead band in the overlap", joint.cylinder.with_values(moved), runs,
                              "command", estimate, options, say, joint.nodes, joint.effects)
        except IdentificationError as e:  # a second start only: the first fit stands
            say(f"  the second start failed ({e}); the first fit stands")
        else:
            stages.append({"stage": "whole model, the dead band in the overlap", "drive": "command", **_summary(again)})
            if again.solver["cost"] < joint.solver["cost"]:
                joint = again
    return joint, stages


def finish(cyl: Cylinder, runs: Sequence[Run], options: CalibrateOptions, joint: IdentifyResult,
           mech: IdentifyResult | None, pneu: IdentifyResult | None, stages: list[dict], t0: float,
           start_share: tuple[float, float] | None = None) -> Calibration:
    """The calibration of a whole-model fit: the friction's std with the model error, what the
    runs determine, the stages (and the share of the data they started from)."""
    if mech is not None and mech.explains_run:
        joint.params.update(with_model_error(joint.params, mech.params))
    return Calibration(cylinder=joint.cylinder, result=joint, identifiability=assess(joint, runs), stages=stages,
                       wall_s=time.perf_counter() - t0, misfit_above=options.misfit, start_share=start_share)


def _dead_band_moved(cyl: Cylinder, want: set[str], say: Callable[[str], None],
                     started: Cylinder | None = None) -> dict[str, float]:
    """The flow characteristic's dead band moved into its overlap (dead_band.py), where the
    overlap and the rises are estimated; not where the fit `started` from that very overlap
    (it went back to the band it was given: a second start would repeat the first)."""
    moved: dict[str, float] = {}
    for d, values in dead_band_in_overlap(cyl).items():
        if started is not None and abs(values[f"overlap_{d}"] - started.value(f"overlap_{d}")) < 1e-3:
            continue
        if set(values) <= want:  # the whole curve of that direction is estimated
            moved.update(values)
            say(f"  the {d} characteristic is closed up to {values[f'overlap_{d}']:.3f} of the command: "
                "its overlap from there")
    return moved


def force_balance(cyl: Cylinder, runs: Sequence[Run], want: set[str], options: CalibrateOptions,
                  say: Callable[[str], None], effects: Sequence[Effect] = ()) -> IdentifyResult | None:
    """Stage 1: a linear start, then the pressure drive (with the mechanical `effects`)."""
    start = {k: v for k, v in force_balance_prefit(cyl, runs).items() if k in want}
    if start:
        say("  force balance, linear start: " + ", ".join(f"{k}={v:.4g}" for k, v in start.items()))
    return run_stage("1/3 force balance (driven by the measured pressures)", cyl.with_values(start), runs, "pressure",
                     [n for n in MECHANICAL if n in want], options, say, effects=effects)


# the Stribeck velocity a break-away start takes (the middle of its realistic span, 3-20 mm/s)
STRIBECK_START = 0.01


def breakaway_fit(start: Cylinder, runs: Sequence[Run], effect: Effect, options: CalibrateOptions,
                  say: Callable[[str], None], file_cyl: Cylinder | None = None) -> IdentifyResult | None:
    """The force balance through the command-driven model (`start`'s valve and chambers held) with
    a stiction `effect` started from the data: the break-away force above the seal level and the
    external force from the break-aways of both directions (prefit.stiction_prefit), the Stribeck
    velocity at STRIBECK_START, the linear start's mass (the file's where the accelerations cannot
    weigh it). Stick-slip leaves the fit from any other start in a wrong basin (a project case:
    859 x the noise without the effect, 89 x with it from its defaults); from this one the
    mechanical quantities settle with the effect held, then everything together, from node states
    afresh. The seal level from the cylinder file's friction law, then, where that fit ends above
    the noise (CRAWLING), from the linear start's Fc and Fv (which take the slips for sliding: Fc
    28.7 N for 24.8 on a reference-plant case, yet its fit went further there); the lower cost
    kept. None where the runs show no stick-slip (the break-aways by the file's seal level)."""
    file_cyl = file_cyl if file_cyl is not None else start
    f = file_cyl.friction
    linear = force_balance_prefit(file_cyl, runs)
    base = start.with_values({"mass": linear.get("mass", file_cyl.mechanics.moving_mass), "Fc": f.Fc, "Fv": f.Fv,
                              "kp": f.kp})
    found = stiction_prefit(base, runs)
    if not found:
        return None
    base = base.with_values({"external_force": found["external_force"]})
    laws = [{"Fc": f.Fc, "Fv": f.Fv}]
    if {"Fc", "Fv"} <= set(linear) and f.Fc + found["Fs_excess"] > linear["Fc"]:
        laws.append({"Fc": linear["Fc"], "Fv": linear["Fv"]})
    best = None
    for law in laws:
        excess = found["Fs_excess"] + f.Fc - law["Fc"]  # the same break-away force
        res = _from_breakaways(base.with_values(law), runs, replace(effect, Fs_excess=excess,
                                                                    v_stribeck=STRIBECK_START), options, say)
        best = lower_cost(best, res)
        if best.solver["residual_sigma"] <= CRAWLING:
            break
    return best


def _from_breakaways(base: Cylinder, runs: Sequence[Run], effect: Effect, options: CalibrateOptions,
                     say: Callable[[str], None]) -> IdentifyResult:
    say(f"  {effect.name} from the break-aways: Fs_excess={effect.Fs_excess:.4g} N over Fc={base.friction.Fc:.4g} N, "
        f"external_force={base.mechanics.external_force:.4g} N")
    estimate = [n for n in MECHANICAL if n in options.estimate]
    held = run_stage(f"the force balance with {effect.name} held at the break-aways", base, runs, "command", estimate,
                     options, say, effects=(effect,), start_only=False, held=(effect.name,), restart=False)
    free = run_stage(f"the force balance with {effect.name}", held.cylinder, runs, "command", estimate, options, say,
                     effects=held.effects, start_only=False, restart=False)
    return lower_cost(free, held)


# effects with a start from the data: stick-slip leaves a fit from the defaults in a wrong basin
DATA_STARTS = {"stiction": breakaway_fit}


def valve_and_chambers(cyl: Cylinder, runs: Sequence[Run], want: set[str], options: CalibrateOptions,
                       say: Callable[[str], None], effects: Sequence[Effect] = ()) -> IdentifyResult | None:
    """Stage 2: linear starts (offsets where the pressures settle at an end, then the
    characteristic and the dead volumes), then the chambers drive (with the pneumatic `effects`)."""
    offsets = {k: v for k, v in settled_offsets(cyl, runs).items() if k in want}
    start = {k: v for k, v in chamber_prefit(cyl, runs, offsets).items() if k in want}
    start.update(offsets)
    if start:
        say("  valve and chambers, linear start: " + ", ".join(f"{k}={v:.4g}" for k, v in start.items()))
    estimate = [n for n in PNEUMATIC if n in want]
    res = run_stage("2/3 valve and chambers (driven by the measured motion)", cyl.with_values(start), runs,
                    "chambers", estimate, options, say, effects=effects)
    if res is None or res.solver["residual_sigma"] <= OTHER_STARTS_ABOVE:
        return res
    # the valve's multimodal corners: an overlap against a curve that starts flat, the critical
    # ratio against the offsets. Started again from where the fit ended with one of them changed
    # (never worse: the lowest cost is kept)
    for label, values in other_chamber_starts(res.cylinder, want, options.other_starts):
        try:
            again = run_stage(f"2/3 again, {label}", res.cylinder.with_values(values), runs, "chambers", estimate,
                              options, say, res.nodes, res.effects)
        except IdentificationError as e:
            say(f"  that start failed ({e})")
            continue
        if again.solver["cost"] < res.solver["cost"]:
            say(f"  kept: cost {again.solver['cost'] / res.solver['cost'] - 1:+.1%}")
            res = again
        if res.solver["residual_sigma"] <= OTHER_STARTS_ABOVE:
            break
    return res


def other_chamber_starts(cyl: Cylinder, want: set[str], which: Sequence[str] = ("overlap", "critical_ratio")
                         ) -> list[tuple[str, dict[str, float]]]:
    """The valve and chambers' other starts, in the order tried: both overlaps at zero (the same
    curves as dead bands), where both have one each alone (a valve may overlap one way only),
    then the critical ratio low and high (the offsets as they are)."""
    out = []
    each = {d: values for d, values in overlap_as_dead_band(cyl).items() if set(values) <= want}
    if each and "overlap" in which:
        out.append(("the overlaps at zero (the same curves closed up to them)",
                    {k: v for values in each.values() for k, v in values.items()}))
        if len(each) > 1:
            out += [(f"the {d} overlap at zero (the same curve closed up to it)", values) for d, values in each.items()]
    if "critical_ratio" in want and "critical_ratio" in which:
        b = cyl.valve.critical_ratio
        out += [(f"the critical ratio from {x:g}", {"critical_ratio": x}) for x in OTHER_CRITICAL_RATIOS
                if abs(x - b) > 0.05]
    return out


def with_model_error(final: dict[str, Estimate], force_balance: dict[str, Estimate]) -> dict[str, Estimate]:
    """The final estimates of what the force balance also estimated, with the two estimates'
    difference added to the standard deviation (in quadrature). The force balance sees the
    measured pressures and not the valve; the whole model sees the valve through its
    characteristic. Were the model exact, they would agree within the noise; what a valve
    curve of a few knots cannot follow shifts the final friction by more than its noise-only
    std (on the benchmark's reference plant, 0.14 % of Fc at 5 std), and that difference is
    the honest yardstick of it."""
    out = {}
    for n, e in final.items():
        if n in force_balance and n in MECHANICAL:
            d = force_balance[n].value - e.value
            out[n] = replace(e, std=math.sqrt(e.std ** 2 + d * d))
    return out


def _summary(res: IdentifyResult) -> dict:
    return {"status": res.solver["status"], "iterations": res.solver["iterations"],
            "wall_s": res.solver["wall_s"], "residual_sigma": res.solver["residual_sigma"],
            "params": {n: e.value for n, e in res.params.items()}}
