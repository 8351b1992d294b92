"""`combined-reality calibrate`: what the cylinder file only guesses, estimated with the friction."""
from __future__ import annotations

import time

from .. import options
from .common import (add_max_rows, check_paths, eprint, load_config, preflight_runs, progress_printer,
                     read_runs, typed)


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
    c.add_argument("--report", metavar="REPORT.html", type=typed(options.report_file),
                   help="write a self-contained HTML report: the values against the file's, the valve characteristic "
                        "per direction with its band, the fit of every run, VALID's traces, what the runs could not "
                        "determine and what to record")
    c.add_argument("--write-config", metavar="CAL.toml",
                   help="write the calibrated cylinder file (every other subcommand accepts it; comments kept)")
    c.add_argument("--estimate", type=typed(options.parameter_names),
                   help="comma-separated subset of the calibrated parameters, each once (default: all)")
    c.add_argument("--horizon", type=typed(options.positive_seconds, "--horizon"), default=1.0,
                   help="validation simulation horizon, s (default 1)")
    c.add_argument("--interval", type=typed(options.interval), default=0.1,
                   help=f"shooting interval in seconds, at most {options.INTERVAL_MAX:g} (default 0.1)")
    c.add_argument("--max-iter", type=typed(options.whole_number, "--max-iter", lo=1, hi=options.MAX_ITER),
                   default=40, help="Gauss-Newton iterations per stage at most (default 40)")
    add_max_rows(c)
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
    from ..files import check_train_and_valid, clean_json, read_run, write_json_atomic
    from ..files.cylinder_file import write_cylinder_file
    from ..identify import validate

    check_paths({"--json": args.json, "--write-config": args.write_config, "--report": args.report},
                inputs=[args.config, *args.runs, args.validate])
    estimate = CALIBRATED if args.estimate is None else args.estimate
    options.check_estimable(estimate, CALIBRATED)
    start = load_config(args.config)
    runs = read_runs(args.runs, args)
    valid = None
    warning = None
    if args.validate:
        valid = read_run(args.validate, args.max_rows)
        warning = check_train_and_valid(start, runs[0], valid, args.runs[0], args.validate)
    # runs without motion, or friction they cannot determine, end before the fit (identify's rules);
    # its notes follow no refusal
    preflight_runs(start, runs, estimate, held_out=[valid] if valid is not None else [])
    if warning:
        eprint(f"combined-reality calibrate: warning: {warning}")
    say = progress_printer(args.quiet)
    if say:
        say(f"calibrating {len(estimate)} parameters from {len(runs)} run(s), {sum(r.n for r in runs)} samples, "
            "in three stages")
    t0 = time.perf_counter()
    cal = calibrate(start, runs, CalibrateOptions(estimate=estimate, interval_s=args.interval, max_iter=args.max_iter),
                    progress=say)
    out = cal.to_json(start)
    out["config"] = str(start.source)
    out["inputs"] = [str(p) for p in args.runs]
    print(_table(cal, start))
    s = cal.result.solver
    f = cal.result.fit
    print(f"fit: rmse_x {f['rmse_x'] * 1e6:.2f} um, rmse_p1 {f['rmse_p1']:.0f} Pa, rmse_p2 {f['rmse_p2']:.0f} Pa; "
          f"solver: {s['status']}, residual sigma {s['residual_sigma']:.3g} x noise, "
          f"{time.perf_counter() - t0:.1f} s in all")
    if cal.misfit:
        print(f"not explained: {cal.misfit}")
    validation = None
    if valid is not None:
        validation = validate(cal.cylinder, (), valid, args.horizon)
        val = validation_figures(cal.cylinder, valid, args.horizon, validation, train=runs)
        out["validation"] = val
        print(f"validation on {args.validate}: rmse_x {val['rmse_x'] * 1e6:.2f} um, rmse_p1 {val['rmse_p1']:.0f} Pa, "
              f"rmse_p2 {val['rmse_p2']:.0f} Pa; all outputs {val['normalized_rms']:.2f} x the sensor noise "
              "(1 = a perfect model)")
        if val["caveat"]:
            print(f"prediction: {val['caveat']}")
    for line in cal.identifiability.lines():
        print(line)
    if args.json:
        write_json_atomic(args.json, clean_json(out))
        if say:
            say(f"wrote {args.json}")
    if args.report:
        from ..calibrate.report import write_calibration_report

        write_calibration_report(cal, start, runs, args.report, valid=valid, validation=validation,
                                 inputs=args.runs, figures=out.get("validation"))
        if say:
            say(f"wrote {args.report}")
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
