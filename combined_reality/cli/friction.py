"""`combined-reality friction-map`: the static friction map of recorded runs or points tables;
`combined-reality friction-compare`: the friction models identified dynamically and ranked.

    combined-reality friction-map INPUT [INPUT ...] [--model NAME ...] [--config CYL.toml]
        --json OUT.json [--plot OUT.png] [-q]
    combined-reality friction-compare --config CYL.toml TRAIN.csv --validate VALID.csv
        [--model NAME ...] [--load N] [--horizon S] [--workers N] [--json OUT.json] [-q]

INPUT is a recorded run (t,u,x,p1,p2; the cylinder file gives areas and mass) or a points
table (header with v,F). The map and its JSON: combined_reality.friction_map, docs/friction.md.
The comparison: combined_reality.friction_identify, docs/friction.md.
"""
from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

from .friction_map import FIT_SPECS, FrictionMap, FrictionMapError, SegmentOptions


def _unit(family: str, base: str) -> str:
    """The unit of a parameter, from the model's own PARAMS ('' for dimensionless)."""
    from sim.friction_models import FRICTION_MODELS

    params = FRICTION_MODELS[family].PARAMS
    info = params.get(f"{base}_pos") or params.get(base)
    return "" if info is None or info.unit == "1" else info.unit


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
    p.add_argument("--config", help="cylinder TOML for recorded runs (default: the built-in cylinder A)")
    p.add_argument("--json", required=True, metavar="OUT.json", help="write the map and the fits")
    p.add_argument("--plot", metavar="OUT.png", help="plot the map with the fitted curves (needs matplotlib)")
    p.add_argument("--min-duration", type=float, default=SegmentOptions.min_duration,
                   help=f"shortest constant-velocity stretch of a run, s (default {SegmentOptions.min_duration:g})")
    p.add_argument("--min-speed", type=float, default=SegmentOptions.min_speed,
                   help=f"slowest sustained motion that makes a point, m/s (default {SegmentOptions.min_speed:g})")
    p.add_argument("--spread", type=float, default=SegmentOptions.spread,
                   help=f"largest relative change and spread of the velocity trend within a stretch "
                        f"(default {SegmentOptions.spread:g})")
    p.add_argument("--load", type=float, metavar="N",
                   help="constant normal load of the runs, N (for the load models cv_load, cvs_load)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=run)
    return p


def _model_names(args) -> tuple[list[str] | None, bool]:
    from .cli import UsageError

    if not args.model:
        return None, False
    names = [n.strip() for item in args.model for n in item.split(",") if n.strip()]
    unknown = [n for n in names if n not in FIT_SPECS]
    if unknown or not names:
        raise UsageError(f"--model: unknown model {', '.join(unknown) or '(none given)'} "
                         f"(known: {', '.join(FIT_SPECS)}).")
    return list(dict.fromkeys(names)), True


def run(args) -> int:
    from sim.cylinder import load_cylinder

    from .cli import UsageError, _check_run_against_cylinder, _clean_json, _eprint, _write_json_atomic, \
        default_config_path
    from .friction_map import build_map, is_points_table, plot_map, points_from_run, read_points
    from .runs import read_run

    models, explicit = _model_names(args)
    try:
        options = SegmentOptions(min_duration=args.min_duration, min_speed=args.min_speed, spread=args.spread)
    except FrictionMapError as e:
        raise UsageError(f"{str(e).rstrip('.').replace('min_', '--min-').replace('spread', '--spread')}.") from None
    if args.load is not None and not (math.isfinite(args.load) and args.load >= 0):
        raise UsageError(f"--load must be a non-negative force in N, not {args.load}.")
    say = (lambda msg: None) if args.quiet else _eprint

    cyl = None
    points, breakaways, runs_json = [], [], []
    stuck_time = None
    stuck_speeds = []
    for path in args.inputs:
        try:
            table = is_points_table(path)
            if table:
                pts = read_points(path)
                points.extend(pts)
                nb = sum(p.breakaway for p in pts)
                say(f"{path}: points table, {len(pts) - nb} sliding points" + (f", {nb} breakaway rows" if nb else ""))
                continue
        except FrictionMapError as e:
            raise UsageError(str(e)) from None
        if not Path(path).is_file():
            raise UsageError(f"{path}: file not found.")
        if cyl is None:
            cyl = load_cylinder(args.config if args.config else default_config_path())
        run_ = read_run(path)
        _check_run_against_cylinder(run_, cyl)
        rp = points_from_run(cyl, run_, options, load=args.load)
        points.extend(rp.points)
        breakaways.extend(rp.breakaways)
        stuck_time = (stuck_time or 0.0) + rp.stuck_time
        stuck_speeds.append(rp.stuck_speed)
        runs_json.append({"source": str(path), "duration_s": rp.duration, "points": len(rp.points),
                          "breakaways": len(rp.breakaways), "stuck_time_s": rp.stuck_time,
                          "moving_time_s": rp.moving_time})
        say(f"{path}: run of {rp.duration:.1f} s, {len(rp.points)} constant-velocity points "
            f"({sum(p.v > 0 for p in rp.points)} extending, {sum(p.v < 0 for p in rp.points)} retracting), "
            f"{len(rp.breakaways)} breakaways")
    inputs = ", ".join(str(p) for p in args.inputs)
    if points and all(p.breakaway for p in points):
        raise UsageError(f"{inputs}: only breakaway rows, no sliding points; give the map a sweep's points table "
                         f"or a recorded run beside the breakaway table.")
    if not points:
        raise UsageError(f"{inputs}: no constant-velocity stretch found (at least {options.min_duration:g} s above "
                         f"{options.min_speed:g} m/s within {options.spread:.0%} velocity spread); record moves at "
                         f"constant speed or relax --min-duration / --spread.")
    try:
        fmap = build_map(points, models, breakaways, stuck_speed=max(stuck_speeds) if stuck_speeds else None,
                         stuck_time=stuck_time, min_speed=options.min_speed if runs_json else None, strict=explicit)
    except FrictionMapError as e:
        raise UsageError(f"{inputs}: {e}") from None
    if not any(d.fits for d in fmap.directions.values()):
        # one reason per direction (they differ only in the model's name)
        reasons = "; ".join(next(iter(d.skipped.values())).rstrip(".") for d in fmap.directions.values() if d.skipped)
        raise UsageError(f"{inputs}: no model could be fitted ({reasons}).")

    print(format_table(fmap))
    out = fmap.to_json()
    out["inputs"] = [str(p) for p in args.inputs]
    if cyl is not None:
        out["config"] = str(cyl.source) if cyl.source else None
        out["runs"] = runs_json
        out["segment_options"] = {"min_duration": options.min_duration, "min_speed": options.min_speed,
                                  "spread": options.spread, "stuck_speed": max(stuck_speeds),
                                  "stuck_duration": options.stuck_duration}
    _write_json_atomic(args.json, _clean_json(out))
    say(f"wrote {args.json}")
    if args.plot:
        try:
            Path(args.plot).parent.mkdir(parents=True, exist_ok=True)  # as the JSON writer does
            plot_map(fmap, args.plot, title=f"friction map: {inputs}")
        except FrictionMapError as e:
            _eprint(f"combined-reality friction-map: {e}")
            return 1
        except OSError as e:
            _eprint(f"combined-reality friction-map: --plot {args.plot}: cannot be written ({e.strerror or e}); "
                    f"the JSON is written.")
            return 1
        say(f"wrote {args.plot}")
    return 0


def _value(x: float | None, s: float | None) -> str:
    if x is None:
        return "-"
    if s is None:
        return f"{x:.4g}"
    return f"{x:.4g}±{s:.2g}" if math.isfinite(s) else f"{x:.4g}±inf"


def format_table(fmap: FrictionMap) -> str:
    """Per direction: the points, the stick band, and every fit (metrics, parameters, flags)."""
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
        lines.append(head)
        rows = [("model", "RMSE [N]", "R2", "MAE [N]", "AICc", "parameters (value±std)", "flags")]
        scores = {n: f.aicc for n, f in d.fits.items() if f.aicc is not None}
        best = min(scores, key=scores.get) if scores else None
        lin = d.linear
        if lin is not None:
            pars = f"Fc={_value(lin.Fc, lin.std['Fc'])} N, B={_value(lin.B, lin.std['B'])} N s/m"
            rows.append(("linear", f"{lin.rmse:.3g}", f"{lin.r2:.5f}", f"{lin.mae:.3g}", "", pars, ""))
        for name, f in d.fits.items():
            pars = ", ".join(f"{k}={_value(v, f.std.get(k))}" + (f" {_unit(f.family, k)}" if _unit(f.family, k) else "")
                             for k, v in f.params.items() if v is not None)
            flagged = ", ".join(dict.fromkeys(fl["param"] for fl in f.flags))
            aicc = "" if f.aicc is None else f"{f.aicc:.1f}" + (" *" if name == best else "")
            rows.append((name, f"{f.rmse:.3g}", f"{f.r2:.5f}", f"{f.mae:.3g}", aicc, pars, flagged))
        if len(rows) > 1:
            widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
            lines.extend("  " + "  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows)
        for name, why in d.skipped.items():
            lines.append(f"  skipped {name}: {why}")
    lines.append("Per direction: RMSE, R2 (seed 000 Eq. 10), MAE (mean |F - F_model|, seed 003's mean error), AICc "
                 "(* lowest: the best fit for its number of parameters); flags name the parameters the points do not "
                 "determine (reasons in the JSON).")
    return "\n".join(lines)


# ================================================================ friction-compare

_LOAD_MODELS = ("cv_load", "cvs_load")
_PENALTY_PER_PARAM = 0.01


def _known_compare_models() -> list[str]:
    from .friction_identify import DYNAMIC_SPECS

    return ["nominal", *DYNAMIC_SPECS]


def add_compare_parser(sub) -> argparse.ArgumentParser:
    """Register `friction-compare` on the argparse subparsers `sub`."""
    known = _known_compare_models()
    p = sub.add_parser(
        "friction-compare", help="identify every friction model on TRAIN by multiple shooting, rank them on VALID",
        description="Identify each friction model of the family (docs/friction.md) on the TRAIN run by "
                    "multiple-shooting least squares (all its parameters, per direction, from a start read off "
                    "the run's own equation-error map), simulate it on the VALID run, which no fit sees, in "
                    "segments of --horizon seconds from initial states fitted to each segment, and rank the "
                    "models by the VALID error of all outputs (x, p1, p2) in units of the sensor noise, times "
                    f"(1 + {_PENALTY_PER_PARAM:g} x the number of estimated parameters). 'nominal' is the "
                    "cylinder file's own friction (Fc + Fv v + kp |p1 - p2|). Prints the ranking and the best "
                    "model's parameters per direction.")
    p.add_argument("train", metavar="TRAIN.csv", help="recorded run the models are identified on")
    p.add_argument("--validate", required=True, metavar="VALID.csv",
                   help="recorded run of the same cylinder and sample rate the models are scored on (never fitted)")
    p.add_argument("--config", required=True, metavar="CYL.toml", help="cylinder TOML the runs were recorded on")
    p.add_argument("--model", action="append", metavar="NAME",
                   help=f"model to compare, repeatable or comma-separated (known: {', '.join(known)}; default: "
                        f"all of them except the load models {' and '.join(_LOAD_MODELS)}, which are included "
                        f"only with --load)")
    p.add_argument("--load", type=float, metavar="N",
                   help="constant normal load on the seals and guides, N: the load models (cv_load, cvs_load) need "
                        "it, since runs do not record a load and at their default Fn = 0 the load terms do nothing; "
                        "at one constant load those terms are not separable from Fc, Fs, B (see their std)")
    p.add_argument("--horizon", type=float, default=1.0, metavar="S",
                   help="validation simulation horizon, s (default 1)")
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1, metavar="N",
                   help="parallel processes, one model each (default: the number of CPUs)")
    p.add_argument("--json", metavar="OUT.json", help="write the ranking (ModelComparison rows), the best model "
                                                      "and the options")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=run_compare)
    return p


def _compare_models(args) -> list[str]:
    from .cli import UsageError

    known = _known_compare_models()
    if not args.model:
        return [m for m in known if m not in _LOAD_MODELS or args.load is not None]
    names = list(dict.fromkeys(n.strip() for item in args.model for n in item.split(",") if n.strip()))
    unknown = [n for n in names if n not in known]
    if unknown or not names:
        raise UsageError(f"--model: unknown model {', '.join(unknown) or '(none given)'} (known: {', '.join(known)}).")
    need = [n for n in names if n in _LOAD_MODELS]
    if need and args.load is None:
        raise UsageError(f"--model {', '.join(need)}: a load model needs the normal load, which runs do not record; "
                         f"give it with --load N.")
    return names


def run_compare(args) -> int:
    import time

    from .cli import UsageError, _clean_json, _eprint, _load_config, _write_json_atomic, check_train_and_valid
    from .friction_identify import compare_friction_models
    from .identify import IdentifyOptions
    from .runs import read_run

    models = _compare_models(args)
    if args.load is not None and not (math.isfinite(args.load) and args.load >= 0):
        raise UsageError(f"--load must be a non-negative force in N, not {args.load}.")
    if not (args.horizon > 0 and math.isfinite(args.horizon)):
        raise UsageError(f"--horizon must be a positive number of seconds, not {args.horizon}.")
    if args.workers < 1:
        raise UsageError(f"--workers must be at least 1, not {args.workers}.")
    cyl = _load_config(args.config)
    train, valid = read_run(args.train), read_run(args.validate)
    check_train_and_valid(cyl, train, valid, args.train, args.validate, "compare models on")

    say = (lambda msg: None) if args.quiet else _eprint
    options = IdentifyOptions(max_iter=40, time_limit_s=60.0)
    workers = min(args.workers, len(models))
    say(f"friction-compare: {len(models)} model(s) identified on {args.train} ({train.duration:.1f} s) and scored on "
        f"{args.validate} ({valid.duration:.1f} s, segments of {args.horizon:g} s), {workers} worker(s)")
    t0 = time.perf_counter()
    ranking = compare_friction_models(cyl, train, valid, models, horizon_s=args.horizon, workers=workers,
                                      penalty_per_param=_PENALTY_PER_PARAM, options=options,
                                      progress=None if args.quiet else say, load=args.load)
    best = next((r for r in ranking if r.status != "failed"), None)
    say(f"done in {time.perf_counter() - t0:.1f} s")
    print(format_comparison(ranking, args.horizon))
    if args.json:
        out = {"ranking": [r.to_json() for r in ranking], "best": best.model if best else None,
               "options": {"models": models, "horizon_s": args.horizon, "workers": workers, "load_N": args.load,
                           "penalty_per_param": _PENALTY_PER_PARAM, "max_iter": options.max_iter,
                           "time_limit_s": options.time_limit_s, "interval_s": options.interval_s},
               "config": str(cyl.source) if cyl.source else None, "train": str(args.train),
               "validate": str(args.validate)}
        _write_json_atomic(args.json, _clean_json(out))
        say(f"wrote {args.json}")
    if best is None:
        _eprint("combined-reality friction-compare: every model failed (the reasons are listed above).")
        return 1
    return 0


def _pm(x: float, s: float) -> str:
    if not math.isfinite(x):
        return "-"
    return f"{x:.4g} ± {s:.2g}" if math.isfinite(s) else f"{x:.4g}"


def format_comparison(ranking, horizon_s: float) -> str:
    """The ranking table, the failures' reasons, and the best model's parameters per direction."""
    from sim.friction_models import DIRECTIONS, FRICTION_MODELS

    from .friction_identify import fit_spec
    from .identify import UNITS

    def um(x: float) -> str:
        return f"{x * 1e6:.2f}" if math.isfinite(x) else "-"

    def num(x: float, fmt: str) -> str:
        return format(x, fmt) if math.isfinite(x) else "-"

    rows = [("rank", "model", "params", "TRAIN x [µm]", "VALID x [µm]", "VALID [noise]", "score", "status")]
    for i, r in enumerate(ranking, 1):
        failed = r.status == "failed"
        rows.append((str(i), r.model, "-" if failed else str(r.n_params), um(r.rmse_x_train), um(r.rmse_x_validation),
                     num(r.normalized_rms, ".3f"), num(r.score, ".3f"), r.status))
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    right = {0, 2, 3, 4, 5, 6}
    lines = ["  ".join((c.rjust(w) if i in right else c.ljust(w)) for i, (c, w) in enumerate(zip(row, widths))).rstrip()
             for row in rows]
    lines += [f"  {r.model}: {r.error}" for r in ranking if r.status == "failed"]
    lines.append(f"VALID simulated in segments of {horizon_s:g} s from initial states fitted per segment (parameters "
                 f"from TRAIN only); [noise]: RMS of all outputs' errors in sensor-noise units (1 = the noise); "
                 f"score = [noise] x (1 + {_PENALTY_PER_PARAM:g} x params), lower is better.")
    best = next((r for r in ranking if r.status != "failed"), None)
    if best is None:
        return "\n".join(lines)
    lines.append("")
    lines.append(f"best: {best.model} (identified on TRAIN, value ± std)")
    if best.model == "nominal":
        lines.extend(f"  {n} = {_pm(v, best.std.get(n, math.nan))} {UNITS.get(n, '')}".rstrip()
                     for n, v in best.params.items())
        return "\n".join(lines)
    spec = fit_spec(best.model)
    cls = FRICTION_MODELS[spec.family]
    suffixes = [s for s, _ in DIRECTIONS.values()]
    table = [("parameter", *DIRECTIONS)]
    for base in cls.BASE:
        unit = _unit(spec.family, base)
        cells = []
        for suffix in suffixes:
            name = f"{base}_{suffix}"
            v = best.params.get(name, math.nan)
            cells.append(f"{v:.4g} (fixed)" if base in spec.fixed else _pm(v, best.std.get(name, math.nan)))
        table.append((f"{base} [{unit}]" if unit else base, *cells))
    widths = [max(len(row[i]) for row in table) for i in range(len(table[0]))]
    lines.extend("  " + "  ".join(c.ljust(w) for c, w in zip(row, widths)).rstrip() for row in table)
    for name in cls.SHARED:
        unit = cls.PARAMS[name].unit
        v, sd = best.params.get(name, math.nan), best.std.get(name, math.nan)
        kind = "input, not estimated" if name == "Fn" else "both directions"
        lines.append(f"  {name} = {_pm(v, sd)} {'' if unit == '1' else unit} ({kind})".replace("  (", " ("))
    return "\n".join(lines)
