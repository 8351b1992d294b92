"""Is the online estimate's standard deviation honest? Coverage over many seeds.

    python benchmarks/online_coverage.py [--seeds 20] [--duration 20] [--drop 0.01]

Each seed is a run of the virtual rig (closed-loop position control; a different program,
noise and, with --drop, lost samples per seed) streamed through the moving-horizon
estimator as a live session feeds it (blocks of 20 samples, an update whenever one is due,
the rest taken in at the end), from a start 30 % off the truth. For the final estimate of
every run it prints (estimate - truth) / reported std per parameter; an honest std puts
the truth within 3 std in >= 90 % of the runs (and the RMS of these z near 1). Runs with and
without lost samples are reported separately (`--drop 0` for the second set only).

It is a report: it exits 0 whatever the figures are (non-zero only on a crash).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from combined_reality.identify import MovingHorizonEstimator, OnlineOptions
from combined_reality.simulation import simulate_run
from sim.cylinder import load_cylinder

CFG = Path(__file__).resolve().parents[1] / "configs" / "cyl_a_32x100.toml"


def final_estimate(cyl, run, options: OnlineOptions = OnlineOptions(), block: int = 20):
    """The estimator fed like a live session; its last estimate."""
    start = cyl.with_values({"Fc": 1.3 * cyl.friction.Fc, "Fv": 0.7 * cyl.friction.Fv, "kp": 1.3 * cyl.friction.kp})
    mhe = MovingHorizonEstimator(start, run.sample_period, options)
    last = None
    for k in range(0, run.n, block):
        s = slice(k, k + block)
        mhe.add(run.t[s], run.u[s], run.x[s], run.p1[s], run.p2[s])
        while mhe.ready():
            last = mhe.update()
    mhe.flush()
    while mhe.ready():
        last = mhe.update()
    return last


def coverage(cyl, seeds, duration: float, drop: float) -> np.ndarray:
    zs = []
    for seed in seeds:
        t0 = time.perf_counter()
        run = simulate_run(cyl, duration, seed=seed, drop=drop)
        e = final_estimate(cyl, run)
        z = [(e.values[n] - cyl.value(n)) / e.std[n] for n in ("Fc", "Fv", "kp")]
        zs.append(z)
        print(f"  seed {seed:3d}: z = " + "  ".join(f"{n} {v:+5.2f}" for n, v in zip(("Fc", "Fv", "kp"), z))
              + f"   (window sigma {e.sigma:.3f}, {time.perf_counter() - t0:.1f} s)", flush=True)
    return np.array(zs)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--drop", type=float, default=0.01, help="share of samples lost on the link (0: none)")
    args = ap.parse_args()
    cyl = load_cylinder(CFG)
    seeds = range(200, 200 + args.seeds)
    for drop in sorted({0.0, args.drop}, reverse=True):
        print(f"{args.seeds} runs of {args.duration:g} s, {100 * drop:g} % of the samples lost:")
        z = coverage(cyl, seeds, args.duration, drop)
        inside = (np.abs(z) <= 3).mean(axis=0)
        rms = np.sqrt((z ** 2).mean(axis=0))
        print("  truth within 3 reported std: " + ", ".join(f"{n} {100 * c:.0f} %" for n, c in
                                                             zip(("Fc", "Fv", "kp"), inside))
              + " (target >= 90 %); RMS of z: " + ", ".join(f"{n} {r:.2f}" for n, r in zip(("Fc", "Fv", "kp"), rms)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
