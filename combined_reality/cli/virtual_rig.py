"""`combined-reality virtual-rig`: the virtual rig in real time behind the wire protocol, on a
pseudo-terminal (serial) or as an SLCAN adapter."""
from __future__ import annotations

import math
import re
import signal

from .. import options
from .common import UsageError, eprint, load_config, parse_effects, typed

# option field -> command-line flag, so that the library's messages name what the user typed
_FLAGS = {f: "--" + f.replace("_", "-") for f in ("rate", "jitter_us", "watchdog_ms", "drop", "corrupt",
                                                  "stall_at", "stall_for", "vanish_at", "vanish_for")}
_FLAGS["link_path"] = "--link"


def add_parser(sub) -> None:
    v = sub.add_parser("virtual-rig", help="serve the virtual rig in real time over a pseudo-terminal (serial or SLCAN)",
                       description="Run the virtual rig in real time behind the wire protocol of docs/protocol.md, "
                                   "on a pseudo-terminal that a host opens like a serial port (or an SLCAN CAN "
                                   "adapter). The first line of stdout is the pty path; status and fault messages "
                                   "go to stderr. Runs until SIGINT/SIGTERM or --duration. The cylinder file's "
                                   "[friction] is the truth. With --firmware the compiled rig firmware "
                                   "(hw/firmware) is the rig and this plant its sensors and valve.")
    v.add_argument("--config", help="cylinder TOML file (default: the built-in 32 mm x 100 mm cylinder)")
    kind = v.add_mutually_exclusive_group(required=True)
    kind.add_argument("--serial", action="store_true", help="serial protocol: COBS frames with CRC-16")
    kind.add_argument("--can", action="store_true", help="an SLCAN adapter with the rig on its bus (hw/rig_can.dbc)")
    v.add_argument("--rate", type=typed(options.sample_rate), default=1000.0,
                   help=f"sample rate in Hz, {options.RATE_MIN:g} to {options.RATE_MAX:g} (default 1000)")
    v.add_argument("--effect", action="append", metavar="NAME[:k=v,...]",
                   help="switch on an unmodelled effect in the plant (repeatable)")
    v.add_argument("--seed", type=typed(options.seed), default=1,
                   help=f"seed of the noise, jitter and faults, 0 to {options.SEED_MAX} (default 1)")
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
    v.add_argument("--firmware", metavar="PATH",
                   help="with --serial: the host build of the rig firmware (make -C hw/firmware host -> "
                        "hw/firmware/build/rig-host) is the rig's controller: it owns the pty and runs the protocol, "
                        "watchdog, command bounds and soft limits in its own C code, with this plant as its sensors "
                        "and valve (docs/firmware.md); the injected faults do not apply")
    v.set_defaults(func=run)

# options that inject faults or shape the Python rig's link: the firmware has its own
_PYTHON_RIG_ONLY = (("drop", 0.0), ("corrupt", 0.0), ("stall_at", None), ("stall_for", None), ("vanish_at", None),
                    ("vanish_for", None), ("link", None), ("jitter_us", 20.0))


def run(args) -> int:
    from hw.links import FaultSpec
    from hw.rig_server import RigServer, ServerOptions

    cyl = load_config(args.config)
    effects = parse_effects(args.effect)
    if args.duration is not None and not (args.duration >= 0 and math.isfinite(args.duration)):
        raise UsageError(f"--duration must be a non-negative number of seconds, not {args.duration}.")
    if args.firmware is not None:
        return _run_firmware(args, cyl, effects)
    try:  # the library checks the options (before it builds the plant); its messages name them as fields
        faults = FaultSpec(drop=args.drop, corrupt=args.corrupt, stall_at=args.stall_at, stall_for=args.stall_for,
                           vanish_at=args.vanish_at, vanish_for=args.vanish_for, seed=args.seed)
        options = ServerOptions(rate=args.rate, jitter_us=args.jitter_us, watchdog_ms=args.watchdog_ms)
        server = RigServer(cyl, effects, transport="slcan" if args.can else "serial", options=options, faults=faults,
                           seed=args.seed, noise=not args.no_noise, link_path=args.link, log=eprint,
                           on_path=lambda path: print(path, flush=True), progress=eprint)
    except ValueError as e:  # said with the options' names
        raise _with_flags(e) from None
    print(server.path, flush=True)  # the first line of stdout: what the host opens
    truth = ", ".join(f"{n}={cyl.value(n):g}" for n in ("Fc", "Fv", "kp"))
    eprint(f"virtual rig: '{cyl.name}' ({truth}) at {args.rate:g} Hz, "
           f"{'SLCAN adapter' if args.can else 'serial protocol'} on {server.path}"
           + (f" (link {args.link})" if args.link else "") + "; SIGINT or SIGTERM ends it")
    stats = _run_until_signalled(server, args.duration)
    eprint(f"virtual rig: stopped after {stats.wall_s:.1f} s: {stats.summary()}")
    return 1 if server.failure else 0


def _with_flags(e: ValueError) -> UsageError:
    """A library's message about its option fields, said with the command line's flags."""
    msg = re.sub(r"(?<![\w/.-])[a-z_]+(?![\w/.-])", lambda m: _FLAGS.get(m[0], m[0]), str(e))
    return UsageError(f"{msg}.")


def _run_until_signalled(server, duration: float | None):
    """server.run(duration), with SIGINT and SIGTERM asking it to stop; its statistics."""
    previous = {sig: signal.signal(sig, lambda *_: server.stop()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        return server.run(duration)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _run_firmware(args, cyl, effects) -> int:
    """The plant beside the host-built firmware, which serves the pty."""
    from hw.firmware_link import FirmwareRig
    from hw.rig import RigError

    if args.can:
        raise UsageError("--firmware speaks the serial protocol; use it with --serial, not --can.")
    for name, default in _PYTHON_RIG_ONLY:
        if getattr(args, name) != default:
            flag = _FLAGS.get(name, "--" + name.replace("_", "-"))
            raise UsageError(f"{flag} applies to the Python rig only; with --firmware the link, its timing and "
                             "its faults are the firmware's own.")
    try:
        rig = FirmwareRig(args.firmware, cyl, effects, rate=args.rate, watchdog_ms=args.watchdog_ms, seed=args.seed,
                          noise=not args.no_noise, log=eprint, progress=eprint)
    except ValueError as e:  # said with the options' names
        raise _with_flags(e) from None
    except RigError as e:
        raise UsageError(f"--firmware {args.firmware}: {e}.") from None
    print(rig.path, flush=True)  # the first line of stdout: what the host opens
    truth = ", ".join(f"{n}={cyl.value(n):g}" for n in ("Fc", "Fv", "kp"))
    eprint(f"virtual rig: '{cyl.name}' ({truth}) beside the firmware {args.firmware} at {args.rate:g} Hz, serial "
           f"protocol on {rig.path}; SIGINT or SIGTERM ends it")
    stats = _run_until_signalled(rig, args.duration)
    eprint(f"virtual rig: stopped after {stats.wall_s:.1f} s: {stats.summary()}"
           + (f"; {rig.failure}" if rig.failure else ""))
    return 1 if rig.failure else 0
