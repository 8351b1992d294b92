"""`combined-reality demo`: the whole method on the virtual rig, identified vs true."""
from __future__ import annotations

from pathlib import Path

from .. import options
from .common import check_paths, eprint, load_config, progress_printer, typed
from .identify import format_table


def add_parser(sub) -> None:
    d = sub.add_parser("demo", help="simulate a run on the virtual rig and identify it (identified vs true)",
                       description="Try the method without hardware: simulate a run of the cylinder on the virtual "
                                   "rig (its friction is the truth), write it as a run CSV, identify Fc, Fv, kp from "
                                   "a deliberately poor start by multiple shooting, and print the identified values "
                                   "next to the true ones.")
    d.add_argument("--config", help="cylinder TOML file (default: the built-in 32 mm x 100 mm cylinder)")
    d.add_argument("--duration", type=typed(options.positive_seconds, "--duration"), default=20.0,
                   help="seconds of the simulated run (default 20)")
    d.add_argument("--seed", type=typed(options.seed), default=1,
                   help=f"seed of the excitation and the sensor noise, 0 to {options.SEED_MAX} (default 1)")
    d.add_argument("--out", default="combined_reality_demo",
                   help="folder for the run and the result (default combined_reality_demo; created in a folder "
                        "that exists)")
    d.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    d.set_defaults(func=run)


def run(args) -> int:
    from ..files import clean_json, cylinder_tag, read_run, write_json_atomic, write_run
    from ..identify import IdentifyOptions, identify
    from ..simulation import simulate_run

    options.simulated_samples(args.duration, 1000.0)
    out = Path(args.out)
    check_paths({"the run": out / "demo_run.csv", "the result": out / "demo_identify.json"} if out.is_dir() else {},
                inputs=[args.config], folders={"--out": out})
    cyl = load_config(args.config)
    out.mkdir(exist_ok=True)
    prog = progress_printer(args.quiet)
    eprint(f"1/2 simulating a {args.duration:g} s run of '{cyl.name}' on the virtual rig (seed {args.seed}) ...")
    run_ = simulate_run(cyl, args.duration, args.seed, progress=prog)
    run_path = out / "demo_run.csv"
    write_run(run_path, run_, comments=[cylinder_tag(cyl), f"combined-reality demo: {cyl.name}, seed {args.seed}"])
    run_ = read_run(run_path)
    start = cyl.with_values({"Fc": cyl.friction.Fc * 0.4, "Fv": cyl.friction.Fv * 3.0 + 10.0,
                             "kp": cyl.friction.kp * 0.2})
    eprint(f"2/2 identifying Fc, Fv, kp by multiple shooting from a poor start "
           f"(Fc={start.friction.Fc:.3g}, Fv={start.friction.Fv:.3g}, kp={start.friction.kp:.3g}) ...")
    result = identify(start, [run_], IdentifyOptions(prefit=False), progress=prog)
    write_json_atomic(out / "demo_identify.json", clean_json(result.to_json()))
    print(f"\nIdentified vs true friction of '{cyl.name}' ({run_path}, {run_.duration:.1f} s at "
          f"{1 / run_.sample_period:.0f} Hz):")
    print(format_table(result, truth=cyl))
    print(f"\nwrote {run_path} and {out / 'demo_identify.json'}")
    return 0 if result.solver["status"] == "converged" else 1
