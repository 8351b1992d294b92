"""`combined-reality procedure breakaway|sweep`: static friction tests on a rig (docs/procedures.md).

    combined-reality procedure sweep --serial /dev/ttyACM0 --config cyl.toml --record sweep.csv \\
        --out points.csv --json sweep.json

Exit status as for every subcommand: 0 success, 2 bad input (UsageError, one sentence),
1 the procedure failed (the rig never moved, went silent, ...), 130 interrupted.
"""
from __future__ import annotations

import math
import re
import signal
import threading
import time
from pathlib import Path

from .. import options
from .common import UsageError, check_paths, eprint, load_config, open_rig, parse_effects, typed

KINDS = ("breakaway", "sweep")
_DIRECTIONS = {"both": (1, -1), "extension": (1,), "retraction": (-1,)}
# option field -> command-line flag, so that the library's messages name what the user typed
_FLAGS = {"trials": "--trials", "force_rate": "--force-rate", "speeds": "--speeds", "v_min": "--vmin",
          "v_max": "--vmax", "attempts": "--attempts", "u_max": "--u-max", "margin": "--margin", "start": "--start"}


def add_parser(sub) -> None:
    p = sub.add_parser(
        "procedure", help="automated static friction tests on a rig: breakaway force, constant-speed sweep",
        description="Run a static friction test on a rig (live or virtual) and write the points a friction map "
                    "is fitted to. breakaway: the net force is raised slowly from rest until the piston moves, "
                    "--trials times per direction. sweep: strokes at --speeds constant speeds per direction under "
                    "closed-loop velocity control, one point (mean velocity, mean friction) per stroke. Every "
                    "sample is recorded as it arrives (--record); commands are bounded, soft stroke limits apply, "
                    "and the valve is centred at the end, on Ctrl-C and on any error.")
    p.add_argument("kind", choices=KINDS, help="breakaway or sweep")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--serial", metavar="PORT", help="a rig on a serial port (docs/protocol.md)")
    src.add_argument("--can", metavar="CHANNEL", help="a rig on CAN (hw/rig_can.dbc), via python-can")
    src.add_argument("--virtual", action="store_true",
                     help="the virtual rig in this process, as fast as the CPU allows (--realtime: at its clock)")
    p.add_argument("--interface", default="socketcan", help="python-can interface for --can (default socketcan)")
    p.add_argument("--realtime", action="store_true", help="with --virtual: run at the rig's clock")
    p.add_argument("--effect", action="append", metavar="SPEC",
                   help="with --virtual: an unmodelled effect as truth, e.g. stiction:Fs_excess=10,v_stribeck=0.01")
    p.add_argument("--seed", type=typed(options.seed), default=0,
                   help=f"with --virtual: seed of the sensor noise, 0 to {options.SEED_MAX} (default 0)")
    p.add_argument("--config", help="cylinder TOML (default: the built-in cylinder A)")
    p.add_argument("--trials", type=int, help="breakaway: trials per direction (default 15)")
    p.add_argument("--force-rate", type=float, metavar="N_PER_S",
                   help="breakaway: slope of the net-force ramp, N/s (default 20)")
    p.add_argument("--start", type=float, metavar="FRACTION",
                   help="breakaway: where each trial starts, fraction of the stroke (default 0.5)")
    p.add_argument("--speeds", type=int, help="sweep: target speeds per direction, log-spaced (default 8)")
    p.add_argument("--vmin", type=float, metavar="V", help="sweep: slowest target speed, m/s (default vmax / 20)")
    p.add_argument("--vmax", type=float, metavar="V",
                   help="sweep: fastest target speed, m/s (default: the working travel in 0.4 s, at most 0.5)")
    p.add_argument("--attempts", type=int, metavar="N",
                   help="sweep: strokes per target at most; one that gives no steady point (stick-slip, or ringing "
                        "on a busy host) is run again from its start (default 2)")
    p.add_argument("--directions", choices=tuple(_DIRECTIONS), default="both",
                   help="which directions to test: both (default), extension or retraction")
    p.add_argument("--u-max", type=float, default=0.8, help="command bound (default 0.8)")
    p.add_argument("--margin", type=float, default=0.1,
                   help="soft stroke limits: keep this fraction of the stroke from each end (default 0.1)")
    p.add_argument("--record", metavar="RUN.csv", help="run CSV written as samples arrive")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --record file")
    p.add_argument("--out", required=True, metavar="POINTS.csv",
                   help="points table for the friction map: header v,F,F_std,v_std,count,dp,pc,breakaway (SI, "
                        "signed: + extension); breakaway: one row per direction, marked breakaway = 1 so that the "
                        "map does not fit it as a sliding point")
    p.add_argument("--json", metavar="OUT.json", help="per-trial / per-speed details")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=run)


def run(args) -> int:
    from hw.realtime import HOST_PRIORITY
    from hw.rig import RigError

    from ..files import cylinder_tag
    from ..friction.procedures import ProcedureError, late_commands

    cyl = load_config(args.config)
    opts = _options(args, cyl)
    effects = parse_effects(args.effect)
    if (effects or args.realtime) and not args.virtual:
        raise UsageError(f"{'--effect' if effects else '--realtime'} applies to the virtual rig; it needs "
                         "--virtual.")
    _check_paths(args)
    rig = open_rig(args, cyl, effects, paced=args.realtime)
    if not args.config:
        from ..files import BUILT_IN

        eprint(BUILT_IN)
    where = f"serial {args.serial}" if args.serial else f"CAN {args.can} ({args.interface})" if args.can \
        else "virtual rig" + (f" with {', '.join(args.effect)}" if args.effect else "")
    comments = [cylinder_tag(cyl), f"combined-reality procedure {args.kind}: cylinder {cyl.name!r} ({cyl.source}), {where}",
                f"started {time.strftime('%Y-%m-%d %H:%M:%S')}"]
    progress = None if args.quiet else eprint
    t_wall = time.perf_counter()
    try:
        # a rig at its own clock is answered at real-time priority where the OS grants it (an
        # unpaced virtual rig waits for the host: that loop would never let go of the CPU)
        realtime = HOST_PRIORITY if not args.virtual or args.realtime else None
        result = _with_sigterm(lambda: _run_procedure(args.kind, rig, cyl, opts, args.record, comments, progress,
                                                      realtime))
    except (ProcedureError, RigError) as e:  # the procedure has centred the valve already
        _write_partial(args, cyl, e, comments, where, time.perf_counter() - t_wall, str(e))
        eprint(f"combined-reality procedure: {e}" + (f" (recorded so far: {args.record})" if args.record else "")
               + _partial_said(args, e))
        return 1
    except KeyboardInterrupt as e:
        _write_partial(args, cyl, e, comments, where, time.perf_counter() - t_wall, "interrupted")
        eprint("combined-reality procedure: interrupted: valve centred"
               + (f", recording {args.record} closed" if args.record else "") + _partial_said(args, e) + ".")
        return 130
    wall = time.perf_counter() - t_wall
    _write_outputs(args, cyl, result, comments, where, wall)
    print(_summary(args.kind, result))
    if args.kind == "sweep" and not result.table():
        late = late_commands(result.counters)
        busy = f"; {late}: the host is too busy for the velocity loop, run on a quieter one" if late else ""
        eprint(f"combined-reality procedure: no steady point: every stroke stuck, slipped or was too short, "
               f"{len(result.retried)} of them run again{busy} (see the lines above; try other --vmin/--vmax).")
        return 1
    return 0


# ------------------------------------------------------------------ pieces

def _options(args, cyl):
    from ..friction.procedures import BreakawayOptions, SafetyOptions, SweepOptions, target_speeds

    given = {f: getattr(args, f) for f in ("trials", "force_rate", "start", "speeds", "vmin", "vmax", "attempts")
             if getattr(args, f) is not None}
    other = {"breakaway": ("speeds", "vmin", "vmax", "attempts"), "sweep": ("trials", "force_rate", "start")}[args.kind]
    wrong = [f"--{f.replace('_', '-')}" for f in other if f in given]
    if wrong:
        raise UsageError(f"{', '.join(wrong)} {'does' if len(wrong) == 1 else 'do'} not apply to the {args.kind} "
                         f"procedure.")
    for name in ("force_rate", "start", "vmin", "vmax", "u_max", "margin"):
        v = getattr(args, name)
        if v is not None and not math.isfinite(v):
            raise UsageError(f"--{name.replace('_', '-')} must be a finite number, not {v}.")
    try:
        safety = SafetyOptions(u_max=args.u_max, margin=args.margin)
        directions = _DIRECTIONS[args.directions]
        if args.kind == "breakaway":
            kw = {k: v for k, v in (("trials", args.trials), ("force_rate", args.force_rate), ("start", args.start))
                  if v is not None}
            return BreakawayOptions(directions=directions, safety=safety, **kw)
        kw = {k: v for k, v in (("speeds", args.speeds), ("v_min", args.vmin), ("v_max", args.vmax),
                                ("attempts", args.attempts)) if v is not None}
        opts = SweepOptions(directions=directions, safety=safety, **kw)
        target_speeds(cyl, opts)  # checks --vmin against the default --vmax of this cylinder
        return opts
    except ValueError as e:  # the library checks the options; its messages name them as fields
        msg = re.sub(r"(?<![\w/.-])[a-z_]+(?![\w/.-])", lambda m: _FLAGS.get(m[0], m[0]), str(e))
        raise UsageError(f"{msg}.") from None


def _check_paths(args) -> None:
    check_paths({"--record": args.record, "--out": args.out, "--json": args.json}, inputs=[args.config])
    if args.record and Path(args.record).exists() and not args.overwrite:
        raise UsageError(f"--record {args.record} exists; a recording is never overwritten unless you pass "
                         "--overwrite.")


def _with_sigterm(fn):
    """Run fn with SIGTERM ending it like Ctrl-C (valve centred, files complete)."""
    if threading.current_thread() is not threading.main_thread():
        return fn()

    def _term(*_):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, _term)
    try:
        return fn()
    finally:
        signal.signal(signal.SIGTERM, previous)


def _run_procedure(kind, rig, cyl, opts, record, comments, progress, realtime):
    from ..friction.procedures import breakaway_test, speed_sweep

    fn = breakaway_test if kind == "breakaway" else speed_sweep
    try:
        return fn(rig, cyl, opts, record_to=record, record_comments=comments, progress=progress, realtime=realtime)
    finally:
        rig.stop()  # the procedure stops the rig itself; this covers a failure before it started (idempotent)


def _write_partial(args, cyl, e: BaseException, comments, where: str, wall: float, why: str) -> None:
    """The points measured before the procedure ended early, marked so in both files."""
    partial = getattr(e, "partial", None)
    if partial is not None:
        _write_outputs(args, cyl, partial, comments + [f"ended early, these are the points before: {why}"], where,
                       wall, error=why)


def _partial_said(args, e: BaseException) -> str:
    partial = getattr(e, "partial", None)
    if partial is None:
        return ""
    n = len(partial.table())
    return f"; the {n} point{'' if n == 1 else 's'} measured before are in {args.out}" + \
        (f" and {args.json}" if args.json else "")


def _write_outputs(args, cyl, result, comments, where: str, wall: float, error: str | None = None) -> None:
    from ..files import clean_json, write_json_atomic
    from ..friction.procedures import write_points

    if args.kind == "breakaway":
        what = [f"breakaway (static) friction, one row per direction, mean of {result.options.trials} trial(s): "
                "F = peak net pneumatic force (p1 A1 - p2 A2 - pa (A1 - A2) - weight) of a slow force ramp before "
                "motion was detected (N, + extension); v = velocity at that peak (creep or pre-sliding, m/s), its "
                "sign the direction"]
    else:
        n_unsteady = sum(not p.steady for p in result.points)
        what = ["v: mean velocity (m/s, + extension), F: mean friction (N, sign of v) over the steady part of a "
                "constant-speed stroke, from Newton's law with the measured pressures",
                f"{len(result.table())} steady points; {n_unsteady} unsteady (stick-slip) and {len(result.skipped)} "
                f"strokes without a point left out; {len(result.retried)} strokes without a steady point run again"]
    what.append("F_std, v_std: spreads (N, m/s); count: samples (sweep) or trials (breakaway) averaged; "
                "dp: mean |p1 - p2| (Pa); pc: counter pressure (Pa gauge: p2 - pa extending, p1 - pa retracting); "
                "breakaway: 1 a breakaway force, 0 a sliding point")
    details = f"details: {args.json}" if args.json else "details: run with --json"
    write_points(args.out, result.table(), comments + what + [details])
    out = {**result.to_json(), "config": str(cyl.source), "rig": where, "record": args.record, "out": args.out,
           "wall_s": round(wall, 3)}
    if error is not None:
        out["error"] = error
    if args.json:
        write_json_atomic(args.json, clean_json(out))
    if not args.quiet:
        c = result.counters
        eprint(f"{c['samples']} samples in {wall:.1f} s, longest host pause {1e3 * c['longest_host_pause_s']:.0f} ms"
                + (f"; recorded to {args.record}" if args.record else "") + f"; wrote {args.out}"
                + (f" and {args.json}" if args.json else ""))


def _summary(kind: str, result) -> str:
    from ..friction.procedures import DIRECTION_NAMES

    if kind == "breakaway":
        lines = [f"breakaway force, mean ± std of {result.options.trials} trial(s):"]
        lines += [f"  {DIRECTION_NAMES[s.direction]:10s} {s.mean:+9.3f} ± {s.std:.3f} N  (at {1e3 * s.v:+.2f} mm/s, "
                  f"|p1 - p2| = {s.dp / 1e5:.2f} bar)" for s in result.summary]
        return "\n".join(lines)
    lines = ["direction   target m/s   v m/s                 F N                  samples  steady"]
    for p in sorted(result.points, key=lambda p: p.v):
        lines.append(f"{DIRECTION_NAMES[p.direction]:10s}  {p.target:+9.4f}  {p.v:+9.4f} ± {p.v_std:<8.2g}  "
                     f"{p.F:+9.3f} ± {p.F_sem:<8.2g}  {p.n:7d}  {'yes' if p.steady else 'no'}")
    for s in result.skipped:
        lines.append(f"{DIRECTION_NAMES[s['direction']]:10s}  {s['target']:+9.4f}  no point: {s['reason']}")
    return "\n".join(lines)
