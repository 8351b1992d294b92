"""`combined-reality live` (a rig driven by an experiment program, the model in lock-step,
online estimation) and `combined-reality replay` (a recorded run through the same session)."""
from __future__ import annotations

import math
import signal
import time
from pathlib import Path

from .. import options
from ..live.catalogue import DESCRIPTIONS
from .common import (EFFECT_HELP, UsageError, add_max_rows, check_paths, eprint,
                     estimate_list, load_config, open_rig, parse_effects, preflight_runs, rerun_mode,
                     typed)


def _add_online_arguments(a) -> None:
    a.add_argument("--config", help="cylinder TOML (default: for replay the one the run's header names; else the "
                                    "built-in cylinder A, said so)")
    a.add_argument("--json", help="write the final online estimate (identify format, plus its history)")
    a.add_argument("--rerun", nargs="+", default=["off"], metavar="MODE",
                   help="spawn | connect ADDR | save FILE | off (default off); spawn without a display (or when "
                        "the viewer does not start) saves a .rrd next to the recording instead")
    a.add_argument("--estimate", type=typed(options.parameter_names),
                   help="comma-separated parameters, each once (default Fc,Fv,kp)")
    a.add_argument("--window", type=typed(options.window), default=2.0,
                   help=f"moving horizon, s (default 2, at most {options.MAX_WINDOW:g})")
    a.add_argument("--update", type=typed(options.update), default=0.2,
                   help=f"data between estimator updates, s (default 0.2, at least {options.MIN_UPDATE:g})")
    a.add_argument("--memory", type=typed(options.positive_seconds, "--memory", allow_inf=True), default=math.inf,
                   help="forgetting time constant of old data, s (default inf: keep all data, and follow a change "
                        "or a drift of the friction by itself; a finite memory replaces following a drift)")
    a.add_argument("--give-up", type=typed(options.positive_seconds, "--give-up"), default=5.0,
                   help="end the session after this long without samples, s")
    a.add_argument("-q", "--quiet", action="store_true",
                   help="no status line (warnings and the summary are still printed)")


def add_parsers(sub) -> None:
    lv = sub.add_parser("live", help="run an experiment on a rig with the model in lock-step and online estimation",
                        description="Drive a rig with a safe experiment program, record every sample, simulate "
                                    "the model with the same command and estimate the friction online.")
    src = lv.add_mutually_exclusive_group(required=True)
    src.add_argument("--serial", metavar="PORT", help="a rig on a serial port (docs/protocol.md)")
    src.add_argument("--can", metavar="CHANNEL", help="a rig on CAN (hw/rig_can.dbc), via python-can")
    src.add_argument("--virtual", action="store_true", help="the virtual rig in this process, in real time")
    lv.add_argument("--interface", default="socketcan",
                    help="python-can interface for --can (default socketcan; slcan, ...)")
    lv.add_argument("--program", default="mixed",
                    help="; ".join(f"{name}: {what}" for name, what in DESCRIPTIONS.items())
                    + "; file:CMD.csv: the commands of a t,u CSV file (default mixed)")
    lv.add_argument("--duration", type=typed(options.live_duration), required=True,
                    help=f"seconds of rig time (at most {options.MAX_LIVE_DURATION:g})")
    lv.add_argument("--record", required=True, help="run CSV written as samples arrive")
    lv.add_argument("--overwrite", action="store_true", help="replace an existing --record file")
    lv.add_argument("--seed", type=typed(options.seed), default=0,
                    help=f"seed of the experiment program (and the virtual rig), 0 to {options.SEED_MAX}")
    lv.add_argument("--rate", type=typed(options.sample_rate), default=1000.0,
                    help=f"sample rate of the rig, Hz, {options.RATE_MIN:g} to {options.RATE_MAX:g} (default 1000)")
    lv.add_argument("--effect", action="append", metavar="SPEC", help=f"with --virtual: {EFFECT_HELP}, as truth")
    _add_online_arguments(lv)
    lv.set_defaults(func=run_live)

    rp = sub.add_parser("replay", help="replay a recorded run through the lock-step model and the online estimator",
                        description="Feed a recorded run, sample by sample, through the same session as live: the "
                                    "model simulated with the recorded command, the online estimate, the console "
                                    "and Rerun views.")
    rp.add_argument("run", help="recorded run CSV")
    rp.add_argument("--speed", type=typed(options.replay_speed), default=1.0,
                    help="1 = real time, 2 = twice as fast, max = as fast as possible")
    add_max_rows(rp)
    _add_online_arguments(rp)
    rp.set_defaults(func=run_replay)


def run_live(args) -> int:
    from ..live import Console, make_program

    record = Path(args.record)
    program_file = args.program[len("file:"):] if args.program.startswith("file:") else None
    _check_outputs(args, record, [args.config, program_file])
    if record.exists() and not args.overwrite:
        raise UsageError(f"--record {record} exists; a recording is never overwritten unless you pass --overwrite.")
    cyl = load_config(args.config)
    options = _online_options(args, cyl)  # refused before the rig is opened
    try:
        program = make_program(args.program, cyl, args.duration, seed=args.seed)
    except (ValueError, OSError) as e:
        raise UsageError(f"--program {args.program}: {e}") from None
    effects = parse_effects(args.effect)
    if effects and not args.virtual:
        raise UsageError("--effect switches effects on in the virtual rig; it needs --virtual.")
    console = Console(status=not args.quiet)
    link_events: list[str] = []  # what the link and the rig said, kept for the JSON as well

    def link_event(msg: str) -> None:
        link_events.append(msg)
        console.warn(msg)

    rig = open_rig(args, cyl, effects, rate=args.rate, paced=True, on_event=link_event)
    if not args.config:
        from ..files import BUILT_IN

        console.warn(BUILT_IN)
    return _run_session(args, cyl, options, rig, program, args.duration, args.record, 1.0 / args.rate,
                        pipelined=False, console=console, link_events=link_events)


def run_replay(args) -> int:
    from ..files import cylinder_for_runs, read_run
    from ..live import Console, ReplayRig

    speed = args.speed
    _check_outputs(args, None, [args.config, args.run])
    run = read_run(args.run, args.max_rows)
    cyl, which = cylinder_for_runs(args.config, [run])
    if run.n < 3:
        raise UsageError(f"{args.run}: a run needs at least 3 samples.")
    options = _online_options(args, cyl)  # refused before anything is said
    preflight_runs(cyl, [run])
    if which and not args.quiet:
        eprint(which)
    return _run_session(args, cyl, options, ReplayRig(run, speed), None, None, None, run.sample_period,
                        pipelined=speed == math.inf, console=Console(status=not args.quiet))


def _check_outputs(args, record: Path | None, inputs) -> None:
    """--record, --json and --rerun save FILE, checked before the session (files.check_outputs)."""
    mode, target = rerun_mode(args.rerun)
    check_paths({"--record": record, "--json": args.json, "--rerun save": target if mode == "save" else None},
                inputs=inputs)


def _online_options(args, cyl):
    from ..identify import OnlineOptions

    names = estimate_list(args.estimate, cyl)
    if args.update > args.window:
        raise UsageError(f"--update ({args.update:g} s) must not exceed --window ({args.window:g} s).")
    return OnlineOptions(window_s=args.window, update_s=args.update, memory_s=args.memory, estimate=names)


def _rerun_sink(args, cyl, window_s: float, near: str, say):
    """The Rerun view in its own process; `spawn` without a display saves next to `near`."""
    mode, target = rerun_mode(args.rerun)
    if mode == "off":
        return None
    from ..live.rerun_sink import RerunProcessSink
    from ..report.rerun import fallback_path

    return RerunProcessSink(mode, target, cyl, window_s, fallback=fallback_path(near) if mode == "spawn" else None,
                            say=say)


class _Signals:
    """SIGINT and SIGTERM while a session runs: the first asks the session to stop (it ends
    within a second: valve centred, files complete); before the session loop, and for a
    second signal, they interrupt at once."""

    NAMES = {signal.SIGINT: "interrupted (Ctrl-C)", signal.SIGTERM: "terminated (SIGTERM)"}

    def __init__(self, on_stop=None):
        self.reason: str | None = None
        self.in_loop = False
        self.on_stop = on_stop
        self._previous = {sig: signal.signal(sig, self._handle) for sig in self.NAMES}

    def _handle(self, signum, _frame) -> None:
        if self.reason is not None or not self.in_loop:
            raise KeyboardInterrupt
        self.reason = self.NAMES[signum]
        if self.on_stop:
            self.on_stop()

    def stop(self) -> str | None:
        return self.reason

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def _run_session(args, cyl, options, rig, program, duration, record: str | None, sample_period: float,
                 pipelined: bool, console, link_events: list[str] | None = None) -> int:
    from ..files import clean_json, cylinder_tag, write_json_atomic
    from ..live import ConsoleSink, SessionMonitor, assemble_session, conclude_session, run_session

    rr_sink = None

    def hurry() -> None:  # a stopped session gives its view a fraction of a second, not a minute
        if rr_sink is not None:
            rr_sink.hurry()

    signals = _Signals(hurry)
    estimator = None
    try:
        try:
            rr_sink = _rerun_sink(args, cyl, options.window_s, record or args.run, console.warn)
        except ValueError as e:
            raise UsageError(str(e)) from None

        def link_counters() -> dict:
            stats = rig.stats
            if stats is None:
                return {}
            return {"lost": stats.samples_lost, "corrupt": stats.frames_corrupt, "late": stats.commands_late}

        monitor = SessionMonitor()
        sinks = [s for s in (ConsoleSink(console, link_counters, monitor), rr_sink) if s is not None]
        if not args.quiet:
            console.say("preparing the model (compiled once, then cached) ...")
        parts = assemble_session(cyl, sample_period, options, live=args.command != "replay", pipelined=pipelined,
                                 viewer=rr_sink is not None)
        estimator = parts.estimator
        comments = [cylinder_tag(cyl), f"combined-reality {args.command}: {cyl.name}", f"config {cyl.source}",
                    f"started {time.strftime('%Y-%m-%d %H:%M:%S')}"]
        t_wall = time.perf_counter()
        signals.in_loop = True
        result = run_session(cyl, rig, estimator=estimator, program=program, duration=duration, record_to=record,
                             record_comments=comments, sinks=sinks, simulator=parts.simulator, on_event=console.warn,
                             give_up_s=args.give_up, expected_period=sample_period, stop=signals.stop,
                             realtime=parts.realtime, monitor=monitor, on_judgement=console.say)
    finally:
        signals.restore()
        if estimator is not None:
            estimator.close()
        if rr_sink is not None and rr_sink.proc.is_alive():
            rr_sink.hurry()
            rr_sink.close()
        console.close()
    wall = time.perf_counter() - t_wall
    c = result.counters
    summary = (f"{result.stop_reason}: {c['samples']} samples in {wall:.1f} s"
               + "".join(f", {c[k]} {label}" for k, label in (
                   ("samples_lost", "samples lost"), ("frames_corrupt", "frames corrupt"), ("gaps", "gaps"),
                   ("incomplete", "samples with a channel not measured"), ("invalid", "samples unusable"),
                   ("rig_overruns", "samples after a missed rig deadline"), ("commands_late", "commands late"),
                   ("host_overflow", "samples dropped by a full host queue"), ("reconnects", "reconnects"),
                   ("rig_errors", "rig errors")) if c.get(k)))
    console.say(summary)
    for line in console.summary():
        console.say(f"  {line}")
    if record:
        received = c.get("samples", 0) + c.get("invalid", 0) + c.get("host_overflow", 0)
        console.say(f"recorded {result.run.n} samples to {record}"
                    + ("" if "host_overflow" not in c else f" (the link received {received})"))
    end = conclude_session(result, options.estimate, cyl)
    for line in end.lines(result):
        print(line)
    if args.json:
        write_json_atomic(args.json, clean_json(result.document(options, wall, link_events or [], end.no_estimate)))
        console.say(f"wrote {args.json}")
    if estimator.error:
        return 1
    return end.status(result, replayed=args.command == "replay")
