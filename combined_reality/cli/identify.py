"""`combined-reality identify`: friction (or any estimable parameter) from recorded runs."""
from __future__ import annotations

from pathlib import Path

from sim.cylinder import ESTIMABLE, Cylinder

from .. import options
from .common import (UsageError, add_max_rows, check_paths, eprint, estimate_list, load_config, parse_effects,
                     preflight_runs, progress_printer, read_runs, typed)


def add_parser(sub) -> None:
    i = sub.add_parser("identify", help="identify friction parameters from recorded runs",
                       description="Identify parameters (Fc, Fv, kp by default) from one or more recorded runs, "
                                   "fitted jointly, by multiple-shooting least squares: the model is driven by the "
                                   "recorded valve command and its parameters are adjusted until the simulated "
                                   "position and pressures match the measured ones. Prints the estimates with "
                                   "standard deviations and the fit; exit status 1 if the solver did not converge, 2 "
                                   "if the runs cannot determine a chosen parameter (the message says which and why).")
    i.add_argument("--config", required=True, help="cylinder TOML file (its values are the starting point)")
    i.add_argument("runs", nargs="+", metavar="RUN.csv", help="recorded runs")
    i.add_argument("--json", help="write the result as JSON (docs/formats.md)")
    i.add_argument("--report", metavar="REPORT.html", type=typed(options.report_file),
                   help="write a self-contained HTML report: measured vs simulated per run, the errors against time, "
                        "velocity and position, the friction law found, the iterations")
    i.add_argument("--estimate", type=typed(options.parameter_names),
                   help=f"comma-separated parameters, each once (default from the config, else Fc,Fv,kp; "
                        f"estimable: {', '.join(ESTIMABLE)})")
    i.add_argument("--drive", choices=["command", "pressure", "chambers"],
                   help="command: full model driven by the recorded valve command (default); "
                        "pressure: piston only, driven by the measured pressures; "
                        "chambers: valve and chambers only, driven by the command and the measured motion")
    i.add_argument("--effect", action="append", metavar="NAME[:k=v,...]",
                   help="add an unmodelled effect to the model (its parameters may be estimated as NAME.param)")
    i.add_argument("--interval", type=typed(options.interval), default=0.1,
                   help=f"shooting interval in seconds, at most {options.INTERVAL_MAX:g} (default 0.1)")
    i.add_argument("--max-iter", type=typed(options.whole_number, "--max-iter", lo=1, hi=options.MAX_ITER),
                   default=40, help="Gauss-Newton iterations at most (default 40)")
    i.add_argument("--no-prefit", action="store_true",
                   help="start from the config's friction values, not from the equation-error fit")
    i.add_argument("--write-config", metavar="OUT.toml",
                   help="write the cylinder file with the identified values (the comments of --config kept)")
    add_max_rows(i)
    i.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    i.set_defaults(func=run)


def format_table(result, truth: Cylinder | None = None) -> str:
    """The estimates of an IdentifyResult (value, std, unit, start; with `truth`, the true value and the error),
    the fit and the solver's status, as printed by identify and demo."""
    rows = [("parameter", "value", "std", "unit", "initial") + (("true", "error") if truth else ())]
    unknown = set(result.not_determined)
    for n, e in result.params.items():
        std = f"{e.std:.3g}" + (" (at bound)" if e.at_bound else "") + (" not determined" if n in unknown else "")
        row = (n, f"{e.value:.6g}", std, e.unit, f"{e.initial:.4g}")
        if truth:
            tv = truth.value(n) if "." not in n else float("nan")
            err = (e.value - tv) / tv * 100 if tv else float("nan")
            row += (f"{tv:.6g}", f"{err:+.2f} %")
        rows.append(row)
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
    f = result.fit
    fit = [f"rmse_x {f['rmse_x'] * 1e6:.2f} um (R2 {f['r2_x']:.6f})"] if "rmse_x" in f else []  # (chambers: no x)
    if "rmse_p1" in f:
        fit.append(f"rmse_p1 {f['rmse_p1']:.0f} Pa, rmse_p2 {f['rmse_p2']:.0f} Pa")
    if "kp" in result.params:
        kp = result.params["kp"]
        lines.append(f"(kp = {kp.value * 1e5:.4g} +- {kp.std * 1e5:.2g} N/bar)")
    s = result.solver
    lines.append("fit: " + "; ".join(fit))
    status = s["status"] if not unknown or s["status"] != "converged" else \
        f"stopped, but the data do not determine {', '.join(sorted(unknown))} (std >= |value|),"
    lines.append(f"solver: {status} after {s['iterations']} iterations, {s['wall_s']:.2f} s "
                 f"({result.drive} drive, {s['n_samples']} samples, residual sigma {s['residual_sigma']:.3g} x noise)")
    return "\n".join(lines)


def run(args) -> int:
    from ..files import clean_json, write_json_atomic
    from ..files.cylinder_file import write_cylinder_file
    from ..identify import IdentifyOptions, check_drive, identify

    check_paths({"--json": args.json, "--write-config": args.write_config, "--report": args.report},
                inputs=[args.config, *args.runs])
    effects = parse_effects(args.effect)
    cyl = load_config(args.config)
    effect_params = sorted(f"{e.name}.{n}" for e in effects for n in e.param_names())
    estimate = estimate_list(args.estimate, cyl, known=(*ESTIMABLE, *effect_params))
    runs = read_runs(args.runs, args)
    drive = args.drive or cyl.identify.drive
    check_drive(drive, estimate)
    opts = IdentifyOptions(drive=drive, estimate=estimate, interval_s=args.interval, max_iter=args.max_iter,
                           prefit=not args.no_prefit)
    preflight_runs(cyl, runs, estimate)  # before any progress line: a refusal is the only line on stderr
    prog = progress_printer(args.quiet)
    if prog:
        prog(f"identifying {', '.join(estimate)} from {len(runs)} run(s), {sum(r.n for r in runs)} samples, "
             f"{drive} drive")
    result = identify(cyl, runs, opts, effects=effects, progress=prog)
    unknown = result.not_determined
    if args.json:
        write_json_atomic(args.json, clean_json(result.document(config=cyl.source, inputs=args.runs)))
        if prog:
            prog(f"wrote {args.json}")
    if args.write_config:
        write_cylinder_file(args.write_config, result.cylinder, note=f"identified from {', '.join(args.runs)}")
        if prog:
            prog(f"wrote {args.write_config} (the comments of {cyl.source} kept)")
    if args.report:
        from ..identify.report import write_fit_report

        why = {n: ("a standard deviation as large as the value; record moves that excite it (both directions, several "
                   "speeds and pressure differences) or leave it out of --estimate") for n in unknown}
        write_fit_report(result, runs, args.report, inputs=args.runs, not_determined=why)
        if prog:
            prog(f"wrote {args.report}")
    print(format_table(result))
    # a misfit says so first: its standard deviations do not tell what the run determines
    if unknown and result.explains_run:
        names = ", ".join(p.name for p in map(Path, args.runs))
        worst = result.params[unknown[0]]
        raise UsageError(f"{names}: {'this run' if len(args.runs) == 1 else 'these runs'} cannot determine "
                         f"{', '.join(unknown)}: {unknown[0]} = {worst.value:.4g} +- {worst.std:.2g} {worst.unit}, a "
                         "standard deviation as large as the value; record moves that excite it (both directions, "
                         "several speeds and pressure differences) or leave it out of --estimate.")
    status = result.solver["status"]
    if status != "converged":
        eprint(f"combined-reality identify: the solver stopped without converging ({status}); "
               "the estimates above are the last iterate.")
    if not result.explains_run:
        eprint(f"combined-reality identify: the model does not explain the run (residual "
               f"{result.solver['residual_sigma']:.3g} x the sensor noise), so the values above describe a misfit; "
               "if the cylinder file's valve, dead volumes, mass or sensor offsets are guesses, run "
               "`combined-reality calibrate`; if an effect the model lacks is at work, run `combined-reality diagnose`.")
    return 0 if status == "converged" and result.explains_run else 1
