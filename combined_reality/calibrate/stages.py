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

from sim.cylinder import FLOW_CHARACTERISTIC, OPENING_GRID, VALVE_DIRECTIONS, Cylinder

from ..files import Run
from ..identify import Estimate, IdentificationError, IdentifyOptions, IdentifyResult, PriorRow, identify, validate
from ..progress import stage_steps
from .dead_band import dead_band_in_overlap
from .identifiability import Identifiability, assess
from .prefit import chamber_prefit, force_balance_prefit, settled_offsets

__all__ = ["MECHANICAL", "PNEUMATIC", "CALIBRATED", "CalibrateOptions", "Calibration", "calibrate",
           "smooth_valve_prior", "validation_figures", "with_model_error"]

# what each stage estimates
MECHANICAL = ("Fc", "Fv", "kp", "mass", "external_force")
PNEUMATIC = ("critical_ratio", "dead_volume_cap", "dead_volume_rod", "offset_p1", "offset_p2", *FLOW_CHARACTERISTIC)
CALIBRATED = (*MECHANICAL, *PNEUMATIC)


# the flow characteristic's slope may change from one grid segment to the next by about this much
# (in units of the linear law's slope) without cost: a smooth valve; what the runs do not open
# follows its neighbours instead of staying undetermined. Where the runs open the valve, the
# data outweigh it. At 0.3, a clean 12 s run whose commands stopped at 0.295 left the curve
# beyond at 0.83 of the true slope (a rise the data barely reach, pulled by the cubic's knot
# slopes), and VALID, which went to 0.45, was missed by 1.26 x the noise; at 0.05, 1.02 x.
SLOPE_CHANGE = 0.05


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


@dataclass
class Calibration:
    """The calibrated cylinder, the final (joint) fit, what each stage found and what the runs
    determine."""

    cylinder: Cylinder
    result: IdentifyResult
    identifiability: Identifiability
    stages: list[dict] = field(default_factory=list)
    wall_s: float = 0.0

    def to_json(self, start: Cylinder | None = None) -> dict:
        """The identify format (params, fit, solver) plus the stages, the valve characteristic
        and the identifiability; with `start` (the cylinder file), each parameter's file value."""
        out = self.result.to_json()
        if start is not None:
            for n, d in out["params"].items():
                d["file"] = start.value(n)
        out["solver"] = {**out["solver"], "wall_s": round(self.wall_s, 3), "stages": self.stages}
        v = self.cylinder.valve
        out["valve"] = {"opening": list(OPENING_GRID), **{
            d: {"overlap": getattr(v, f"overlap_{d}"), "flow": list(getattr(v, f"flow_{d}")),
                "conductance": [x * v.sonic_conductance for x in getattr(v, f"flow_{d}")]}
            for d in VALVE_DIRECTIONS}}
        out["identifiability"] = self.identifiability.to_json()
        return out


def validation_figures(cyl: Cylinder, valid: Run, horizon_s: float = 1.0, val=None) -> dict:
    """The calibrated model scored on a run no fit saw: open-loop segments of about
    `horizon_s` from initial states fitted per segment (as the diagnosis scores); `val`: that
    validation, where it was made already."""
    val = val if val is not None else validate(cyl, (), valid, horizon_s)
    return {"rmse_x": val.rmse("x"), "rmse_p1": val.rmse("p1"), "rmse_p2": val.rmse("p2"),
            "normalized_rms": val.normalized_rms(), "horizon_s": horizon_s, "segments": len(val.segments),
            "status": val.status}


def _stage(name: str, cyl: Cylinder, runs: Sequence[Run], drive: str, estimate: Sequence[str],
           opts: CalibrateOptions, say: Callable[[str], None], nodes: np.ndarray | None = None) -> IdentifyResult | None:
    if not estimate:
        return None
    t0 = time.perf_counter()
    # the first two stages only start the whole model's fit, which settles their node states
    # and escapes a wrong basin itself (it is restarted when it ends above the noise)
    start_only = drive != "command"
    res = identify(cyl, runs, IdentifyOptions(drive=drive, estimate=tuple(estimate), interval_s=opts.interval_s,
                                              max_iter=opts.max_iter, prefit=False, threads=opts.threads,
                                              start_only=start_only, restart_misfit=not start_only),
                   prior=smooth_valve_prior(), nodes=nodes, progress=stage_steps(say, name))
    say(f"  {name}: {res.solver['status']} after {res.solver['iterations']} iterations, "
        f"{time.perf_counter() - t0:.1f} s, residual {res.solver['residual_sigma']:.3g} x noise")
    return res


def calibrate(cyl: Cylinder, runs: Sequence[Run], options: CalibrateOptions = CalibrateOptions(),
              progress: Callable[[str], None] | None = None) -> Calibration:
    """Estimate `options.estimate` from the runs in three stages (module docstring)."""
    t0 = time.perf_counter()
    say = progress or (lambda _msg: None)
    want = set(options.estimate)
    stages: list[dict] = []

    # 1 and 2 need nothing from each other: the force balance runs in a thread beside the valve
    # and chambers (the compiled evaluations release the GIL), on one thread of its own
    if options.threads > 1:
        with ThreadPoolExecutor(1) as pool:
            mech_job = pool.submit(_force_balance, cyl, runs, want, replace(options, threads=1), say)
            pneu = _valve_and_chambers(cyl, runs, want, options, say)
            mech = mech_job.result()
    else:
        mech = _force_balance(cyl, runs, want, options, say)
        pneu = _valve_and_chambers(cyl, runs, want, options, say)
    if mech is not None:
        stages.append({"stage": "force balance", "drive": "pressure", **_summary(mech)})
    if pneu is not None:
        stages.append({"stage": "valve and chambers", "drive": "chambers", **_summary(pneu)})

    # 3. everything together, driven by the command, from the stages' values
    values: dict[str, float] = {}
    if pneu is not None:
        values.update({n: e.value for n, e in pneu.params.items()})
    if mech is not None:
        values.update({n: e.value for n, e in mech.params.items()})
        if "external_force" in values:
            # stage 1 measured F_ext - o1 A1 + o2 A2 (offsets taken as zero there)
            g = cyl.geometry
            o1 = values.get("offset_p1", cyl.sensors.offset_p1) - cyl.sensors.offset_p1
            o2 = values.get("offset_p2", cyl.sensors.offset_p2) - cyl.sensors.offset_p2
            values["external_force"] += o1 * g.area_cap - o2 * g.area_rod
    start = cyl.with_values(values)
    start = start.with_values(_dead_band_moved(start, want, say))
    # node states from the stages: motion from the force balance, pressures from the chambers
    nodes = np.vstack([pneu.nodes[:2], mech.nodes[:2]]) if mech is not None and pneu is not None else None
    estimate = [n for n in CALIBRATED if n in want]
    joint = _stage("3/3 the whole model (driven by the command)", start, runs, "command", estimate, options, say, nodes)
    if joint is None:
        raise IdentificationError("nothing to calibrate: the estimate list is empty.")
    stages.append({"stage": "whole model", "drive": "command", **_summary(joint)})
    moved = _dead_band_moved(joint.cylinder, want, say, start)
    if moved:  # the whole model closed a dead band of its own: once more, from the same curve said so
        try:
            again = _stage("3/3 again, the dead band in the overlap", joint.cylinder.with_values(moved), runs,
                           "command", estimate, options, say, joint.nodes)
        except IdentificationError as e:  # a second start only: the first fit stands
            say(f"  the second start failed ({e}); the first fit stands")
        else:
            stages.append({"stage": "whole model, the dead band in the overlap", "drive": "command", **_summary(again)})
            if again.solver["cost"] < joint.solver["cost"]:
                joint = again
    if mech is not None and mech.explains_run:
        joint.params.update(with_model_error(joint.params, mech.params))
    return Calibration(cylinder=joint.cylinder, result=joint, identifiability=assess(joint, runs), stages=stages,
                       wall_s=time.perf_counter() - t0)


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


def _force_balance(cyl: Cylinder, runs: Sequence[Run], want: set[str], options: CalibrateOptions,
                   say: Callable[[str], None]) -> IdentifyResult | None:
    """Stage 1: a linear start, then the pressure drive."""
    start = {k: v for k, v in force_balance_prefit(cyl, runs).items() if k in want}
    if start:
        say("  force balance, linear start: " + ", ".join(f"{k}={v:.4g}" for k, v in start.items()))
    return _stage("1/3 force balance (driven by the measured pressures)", cyl.with_values(start), runs, "pressure",
                  [n for n in MECHANICAL if n in want], options, say)


def _valve_and_chambers(cyl: Cylinder, runs: Sequence[Run], want: set[str], options: CalibrateOptions,
                        say: Callable[[str], None]) -> IdentifyResult | None:
    """Stage 2: linear starts (offsets where the pressures settle at an end, then the
    characteristic and the dead volumes), then the chambers drive."""
    offsets = {k: v for k, v in settled_offsets(cyl, runs).items() if k in want}
    start = {k: v for k, v in chamber_prefit(cyl, runs, offsets).items() if k in want}
    start.update(offsets)
    if start:
        say("  valve and chambers, linear start: " + ", ".join(f"{k}={v:.4g}" for k, v in start.items()))
    return _stage("2/3 valve and chambers (driven by the measured motion)", cyl.with_values(start), runs, "chambers",
                  [n for n in PNEUMATIC if n in want], options, say)


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
