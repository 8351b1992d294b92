"""`combined-reality diagnose`: why the simulation still differs from the rig."""
from __future__ import annotations

import math
import os

from .. import options
from .common import (UsageError, add_max_rows, check_paths, eprint, preflight_runs,
                     progress_printer, rerun_mode, typed)


def add_parser(sub) -> None:
    dg = sub.add_parser("diagnose",
                        help="explain the sim-to-real gap: where, which unmodelled effect, how far it shrinks",
                        description="Identify the nominal model on TRAIN and score it on VALID, a run no fit sees; "
                                    "then add every effect of the vocabulary in turn, re-identify it on TRAIN and "
                                    "score it on VALID. Prints the verdict (the effect that best explains the gap, "
                                    "or none), the ranking with each candidate's shrink of the validation error, "
                                    "and where the gap lies (operating regimes, subsystems).")
    dg.add_argument("train", nargs="+", metavar="TRAIN.csv",
                    help="run CSV the models are identified on; with --calibrate several (a calibration run and an "
                         "ordinary one) are calibrated together")
    dg.add_argument("--validate", required=True, help="run CSV the models are scored on (never fitted)")
    dg.add_argument("--config", help="cylinder TOML (default: the one TRAIN's header names, else the built-in "
                                     "cylinder A)")
    dg.add_argument("--json", help="write the diagnosis (docs/formats.md)")
    dg.add_argument("--report", metavar="REPORT.html", type=typed(options.report_file),
                    help="write a self-contained HTML report with plots")
    dg.add_argument("--rerun", nargs="+", default=["off"], metavar="MODE",
                    help="show the diagnosis in Rerun: spawn | connect ADDR | save FILE.rrd | off (default)")
    dg.add_argument("--candidates", help="comma-separated effects to try (default: the whole vocabulary)")
    dg.add_argument("--horizon", type=typed(options.positive_seconds, "--horizon"), default=1.0,
                    help="validation simulation horizon, s (default 1)")
    dg.add_argument("--workers", type=typed(options.whole_number, "--workers", lo=1, hi=1024),
                    default=os.cpu_count() or 1, help="parallel processes for the candidates (default: the number "
                                                      "of CPUs)")
    dg.add_argument("--calibrate", action="store_true",
                    help="calibrate the cylinder file's valve characteristic, dead volumes, mass and sensor offsets on "
                         "TRAIN with every candidate effect and compare the calibrated models on VALID: mis-set "
                         "quantities are reported as such, not taken for an effect, and an effect is not bent into "
                         "them")
    add_max_rows(dg)
    dg.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    dg.set_defaults(func=run)


def run(args) -> int:
    from sim.effects import EFFECTS

    from ..diagnose import DiagnoseOptions, diagnose
    from ..files import check_train_and_valid, clean_json, cylinder_for_runs, read_run, write_json_atomic

    if len(args.train) > 1 and not args.calibrate:
        raise UsageError("several TRAIN runs are calibrated together with --calibrate; without it, give one.")
    names = options.parameter_names(args.candidates, "--candidates") if args.candidates is not None else tuple(EFFECTS)
    unknown = [n for n in names if n not in EFFECTS]
    if unknown:
        raise UsageError(f"--candidates: unknown effect {', '.join(unknown)} (known: {', '.join(EFFECTS)}).")
    mode, target = rerun_mode(args.rerun)
    check_paths({"--json": args.json, "--report": args.report, "--rerun save": target if mode == "save" else None},
                inputs=[args.config, *args.train, args.validate])
    train, valid = [read_run(p, args.max_rows) for p in args.train], read_run(args.validate, args.max_rows)
    cyl, which = cylinder_for_runs(args.config, [*train, valid])
    warnings = [w for run, name in zip(train, args.train)
                if (w := check_train_and_valid(cyl, run, valid, name, args.validate))]
    opts = DiagnoseOptions(candidates=names, horizon_s=args.horizon, workers=max(1, args.workers),
                           calibrate=args.calibrate)
    preflight_runs(cyl, [*train, valid])  # last: its notes follow no refusal
    if which and not args.quiet:
        eprint(which)
    for warning in warnings:
        eprint(f"combined-reality diagnose: warning: {warning}")
    diagnosis = diagnose(cyl, train, valid, opts, progress=progress_printer(args.quiet))
    result = diagnosis.to_json()
    print(format_summary(result, args.horizon))
    if args.json:
        write_json_atomic(args.json, clean_json(result))
        if not args.quiet:
            eprint(f"wrote {args.json}")
    if args.report:
        from ..diagnose.report import write_report

        write_report(diagnosis, args.report)
        if not args.quiet:
            eprint(f"wrote {args.report}")
    if mode != "off":
        from ..diagnose.rerun import log_diagnosis
        from ..report.rerun import close_recording, fallback_path, open_recording

        # without a display, next to the report (or the validation run)
        rec = open_recording(mode, target, fallback=fallback_path(args.report or args.validate), say=eprint)
        log_diagnosis(diagnosis, rec)
        if not close_recording(rec):  # the .rrd (or the viewer) holds everything before the process ends
            eprint("the Rerun viewer did not take the diagnosis (it went away)")
    return 0


def format_summary(result: dict, horizon_s: float) -> str:
    """The console view of a diagnosis (its JSON form): baseline, verdict, ranking, where."""
    base = result["baseline"]
    cal = result.get("calibration") or {}
    by = f" with {cal['model']}" if cal.get("model", "none") != "none" else ""
    lines = [f"validation position RMSE of the nominal model{' (calibrated on TRAIN)' if cal else ''}: "
             f"{base['rmse_x_validation'] * 1e6:.1f} um "
             f"(segments of {horizon_s:g} s, all outputs {base['normalized_rms']:.2f} x the sensor noise)",
             *(f"mis-set in the cylinder file (calibrated on TRAIN{by}): {m['quantity']} {m['file']:.4g} -> "
               f"{m['calibrated']:.4g} {m['unit']}" + (f" ({m['change']:+.1%})" if math.isfinite(m['change']) else "")
               for m in cal.get("mis_set", [])),
             *(f"these runs cannot separate {c['effect']}.{c['parameter']} from {c['quantity']} "
               f"(correlation {c['r']:+.3f})" for c in cal.get("confounded", [])),
             *(f"{e['effect']} may be imitated by {e['from']}: what separates them best, {e['needs']}: "
               f"{e['found']}" for e in cal.get("not_separated", [])),
             *([f"calibration: {cal['misfit']}"] if cal.get("misfit") else []),
             f"verdict: {result['verdict']}" + (f" ({result['verdict_note']})" if result.get("verdict_note") else ""),
             *([f"caveat: {result['verdict_caveat']}"] if result.get("verdict_caveat") else []),
             *([f"prediction: {(result.get('prediction') or {})['caveat']}"]
               if (result.get("prediction") or {}).get("caveat") else []),
             f"{'effect':20s} {'shrink':>8s} {'all out':>8s} {'z':>6s} {'rmse_x [um]':>12s}  parameters"]
    for c in result["ranking"]:
        if not math.isfinite(c["shrink"]):  # not validated: say why instead of nan%
            lines.append(f"{c['effect']:20s} not scored: {c.get('error') or c['status']}")
            continue
        pars = ", ".join(f"{k}={v:.4g}±{c['std'][k]:.2g}" for k, v in c["params"].items())
        mark = "*" if c["significant"] else " "
        lines.append(f"{c['effect']:20s} {c['shrink']:8.1%} {c['shrink_all']:8.1%} {c['z']:6.1f}{mark}"
                     f"{c['rmse_x_validation'] * 1e6:12.1f}  {pars or c.get('error', '')}")
    if result["pair"] is not None:
        c = result["pair"]
        if math.isfinite(c["shrink"]):
            lines.append(f"best pair {c['effect']}: shrink {c['shrink']:.1%}"
                         + ("" if c["significant"] else " (no significant gain over the best single effect)"))
        else:
            lines.append(f"best pair {c['effect']}: not scored: {c.get('error') or c['status']}")
    lines.append("where the gap lies (share of the squared error / share of the samples):")
    for r in result["regions"][:5]:
        lines.append(f"  {r['where']:34s} {r['share_of_error']:6.1%} / {r['fraction_of_samples']:6.1%}")
    for r in result["subsystems"]:
        lines.append(f"  {r['subsystem']:62s} {r['share_of_error']:6.1%} of the excess error")
    return "\n".join(lines)
