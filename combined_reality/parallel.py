"""Independent pieces of work over a pool of forked processes, with results in job order.

Used where the pieces are fits that share nothing (the diagnosis's candidates, a
validation's segments). The results never depend on which process finished first, so the
same inputs give the same outputs on any machine, with any number of workers.
"""
from __future__ import annotations

import multiprocessing as mp
from typing import Any, Callable

__all__ = ["run_jobs", "workers_here"]


def workers_here(workers: int) -> int:
    """The processes (or threads) a piece of work may use where it runs: one inside a pool's
    process, whose siblings hold the other cores; `workers` elsewhere."""
    return 1 if mp.current_process().daemon else max(1, workers)


def run_jobs(work: Callable[[Any], Any], jobs: list, workers: int,
             enough: Callable[[Any], bool] | None = None) -> list:
    """`work` of each of `jobs`, in job order. With `enough`, the results end at the first job
    (in job order, whatever finished first) for which it holds: the same work counts on any
    machine and any number of workers; the later jobs still running are stopped.

    The pool's processes get the jobs when they are forked (_hold_jobs), and a task is a job's
    index. A task that carries its job (megabytes with the runs) can be caught half-written
    into the pool's pipe when the pool is stopped early, and terminate() then waits for it
    forever: that hung a benchmark run. Inside a pool's process (a daemon, which cannot fork
    a pool of its own) the jobs run one after the other."""
    parallel = workers_here(workers) > 1 and len(jobs) > 1
    pool = mp.get_context("fork").Pool(min(workers, len(jobs)), initializer=_hold_jobs, initargs=(work, jobs)) \
        if parallel else None
    results: list = []
    try:
        for r in pool.imap(_held_job, range(len(jobs))) if pool is not None else map(work, jobs):
            results.append(r)
            if enough is not None and enough(r):
                break
    finally:
        if pool is not None:
            pool.terminate()
            pool.join()
    return results


# a pool process's jobs and their work (set once per process by _hold_jobs, which the pool
# runs in each process it forks: the jobs arrive with the fork, never through its pipe)
_held: tuple[Callable, list] | None = None


def _hold_jobs(work: Callable, jobs: list) -> None:
    global _held
    _held = (work, jobs)


def _held_job(i: int):
    work, jobs = _held
    return work(jobs[i])
