"""`combined-reality calibrate`: what the cylinder file only guesses, estimated with the friction."""
from __future__ import annotations

import math
import time

from .common import UsageError, eprint, load_config, progress_printer


def add_parser(sub) -> None:
    c = sub.add_parser(
        "calibrate", help="estimate the valve characteristic, dead volumes, mass, sensor offsets and friction",
        description="Estimate what the cylinder file only guesses — the valve's flow characteristic per direction "
                    "(overlap and curve), its critical ratio, both dead volumes, the moving mass, the offsets of "
                    "both pressure sensors and a constant external force — together with the friction Fc, Fv, kp, "
                    "staged the way the physics separates them: the piston's force balance driven by the measured "
                    "pressures, the valve and chambers driven by the measured motion, then the whole model driven "
                    "by the command. Record the runs with `live --program calibration` (it creeps through the "
                    "valve's overlap, moves slowly across the stroke both ways, holds at both end stops with the "
                    "valve open and closed, and pulses the valve). Writes the calibrated "
                    "cylinder file with your comments kept, and says what the runs could not determine.")
    c.add_argument("--config", required=True, help="cylinder TOML file (its values are the starting guesses)")
    c.add_argument("runs", nargs="+", metavar="RUN.csv", help="recorded runs, calibrated jointly")
    c.add_argument("--validate", metavar="VALID.csv",
                   help="a run of the same cylinder no fit sees: the calibrated model is scored on it")
    c.add_argument("--json", metavar="OUT.json", help="write the result (identify format plus valve, stages, "
                                                      "identifiability and validation)")
    c.add_argument("--write-config", metavar="CAL.toml",
                   help="write the calibrated cylinder file (every other subcommand accepts it; comments kept)")
    c.add_argument("--estimate", help="comma-separated subset of the calibrated parameters (default: all)")
    c.add_argument("--horizon", type=float, default=1.0, help="validation simulation horizon, s (default 1)")
    c.add_argument("--interval", type=float, default=0.1, help="shooting interval in seconds (default 0.1)")
    c.add_argument("--max-iter", type=int, default=40, help="Gauss-Newton iterations per stage at most (default 40)")
    c.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    c.set_defaults(func=run)


def _table(cal, start) -> str:
    rows = [("parameter", "value", "std", "unit", "file")]
    for n, e in cal.result.params.items():
        if n.startswith("flow_"):
            continue  # the characteristic is shown as a curve below
        rows.append((n, f"{e.value:.6g}", f"{e.std:.3g}" + (" (at bound)" if e.at_bound else ""), e.unit,
                     f"{start.value(n):.4g}"))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
    v = cal.cylinder.valve
    from sim.cylinder import OPENING_GRID

    grid = " ".join(f"{g:>5.0%}" for g in OPENING_GRID)
    lines.append(f"valve: C / sonic_conductance at the opening beyond the overlap  {grid}")
    for d in ("extend", "retract"):
        levels = " ".join(f"{x:5.3f}" for x in getattr(v, f"flow_{d}"))
        lines.append(f"  {d:7s} (overlap {getattr(v, f'overlap_{d}'):.3f}){'':38s}{levels}")
    return "\n".join(lines)


def run(args) -> int:
    from ..calibrate import CALIBRATED, CalibrateOptions, calibrate, validation_figures
    from ..files import (check_run_against_cylinder, check_train_and_valid, clean_json, read_run, write_json_atomic)
    from ..files.cylinder_file import write_cylinder_file
    from ..identify import IdentificationError

    start = load_config(args.config)
    runs = [read_run(p) for p in args.runs]
    for r in runs:
        check_run_against_cylinder(r, start)
    valid = None
    if args.validate:
        valid = read_run(args.validate)
        check_train_and_valid(start, runs[0], valid, args.runs[0], args.validate, "calibrate")
    estimate = CALIBRATED
    if args.estimate is not None:
        estimate = tuple(s.strip() for s in args.estimate.split(",") if s.strip())
        unknown = [n for n in estimate if n not in CALIBRATED]
        if unknown or not estimate:
            raise UsageError(f"--estimate: {', '.join(unknown) or 'nothing given'} is not calibrated (calibrated: "
                             f"{', '.join(CALIBRATED)}).")
    for name, v in (("--interval", args.interval), ("--horizon", args.horizon)):
        if not (v > 0 and math.isfinite(v)):
            raise UsageError(f"{name} must be a positive number of seconds, not {v}.")
    if args.max_iter < 1:
        raise UsageError(f"--max-iter must be at least 1, not {args.max_iter}.")
    say = progress_printer(args.quiet)
    if say:
        say(f"calibrating {len(estimate)} parameters from {len(runs)} run(s), {sum(r.n for r in runs)} samples, "
            "in three stages")
    t0 = time.perf_counter()
    try:
        cal = calibrate(start, runs, CalibrateOptions(estimate=estimate, interval_s=args.interval,
                                                      max_iter=args.max_iter), progress=say)
    except IdentificationError as e:
        eprint(f"combined-reality calibrate: {e}")
        return 1
    out = cal.to_json(start)
    out["config"] = str(start.source)
    out["inputs"] = [str(p) for p in args.runs]
    print(_table(cal, start))
    s = cal.result.solver
    f = cal.result.fit
    print(f"fit: rmse_x {f['rmse_x'] * 1e6:.2f} um, rmse_p1 {f['rmse_p1']:.0f} Pa, rmse_p2 {f['rmse_p2']:.0f} Pa; "
          f"solver: {s['status']}, residual sigma {s['residual_sigma']:.3g} x noise, "
          f"{time.perf_counter() - t0:.1f} s in all")
    if valid is not None:
        val = validation_figures(cal.cylinder, valid, args.horizon)
        out["validation"] = val
        print(f"validation on {args.validate}: rmse_x {val['rmse_x'] * 1e6:.2f} um, rmse_p1 {val['rmse_p1']:.0f} Pa, "
              f"rmse_p2 {val['rmse_p2']:.0f} Pa; all outputs {val['normalized_rms']:.2f} x the sensor noise "
              "(1 = a perfect model)")
    for line in cal.identifiability.lines():
        print(line)
    if args.json:
        write_json_atomic(args.json, clean_json(out))
    if args.write_config:
        note = f"calibrated from {', '.join(args.runs)}"
        header = [f"Calibrated by combined-reality calibrate on {time.strftime('%Y-%m-%d %H:%M')} from "
                  f"{', '.join(args.runs)} (starting from {start.source}); residual {s['residual_sigma']:.3g} x the "
                  "sensor noise" + (f", validation {out['validation']['normalized_rms']:.3g} x" if valid else "") + "."]
        write_cylinder_file(args.write_config, cal.cylinder, note=note, header=header)
        if say:
            say(f"wrote {args.write_config} (the comments of {start.source} kept)")
    if s["status"] != "converged":
        eprint(f"combined-reality calibrate: the solver stopped without converging ({s['status']}); the values "
               "above are the last iterate.")
        return 1
    if not cal.result.explains_run:
        eprint(f"combined-reality calibrate: even calibrated, the model does not explain the run (residual "
               f"{s['residual_sigma']:.3g} x the sensor noise): an effect the model lacks is at work; run "
               "`combined-reality diagnose` with the calibrated cylinder file.")
        return 1
    return 0
