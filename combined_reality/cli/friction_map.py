"""`combined-reality friction-map`: the static friction map of recorded runs or points tables.

    combined-reality friction-map INPUT [INPUT ...] [--model NAME ...] [--config CYL.toml]
        --json OUT.json [--plot OUT.png] [-q]

INPUT is a recorded run (t,u,x,p1,p2; the cylinder file gives areas and mass) or a points
table (header with v,F). The map and its JSON: combined_reality.friction.map, docs/friction.md.
"""
from __future__ import annotations

import argparse
import math
import os

from .. import options
from ..friction.specs import FIT_SPECS, PARSIMONY, PLOT_FORMATS, FrictionMapError, SegmentOptions
from .common import UsageError, add_max_rows, check_paths, eprint, progress_printer, typed


def add_parser(sub) -> argparse.ArgumentParser:
    """Register `friction-map` on the argparse subparsers `sub`."""
    p = sub.add_parser(
        "friction-map", help="static friction-velocity map of runs or points tables, fitted by the friction models",
        description="Build the static friction map (seeds 000, 004): one point per constant-velocity stretch of "
                    "each recorded run (friction from Newton's law with the measured pressures) or the rows of "
                    "points tables (CSV with columns v,F in m/s and N, the sign of v giving the direction), "
                    "and fit the friction models per direction with uncertainties and identifiability flags.")
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="recorded run CSV (t,u,x,p1,p2) or points table CSV (v,F[,F_std,count,dp,pc,load,breakaway]); "
                        "rows with breakaway = 1 (procedure breakaway) are breakaway forces, not sliding points")
    p.add_argument("--model", action="append", metavar="NAME",
                   help=f"model to fit, repeatable or comma-separated (default: every model that the points "
                        f"allow; known: {', '.join(FIT_SPECS)})")
    p.add_argument("--config", help="cylinder TOML for recorded runs (default: the one the first run's header names, "
                                    "else the built-in cylinder A)")
    p.add_argument("--json", required=True, metavar="OUT.json", help="write the map and the fits")
    p.add_argument("--plot", metavar="OUT.png", help="plot the map with the fitted curves (needs matplotlib)")
    p.add_argument("--min-duration", type=typed(options.positive_seconds, "--min-duration"),
                   default=SegmentOptions.min_duration,
                   help=f"shortest constant-velocity stretch of a run, s (default {SegmentOptions.min_duration:g})")
    p.add_argument("--min-speed", type=typed(options.positive_number, "--min-speed"), default=SegmentOptions.min_speed,
                   help=f"slowest sustained motion that makes a point, m/s (default {SegmentOptions.min_speed:g})")
    p.add_argument("--spread", type=typed(options.positive_number, "--spread"), default=SegmentOptions.spread,
                   help=f"largest relative change and spread of the velocity trend within a stretch "
                        f"(default {SegmentOptions.spread:g})")
    p.add_argument("--load", type=typed(options.load), metavar="N",
                   help="constant normal load of the runs, N (for the load models cv_load, cvs_load)")
    add_max_rows(p)
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=run)
    return p


def _model_names(args) -> tuple[list[str] | None, bool]:
    if not args.model:
        return None, False
    names = [n.strip() for item in args.model for n in item.split(",") if n.strip()]
    unknown = [n for n in names if n not in FIT_SPECS]
    if unknown or not names:
        raise UsageError(f"--model: unknown model {', '.join(unknown) or '(none given)'} "
                         f"(known: {', '.join(FIT_SPECS)}).")
    return list(dict.fromkeys(names)), True


def run(args) -> int:
    from ..files import OutputError, WriteError, clean_json, write_json_atomic
    from ..friction import gather_map_inputs, map_of_inputs, plot_map

    models, explicit = _model_names(args)
    if args.plot and os.path.splitext(args.plot)[1].lstrip(".").lower() not in PLOT_FORMATS:
        raise UsageError(f"--plot {args.plot}: name the plot with one of the suffixes "
                         f"{', '.join('.' + f for f in PLOT_FORMATS)} (it says the image format).")
    check_paths({"--json": args.json, "--plot": args.plot}, inputs=[args.config, *args.inputs])
    segments = SegmentOptions(min_duration=args.min_duration, min_speed=args.min_speed, spread=args.spread)
    say = (lambda msg: None) if args.quiet else eprint
    got = gather_map_inputs(args.inputs, args.config, segments, load=args.load, max_rows=args.max_rows, say=say,
                            note=eprint)
    fmap = map_of_inputs(got, models, strict=explicit, progress=progress_printer(args.quiet))
    print(format_table(fmap))
    write_json_atomic(args.json, clean_json(got.document(fmap)))
    say(f"wrote {args.json}")
    if args.plot:
        try:
            plot_map(fmap, args.plot, title=f"friction map: {got.names}")
        except FrictionMapError as e:
            eprint(f"combined-reality friction-map: {e}")
            return 1
        except (OutputError, WriteError) as e:  # atomic_write's sentence, with what is there
            eprint(f"combined-reality friction-map: --plot {str(e).rstrip('.')}; the JSON {args.json} is written.")
            return e.exit_status
        say(f"wrote {args.plot}")
    return 0


def _value(x: float | None, s: float | None) -> str:
    if x is None:
        return "-"
    if s is None:
        return f"{x:.4g}"
    return f"{x:.4g}±{s:.2g}" if math.isfinite(s) else f"{x:.4g}±inf"


def _parameters(f) -> str:
    """value±std per parameter; 'not determined' instead of a number the points do not pin down."""
    from sim.friction_models import parameter_unit

    out = []
    for k, v in f.params.items():
        if v is None and k not in f.not_determined:
            continue
        unit = parameter_unit(f.family, k)
        text = "not determined" if k in f.not_determined else _value(v, f.std.get(k)) + (f" {unit}" if unit else "")
        out.append(f"{k}={text}")
    return ", ".join(out)


def _verdict(name: str, f, best: str | None) -> str:
    if name == best:
        return "best"
    if f.status != "converged":
        return f.status
    if f.not_determined:
        return "not determined: " + ", ".join(f.not_determined)
    if f.problems:  # in short; the sentences are in the JSON
        return "; ".join("curve leaves the data's range" if "leaves" in p else "Fs below Fc" if "static level" in p
                         else p for p in f.problems)
    return ""


def format_table(fmap, width: int = 100) -> str:
    """Per direction: the points, the stick band, what changed together, and every fit (number
    of parameters, metrics, verdict and flags on one line, its parameters wrapped below), all
    within `width` columns; the best fit is starred (FrictionMap's parsimony rule)."""
    import textwrap

    def wrap(text: str, indent: str, first: str | None = None) -> list[str]:
        return textwrap.wrap(text, width, initial_indent=indent if first is None else first,
                             subsequent_indent=indent, break_on_hyphens=False)

    lines = []
    for direction, d in fmap.directions.items():
        band = d.stick_band
        speeds = sorted(abs(p.v) for p in d.points if not p.breakaway)
        if speeds:
            head = (f"{direction}: {len(speeds)} sliding points, {speeds[0] * 1e3:.3g} .. {speeds[-1] * 1e3:.3g} mm/s; "
                    f"stick band: no steady sliding below {band.dv * 1e3:.3g} mm/s"
                    + (" (the detector's min speed)" if band.at_detector_limit else ""))
        else:
            head = f"{direction}: no sliding points"
        if band.breakaway_count:
            std = f" ± {band.breakaway_std:.2g}" if band.breakaway_std is not None else ""
            head += f"; {band.breakaway_count} breakaways, mean {band.breakaway_mean:.4g}{std} N"
        lines += wrap(head, "    ", "")
        for c in d.confounded:
            lines += wrap(f"note: {c.sentence(direction)}.", "    ", "  ")
        rows = []  # (model, k, RMSE, R2, MAE, AICc, verdict, parameters)
        best = d.best
        lin = d.linear
        if lin is not None:
            pars = f"Fc={_value(lin.Fc, lin.std['Fc'])} N, B={_value(lin.B, lin.std['B'])} N s/m"
            verdict = "B < 0: not physical" + (" (speed stands in for another quantity)" if d.confounded else "") \
                if lin.B < 0 else ""
            rows.append(("linear", "2", f"{lin.rmse:.3g}", f"{lin.r2:.5f}", f"{lin.mae:.3g}", "", verdict, pars))
        for name, f in d.fits.items():
            flagged = [p for p in dict.fromkeys(fl["param"] for fl in f.flags) if p not in f.not_determined]
            verdict = _verdict(name, f, best) + (f"; flags: {', '.join(flagged)}" if flagged else "")
            aicc = "" if f.aicc is None else f"{f.aicc:.1f}" + (" *" if name == best else "")
            rows.append((name, str(len(f.free)), f"{f.rmse:.3g}", f"{f.r2:.5f}", f"{f.mae:.3g}", aicc,
                         verdict.lstrip("; "), _parameters(f)))
        if rows:
            head_row = ("model", "k", "RMSE [N]", "R2", "MAE [N]", "AICc", "verdict")
            widths = [max(len(r[i]) for r in [head_row, *rows]) for i in range(6)]
            fmt = lambda r: "  " + "  ".join(c.ljust(w) for c, w in zip(r[:6], widths))  # noqa: E731
            lines.append((fmt(head_row) + "  verdict").rstrip())
            for r in rows:
                lead = fmt(r) + "  "
                lines += wrap(r[6], " " * len(lead), lead) if r[6] else [lead.rstrip()]
                if r[7]:
                    lines += wrap(r[7], "      ")
        lacking = {}
        for name, why in d.skipped.items():
            if why.startswith(f"model {name} needs "):
                lacking.setdefault(why.split(" needs ")[1].split(" for every point")[0], []).append(name)
            else:
                lines += wrap(f"skipped {name}: {why}", "    ", "  ")
        for what, names in lacking.items():
            lines += wrap(f"not fitted, the points carry no {what}: {', '.join(names)}", "    ", "  ")
    lines += wrap("Per direction: k the parameters fitted, RMSE, R2 (seed 000 Eq. 10), MAE (mean |F - F_model|, "
                  "seed 003's mean error), AICc; * the best: among the fits whose parameters the points determine "
                  "and whose curve is sound, the fewest parameters (then the product's own law cv_dp) within "
                  f"{PARSIMONY:g} AICc of the lowest; flags name parameters the points determine poorly (reasons "
                  "in the JSON).", "", "")
    return "\n".join(lines)
