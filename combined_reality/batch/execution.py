"""Batch identification of many cylinders: the jobs of a manifest in, one row per cylinder
out, on local processes or on a dask.distributed cluster.

Every cylinder is one task (`run_job`), a pure function of its inputs: it loads the cylinder
file and the runs (or has the virtual rig make them), identifies the friction model chosen
for it by multiple shooting and, if asked, diagnoses the gap. A task never raises: a bad
file or a solver failure becomes the row's status and error. Tasks run on any
`concurrent.futures.Executor` (a process pool, or dask's `Client.get_executor()`), so the
pipeline does not know which one it has.

Incremental: a row is stored under DIR/cache/ keyed by the content hash of everything it
depends on (the cylinder file's and runs' bytes, the simulation recipe, the model, the
options, the source code); an unchanged cylinder is not recomputed. results.csv and
results.parquet are rewritten atomically after every finished cylinder, so an interrupted
batch leaves valid files holding what was done.
"""
from __future__ import annotations

import csv
import io
import json
import math
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Executor, Future, as_completed
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from sim.cylinder import ConfigError, load_cylinder
from sim.extension import check_combination
from sim.friction_models import FrictionModel, parse_truth_spec

from ..diagnose import DiagnoseOptions, diagnose
from ..files import RunFormatError, atomic_write, check_distinct_runs, cylinder_tag, read_run, write_run
from ..friction import identify_model, model_parameters
from ..identify import IdentificationError, IdentifyOptions, preflight, velocity_estimate
from ..simulation import simulate_run
from .manifest import CylinderJob
from .report import write_batch_report

__all__ = ["run_job", "run_batch", "BatchSummary", "columns", "write_results", "read_results_csv", "RUNS_DIR",
           "SIMULATED_RUNS"]

RUNS_DIR = "runs"  # DIR/runs: the simulated runs, written by the client
SIMULATED_RUNS = "simulated_runs"  # the key under which a task returns the runs it simulated


# ------------------------------------------------------------------ one cylinder (the task)

class _RowError(Exception):
    pass


def _load_inputs(job: CylinderJob):
    try:
        cyl = load_cylinder(job.config)
    except FileNotFoundError:
        raise _RowError(f"cylinder file {job.config} not found") from None
    except (ConfigError, OSError, ValueError) as e:
        raise _RowError(f"cylinder file: {e}") from None
    runs, truth, notes = [], {}, []
    if job.simulate is not None:
        s = job.simulate
        try:
            effects = [parse_truth_spec(x) for x in s.effects]
            check_combination(effects)
        except ValueError as e:
            raise _RowError(f"simulate.effect: {e}") from None
        model = next((e for e in effects if isinstance(e, FrictionModel)), None)
        truth = ({f"truth_{k}": v for k, v in zip(model.param_names(), model.values())} if model is not None
                 else {f"truth_{k}": cyl.value(k) for k in ("Fc", "Fv", "kp")})
        for k in range(s.runs):
            # the task returns the run; the client writes it under --out (a worker's folder is not the user's)
            name = f"{RUNS_DIR}/{job.stem}_{k + 1}.csv"
            run = replace(simulate_run(cyl, s.duration, s.seed + k, s.rate, effects, noise=s.noise), source=Path(name),
                          comments=(cylinder_tag(cyl), f"combined-reality batch: virtual rig, seed {s.seed + k}; "
                                                       f"truth: {'; '.join(s.effects) or 'the cylinder file'}"))
            runs.append(run)
    else:
        for p in job.runs:
            try:
                run = read_run(p, job.max_rows)
            except FileNotFoundError:
                raise _RowError(f"run {p} not found") from None
            except (RunFormatError, OSError, ValueError) as e:
                raise _RowError(str(e)) from None
            try:
                notes += preflight(cyl, [run]).notes
            except (RunFormatError, ConfigError) as e:
                raise _RowError(str(e)) from None
            runs.append(run)
        try:
            check_distinct_runs(runs, [Path(p).name for p in job.runs])
        except RunFormatError as e:
            raise _RowError(str(e)) from None
        rates = {round(r.sample_period, 9) for r in runs}
        if len(rates) > 1:
            raise _RowError("the runs have different sample rates; identify runs of one rig and rate together")
    return cyl, runs, truth, notes


def _run_statistics(cyl, runs) -> dict:
    """The operating conditions of the runs: what the report evaluates pressure-dependent
    curves at, and how far the curves reach."""
    pa = cyl.supply.atmosphere
    v = [velocity_estimate(r.t, r.x) for r in runs]
    pc = np.concatenate([np.where(vi >= 0, r.p2 - pa, r.p1 - pa) for vi, r in zip(v, runs)])
    return {"mean_dp": float(np.concatenate([np.abs(r.p1 - r.p2) for r in runs]).mean()),
            "mean_pc": float(pc.mean()),
            "max_speed": float(np.percentile(np.abs(np.concatenate(v)), 99.5)),
            "duration_s": float(sum(r.t[-1] - r.t[0] for r in runs))}


def run_job(job: CylinderJob) -> dict:
    """Identify one cylinder: its row (never raises; failures are the row's status). The runs
    the virtual rig made come back under SIMULATED_RUNS (run_batch writes them and takes the
    key out of the row): a task writes no file, so that on a cluster nothing lands in a
    worker's folder."""
    t0 = time.perf_counter()
    row: dict = {"name": job.name, "status": "failed", "error": "", "model": job.model,
                 "config": job.config, "source": "simulated" if job.simulate else "recorded",
                 "n_runs": job.simulate.runs if job.simulate else len(job.runs)}
    try:
        with np.errstate(all="ignore"):
            row.update(_identify_row(job, row))
        row["status"] = "ok"
    except _RowError as e:
        row["error"] = str(e)
    except Exception as e:  # a solver failure must not end the batch; its row says what happened
        kind = "identification failed" if isinstance(e, IdentificationError) else type(e).__name__
        row["error"] = f"{kind}: {e}"
    row["wall_s"] = time.perf_counter() - t0
    return row


def _identify_row(job: CylinderJob, row: dict) -> dict:
    cyl, runs, truth, notes = _load_inputs(job)
    if job.simulate is not None:
        row[SIMULATED_RUNS] = runs  # kept also when the identification fails: they show why
    g = cyl.geometry
    out: dict = {"cylinder": cyl.name, "bore": g.bore, "rod": g.rod, "stroke": g.stroke,
                 "supply_pressure": cyl.supply.pressure, "atmosphere": cyl.supply.atmosphere,
                 **_run_statistics(cyl, runs)}
    res = identify_model(cyl, runs, job.model, IdentifyOptions(threads=1))
    values, std = model_parameters(res)
    for k, v in values.items():
        out[k], out[f"{k}_std"] = v, std.get(k, math.nan)
    out.update(truth)
    out.update({"rmse_x": res.fit.get("rmse_x"), "r2_x": res.fit.get("r2_x"), "rmse_p1": res.fit.get("rmse_p1"),
                "rmse_p2": res.fit.get("rmse_p2"), "solver_status": res.status,
                "iterations": res.solver["iterations"]})
    warnings = list(notes)
    if res.status == "not_determined":
        warnings.append(f"the data do not determine {', '.join(res.not_determined)}")
    elif res.status != "converged":
        warnings.append(f"the solver stopped with status {res.status}")
    if warnings:
        out["warning"] = "; ".join(warnings)  # the preflight's notes (what it was not sure of) first
    if job.diagnose:
        out.update(_diagnose_row(cyl, runs))
    return out


def _diagnose_row(cyl, runs) -> dict:
    if len(runs) < 2:
        return {"verdict": None, "diagnosis_error": "a diagnosis needs two runs (TRAIN and VALID); give two runs "
                                                    "or simulate.runs = 2"}
    d = diagnose(cyl, runs[0], runs[-1], DiagnoseOptions(workers=1))
    best = d.best
    return {"verdict": d.verdict, "verdict_shrink": best.shrink if best is not None else None,
            "baseline_rmse_x_validation": d.baseline["rmse_x_validation"]}


# ------------------------------------------------------------------ output files

_FIRST = ("name", "status", "error", "model", "source", "n_runs", "cylinder", "config", "bore", "rod", "stroke",
          "supply_pressure", "atmosphere", "duration_s", "mean_dp", "mean_pc", "max_speed")
_METRICS = ("rmse_x", "r2_x", "rmse_p1", "rmse_p2", "solver_status", "iterations", "warning", "verdict",
            "verdict_shrink", "baseline_rmse_x_validation", "diagnosis_error", "wall_s", "hash", "cached")


def columns(rows: Sequence[dict]) -> list[str]:
    """First the identity and cylinder columns, then each parameter followed by its _std (and
    truth_), in order of appearance, then the fit metrics."""
    params: list[str] = []
    for r in rows:
        for k in r:
            if k in _FIRST or k in _METRICS or k.endswith("_std") or k.startswith("truth_") or k in params:
                continue
            params.append(k)
    cols = list(_FIRST)
    for p in params:
        cols += [p, f"{p}_std"]
        if any(f"truth_{p}" in r for r in rows):
            cols.append(f"truth_{p}")
    extra = [k for r in rows for k in r if k not in cols and k not in _METRICS]
    cols += list(dict.fromkeys(extra))
    cols += [m for m in _METRICS if any(m in r for r in rows)]
    return cols


def _cell(v):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return ""
    if isinstance(v, float):
        return repr(v)
    return v


def write_results(out_dir: Path, rows: Sequence[dict]) -> None:
    """results.csv and results.parquet, each replaced atomically."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    cols = columns(rows)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(cols)
    for r in rows:
        w.writerow([_cell(r.get(c)) for c in cols])
    atomic_write(out_dir / "results.csv", buf.getvalue().encode())

    def typed(c):
        vals = [r.get(c) for r in rows]
        present = [v for v in vals if v is not None]
        if present and all(isinstance(v, bool) for v in present):
            return pa.array(vals, pa.bool_())
        if present and all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in present):
            return pa.array([None if v is None else int(v) for v in vals], pa.int64())
        if present and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in present):
            return pa.array([None if v is None else float(v) for v in vals], pa.float64())
        return pa.array([None if v is None else str(v) for v in vals], pa.string())

    table = pa.table({c: typed(c) for c in cols})
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink)
    atomic_write(out_dir / "results.parquet", sink.getvalue().to_pybytes())


def read_results_csv(path: Path) -> list[dict]:
    """results.csv back as rows (numbers as float, empty cells as None)."""
    rows = []
    with open(path, newline="", encoding="utf-8") as f:
        for r in csv.DictReader(f):
            row = {}
            for k, v in r.items():
                if v == "":
                    row[k] = None
                    continue
                try:
                    row[k] = float(v)
                except ValueError:
                    row[k] = v
            rows.append(row)
    return rows


# ------------------------------------------------------------------ the batch

@dataclass
class BatchSummary:
    out_dir: str
    total: int
    ok: int
    failed: int
    cached: int
    wall_s: float
    rows: list[dict] = field(default_factory=list)
    scheduler: str = "local"
    workers: int = 1

    def to_json(self) -> dict:
        return {"out": self.out_dir, "cylinders": self.total, "ok": self.ok, "failed": self.failed,
                "reused_unchanged": self.cached, "wall_s": round(self.wall_s, 3), "scheduler": self.scheduler,
                "workers": self.workers, "results_csv": str(Path(self.out_dir) / "results.csv"),
                "results_parquet": str(Path(self.out_dir) / "results.parquet"),
                "report": str(Path(self.out_dir) / "report.html"),
                "failures": [{"name": r["name"], "error": r.get("error", "")} for r in self.rows
                             if r.get("status") != "ok"],
                "rows": [{k: _json_value(v) for k, v in r.items()} for r in self.rows]}


def _json_value(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, np.generic):
        return v.item()
    return v


class _Cache:
    """Finished rows keyed by content hash (one small JSON per cylinder, written atomically)."""

    def __init__(self, out_dir: Path):
        self.dir = out_dir / "cache"
        self.dir.mkdir(exist_ok=True)

    def _path(self, job: CylinderJob, key: str) -> Path:
        return self.dir / f"{job.stem}.{key}.json"

    def get(self, job: CylinderJob, key: str) -> dict | None:
        try:
            row = json.loads(self._path(job, key).read_text())
        except (OSError, ValueError):
            return None
        return row if row.get("status") == "ok" else None

    def put(self, job: CylinderJob, key: str, row: dict) -> None:
        for old in self.dir.glob(f"{job.stem}.*.json"):
            old.unlink(missing_ok=True)
        atomic_write(self._path(job, key), json.dumps({k: _json_value(v) for k, v in row.items()}).encode())


def run_batch(jobs: Sequence[CylinderJob], out_dir: Path, executor: Executor | None = None,
              progress: Callable[[int, int, dict, float], None] | None = None,
              on_start: Callable[[int, int], None] | None = None, report: bool = True,
              scheduler: str = "local", workers: int = 1) -> BatchSummary:
    """Run the jobs (cached rows reused), writing results after every finished cylinder.
    `progress(done, total, row, elapsed_s)` is called as rows arrive."""
    t0 = time.perf_counter()
    out_dir.mkdir(parents=True, exist_ok=True)
    cache = _Cache(out_dir)
    rows: list[dict | None] = [None] * len(jobs)
    keys = [j.content_hash() for j in jobs]
    todo = []
    n_cached = 0
    for i, (job, key) in enumerate(zip(jobs, keys)):
        hit = cache.get(job, key)
        if hit is not None:
            rows[i] = {**hit, "cached": True}
            n_cached += 1
        else:
            todo.append(i)
    done = n_cached
    if on_start:
        on_start(n_cached, len(jobs))

    def finished(i: int, row: dict) -> None:
        nonlocal done
        simulated = row.pop(SIMULATED_RUNS, None)
        if simulated:
            (out_dir / RUNS_DIR).mkdir(exist_ok=True)
            for run in simulated:  # the client writes every file, under out_dir
                write_run(out_dir / run.source, run, comments=run.comments)
            row["run_files"] = "; ".join(str(run.source) for run in simulated)
        row["hash"] = keys[i]
        rows[i] = row
        if row.get("status") == "ok":
            cache.put(jobs[i], keys[i], row)
        done += 1
        write_results(out_dir, [r for r in rows if r is not None])
        if progress:
            progress(done, len(jobs), row, time.perf_counter() - t0)

    if n_cached:
        write_results(out_dir, [r for r in rows if r is not None])
    if todo:
        if executor is None:
            for i in todo:
                finished(i, run_job(jobs[i]))
        else:
            futures: dict[Future, int] = {executor.submit(run_job, jobs[i]): i for i in todo}
            try:
                for fut in as_completed(futures):
                    i = futures[fut]
                    try:
                        row = fut.result()
                    except Exception as e:  # the worker itself died (out of memory, killed)
                        row = {"name": jobs[i].name, "status": "failed", "model": jobs[i].model,
                               "error": f"the worker running it failed: {type(e).__name__}: {e}"}
                    finished(i, row)
            except BaseException:
                # Ctrl-C: what is queued is dropped at once (the files hold what was done)
                for fut in futures:
                    fut.cancel()
                raise
    final = [r for r in rows if r is not None]  # written as they came
    if report:
        write_batch_report(final, out_dir / "report.html", png_dir=out_dir / "report")
    ok = sum(1 for r in final if r.get("status") == "ok")
    summary = BatchSummary(out_dir=str(out_dir), total=len(jobs), ok=ok, failed=len(final) - ok, cached=n_cached,
                           wall_s=time.perf_counter() - t0, rows=final, scheduler=scheduler, workers=workers)
    atomic_write(out_dir / "summary.json", json.dumps(summary.to_json(), indent=1).encode())
    return summary



