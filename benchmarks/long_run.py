"""Long recordings: time and peak memory of identify (and replay, calibrate) against the
length of the run.

    python benchmarks/long_run.py [--durations 60 600 3600] [--cache DIR] [--baseline CHECKOUT]
                                  [--cli] [--replay 60 600] [--calibrate 60 600] [--gaps 1]

Every figure comes from a fresh process: its wall time, its CPU time (user + system, all
threads: less at the mercy of other work on a shared machine than the wall time) and its peak
resident memory (the kernel's maximum RSS of that child, os.wait4), so nothing of one case
stays in another.

For each duration (at 1 kHz, cylinder A, the virtual rig under closed-loop position control):

1. `combined-reality simulate --duration D` writes the run CSV (measured: the simulate path);
2. the CSV is read once by read_run and kept as a .npz beside it (measured: reading alone);
3. `identify` with default options on that run, loaded from the .npz (measured: the fit alone,
   the headline figures), with its estimates against the truth in units of their std;
4. with --cli, `combined-reality identify` on the CSV (reading and fit, as a user runs it).

The runs are cached in --cache (default $TMPDIR/combined_reality_long_run), keyed by
duration and seed. --baseline runs step 3 also with another checkout's code (e.g. the code
before this benchmark, for the ratio of time and memory on the short runs; --baseline-max
caps the durations it is run for, and with --calibrate-baseline the calibrate rows too).
--replay and --calibrate measure `combined-reality replay --speed max` and `combined-reality
calibrate` (every calibrated quantity, on the CSV, as a user runs them) on runs of those
durations: wall, CPU and peak RSS, the peak's growth per sample beyond the shortest run's (the
run's own arrays, read as floats, are 40 bytes a sample) and the estimates against the truth (the
cylinder file the run was simulated with). `--durations` with no value skips the identify rows.
--gaps P makes the runs lossy before identify: one sample lost in every P seconds (at a seeded
place within each), so that an hour with --gaps 1 is 3600 gap-free pieces, each identified from
its own initial state.

The targets: peak memory of identify at 3600 s <= 1 GB, time growing no worse than linearly
(CPU time / duration relative to the shortest case <= 1, allowing for load), and the estimates of
the longest run within their std of the truth (the estimates corrected for the identifier's own
discretisation error, identify.discretisation; the error without that correction is printed too).
calibrate and replay: peak memory growing with the run by no more than its data (a few arrays of
its length), time no worse than linearly.
It is a report: it exits 0 whatever the figures are (non-zero only on a crash).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CFG = REPO / "configs" / "cyl_a_32x100.toml"
TARGET_PEAK_MB = 1000.0  # identify of the longest run, at most
NAMES = ("Fc", "Fv", "kp")


def measured(cmd: list[str], env: dict | None = None, cwd: Path | None = None) -> dict:
    """Run `cmd` as a child: its wall time, peak RSS (MB), exit code and output."""
    t0 = time.perf_counter()
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        proc = subprocess.Popen(cmd, stdout=out, stderr=err, env=env, cwd=cwd)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        wall = time.perf_counter() - t0
        out.seek(0)
        err.seek(0)
        return {"wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime, "peak_mb": usage.ru_maxrss / 1024.0,
                "rc": proc.returncode,
                "stdout": out.read().decode(errors="replace"), "stderr": err.read().decode(errors="replace")}


# ------------------------------------------------------------------ the children

def child_read(csv: str, npz: str) -> None:
    """Read the run CSV as the tool does; keep it as .npz for the fits."""
    import numpy as np

    from combined_reality.files import read_run

    run = read_run(csv)
    np.savez(npz, t=run.t, u=run.u, x=run.x, p1=run.p1, p2=run.p2)
    print(json.dumps({"n": run.n}))


def child_identify(npz: str) -> None:
    """identify with default options on the run kept in `npz`; the result as JSON on stdout."""
    import numpy as np

    from combined_reality.files import Run
    from combined_reality.identify import identify
    from sim.cylinder import load_cylinder

    cyl = load_cylinder(CFG)
    with np.load(npz) as d:
        run = Run(t=d["t"], u=d["u"], x=d["x"], p1=d["p1"], p2=d["p2"])
    t0 = time.perf_counter()
    res = identify(cyl, [run])
    print(json.dumps({"fit_s": time.perf_counter() - t0, "status": res.solver["status"], "pieces": len(res.fit_per_run),
                      "iterations": res.solver["iterations"], "residual_sigma": res.solver["residual_sigma"],
                      "n_intervals": res.solver["n_intervals"], "discretisation": res.solver.get("discretisation"),
                      "params": {n: [e.value, e.std] for n, e in res.params.items()},
                      "truth": {n: cyl.value(n) for n in NAMES}}))


# ------------------------------------------------------------------ the report

def cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "combined_reality", *args]


def ensure_run(cache: Path, duration: float, seed: int) -> tuple[Path, Path, dict, dict]:
    """(csv, npz, simulate figures, read figures); figures are {} where the cache had them."""
    stem = cache / f"run_{duration:g}s_seed{seed}"
    csv, npz, figs = stem.with_suffix(".csv"), stem.with_suffix(".npz"), stem.with_suffix(".json")
    known = json.loads(figs.read_text()) if figs.exists() else {}
    if not csv.exists():
        sim = measured(cli("simulate", "--config", str(CFG), "--duration", f"{duration:g}", "--seed", str(seed),
                           "-o", str(csv), "-q"), cwd=REPO)
        if sim["rc"] != 0:
            raise SystemExit(f"simulate failed: {sim['stderr']}")
        known["simulate"] = {k: sim[k] for k in ("wall_s", "cpu_s", "peak_mb")}
    if not npz.exists():
        rd = measured([sys.executable, __file__, "--child-read", str(csv), str(npz)], cwd=REPO)
        if rd["rc"] != 0:
            raise SystemExit(f"reading failed: {rd['stderr']}")
        known["read"] = {k: rd[k] for k in ("wall_s", "cpu_s", "peak_mb")}
    figs.write_text(json.dumps(known))
    return csv, npz, known.get("simulate", {}), known.get("read", {})


def lossy(npz: Path, period: float, seed: int) -> Path:
    """The run of `npz` losing one sample in every `period` seconds (cached beside it)."""
    import numpy as np

    out = npz.with_name(f"{npz.stem}_gaps{period:g}.npz")
    if not out.exists():
        with np.load(npz) as d:
            cols = {k: d[k] for k in ("t", "u", "x", "p1", "p2")}
        t = cols["t"]
        n = int((t[-1] - t[0]) // period)
        rng = np.random.default_rng(seed)
        lost = np.searchsorted(t, t[0] + (np.arange(n) + rng.uniform(0.1, 0.9, n)) * period)
        keep = np.ones(len(t), bool)
        keep[lost] = False
        np.savez(out, **{k: v[keep] for k, v in cols.items()})
    return out


def identify_case(npz: Path, checkout: Path | None = None) -> dict:
    env = dict(os.environ)
    if checkout is not None:  # that checkout's package first on the path
        env["PYTHONPATH"] = str(checkout) + os.pathsep + env.get("PYTHONPATH", "")
    m = measured([sys.executable, str(Path(__file__).resolve()), "--child-identify", str(npz)], env=env,
                 cwd=checkout or REPO)
    if m["rc"] != 0:
        return {**m, "error": m["stderr"].strip().splitlines()[-1:] or ["?"]}
    return {**m, **json.loads(m["stdout"].strip().splitlines()[-1])}


SHOWN = ("Fc", "Fv", "kp", "mass", "critical_ratio", "dead_volume_cap", "dead_volume_rod")  # calibrate's table


def cli_case(kind: str, csv: Path, checkout: Path | None = None) -> dict:
    """`combined-reality calibrate` or `replay --speed max` on the run CSV, with its JSON: the
    figures, the status and the estimates as {name: [value, std, truth]}."""
    env = dict(os.environ)
    if checkout is not None:
        env["PYTHONPATH"] = str(checkout) + os.pathsep + env.get("PYTHONPATH", "")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out.json"
        args = ("--speed", "max") if kind == "replay" else ()
        m = measured(cli(kind, *args, "--config", str(CFG), "-q", "--json", str(out), str(csv)), env=env,
                     cwd=checkout or REPO)
        doc = json.loads(out.read_text()) if out.exists() else None
    if doc is None:  # exit 1 with the document written: finished, said why (status, sigma)
        return {**m, "error": m["stderr"].strip().splitlines()[-1:] or ["?"]}
    from sim.cylinder import load_cylinder

    cyl = load_cylinder(CFG)  # the truth of the simulated run
    solver = doc["solver"]
    return {**m, "status": solver["status"], "residual_sigma": solver.get("residual_sigma", doc["fit"].get("sigma")),
            "params": {n: [d["value"], d["std"], cyl.value(n)] for n, d in doc["params"].items()},
            "stages": [[s["stage"], s["iterations"], s["wall_s"], s.get("data_s")] for s in solver.get("stages", ())],
            "start_share": solver.get("start_share")}


def print_cli_rows(kind: str, cases: list[tuple[float, dict]]) -> None:
    """The table of `kind` against the run's length: figures, ratios to the shortest, estimates."""
    ok = [(d, m) for d, m in cases if "error" not in m]
    what = ("every calibrated quantity, the command line on the CSV" if kind == "calibrate"
            else "--speed max, the command line on the CSV")
    print(f"\n{kind} ({what}) of runs at 1 kHz, each in a fresh process")
    print(f"{'duration':>9} {'samples':>9} {'wall s':>8} {'cpu s':>8} {'cpu/s':>7} {'vs first':>9} {'peak MB':>8} "
          f"{'vs first':>9} {'B/sample':>9} {'status':>14} {'sigma':>6}  estimates (truth; error in std)")
    for d, m in cases:
        if "error" in m:
            print(f"{d:>9g} failed (exit {m['rc']}): {m['error'][0]}  (peak {m['peak_mb']:.0f} MB)")
            continue
        d0, m0 = ok[0]
        per = m["cpu_s"] / d
        grown = ((m["peak_mb"] - m0["peak_mb"]) * 2**20 / ((d - d0) * 1000)) if d > d0 else float("nan")
        names = [n for n in (SHOWN if kind == "calibrate" else NAMES) if n in m["params"]]
        est = "  ".join(f"{n} {v:.5g}+-{s:.2g} ({t:.4g}; {(v - t) / s:+.2f})" for n, (v, s, t) in
                        ((n, m["params"][n]) for n in names))
        worst = max((abs(v - t) / s for v, s, t in m["params"].values() if s > 0), default=float("nan"))
        sigma = m["residual_sigma"] if m["residual_sigma"] is not None else float("nan")
        print(f"{d:>9g} {int(d * 1000):>9d} {m['wall_s']:>8.1f} {m['cpu_s']:>8.1f} {per:>7.3f} "
              f"{per / (m0['cpu_s'] / d0):>9.2f} {m['peak_mb']:>8.0f} {m['peak_mb'] / m0['peak_mb']:>9.2f} "
              f"{grown:>9.0f} {m['status']:>14} {sigma:>6.3f}  {est}  (all {len(m['params'])}: within {worst:.2f} std)")
    staged = [(d, m) for d, m in ok if m.get("stages")]
    if staged:
        print("its stages (iterations, wall s; the data they saw where the stages started from a share of it):")
        for d, m in staged:
            share = m.get("start_share")
            print(f"{d:>9g} s" + (f" (stages from {share['seconds']:g} s of {share['of']:g} s)" if share else "") + ": "
                  + "; ".join(f"{name} {it} it {w:.0f} s" + (f" [{ds:g} s]" if ds is not None else "")
                              for name, it, w, ds in m["stages"]))
    if len(ok) > 1:
        (d0, m0), (d1, m1) = ok[0], ok[-1]
        print(f"longest ({d1:g} s) against shortest ({d0:g} s): peak {m1['peak_mb']:.0f} / {m0['peak_mb']:.0f} MB "
              f"(+{(m1['peak_mb'] - m0['peak_mb']) * 2**20 / ((d1 - d0) * 1000):.0f} bytes per sample of data more; "
              f"the run's columns alone are 40), CPU time per second of data "
              f"{m1['cpu_s'] / d1 / (m0['cpu_s'] / d0):.2f} x the shortest's")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--durations", type=float, nargs="*", default=[60.0, 600.0, 3600.0],
                    help="durations to identify (s); none: no identify rows")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "combined_reality_long_run")
    ap.add_argument("--baseline", type=Path, help="another checkout whose identify is measured beside")
    ap.add_argument("--baseline-max", type=float, default=60.0, help="longest run given to --baseline (s)")
    ap.add_argument("--cli", action="store_true", help="also `combined-reality identify` on the CSV")
    ap.add_argument("--replay", type=float, nargs="*", default=[], help="durations to replay (s)")
    ap.add_argument("--calibrate", type=float, nargs="*", default=[], help="durations to calibrate (s)")
    ap.add_argument("--gaps", type=float, help="identify the runs losing one sample in every GAPS seconds")
    ap.add_argument("--calibrate-baseline", action="store_true",
                    help="--baseline's checkout calibrates too (durations up to --baseline-max)")
    ap.add_argument("--child-read", nargs=2, help=argparse.SUPPRESS)
    ap.add_argument("--child-identify", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child_read:
        child_read(*args.child_read)
        return 0
    if args.child_identify:
        child_identify(args.child_identify)
        return 0

    args.cache.mkdir(parents=True, exist_ok=True)
    durations = sorted(args.durations)
    rows = []
    for d in durations:
        csv, npz, sim, rd = ensure_run(args.cache, d, args.seed)
        if args.gaps:
            npz = lossy(npz, args.gaps, args.seed)
        print(f"[{d:g} s] run ready ({csv.stat().st_size / 2**20:.0f} MB CSV)", flush=True)
        row = {"duration": d, "simulate": sim, "read": rd, "identify": identify_case(npz)}
        print(f"[{d:g} s] identify: {row['identify']['wall_s']:.1f} s, {row['identify']['peak_mb']:.0f} MB", flush=True)
        if args.baseline and d <= args.baseline_max:
            row["baseline"] = identify_case(npz, args.baseline)
        if args.cli:
            c = measured(cli("identify", "--config", str(CFG), str(csv)), cwd=REPO)
            row["cli"] = {k: c[k] for k in ("wall_s", "cpu_s", "peak_mb", "rc")}
        rows.append(row)
    extra: dict[str, list[tuple[float, dict]]] = {"replay": [], "calibrate": [], "calibrate, baseline": []}
    for kind, lengths in (("replay", args.replay), ("calibrate", args.calibrate)):
        for d in sorted(lengths):
            csv, *_ = ensure_run(args.cache, d, args.seed)
            m = cli_case(kind, csv)
            extra[kind].append((d, m))
            print(f"[{d:g} s] {kind}: {m['wall_s']:.1f} s, {m['peak_mb']:.0f} MB, exit {m['rc']}", flush=True)
            if kind == "calibrate" and args.baseline and args.calibrate_baseline and d <= args.baseline_max:
                b = cli_case(kind, csv, args.baseline)
                extra["calibrate, baseline"].append((d, b))
                print(f"[{d:g} s] calibrate with {args.baseline}: {b['wall_s']:.1f} s, {b['peak_mb']:.0f} MB", flush=True)
    if rows:
        print_identify(rows, args.baseline, args.gaps)
    for kind, cases in extra.items():
        if cases:
            print_cli_rows(kind, cases)
    print("\nthe other steps (fresh processes; {} where the run came from the cache):")
    for r in rows:
        parts = []
        for k in ("simulate", "read", "cli"):
            if r.get(k):
                parts.append(f"{k} {r[k]['wall_s']:.1f} s (cpu {r[k].get('cpu_s', float('nan')):.1f} s) {r[k]['peak_mb']:.0f} MB")
        print(f"{r['duration']:>9g} s: " + ("; ".join(parts) or "{}"))
    return 0


def print_identify(rows: list[dict], baseline: Path | None, gaps: float | None = None) -> None:
    """The identify table, the discretisation term, the longest run against the targets and the baseline."""
    print()
    print("identify (default options) of runs at 1 kHz, each in a fresh process; the run loaded from .npz"
          + (f", one sample lost in every {gaps:g} s (pieces: gap-free pieces of 60 s at most)" if gaps else ""))
    first = rows[0]["identify"]
    print(f"{'duration':>9} {'samples':>9} {'wall s':>8} {'cpu s':>8} {'cpu/s':>7} {'vs first':>9} {'peak MB':>8} "
          f"{'iter':>5} {'pieces':>6} {'status':>10} {'sigma':>6}  estimates (truth; error in std)")
    for r in rows:
        i = r["identify"]
        if "error" in i:
            print(f"{r['duration']:>9g} failed: {i['error'][0]}  (peak {i['peak_mb']:.0f} MB)")
            continue
        per = i["cpu_s"] / r["duration"]
        rel = per / (first["cpu_s"] / rows[0]["duration"])
        est = "  ".join(f"{n} {v:.5g}+-{s:.2g} ({i['truth'][n]:.4g}; {(v - i['truth'][n]) / s:+.2f})"
                        for n, (v, s) in i["params"].items())
        print(f"{r['duration']:>9g} {int(r['duration'] * 1000):>9d} {i['wall_s']:>8.1f} {i['cpu_s']:>8.1f} {per:>7.3f} {rel:>9.2f} "
              f"{i['peak_mb']:>8.0f} {i['iterations']:>5d} {i.get('pieces', 0):>6d} {i['status']:>10} "
              f"{i['residual_sigma']:>6.3f}  {est}")
    print("\nthe discretisation term (identify.discretisation): the estimates' shift towards a 20 x finer "
          "integration, applied to them; the error of the estimate without it in units of the statistical std")
    for r in rows:
        i, term = r["identify"], r["identify"].get("discretisation")
        if "error" in i or not term:
            continue
        parts = []
        for n, (v, s) in i["params"].items():
            stat = max(s * s - term["std"][n] ** 2, 0.0) ** 0.5
            before = v - term["shift"][n] - i["truth"][n]
            parts.append(f"{n} {term['shift'][n]:+.2g} (without it {before / stat:+.2f} stat std)")
        print(f"{r['duration']:>9g} s (measured on {term['span_s']:g} s of it): " + "  ".join(parts))
    last = rows[-1]["identify"]
    if "error" not in last:
        worst = max(abs(v - last["truth"][n]) / s for n, (v, s) in last["params"].items())
        print(f"\nlongest ({rows[-1]['duration']:g} s): peak {last['peak_mb']:.0f} MB (target <= {TARGET_PEAK_MB:.0f}), "
              f"CPU time per second of data {last['cpu_s'] / rows[-1]['duration'] / (first['cpu_s'] / rows[0]['duration']):.2f}"
              f" x the shortest's (<= 1: linear or better), estimates within {worst:.2f} std of the truth")
    base = [r for r in rows if "baseline" in r]
    if base:
        print(f"\nthis code vs {baseline} (same runs, same process setup):")
        for r in base:
            b, i = r["baseline"], r["identify"]
            if "error" in b:
                print(f"{r['duration']:>9g} s: baseline failed ({b['error'][0]}; peak {b['peak_mb']:.0f} MB)")
                continue
            rel = max(abs(i["params"][n][k] / b["params"][n][k] - 1) for n in i["params"] for k in (0, 1))
            same = "identical" if rel == 0 else f"equal to {rel:.1e} (relative)"
            print(f"{r['duration']:>9g} s: wall {i['wall_s']:.2f} / {b['wall_s']:.2f} s = {i['wall_s'] / b['wall_s']:.2f}, "
                  f"cpu {i['cpu_s']:.2f} / {b['cpu_s']:.2f} s = {i['cpu_s'] / b['cpu_s']:.2f}, "
                  f"fit {i['fit_s']:.2f} / {b['fit_s']:.2f} s = {i['fit_s'] / b['fit_s']:.2f}, peak {i['peak_mb']:.0f} / "
                  f"{b['peak_mb']:.0f} MB; estimates and std {same}")


if __name__ == "__main__":
    sys.exit(main())
