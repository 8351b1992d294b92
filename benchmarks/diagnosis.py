"""Benchmark of withheld effects: can the diagnosis name an effect the model lacks?

For every word of the vocabulary and every cylinder (two sizes by default), the virtual
rig makes a 20 s TRAIN and a 20 s VALID run (different excitations) with the effect
switched on at a random realistic strength (Effect.random: log-uniform from barely
visible to strong, random sign and shape); `diagnose` (which lacks the effect) names a
verdict. Clean runs (no effect) must give `none`.

Prints the confusion matrix, top-1 accuracy, the verdicts on clean runs, the median
shrink (of the true effect's candidate, on VALID) and the time per diagnosis, as an
absolute figure and as a ratio to a nominal identification of the same TRAIN run
measured in the same process (the machines are shared; the ratio travels better).

    python benchmarks/diagnosis.py                 # 10 effects x 2 cylinders x 1 draw + 4 clean
    python benchmarks/diagnosis.py --draws 2 --out bench_diag   # results per case, resumable
    python benchmarks/diagnosis.py --quick         # 5 effects on one cylinder, 10 s runs

Targets (issue 4): top-1 >= 90 %, `none` on every clean run, median shrink >= 60 %,
a 20 s + 20 s diagnosis in <= 60 s on a 2-core machine.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
import zlib
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from combined_reality.live import simulate_run  # noqa: E402
from combined_reality.diagnose import DiagnoseOptions, diagnose  # noqa: E402
from combined_reality.identify import IdentifyOptions, identify  # noqa: E402
from sim.cylinder import load_cylinder  # noqa: E402
from sim.effects import EFFECTS  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SHORT = {"stiction": "stict", "friction_asymmetry": "f_asym", "friction_position": "f_pos",
         "friction_dynamics": "f_dyn", "valve_deadzone": "v_dz", "valve_delay": "v_del", "leakage": "leak",
         "heat_transfer": "heat", "supply_droop": "droop"}
QUICK_EFFECTS = ("stiction", "mass", "valve_delay", "leakage", "heat_transfer")


def case_list(effects, cylinders, draws: int, clean: int) -> list[dict]:
    cases = []
    for cfg in cylinders:
        for d in range(draws):
            for name in effects:
                cases.append({"cylinder": cfg, "effect": name, "draw": d})
        for d in range(clean):
            cases.append({"cylinder": cfg, "effect": "none", "draw": d})
    return cases


def case_id(c: dict) -> str:
    return f"{c['cylinder']}__{c['effect']}__{c['draw']}"


def run_case(c: dict, duration: float, workers: int, reports: Path | None = None) -> dict:
    cyl = load_cylinder(ROOT / "configs" / f"{c['cylinder']}.toml")
    seed = zlib.crc32(case_id(c).encode()) % 100_000
    rng = np.random.default_rng(seed)
    effects = [] if c["effect"] == "none" else [EFFECTS[c["effect"]].random(rng, cyl)]
    train = simulate_run(cyl, duration, seed, effects=effects)
    valid = simulate_run(cyl, duration, seed + 1, effects=effects)
    t0 = time.perf_counter()
    identify(cyl, [train], IdentifyOptions())
    t_ident = time.perf_counter() - t0
    t0 = time.perf_counter()
    dg = diagnose(cyl, train, valid, DiagnoseOptions(workers=workers))
    t_diag = time.perf_counter() - t0
    res = dg.to_json()
    if reports is not None:
        from combined_reality.diagnose.report import write_report

        write_report(dg, reports / f"{case_id(c)}.html", png_dir=reports / case_id(c))
    true = next((r for r in res["ranking"] if r["effect"] == c["effect"]), None)
    verdict_row = next((r for r in res["ranking"] if r["effect"] == res["verdict"]), None)
    return {**c, "seed": seed, "truth": effects[0].as_dict() if effects else {},
            "verdict": res["verdict"], "ranking": [(r["effect"], r["shrink"], r["shrink_all"], r["z"],
                                                    r["significant"]) for r in res["ranking"]],
            "true_shrink": true["shrink"] if true else None,
            "true_params": true["params"] if true else None,
            "verdict_shrink": verdict_row["shrink"] if verdict_row else None,
            "baseline_rmse_x": res["baseline"]["rmse_x_validation"],
            "baseline_normalized": res["baseline"]["normalized_rms"],
            "pair": res["pair"]["effect"] if res["pair"] else None,
            "t_diagnose": t_diag, "t_identify": t_ident}


def report(results: list[dict], effects) -> None:
    labels = list(effects) + ["none"]
    verdicts = labels + sorted({r["verdict"] for r in results} - set(labels))
    width = max(len(x) for x in labels) + 1
    print("\nconfusion matrix (rows: true effect, columns: verdict)")
    short = [SHORT.get(v, v[:6]) for v in verdicts]
    print(" " * width + " ".join(f"{s:>6s}" for s in short))
    for lab in labels:
        rows = [r for r in results if r["effect"] == lab]
        if not rows:
            continue
        counts = [sum(r["verdict"] == v for r in rows) for v in verdicts]
        print(f"{lab:{width}s}" + " ".join(f"{n:6d}" if n else f"{'.':>6s}" for n in counts))
    eff_rows = [r for r in results if r["effect"] != "none"]
    clean = [r for r in results if r["effect"] == "none"]
    hits = sum(r["verdict"] == r["effect"] for r in eff_rows)
    shrinks = [r["true_shrink"] for r in eff_rows if r["true_shrink"] is not None and math.isfinite(r["true_shrink"])]
    t = np.array([r["t_diagnose"] for r in results])
    ratio = np.array([r["t_diagnose"] / r["t_identify"] for r in results])
    print(f"\ntop-1 accuracy: {hits}/{len(eff_rows)} = {hits / max(1, len(eff_rows)):.1%}   (target >= 90 %)")
    print(f"clean runs: {sum(r['verdict'] == 'none' for r in clean)}/{len(clean)} verdict none   "
          f"({', '.join(r['verdict'] for r in clean)})")
    if shrinks:
        print(f"median shrink of the true effect on VALID: {np.median(shrinks):.1%}   (target >= 60 %; "
              f"quartiles {np.percentile(shrinks, 25):.1%} .. {np.percentile(shrinks, 75):.1%})")
    print(f"time per diagnosis (20 s + 20 s unless --duration): median {np.median(t):.1f} s, max {t.max():.1f} s "
          f"(target <= 60 s); {np.median(ratio):.1f}x a nominal identification of TRAIN in the same process")
    misses = [r for r in eff_rows if r["verdict"] != r["effect"]]
    if misses:
        print("\nmisses:")
        for r in misses:
            top = ", ".join(f"{e} {s:.0%}/{sa:.0%} t={t_:.1f}{'*' if sig else ''}" for e, s, sa, t_, sig in r["ranking"][:3])
            truth = ", ".join(f"{k}={v:.3g}" for k, v in r["truth"].items())
            print(f"  {r['cylinder']} {r['effect']}({truth}) -> {r['verdict']}; {top}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="5 effects, one cylinder, 10 s runs, 1 clean run")
    ap.add_argument("--cylinders", default="cyl_a_32x100,ind4_norgren_50x400")
    ap.add_argument("--effects", default=",".join(EFFECTS))
    ap.add_argument("--draws", type=int, default=1, help="random strengths per effect and cylinder")
    ap.add_argument("--clean", type=int, default=2, help="clean runs per cylinder")
    ap.add_argument("--duration", type=float, default=20.0, help="seconds of TRAIN and of VALID")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--out", help="folder for per-case results (re-running skips cases already there)")
    ap.add_argument("--reports", help="folder for the HTML report (and its plots as PNG) of every case")
    args = ap.parse_args()
    effects = tuple(n for n in args.effects.split(",") if n)
    cylinders = args.cylinders.split(",")
    if args.quick:
        effects, cylinders, args.duration, args.clean = QUICK_EFFECTS, cylinders[:1], 10.0, 1
    cases = case_list(effects, cylinders, args.draws, args.clean)
    out = Path(args.out) if args.out else None
    for folder in (out, Path(args.reports) if args.reports else None):
        if folder:
            folder.mkdir(parents=True, exist_ok=True)
    results = []
    t_all = time.perf_counter()
    for i, c in enumerate(cases, 1):
        path = out / f"{case_id(c)}.json" if out else None
        if path and path.exists():
            results.append(json.loads(path.read_text()))
            continue
        r = run_case(c, args.duration, args.workers, Path(args.reports) if args.reports else None)
        results.append(r)
        if path:
            tmp = path.with_suffix(".tmp")
            tmp.write_text(json.dumps(r, indent=1))
            os.replace(tmp, path)
        mark = "ok " if r["verdict"] == c["effect"] else "MISS"
        print(f"[{i:3d}/{len(cases)}] {mark} {c['cylinder']:22s} {c['effect']:19s} -> {r['verdict']:19s} "
              f"true shrink {r['true_shrink'] if r['true_shrink'] is not None else float('nan'):6.1%}  "
              f"{r['t_diagnose']:5.1f} s", flush=True)
    print(f"\n{len(cases)} cases in {time.perf_counter() - t_all:.0f} s")
    report(results, effects)
    return 0


if __name__ == "__main__":
    sys.exit(main())
