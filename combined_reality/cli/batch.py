"""`combined-reality batch`: identify many cylinders, on local processes or a dask cluster.

    combined-reality batch MANIFEST.toml --out DIR [--workers N] [--scheduler ADDRESS]
        [--diagnose] [--json OUT.json] [--no-report] [-q]

The manifest and the outputs: combined_reality.batch, docs/batch.md. Exit status 0 when every
cylinder was identified, 1 when some failed (their rows say why), 2 for a bad manifest.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from .. import options
from .common import UsageError, add_max_rows, check_paths, eprint, typed


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "batch", help="identify every cylinder of a manifest (local processes or a dask cluster), with a report",
        description="Identify the friction of many cylinders: the manifest lists [[cylinder]] tables with name, "
                    "config (a cylinder file) and runs (recorded runs, identified jointly) or simulate = "
                    "{duration, seed, effect, runs} (the virtual rig makes the runs), and optionally model "
                    "(per cylinder, or once at the top for all: nominal, or a friction model of the family). "
                    "Relative paths are relative to the manifest. Writes DIR/results.csv, DIR/results.parquet, "
                    "DIR/report.html, DIR/summary.json and the simulated runs in DIR/runs (all on this machine, also "
                    "with a cluster: workers return data); re-running skips cylinders whose inputs and options are "
                    "unchanged. Simulations are bounded to 1e6 samples per cylinder. Exit status 1 if some "
                    "cylinders failed, 2 for a bad manifest.")
    p.add_argument("manifest", metavar="MANIFEST.toml", help="the manifest: [[cylinder]] tables (docs/batch.md)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for the results (created)")
    p.add_argument("--workers", type=typed(options.whole_number, "--workers", lo=1, hi=1024), default=None,
                   help="local worker processes (default: all cores); with --scheduler, ignored")
    p.add_argument("--scheduler", metavar="ADDRESS", type=typed(options.scheduler_address),
                   help="run on an existing dask.distributed cluster, e.g. tcp://10.0.0.5:8786 (its workers need "
                        "combined-reality installed)")
    p.add_argument("--allow-outside", action="store_true",
                   help="let the manifest name cylinder files and runs outside its own folder (refused without it, "
                        "so that a manifest from elsewhere cannot make the batch read any file)")
    p.add_argument("--diagnose", action="store_true",
                   help="also diagnose each cylinder (first run TRAIN, last run VALID; simulated cylinders get "
                        "two runs)")
    p.add_argument("--json", metavar="OUT.json", help="write the summary as JSON ('-' for stdout)")
    p.add_argument("--no-report", action="store_true", help="skip the HTML report")
    add_max_rows(p)
    p.add_argument("-q", "--quiet", action="store_true", help="no progress")
    p.set_defaults(func=run)
    return p


def _fmt_s(s: float) -> str:
    s = max(0.0, s)
    return f"{s:.0f} s" if s < 90 else f"{s / 60:.1f} min" if s < 5400 else f"{s / 3600:.1f} h"


class _Progress:
    """A bar with ETA on a terminal (tqdm), plain lines otherwise."""

    def __init__(self, quiet: bool):
        self.quiet = quiet
        self.bar = None
        self.t0 = time.perf_counter()
        self.base = 0

    def start(self, cached: int, total: int) -> None:
        self.base = cached
        if self.quiet:
            return
        if cached:
            print(f"{cached} of {total} cylinders unchanged since the last run: their rows are reused",
                  file=sys.stderr, flush=True)
        if sys.stderr.isatty():
            from tqdm import tqdm

            self.bar = tqdm(total=total, initial=cached, unit="cyl", file=sys.stderr, dynamic_ncols=True,
                            bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}] {postfix}")

    def __call__(self, done: int, total: int, row: dict, elapsed: float) -> None:
        if self.quiet:
            return
        status = "ok" if row.get("status") == "ok" else f"FAILED: {row.get('error', '')}"
        if self.bar is not None:
            self.bar.set_postfix_str(f"{row['name']}: {status}"[:60])
            self.bar.update(1)
            return
        computed = done - self.base
        left = total - done
        eta = f", about {_fmt_s(elapsed / computed * left)} left" if computed and left else ""
        print(f"[{done}/{total}] {row['name']}: {status} ({row.get('wall_s', 0.0):.1f} s){eta}",
              file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def format_rows(rows: list[dict], width: int = 100) -> str:
    """The batch as a table for the console: per cylinder its model, status, position fit and
    verdict, and its parameters (value ± std in a unit for people) on lines of their own,
    within `width` columns."""
    import math
    import textwrap

    from sim.cylinder import PARAMETERS
    from sim.friction_models import FRICTION_MODELS, parameter_unit

    from ..report.text import format_value, um

    skip = {"name", "status", "error", "model", "source", "n_runs", "cylinder", "config", "bore", "rod", "stroke",
            "supply_pressure", "atmosphere", "duration_s", "mean_dp", "mean_pc", "max_speed", "rmse_x", "r2_x",
            "rmse_p1", "rmse_p2", "solver_status", "iterations", "warning", "verdict", "verdict_shrink",
            "baseline_rmse_x_validation", "diagnosis_error", "wall_s", "hash", "cached"}
    name_w = min(28, max([len("cylinder")] + [len(str(r["name"])) for r in rows]))
    lines = [f"{'cylinder':{name_w}s}  {'model':10s} {'status':10s} {'rmse_x':>10s}  verdict"]
    for r in rows:
        ok = r.get("status") == "ok"
        rmse = um(r["rmse_x"]) if ok and r.get("rmse_x") is not None else ""
        status = (r.get("solver_status") or "ok") if ok else "FAILED"
        lines.append(f"{str(r['name'])[:name_w]:{name_w}s}  {str(r.get('model') or ''):10s} {status:10s} "
                     f"{rmse:>10s}  {r.get('verdict') or ''}".rstrip())
        if not ok:
            lines += textwrap.wrap(str(r.get("error", "")), width, initial_indent="    ", subsequent_indent="    ")
            continue
        model = r.get("model") or "nominal"

        def unit(k: str) -> str:
            if model in FRICTION_MODELS:
                base = k[:-4] if k.endswith(("_pos", "_neg")) else k
                return parameter_unit(model, base)
            return PARAMETERS[k].unit if k in PARAMETERS else ""

        params = [k for k in r if k not in skip and not k.endswith("_std") and not k.startswith("truth_")
                  and isinstance(r[k], (int, float)) and r[k] is not None]
        cells = [f"{k} {format_value(r[k], r.get(f'{k}_std'), unit(k))}" for k in params
                 if not (isinstance(r[k], float) and math.isnan(r[k]))]
        lines += textwrap.wrap(", ".join(cells), width, initial_indent="    ", subsequent_indent="    ")
    return "\n".join(lines)


def _connect(address: str):
    try:
        from distributed import Client
    except ImportError:
        raise UsageError("--scheduler needs dask.distributed, an extra of the install: "
                         "pip install 'combined-reality[cluster]'.") from None
    try:
        return Client(address, timeout="10s")
    except (OSError, TimeoutError) as e:
        raise UsageError(f"cannot reach the dask scheduler at {address}: {e}.") from None


def run(args) -> int:
    from ..batch import load_manifest, run_batch, share_compiled_code
    from ..files import write_json_atomic

    out = Path(args.out)
    check_paths({"--json": args.json}, inputs=[args.manifest], folders={"--out": out})
    jobs = load_manifest(args.manifest, diagnose=args.diagnose, allow_outside=args.allow_outside, max_rows=args.max_rows)
    renamed = [j for j in jobs if j.file_stem != j.name]
    if renamed and not args.quiet:  # which files belong to which cylinder
        eprint("file names of cylinders whose names a file name cannot hold as they are: "
               + "; ".join(f"'{j.name}' -> {j.file_stem}" for j in renamed))
    progress = _Progress(args.quiet)
    say = (lambda m: None) if args.quiet else eprint
    with contextlib.ExitStack() as stack:
        stack.callback(progress.close)
        if args.scheduler:
            client = _connect(args.scheduler)
            stack.callback(client.close)
            workers = len(client.scheduler_info().get("workers", {}))
            n = share_compiled_code(client)
            say(f"dask cluster {args.scheduler}: {workers} workers" + (f"; compiled model code installed on them "
                                                                        f"({n} files)" if n else ""))
            executor, where = client.get_executor(pure=False), args.scheduler
        else:
            workers = min(args.workers or os.cpu_count() or 1, max(1, len(jobs)))
            say(f"{len(jobs)} cylinders on {workers} local process{'es' if workers > 1 else ''}")
            executor = stack.enter_context(ProcessPoolExecutor(workers)) if workers > 1 else None
            where = "local"
        summary = run_batch(jobs, out, executor, progress=progress, on_start=progress.start,
                            report=not args.no_report, scheduler=where, workers=workers)
    doc = summary.to_json()
    if args.json == "-":
        json.dump(doc, sys.stdout, indent=1)
        print()
    elif args.json:
        write_json_atomic(args.json, doc)
        say(f"wrote {args.json}")
    if args.json != "-":
        print(format_rows(doc["rows"]))
    if not args.quiet:
        print(f"{summary.ok} of {summary.total} cylinders identified, {summary.failed} failed "
              f"({_fmt_s(summary.wall_s)}); results in {out / 'results.csv'}"
              + ("" if args.no_report else f", report {out / 'report.html'}"), file=sys.stderr)
        for f in doc["failures"]:
            print(f"  {f['name']}: {f['error']}", file=sys.stderr)
    return 0 if summary.failed == 0 else 1
