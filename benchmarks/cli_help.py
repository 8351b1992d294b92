"""How fast is `--help`, against starting Python itself?

    python benchmarks/cli_help.py [--repeat N]

Each help (`combined-reality --help` and every subcommand's `--help`) runs as its own process,
warm (the bytecode written by a first run), N times; the figure is the median wall time and
its ratio to the median of `python -c pass` measured in the same run, beside the target of
0.3 s warm. tests/test_architecture.py guards what makes it fast: help imports neither the
numerics nor the application.

It is a report: it exits 0 whatever the figures are (non-zero only on a crash).
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TARGET_S = 0.3


def wall(argv: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True, cwd=ROOT)
    return time.perf_counter() - t0


def median_wall(argv: list[str], repeat: int) -> float:
    wall(argv)  # bytecode cache written
    return statistics.median(wall(argv) for _ in range(repeat))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=7, help="runs per command (default 7)")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    from combined_reality.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    run = [sys.executable, "-c", "import sys; from combined_reality.cli import main; sys.exit(main(sys.argv[1:]))"]
    base = median_wall([sys.executable, "-c", "pass"], args.repeat)
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}")
    print(f"python -c pass: {1e3 * base:.0f} ms (median of {args.repeat})\n")
    print(f"{'command':42s} {'median':>8s} {'/ pass':>7s}  target {TARGET_S:g} s")
    worst = 0.0
    for name in ["", *sub.choices]:
        t = median_wall([*run, *([name] if name else []), "--help"], args.repeat)
        worst = max(worst, t)
        label = f"combined-reality {name} --help".replace("  ", " ")
        print(f"{label:42s} {1e3 * t:6.0f} ms {t / base:6.1f}x  {'met' if t <= TARGET_S else 'MISSED'}")
    print(f"\nslowest: {1e3 * worst:.0f} ms ({worst / base:.1f} x python -c pass); load average at the end "
          f"{os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
