"""`combined-reality friction-compare`: the friction models identified dynamically on TRAIN by
multiple shooting and ranked on VALID.

    combined-reality friction-compare --config CYL.toml TRAIN.csv --validate VALID.csv
        [--model NAME ...] [--load N] [--horizon S] [--workers N] [--json OUT.json] [-q]

The comparison: combined_reality.friction.dynamic, docs/friction.md.
"""
from __future__ import annotations

import argparse
import math
import os
import time

from .. import options
from .common import UsageError, add_max_rows, check_paths, eprint, load_config, preflight_runs, typed

_LOAD_MODELS = ("cv_load", "cvs_load")
_PENALTY_PER_PARAM = 0.01


def _known_compare_models() -> list[str]:
    from ..friction.specs import DYNAMIC_SPECS

    return ["nominal", *DYNAMIC_SPECS]


def add_parser(sub) -> argparse.ArgumentParser:
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
    p.add_argument("--load", type=typed(options.load), metavar="N",
                   help="constant normal load on the seals and guides, N: the load models (cv_load, cvs_load) need "
                        "it, since runs do not record a load and at their default Fn = 0 the load terms do nothing; "
                        "at one constant load those terms are not separable from Fc, Fs, B (see their std)")
    p.add_argument("--horizon", type=typed(options.positive_seconds, "--horizon"), default=1.0, metavar="S",
                   help="validation simulation horizon, s (default 1)")
    p.add_argument("--workers", type=typed(options.whole_number, "--workers", lo=1, hi=1024),
                   default=os.cpu_count() or 1, metavar="N",
                   help="parallel processes, one model each (default: the number of CPUs)")
    p.add_argument("--json", metavar="OUT.json", help="write the ranking (ModelComparison rows), the best model "
                                                      "and the options")
    add_max_rows(p)
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=run)
    return p


def _compare_models(args) -> list[str]:
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


def run(args) -> int:
    from ..files import check_train_and_valid, clean_json, read_run, write_json_atomic
    from ..friction import compare_friction_models
    from ..identify import IdentifyOptions

    models = _compare_models(args)
    check_paths({"--json": args.json}, inputs=[args.config, args.train, args.validate])
    cyl = load_config(args.config)
    train, valid = read_run(args.train, args.max_rows), read_run(args.validate, args.max_rows)
    warning = check_train_and_valid(cyl, train, valid, args.train, args.validate)
    options = IdentifyOptions(max_iter=40)  # no wall-clock limit: the ranking must not depend on load
    preflight_runs(cyl, [train], options.estimate, held_out=[valid])  # TRAIN must determine the nominal friction
    if warning:
        eprint(f"combined-reality friction-compare: warning: {warning}")

    say = (lambda msg: None) if args.quiet else eprint
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
                           "time_limit_s": None, "interval_s": options.interval_s},
               "config": str(cyl.source) if cyl.source else None, "train": str(args.train),
               "validate": str(args.validate)}
        write_json_atomic(args.json, clean_json(out))
        say(f"wrote {args.json}")
    if best is None:
        eprint("combined-reality friction-compare: every model failed (the reasons are listed above).")
        return 1
    return 0


def _pm(x: float, s: float) -> str:
    if not math.isfinite(x):
        return "-"
    return f"{x:.4g} ± {s:.2g}" if math.isfinite(s) else f"{x:.4g}"


def format_comparison(ranking, horizon_s: float) -> str:
    """The ranking table, the failures' reasons, and the best model's parameters per direction."""
    from sim.friction_models import parameter_unit

    from sim.friction_models import DIRECTIONS, FRICTION_MODELS

    from ..friction.dynamic import fit_spec
    from ..identify import UNITS

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
        lines.extend(f"  {n} = no estimate (TRAIN does not determine it)" if n in best.not_determined else
                     f"  {n} = {_pm(v, best.std.get(n, math.nan))} {UNITS.get(n, '')}".rstrip()
                     for n, v in best.params.items())
        return "\n".join(lines)
    spec = fit_spec(best.model)
    cls = FRICTION_MODELS[spec.family]
    suffixes = [s for s, _ in DIRECTIONS.values()]
    table = [("parameter", *DIRECTIONS)]
    for base in cls.BASE:
        unit = parameter_unit(spec.family, base)
        cells = []
        for suffix in suffixes:
            name = f"{base}_{suffix}"
            v = best.params.get(name, math.nan)
            cells.append(f"{v:.4g} (fixed)" if base in spec.fixed else "no estimate" if name in best.not_determined
                         else _pm(v, best.std.get(name, math.nan)))
        table.append((f"{base} [{unit}]" if unit else base, *cells))
    widths = [max(len(row[i]) for row in table) for i in range(len(table[0]))]
    lines.extend("  " + "  ".join(c.ljust(w) for c, w in zip(row, widths)).rstrip() for row in table)
    for name in cls.SHARED:
        unit = cls.PARAMS[name].unit
        v, sd = best.params.get(name, math.nan), best.std.get(name, math.nan)
        kind = "input, not estimated" if name == "Fn" else "both directions"
        shown = "no estimate" if name in best.not_determined else f"{_pm(v, sd)} {'' if unit == '1' else unit}"
        lines.append(f"  {name} = {shown} ({kind})".replace("  (", " ("))
    return "\n".join(lines)
