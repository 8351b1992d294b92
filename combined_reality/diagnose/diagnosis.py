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

import math
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from sim.cylinder import Cylinder
from sim.effects import EFFECTS

from ..files import Run
from ..identify import (IdentifyOptions, Validation, identify, regions, untaught_regions, validate, validation_segments,
                        velocity_estimate)
from ..parallel import run_jobs
from ..progress import counter, stage_steps
from .candidates import NESTED_START, Candidate, NominalFit, candidate_starts, has_nested_start, score_candidate
from .fits import best_of_starts, fit_first, further_scored, further_starts, validate_screened
from .options import DiagnoseOptions
from .subsystems import regressor_correlations, subsystem_split
from .text import fit_caveat, prediction_caveat
from .verdict import best_pair, decide, fold_absent_partner, ranked, with_fold_note
from .where import whiteness


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
    # every TRAIN run (with calibrate: a calibration run and an ordinary one may be given); () is (train,)
    train_runs: tuple[Run, ...] = ()

    @property
    def best(self) -> Candidate | None:
        """The candidate the verdict names (a single effect or the pair); None for `none` and
        `unexplained`."""
        if self.pair is not None and self.verdict == self.pair.effect:
            return self.pair
        return next((c for c in self.ranking if c.effect == self.verdict), None)

    @property
    def shown_validation(self) -> Validation | None:
        """VALID as the model the verdict shows predicts it: the verdict's candidate, the nominal
        model for `none`; None for `unexplained`."""
        if self.best is not None:
            return self.best.validation
        return self.base_validation if self.verdict == "none" else None

    def prediction(self) -> dict | None:
        """How far the shown model's predictions can be trusted: its normalized RMS on VALID, and
        beyond options.trusted_valid x the noise the regimes where its error gathers
        (untaught_regions) and the caveat in words ("" within it); None for `unexplained`."""
        val = self.shown_validation
        if val is None:
            return None
        nrms = val.normalized_rms()
        within = self.options.trusted_valid
        train = self.train_runs or (self.train,)
        where = [] if nrms <= within else untaught_regions(self.cylinder, train, self.valid, val)
        return {"model": self.verdict, "normalized_rms": nrms, "trusted_within": within, "regions": where,
                "caveat": "" if nrms <= within else prediction_caveat(self, nrms, where)}

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
            "verdict_caveat": fit_caveat(self.best) if self.best is not None else "",
            "prediction": self.prediction(),
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


def _call(job):
    """A job of a process pool: (function, its arguments)."""
    fn, args = job
    return fn(*args)


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

    pair, folded = None, ""
    if opts.pair and best is not None:
        pair = best_pair(start, train, valid, ranking, base_val, base_rmse, segments, opts, say)
        ranking, pair, folded = fold_absent_partner(ranking, pair)
        best = ranking[0]
    verdict, verdict_note = decide(base_val, best, pair, opts)
    verdict_note = with_fold_note(verdict, verdict_note, best, folded)
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
