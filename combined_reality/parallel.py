"""Independent pieces of work over a pool of forked processes, with results in job order.

Used where the pieces are fits that share nothing (the diagnosis's candidates, a
validation's segments). The results never depend on which process finished first, so the
same inputs give the same outputs on any machine, with any number of workers.
"""
from __future__ import annotations

import multiprocessing as mp
from typing import Any, Callable, Iterator

__all__ = ["iter_jobs", "run_jobs", "runs_in_pool", "workers_here"]


def workers_here(workers: int) -> int:
    """The processes (or threads) a piece of work may use where it runs: one inside a pool's
    process, whose siblings hold the other cores; `workers` elsewhere."""
    return 1 if mp.current_process().daemon else max(1, workers)


def runs_in_pool(workers: int, n_jobs: int) -> bool:
    """Whether run_jobs and iter_jobs farm `n_jobs` out to a pool of processes here."""
    return workers_here(workers) > 1 and n_jobs > 1


def run_jobs(work: Callable[[Any], Any], jobs: list, workers: int,
             enough: Callable[[Any], bool] | None = None, on_result: Callable[[Any], None] | None = None) -> list:
    """`work` of each of `jobs`, in job order. With `enough`, the results end at the first job
    (in job order, whatever finished first) for which it holds: the same work counts on any
    machine and any number of workers; the later jobs still running are stopped. `on_result`
    hears of each result as it is taken (progress)."""
    results: list = []
    it = iter_jobs(work, jobs, workers)
    try:
        for r in it:
            results.append(r)
            if on_result is not None:
                on_result(r)
            if enough is not None and enough(r):
                break
    finally:
        it.close()  # stops the pool's jobs still running
    return results


def iter_jobs(work: Callable[[Any], Any], jobs: list, workers: int) -> Iterator[Any]:
    """`work` of each of `jobs`, yielded in job order as they are done, while the pool works on
    the later ones; closing the iterator stops them. The pool is gone before the last result
    is yielded, so that whoever takes it may fork a pool of its own.

    The pool's processes get the jobs when they are forked (_hold_jobs), and a task is a job's
    index. A task that carries its job (megabytes with the runs) can be caught half-written
    into the pool's pipe when the pool is stopped early, and terminate() then waits for it
    forever: that hung a benchmark run. Inside a pool's process (a daemon, which cannot fork
    a pool of its own) the jobs run one after the other."""
    if not runs_in_pool(workers, len(jobs)):
        yield from map(work, jobs)
        return
    pool = mp.get_context("fork").Pool(min(workers, len(jobs)), initializer=_hold_jobs, initargs=(work, jobs))
    try:
        results = pool.imap(_held_job, range(len(jobs)))
        for _ in range(len(jobs) - 1):
            yield next(results)
        last = next(results)
    finally:
        pool.terminate()
        pool.join()
    yield last


# a pool process's jobs and their work (set once per process by _hold_jobs, which the pool
# runs in each process it forks: the jobs arrive with the fork, never through its pipe)
_held: tuple[Callable, list] | None = None


def _hold_jobs(work: Callable, jobs: list) -> None:
    global _held
    _held = (work, jobs)


def _held_job(i: int):
    work, jobs = _held
    return work(jobs[i])
