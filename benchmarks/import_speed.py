"""`combined-reality import` of long delimited lab recordings: wall time and peak memory.

A lab CSV as a German DAQ program writes it (semicolons, decimal commas, a preamble, cp1252,
milliseconds, volts, millimetres, bar gauge) with five further channels the mapping does not
read, at 1 kHz, is imported in a process of its own per length. Printed: wall time, peak RSS,
and per second of data the ratio to the shortest run (a reader that reads once, as a stream,
stays near 1 in time and its memory grows by the columns alone).

    python benchmarks/import_speed.py                       # 60 s, 600 s, 3600 s
    python benchmarks/import_speed.py --durations 60,600
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RATE = 1000.0
HEADER = "Zeit [ms];Ventil [V];Weg [mm];P_A [bar];P_B [bar];T1 [C];T2 [C];T3 [C];T4 [C];T5 [C]"
MAPPING = """\
[source]
delimiter = ";"
decimal = ","
[columns]
t = { from = "Zeit [ms]", unit = "ms" }
u = { from = "Ventil [V]", unit = "V", zero = 5.0, span = 5.0 }
x = { from = "Weg [mm]", unit = "mm" }
p1 = { from = "P_A [bar]", unit = "bar", gauge = true }
p2 = { from = "P_B [bar]", unit = "bar", gauge = true }
[atmosphere]
pressure = 101300.0
"""


def write_lab_csv(path: Path, seconds: float, seed: int = 1) -> None:
    n = int(seconds * RATE) + 1
    rng = np.random.default_rng(seed)
    with open(path, "w", encoding="cp1252") as f:
        f.write("Messung 3\nPrüfstand B\n" + HEADER + "\n")
        for a in range(0, n, 100_000):
            t = np.arange(a, min(n, a + 100_000)) / RATE
            k = t.size
            s = np.sin(2 * np.pi * 0.5 * t)
            cols = [np.char.mod("%.3f", t * 1e3), np.char.mod("%.7f", 3 * s + 5 + 0.05 * rng.standard_normal(k)),
                    np.char.mod("%.6f", 50 + 40 * np.sin(2 * np.pi * 0.5 * t - 0.3)),
                    np.char.mod("%.7f", 3 + 2 * s + 0.003 * rng.standard_normal(k)),
                    np.char.mod("%.7f", 3 - 2 * s + 0.003 * rng.standard_normal(k)),
                    *[np.char.mod("%.4f", 20 + 0.1 * rng.standard_normal(k)) for _ in range(5)]]
            f.write("\n".join(";".join(c).replace(".", ",") for c in zip(*cols)) + "\n")


def import_once(raw: Path, mapping: Path, out: Path) -> tuple[float, float, float]:
    """(wall s, CPU s, peak RSS MB) of one import in its own process (its own rusage: wait4)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "combined_reality", "import", str(raw), "--map", str(mapping),
                             "-o", str(out), "-q"], cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise SystemExit(f"import of {raw.name} failed (exit {proc.returncode})")
    return wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--durations", default="60,600,3600", help="s of recording, comma-separated, shortest first")
    args = ap.parse_args()
    durations = [float(d) for d in args.durations.split(",")]
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        mapping = folder / "map.toml"
        mapping.write_text(MAPPING, encoding="utf-8")
        for d in durations:
            raw = folder / f"lab_{d:g}.csv"
            write_lab_csv(raw, d)
            size = raw.stat().st_size
            wall, cpu, peak = import_once(raw, mapping, folder / f"run_{d:g}.csv")
            rows.append((d, size, wall, cpu, peak))
            raw.unlink()
    d0, _, _, cpu0, _ = rows[0]
    print("\nimport of a delimited lab recording at 1 kHz (ten columns, five mapped), a process per run:")
    print(f"{'recording':>10} {'text MB':>8} {'wall s':>7} {'CPU s':>6} {'CPU/s vs first':>15} {'peak RSS MB':>12}"
          f" {'peak growth per s':>18}")
    for d, size, wall, cpu, peak in rows:
        growth = "" if d == d0 else f"{(peak - rows[0][4]) / (d - d0) * 1e3:.0f} kB"
        print(f"{d:>9g}s {size / 1e6:>8.0f} {wall:>7.1f} {cpu:>6.1f} {(cpu / d) / (cpu0 / d0):>15.2f} {peak:>12.0f}"
              f" {growth:>18}")
    print(f"load average at the end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
