"""The `combined-reality` command line (FORMATS.md contract).

Exit status: 0 success, 2 bad input (files, options), 1 a failure of the tool.
Errors are one sentence on stderr; --debug shows the traceback.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from importlib import resources
from pathlib import Path
from typing import Sequence

from sim.cylinder import ESTIMABLE, ConfigError, Cylinder, load_cylinder

from .runs import Run, RunFormatError, read_run, write_run


class UsageError(ValueError):
    """Bad input from the command line (exit status 2)."""


# ------------------------------------------------------------------ helpers

def _eprint(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _progress(quiet: bool):
    return None if quiet else _eprint


def default_config_path() -> Path:
    return Path(str(resources.files("combined_reality") / "data" / "cyl_a_32x100.toml"))


def _load_config(path: str | None) -> Cylinder:
    return load_cylinder(path if path else default_config_path())


def _write_text_atomic(path: str | Path, text: str) -> None:
    """Write via a temporary file and rename: readers see the old file or the whole new one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _write_json_atomic(path: str | Path, data: dict) -> None:
    _write_text_atomic(path, json.dumps(data, indent=2, allow_nan=False, default=_json_default) + "\n")


def _json_default(o):
    try:
        return float(o)
    except (TypeError, ValueError):
        return str(o)


def _clean_json(obj):
    """NaN/inf are not JSON: report them as null."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _clean_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean_json(v) for v in obj]
    return obj


def _parse_effects(specs: Sequence[str] | None):
    from sim.effects import parse_effect_spec

    effects = []
    for spec in specs or ():
        try:
            effects.append(parse_effect_spec(spec))
        except ValueError as e:
            raise UsageError(f"--effect {spec}: {e}.") from None
    return effects


def _check_run_against_cylinder(run: Run, cyl: Cylinder) -> None:
    L = cyl.geometry.stroke
    lo, hi = float(run.x.min()), float(run.x.max())
    if lo < -0.1 * L or hi > 1.1 * L:
        raise UsageError(f"{run.source}: position spans {lo:.4g} to {hi:.4g} m but the stroke in "
                         f"{cyl.source or 'the cylinder file'} is {L:g} m (wrong unit, wrong origin or wrong cylinder?).")
    pmax = float(max(run.p1.max(), run.p2.max()))
    if pmax > 1.5 * cyl.supply.pressure:
        raise UsageError(f"{run.source}: chamber pressure reaches {pmax:.4g} Pa, far above the supply pressure "
                         f"{cyl.supply.pressure:.4g} Pa of {cyl.source or 'the cylinder file'}.")


# ------------------------------------------------------------------ simulate

def simulate_run(cyl: Cylinder, duration: float, seed: int, rate: float = 1000.0, effects=(), noise: bool = True,
                 progress=None) -> Run:
    from hw.virtual_rig import VirtualRig

    from .excitation import PositionProgram
    from .experiment import run_program

    rig = VirtualRig(cyl, effects, rate=rate, seed=seed, noise=noise, progress=progress)
    program = PositionProgram(cyl, duration, seed=seed)
    n = int(round(duration * rate))
    report = (lambda k: progress(f"  simulated {k / rate:5.1f} / {duration:g} s")) if progress else None
    return run_program(rig, program, n, progress=report if progress and n > 5000 else None)


def cmd_simulate(args) -> int:
    cyl = _load_config(args.config)
    if not args.duration > 0 or not math.isfinite(args.duration):
        raise UsageError(f"--duration must be a positive number of seconds, not {args.duration}.")
    if not 10 <= args.rate <= 100_000:
        raise UsageError(f"--rate must lie between 10 and 100000 Hz, not {args.rate}.")
    effects = _parse_effects(args.effect)
    prog = _progress(args.quiet)
    t0 = time.perf_counter()
    run = simulate_run(cyl, args.duration, args.seed, args.rate, effects, noise=not args.no_noise, progress=prog)
    truth = ", ".join(f"{n}={cyl.value(n):g}" for n in ("Fc", "Fv", "kp"))
    eff = "; ".join(f"{e.name}(" + ", ".join(f"{k}={v:g}" for k, v in zip(e.param_names(), e.values())) + ")"
                    for e in effects) or "none"
    write_run(args.output, run, comments=[
        f"combined-reality virtual rig: cylinder {cyl.name!r} ({cyl.source}), seed {args.seed}, {args.rate:g} Hz",
        f"truth: {truth}; effects: {eff}; noise: {'off' if args.no_noise else 'on'}",
    ])
    if not args.quiet:
        _eprint(f"wrote {args.output}: {run.n} samples, {run.duration:.3f} s, in {time.perf_counter() - t0:.2f} s")
    return 0


# ------------------------------------------------------------------ identify

def _format_table(result, truth: Cylinder | None = None) -> str:
    rows = [("parameter", "value", "std", "unit", "initial") + (("true", "error") if truth else ())]
    for n, e in result.params.items():
        row = (n, f"{e.value:.6g}", f"{e.std:.3g}" + (" (at bound)" if e.at_bound else ""), e.unit, f"{e.initial:.4g}")
        if truth:
            tv = truth.value(n) if "." not in n else float("nan")
            err = (e.value - tv) / tv * 100 if tv else float("nan")
            row += (f"{tv:.6g}", f"{err:+.2f} %")
        rows.append(row)
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
    f = result.fit
    fit = [f"rmse_x {f['rmse_x'] * 1e6:.2f} um (R2 {f['r2_x']:.6f})"]
    if "rmse_p1" in f:
        fit.append(f"rmse_p1 {f['rmse_p1']:.0f} Pa, rmse_p2 {f['rmse_p2']:.0f} Pa")
    if "kp" in result.params:
        kp = result.params["kp"]
        lines.append(f"(kp = {kp.value * 1e5:.4g} +- {kp.std * 1e5:.2g} N/bar)")
    s = result.solver
    lines.append("fit: " + "; ".join(fit))
    lines.append(f"solver: {s['status']} after {s['iterations']} iterations, {s['wall_s']:.2f} s "
                 f"({result.drive} drive, {s['n_samples']} samples, residual sigma {s['residual_sigma']:.3g} x noise)")
    return "\n".join(lines)


def _estimate_list(arg: str | None, cyl: Cylinder) -> tuple[str, ...]:
    if arg is None:
        return cyl.identify.estimate
    names = tuple(s.strip() for s in arg.split(",") if s.strip())
    if not names:
        raise UsageError("--estimate needs at least one parameter name.")
    return names


def cmd_identify(args) -> int:
    from .identify import IdentificationError, IdentifyOptions, identify

    cyl = _load_config(args.config)
    runs = [read_run(p) for p in args.runs]
    for r in runs:
        _check_run_against_cylinder(r, cyl)
    effects = _parse_effects(args.effect)
    estimate = _estimate_list(args.estimate, cyl)
    effect_params = {f"{e.name}.{n}" for e in effects for n in e.param_names()}
    for n in estimate:
        if n not in ESTIMABLE and n not in effect_params:
            raise UsageError(f"--estimate: unknown parameter '{n}' (estimable: {', '.join(ESTIMABLE)}"
                             + (f", {', '.join(sorted(effect_params))}" if effect_params else "") + ").")
    drive = args.drive or cyl.identify.drive
    if drive == "pressure":
        bad = [n for n in estimate if n in ("conductance", "critical_ratio", "dead_volume_cap", "dead_volume_rod")]
        if bad:
            raise UsageError(f"--drive pressure uses the measured pressures, so it cannot estimate {', '.join(bad)}.")
    if not args.interval > 0:
        raise UsageError(f"--interval must be positive, not {args.interval}.")
    opts = IdentifyOptions(drive=drive, estimate=estimate, interval_s=args.interval, max_iter=args.max_iter,
                           prefit=not args.no_prefit)
    prog = _progress(args.quiet)
    if prog:
        prog(f"identifying {', '.join(estimate)} from {len(runs)} run(s), {sum(r.n for r in runs)} samples, "
             f"{drive} drive")
    try:
        result = identify(cyl, runs, opts, effects=effects, progress=prog)
    except IdentificationError as e:
        _eprint(f"combined-reality identify: {e}")
        return 1
    out = result.to_json()
    out["config"] = str(cyl.source)
    out["inputs"] = [str(p) for p in args.runs]
    if args.json:
        _write_json_atomic(args.json, _clean_json(out))
    if args.write_config:
        from sim.cylinder import cylinder_to_toml

        _write_text_atomic(args.write_config, cylinder_to_toml(result.cylinder))
    print(_format_table(result))
    status = result.solver["status"]
    if status != "converged":
        _eprint(f"combined-reality identify: the solver stopped without converging ({status}); "
                "the estimates above are the last iterate.")
        return 1
    return 0


# ------------------------------------------------------------------ demo

def cmd_demo(args) -> int:
    from .identify import IdentifyOptions, identify

    cyl = _load_config(args.config)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    prog = _progress(args.quiet)
    _eprint(f"1/2 simulating a {args.duration:g} s run of '{cyl.name}' on the virtual rig (seed {args.seed}) ...")
    run = simulate_run(cyl, args.duration, args.seed, progress=prog)
    run_path = out / "demo_run.csv"
    write_run(run_path, run, comments=[f"combined-reality demo: {cyl.name}, seed {args.seed}"])
    run = read_run(run_path)
    start = cyl.with_values({"Fc": cyl.friction.Fc * 0.4, "Fv": cyl.friction.Fv * 3.0 + 10.0,
                             "kp": cyl.friction.kp * 0.2})
    _eprint(f"2/2 identifying Fc, Fv, kp by multiple shooting from a poor start "
            f"(Fc={start.friction.Fc:.3g}, Fv={start.friction.Fv:.3g}, kp={start.friction.kp:.3g}) ...")
    result = identify(start, [run], IdentifyOptions(prefit=False), progress=prog)
    _write_json_atomic(out / "demo_identify.json", _clean_json(result.to_json()))
    print(f"\nIdentified vs true friction of '{cyl.name}' ({run_path}, {run.duration:.1f} s at "
          f"{1 / run.sample_period:.0f} Hz):")
    print(_format_table(result, truth=cyl))
    print(f"\nwrote {run_path} and {out / 'demo_identify.json'}")
    return 0 if result.solver["status"] == "converged" else 1


# ------------------------------------------------------------------ parser

def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="combined-reality",
                                description="Find out what a servopneumatic cylinder really does: simulate it, "
                                            "identify its friction from recorded runs.")
    p.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = sub.add_parser("simulate", help="make a run on the virtual rig (closed-loop position control)",
                       description="Simulate a run on the virtual rig: the cylinder file's [friction] is the truth, "
                                   "unmodelled effects can be switched on, sensors add white noise.")
    s.add_argument("--config", required=True, help="cylinder TOML file")
    s.add_argument("--duration", type=float, default=20.0, help="seconds (default 20)")
    s.add_argument("--seed", type=int, default=1, help="seed of the excitation and the noise (default 1)")
    s.add_argument("--rate", type=float, default=1000.0, help="sample rate in Hz (default 1000)")
    s.add_argument("--effect", action="append", metavar="NAME[:k=v,...]",
                   help="switch on an unmodelled effect, e.g. stiction:Fs_excess=8,v_stribeck=0.01 "
                        "(repeatable; available: stiction, valve_delay, leakage)")
    s.add_argument("--no-noise", action="store_true", help="noise-free sensors")
    s.add_argument("-o", "--output", required=True, help="run CSV to write")
    s.add_argument("-q", "--quiet", action="store_true")
    s.set_defaults(func=cmd_simulate)

    i = sub.add_parser("identify", help="identify friction parameters from recorded runs",
                       description="Identify parameters from one or more recorded runs (fitted jointly) by "
                                   "multiple-shooting least squares.")
    i.add_argument("--config", required=True, help="cylinder TOML file (its values are the starting point)")
    i.add_argument("runs", nargs="+", metavar="RUN.csv", help="recorded runs")
    i.add_argument("--json", help="write the result as JSON (FORMATS.md)")
    i.add_argument("--estimate", help=f"comma-separated parameters (default from the config, else Fc,Fv,kp; "
                                      f"estimable: {', '.join(ESTIMABLE)})")
    i.add_argument("--drive", choices=["command", "pressure"],
                   help="command: full model driven by the recorded valve command (default); "
                        "pressure: piston only, driven by the measured pressures")
    i.add_argument("--effect", action="append", metavar="NAME[:k=v,...]",
                   help="add an unmodelled effect to the model (its parameters may be estimated as NAME.param)")
    i.add_argument("--interval", type=float, default=0.1, help="shooting interval in seconds (default 0.1)")
    i.add_argument("--max-iter", type=int, default=40, help="Gauss-Newton iterations at most (default 40)")
    i.add_argument("--no-prefit", action="store_true",
                   help="start from the config's friction values, not from the equation-error fit")
    i.add_argument("--write-config", metavar="OUT.toml", help="write the cylinder file with identified values")
    i.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    i.set_defaults(func=cmd_identify)

    d = sub.add_parser("demo", help="simulate a run on the virtual rig and identify it (identified vs true)")
    d.add_argument("--config", help="cylinder TOML file (default: the built-in 32 mm x 100 mm cylinder)")
    d.add_argument("--duration", type=float, default=20.0)
    d.add_argument("--seed", type=int, default=1)
    d.add_argument("--out", default="combined_reality_demo", help="folder for the run and the result")
    d.add_argument("-q", "--quiet", action="store_true")
    d.set_defaults(func=cmd_demo)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (ConfigError, RunFormatError, UsageError) as e:
        if args.debug:
            raise
        _eprint(f"combined-reality {args.command}: {e}")
        return 2
    except KeyboardInterrupt:
        _eprint(f"combined-reality {args.command}: interrupted.")
        return 130
    except Exception as e:  # a failure of the tool, not of the input
        if args.debug:
            raise
        _eprint(f"combined-reality {args.command}: internal error: {e} (run with --debug for the traceback).")
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
