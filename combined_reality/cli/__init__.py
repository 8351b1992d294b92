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
import time
from importlib import resources
from pathlib import Path
from typing import Sequence

from sim.cylinder import ESTIMABLE, ConfigError, Cylinder, load_cylinder

from .runs import Run, RunFormatError, atomic_write, cylinder_identity, cylinder_tag, read_run, \
    recorded_elsewhere, write_run


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
    atomic_write(path, text.encode("utf-8"))


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
    """--effect values: words of the effect vocabulary, or a friction model of the family
    (which replaces the cylinder file's friction), each as 'name:k=v,k=v'."""
    from sim.friction_models import check_combination, parse_truth_spec

    effects = []
    for spec in specs or ():
        try:
            effects.append(parse_truth_spec(spec))
        except ValueError as e:
            raise UsageError(f"--effect {spec}: {e}.") from None
    try:
        check_combination(effects)
    except ValueError as e:
        raise UsageError(f"--effect: {e}.") from None
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
        cylinder_tag(cyl),
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
    write_run(run_path, run, comments=[cylinder_tag(cyl), f"combined-reality demo: {cyl.name}, seed {args.seed}"])
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


# ------------------------------------------------------------------ virtual-rig

def _cmd_virtual_rig(args) -> int:
    import re
    import signal

    from hw.rig_server import FaultSpec, RigServer, ServerOptions

    cyl = _load_config(args.config)
    effects = _parse_effects(args.effect)
    if args.duration is not None and not (args.duration >= 0 and math.isfinite(args.duration)):
        raise UsageError(f"--duration must be a non-negative number of seconds, not {args.duration}.")
    try:  # the library checks the options (before it builds the plant); its messages name them as fields
        faults = FaultSpec(drop=args.drop, corrupt=args.corrupt, stall_at=args.stall_at, stall_for=args.stall_for,
                           vanish_at=args.vanish_at, vanish_for=args.vanish_for, seed=args.seed)
        options = ServerOptions(rate=args.rate, jitter_us=args.jitter_us, watchdog_ms=args.watchdog_ms)
        server = RigServer(cyl, effects, transport="slcan" if args.can else "serial", options=options, faults=faults,
                           seed=args.seed, noise=not args.no_noise, link_path=args.link, log=_eprint,
                           on_path=lambda path: print(path, flush=True), progress=_eprint)
    except ValueError as e:  # said with the options' names
        flags = {f: "--" + f.replace("_", "-") for f in ("rate", "jitter_us", "watchdog_ms", "drop", "corrupt",
                                                         "stall_at", "stall_for", "vanish_at", "vanish_for")}
        flags["link_path"] = "--link"
        msg = re.sub(r"(?<![\w/.-])[a-z_]+(?![\w/.-])", lambda m: flags.get(m[0], m[0]), str(e))
        raise UsageError(f"{msg}.") from None
    print(server.path, flush=True)  # the first line of stdout: what the host opens
    truth = ", ".join(f"{n}={cyl.value(n):g}" for n in ("Fc", "Fv", "kp"))
    _eprint(f"virtual rig: '{cyl.name}' ({truth}) at {args.rate:g} Hz, "
            f"{'SLCAN adapter' if args.can else 'serial protocol'} on {server.path}"
            + (f" (link {args.link})" if args.link else "") + "; SIGINT or SIGTERM ends it")
    previous = {sig: signal.signal(sig, lambda *_: server.stop()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        stats = server.run(args.duration)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    _eprint(f"virtual rig: stopped after {stats.wall_s:.1f} s: {stats.summary()}")
    return 1 if server.failure else 0


# ------------------------------------------------------------------ diagnose

def check_train_and_valid(cyl: Cylinder, train: Run, valid: Run, train_name: str, valid_name: str,
                          verb: str = "diagnose") -> None:
    """Refuse (UsageError) a TRAIN/VALID pair of which a run does not fit the cylinder file
    (stroke, pressures), is shorter than 1 s at 1 kHz, or was recorded on another cylinder
    than the file describes (its cylinder tag), or VALID sampled at another rate than TRAIN.
    `verb` completes the advice: '... ; {verb} runs of the cylinder they were recorded on.'"""
    for r, what in ((train, train_name), (valid, valid_name)):
        _check_run_against_cylinder(r, cyl)
        if r.n < 1000:
            raise UsageError(f"{what}: {r.n} samples are too few (at least 1 s at 1 kHz).")
        theirs = recorded_elsewhere(r, cyl)
        if theirs is not None:
            raise UsageError(f"{what} was recorded on the cylinder '{theirs}', but the cylinder file "
                             f"{cyl.source or ''} describes '{cylinder_identity(cyl)}'; {verb} runs of the "
                             "cylinder they were recorded on.")
    if abs(valid.sample_period / train.sample_period - 1) > 0.01:
        raise UsageError(f"{valid_name} is sampled every {valid.sample_period * 1e3:.3g} ms but {train_name} every "
                         f"{train.sample_period * 1e3:.3g} ms; validate with a run of the same rig and rate.")


def cmd_diagnose(args) -> int:
    from sim.effects import EFFECTS

    from .diagnose import DiagnoseOptions, diagnose

    cyl = _load_config(args.config)
    train, valid = read_run(args.train), read_run(args.validate)
    check_train_and_valid(cyl, train, valid, args.train, args.validate, "diagnose")
    names = tuple(n.strip() for n in args.candidates.split(",") if n.strip()) if args.candidates else tuple(EFFECTS)
    unknown = [n for n in names if n not in EFFECTS]
    if unknown:
        raise UsageError(f"--candidates: unknown effect {', '.join(unknown)} (known: {', '.join(EFFECTS)}).")
    if not (args.horizon > 0 and math.isfinite(args.horizon)):
        raise UsageError(f"--horizon must be a positive number of seconds, not {args.horizon}.")
    rerun_mode, rerun_target = _rerun_mode(args)
    if args.report and not args.report.lower().endswith((".html", ".htm")):
        raise UsageError(f"--report {args.report}: the report is HTML; name it REPORT.html.")
    opts = DiagnoseOptions(candidates=names, horizon_s=args.horizon, workers=max(1, args.workers))
    diagnosis = diagnose(cyl, train, valid, opts, progress=_progress(args.quiet))
    result = diagnosis.to_json()
    base = result["baseline"]
    print(f"validation position RMSE of the nominal model: {base['rmse_x_validation'] * 1e6:.1f} um "
          f"(segments of {args.horizon:g} s, all outputs {base['normalized_rms']:.2f} x the sensor noise)")
    print(f"verdict: {result['verdict']}")
    print(f"{'effect':20s} {'shrink':>8s} {'all out':>8s} {'z':>6s} {'rmse_x [um]':>12s}  parameters")
    for c in result["ranking"]:
        pars = ", ".join(f"{k}={v:.4g}±{c['std'][k]:.2g}" for k, v in c["params"].items())
        mark = "*" if c["significant"] else " "
        print(f"{c['effect']:20s} {c['shrink']:8.1%} {c['shrink_all']:8.1%} {c['z']:6.1f}{mark}"
              f"{c['rmse_x_validation'] * 1e6:12.1f}  {pars or c.get('error', '')}")
    if result["pair"] is not None:
        c = result["pair"]
        print(f"best pair {c['effect']}: shrink {c['shrink']:.1%}"
              + ("" if c["significant"] else " (no significant gain over the verdict alone)"))
    print("where the gap lies (share of the squared error / share of the samples):")
    for r in result["regions"][:5]:
        print(f"  {r['where']:34s} {r['share_of_error']:6.1%} / {r['fraction_of_samples']:6.1%}")
    for r in result["subsystems"]:
        print(f"  {r['subsystem']:62s} {r['share_of_error']:6.1%} of the excess error")
    if args.json:
        _write_json_atomic(args.json, _clean_json(result))
    if args.report:
        from .diagnose_report import write_report

        write_report(diagnosis, args.report)
        if not args.quiet:
            _eprint(f"wrote the report {args.report}")
    if rerun_mode != "off":
        from .diagnose_rerun import log_diagnosis
        from .visual import open_recording

        rec = open_recording(rerun_mode, rerun_target)
        log_diagnosis(diagnosis, rec)
        rec.flush()  # the .rrd (or the viewer) holds everything before the process ends
        rec.disconnect()
    return 0


# ------------------------------------------------------------------ live and replay

def _online_options(args, cyl: Cylinder):
    from .online import OnlineOptions

    names = _estimate_list(args.estimate, cyl)
    for name in ("window", "update"):
        v = getattr(args, name)
        if not (v > 0 and math.isfinite(v)):
            raise UsageError(f"--{name} must be a positive number of seconds, not {v}.")
    if args.update > args.window:
        raise UsageError(f"--update ({args.update:g} s) must not exceed --window ({args.window:g} s).")
    if not args.memory > 0:
        raise UsageError(f"--memory must be a positive number of seconds (or inf), not {args.memory}.")
    return OnlineOptions(window_s=args.window, update_s=args.update, memory_s=args.memory, estimate=names)


def _rerun_mode(args) -> tuple[str, str | None]:
    mode, *rest = args.rerun
    if mode not in ("spawn", "connect", "save", "off"):
        raise UsageError(f"--rerun {mode}: use spawn, connect ADDR, save FILE or off.")
    if mode == "save" and len(rest) != 1:
        raise UsageError("--rerun save needs exactly one file name (--rerun save session.rrd).")
    if mode in ("spawn", "off") and rest or len(rest) > 1:
        raise UsageError(f"--rerun {' '.join(args.rerun)}: too many arguments.")
    return mode, (rest[0] if rest else None)


def _rerun_sink(args, cyl, window_s: float):
    mode, target = _rerun_mode(args)
    if mode == "off":
        return None
    from .visual import RerunSink, open_recording

    return RerunSink(open_recording(mode, target), cyl, window_s)


def _stream_json(result, options, wall_s: float) -> dict:
    import numpy as np

    final = result.final
    walls = np.array([e.wall_s for e in result.estimates]) * 1e3
    out = {"params": {}, "fit": {}, "solver": {
        "status": "online" if final else "no_estimate", "method": "moving-horizon multiple shooting",
        "updates": len(result.estimates), "window_s": options.window_s, "wall_s": round(wall_s, 3),
        "update_ms_p50": float(np.percentile(walls, 50)) if len(walls) else None,
        "update_ms_p95": float(np.percentile(walls, 95)) if len(walls) else None,
        "n_samples": int(result.run.n), "stop_reason": result.stop_reason},
        "link": result.counters, "events": result.events,
        "history": [{"t": e.t, "values": e.values, "std": e.std, "sigma": e.sigma} for e in result.estimates]}
    if final:
        out["params"] = {n: {"value": final.values[n], "std": final.std[n], "unit": final.units[n]} for n in final.values}
        out["fit"] = {**final.rmse, "sigma": final.sigma, "window": list(final.window)}
    return out


def _run_stream(args, cyl, rig, program, duration, record: str | None, sample_period: float, inline: bool) -> int:
    import signal

    from .stream import ConsoleSink, InlineEstimator, LockstepSimulator, ProcessEstimator, run_session

    options = _online_options(args, cyl)
    try:
        rr_sink = _rerun_sink(args, cyl, options.window_s)
    except ValueError as e:
        raise UsageError(str(e)) from None

    def link_counters() -> dict:
        stats = getattr(rig, "stats", None)
        return {} if stats is None else {"lost": stats.samples_lost, "corrupt": stats.frames_corrupt}

    sinks = [s for s in (None if args.quiet else ConsoleSink(_eprint, 1.0, link_counters), rr_sink) if s is not None]
    if not args.quiet:
        _eprint("preparing the model (compiled once, then cached) ...")
    simulator = LockstepSimulator(cyl)
    estimator = (InlineEstimator if inline else ProcessEstimator)(cyl, sample_period, options)
    comments = [cylinder_tag(cyl), f"combined-reality {args.command}: {cyl.name}", f"config {cyl.source}",
                f"started {time.strftime('%Y-%m-%d %H:%M:%S')}"]
    # SIGTERM ends a session like Ctrl-C: valve centred, files complete
    def _term(*_):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, _term)
    t_wall = time.perf_counter()
    try:
        result = run_session(cyl, rig, estimator=estimator, program=program, duration=duration, record_to=record,
                             record_comments=comments, sinks=sinks, simulator=simulator, on_event=_eprint,
                             give_up_s=args.give_up, expected_period=sample_period)
    finally:
        signal.signal(signal.SIGTERM, previous)
        estimator.close()
    wall = time.perf_counter() - t_wall
    c = result.counters
    summary = (f"{result.stop_reason}: {c['samples']} samples in {wall:.1f} s"
               + "".join(f", {c[k]} {k.replace('_', ' ')}" for k in ("samples_lost", "frames_corrupt", "gaps",
                                                                     "reconnects", "rig_errors") if k in c))
    _eprint(summary)
    if record:
        _eprint(f"recorded {result.run.n} samples to {record}")
    final = result.final
    if final:
        print(f"online estimate at t = {final.t:.2f} s ({len(result.estimates)} updates, residual σ = "
              f"{final.sigma:.2f} × noise):")
        for n, v in final.values.items():
            print(f"  {n:4s} = {v:.6g} ± {final.std[n]:.2g} {final.units[n]}")
    else:
        print("no online estimate: fewer samples than one estimation window.")
    if args.json:
        _write_json_atomic(args.json, _clean_json(_stream_json(result, options, wall)))
    if getattr(estimator, "error", None):
        return 1
    return 1 if result.stop_reason.startswith("no samples") else 0


def open_rig(args, cyl: Cylinder, effects=(), *, rate: float = 1000.0, paced: bool = True):
    """The rig named by --serial PORT, --can CH [--interface], else the virtual rig in this
    process (paced to real time, or as fast as the CPU allows)."""
    from hw.rig import RigError

    try:
        if args.serial:
            from hw.serial_rig import SerialRig

            return SerialRig(args.serial, on_event=_eprint)
        if args.can:
            from hw.can_rig import CanRig

            # python-can's slcan waits 2 s after opening unless told otherwise
            extra = {"sleep_after_open": 0.1} if args.interface == "slcan" else {}
            return CanRig(args.can, interface=args.interface, on_event=_eprint, **extra)
    except RigError as e:
        raise UsageError(f"{e}.") from None
    from hw.virtual_rig import VirtualRig

    rig = VirtualRig(cyl, effects, rate=rate, seed=args.seed)
    if paced:
        from .stream import PacedRig

        return PacedRig(rig)
    return rig


def cmd_live(args) -> int:
    from .excitation import make_program

    cyl = _load_config(args.config)
    if not (args.duration > 0 and math.isfinite(args.duration)):
        raise UsageError(f"--duration must be a positive number of seconds, not {args.duration}.")
    try:
        program = make_program(args.program, cyl, args.duration, seed=args.seed)
    except (ValueError, OSError) as e:
        raise UsageError(f"--program {args.program}: {e}") from None
    record = Path(args.record)
    if record.exists() and not args.overwrite:
        raise UsageError(f"--record {record} exists; a recording is never overwritten unless you pass --overwrite.")
    if not record.parent.is_dir():
        raise UsageError(f"--record {record}: the folder {record.parent} does not exist.")
    effects = _parse_effects(args.effect)
    if effects and not args.virtual:
        raise UsageError("--effect switches effects on in the virtual rig; it needs --virtual.")
    rig = open_rig(args, cyl, effects, rate=args.rate, paced=True)
    return _run_stream(args, cyl, rig, program, args.duration, args.record, 1.0 / args.rate, inline=False)


def cmd_replay(args) -> int:
    from .stream import ReplayRig

    cyl = _load_config(args.config)
    run = read_run(args.run)
    _check_run_against_cylinder(run, cyl)
    if run.n < 3:
        raise UsageError(f"{args.run}: a run needs at least 3 samples.")
    speed = math.inf if args.speed == "max" else _positive_float(args.speed, "--speed")
    return _run_stream(args, cyl, ReplayRig(run, speed), None, None, None, run.sample_period, inline=speed == math.inf)


def _positive_float(text: str, what: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise UsageError(f"{what} {text}: give a number or max.") from None
    if not (v > 0 and math.isfinite(v)):
        raise UsageError(f"{what} must be positive, not {text}.")
    return v


def _add_online_arguments(a) -> None:
    a.add_argument("--config", help="cylinder TOML (default: the built-in cylinder A)")
    a.add_argument("--json", help="write the final online estimate (identify format, plus its history)")
    a.add_argument("--rerun", nargs="+", default=["off"], metavar="MODE",
                   help="spawn | connect ADDR | save FILE | off (default off)")
    a.add_argument("--estimate", help="comma-separated parameters (default Fc,Fv,kp)")
    a.add_argument("--window", type=float, default=2.0, help="moving horizon, s (default 2)")
    a.add_argument("--update", type=float, default=0.2, help="data between estimator updates, s (default 0.2)")
    a.add_argument("--memory", type=float, default=math.inf,
                   help="forgetting time constant of old data, s (default inf: keep all)")
    a.add_argument("--give-up", type=float, default=5.0, help="end the session after this long without samples, s")
    a.add_argument("-q", "--quiet", action="store_true", help="no progress lines")


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
                        "(repeatable; any word of the vocabulary, see docs/effects.md), or a friction model "
                        "of the family as the truth's friction, e.g. cvs:Fc_pos=1.59,Fs_pos=6 (docs/friction.md)")
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

    v = sub.add_parser("virtual-rig", help="serve the virtual rig in real time over a pseudo-terminal (serial or SLCAN)",
                       description="Run the virtual rig in real time behind the wire protocol of docs/protocol.md, "
                                   "on a pseudo-terminal that a host opens like a serial port (or an SLCAN CAN "
                                   "adapter). The first line of stdout is the pty path; status and fault messages "
                                   "go to stderr. Runs until SIGINT/SIGTERM or --duration. The cylinder file's "
                                   "[friction] is the truth.")
    v.add_argument("--config", help="cylinder TOML file (default: the built-in 32 mm x 100 mm cylinder)")
    kind = v.add_mutually_exclusive_group(required=True)
    kind.add_argument("--serial", action="store_true", help="serial protocol: COBS frames with CRC-16")
    kind.add_argument("--can", action="store_true", help="an SLCAN adapter with the rig on its bus (hw/rig_can.dbc)")
    v.add_argument("--rate", type=float, default=1000.0, help="sample rate in Hz (default 1000)")
    v.add_argument("--effect", action="append", metavar="NAME[:k=v,...]",
                   help="switch on an unmodelled effect in the plant (repeatable)")
    v.add_argument("--seed", type=int, default=1, help="seed of the noise, jitter and faults (default 1)")
    v.add_argument("--no-noise", action="store_true", help="noise-free sensors")
    v.add_argument("--jitter-us", type=float, default=20.0, help="standard deviation of the tick times (default 20)")
    v.add_argument("--watchdog-ms", type=float, default=50.0,
                   help="host silence after which the valve is centred (default 50)")
    v.add_argument("--drop", type=float, default=0.0, metavar="P", help="probability of dropping a frame")
    v.add_argument("--corrupt", type=float, default=0.0, metavar="P",
                   help="probability of corrupting bytes of a frame (--serial only)")
    v.add_argument("--stall-at", type=float, metavar="T", help="stop sending at T s ...")
    v.add_argument("--stall-for", type=float, metavar="D", help="... for D s (frames are delayed, not lost)")
    v.add_argument("--vanish-at", type=float, metavar="T", help="close the pty at T s (the rig vanishes)")
    v.add_argument("--vanish-for", type=float, metavar="D", help="come back on a new pty after D s (see --link)")
    v.add_argument("--link", metavar="PATH", help="keep a symbolic link PATH to the current pty (like "
                                                  "/dev/serial/by-id), so a host finds the rig again")
    v.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: run until stopped)")
    v.set_defaults(func=_cmd_virtual_rig)

    lv = sub.add_parser("live", help="run an experiment on a rig with the model in lock-step and online estimation",
                        description="Drive a rig with a safe experiment program, record every sample, simulate "
                                    "the model with the same command and estimate the friction online.")
    src = lv.add_mutually_exclusive_group(required=True)
    src.add_argument("--serial", metavar="PORT", help="a rig on a serial port (docs/protocol.md)")
    src.add_argument("--can", metavar="CHANNEL", help="a rig on CAN (hw/rig_can.dbc), via python-can")
    src.add_argument("--virtual", action="store_true", help="the virtual rig in this process, in real time")
    lv.add_argument("--interface", default="socketcan", help="python-can interface for --can (default socketcan; slcan, ...)")
    lv.add_argument("--program", default="mixed",
                    help="mixed | steps | ramps | sines (closed-loop position) | pulses (open loop) | file:CMD.csv")
    lv.add_argument("--duration", type=float, required=True, help="seconds of rig time")
    lv.add_argument("--record", required=True, help="run CSV written as samples arrive")
    lv.add_argument("--overwrite", action="store_true", help="replace an existing --record file")
    lv.add_argument("--seed", type=int, default=0, help="seed of the experiment program (and the virtual rig)")
    lv.add_argument("--rate", type=float, default=1000.0, help="sample rate of the rig, Hz (default 1000)")
    lv.add_argument("--effect", action="append", metavar="SPEC", help="with --virtual: an unmodelled effect as truth")
    _add_online_arguments(lv)
    lv.set_defaults(func=cmd_live)

    dg = sub.add_parser("diagnose", help="explain the sim-to-real gap: where, which unmodelled effect, how far it shrinks")
    dg.add_argument("train", help="run CSV the models are identified on")
    dg.add_argument("--validate", required=True, help="run CSV the models are scored on (never fitted)")
    dg.add_argument("--config", help="cylinder TOML (default: the built-in cylinder A)")
    dg.add_argument("--json", help="write the diagnosis (FORMATS.md)")
    dg.add_argument("--report", metavar="REPORT.html", help="write a self-contained HTML report with plots")
    dg.add_argument("--rerun", nargs="+", default=["off"], metavar="MODE",
                    help="show the diagnosis in Rerun: spawn | connect ADDR | save FILE.rrd | off (default)")
    dg.add_argument("--candidates", help="comma-separated effects to try (default: the whole vocabulary)")
    dg.add_argument("--horizon", type=float, default=1.0, help="validation simulation horizon, s (default 1)")
    dg.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="parallel processes for the candidates")
    dg.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    dg.set_defaults(func=cmd_diagnose)

    rp = sub.add_parser("replay", help="replay a recorded run through the lock-step model and the online estimator")
    rp.add_argument("run", help="recorded run CSV")
    rp.add_argument("--speed", default="1", help="1 = real time, 2 = twice as fast, max = as fast as possible")
    _add_online_arguments(rp)
    rp.set_defaults(func=cmd_replay)

    from . import cli_batch, cli_friction, cli_procedure

    cli_friction.add_parser(sub)
    cli_friction.add_compare_parser(sub)
    cli_procedure.add_parser(sub)
    cli_batch.add_parser(sub)
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
