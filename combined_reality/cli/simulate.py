"""`combined-reality simulate`: a run of the virtual rig, written as a run CSV."""
from __future__ import annotations

import time

from .. import options
from .common import EFFECT_HELP, check_paths, eprint, load_config, parse_effects, progress_printer, typed


def add_parser(sub) -> None:
    s = sub.add_parser("simulate", help="make a run on the virtual rig (closed-loop position control)",
                       description="Simulate a run on the virtual rig under closed-loop position control (steps, "
                                   "ramps, sines): the cylinder file's [friction] is the truth, unmodelled effects "
                                   "can be switched on, sensors add white noise. Writes a run CSV whose first "
                                   "comment names the cylinder.")
    s.add_argument("--config", required=True, help="cylinder TOML file (its friction is the truth)")
    s.add_argument("--duration", type=typed(options.positive_seconds, "--duration"), default=20.0,
                   help=f"seconds (default 20; at least {options.MIN_SAMPLES} samples, at most "
                        f"{options.MAX_SIMULATED_SAMPLES:.0e})")
    s.add_argument("--seed", type=typed(options.seed), default=1,
                   help=f"seed of the excitation and the noise, 0 to {options.SEED_MAX} (default 1)")
    s.add_argument("--rate", type=typed(options.sample_rate), default=1000.0,
                   help=f"sample rate in Hz, {options.RATE_MIN:g} to {options.RATE_MAX:g} (default 1000)")
    s.add_argument("--effect", action="append", metavar="NAME[:k=v,...]", help=f"switch on {EFFECT_HELP}")
    s.add_argument("--no-noise", action="store_true", help="noise-free sensors")
    s.add_argument("-o", "--output", required=True, help="run CSV to write")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    s.set_defaults(func=run)


def run(args) -> int:
    from ..files import cylinder_tag, write_run
    from ..simulation import simulate_run

    options.simulated_samples(args.duration, args.rate)
    check_paths({"-o": args.output}, inputs=[args.config])
    cyl = load_config(args.config)
    effects = parse_effects(args.effect)
    t0 = time.perf_counter()
    run_ = simulate_run(cyl, args.duration, args.seed, args.rate, effects, noise=not args.no_noise,
                        progress=progress_printer(args.quiet))
    truth = ", ".join(f"{n}={cyl.value(n):g}" for n in ("Fc", "Fv", "kp"))
    eff = "; ".join(f"{e.name}(" + ", ".join(f"{k}={v:g}" for k, v in zip(e.param_names(), e.values())) + ")"
                    for e in effects) or "none"
    write_run(args.output, run_, comments=[
        cylinder_tag(cyl),
        f"combined-reality virtual rig: cylinder {cyl.name!r} ({cyl.source}), seed {args.seed}, {args.rate:g} Hz",
        f"truth: {truth}; effects: {eff}; noise: {'off' if args.no_noise else 'on'}",
    ])
    if not args.quiet:
        eprint(f"wrote {args.output}: {run_.n} samples, {run_.duration:.3f} s, in {time.perf_counter() - t0:.2f} s")
    return 0
