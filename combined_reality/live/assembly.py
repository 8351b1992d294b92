"""A session put together for where it runs: which estimator (a thread one window behind for a
replay as fast as possible, else its own process, ahead of or behind acquisition), at which
priority acquisition runs, and how the lock-step model resynchronises."""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass

from hw.realtime import HOST_PRIORITY, realtime_available
from sim.cylinder import Cylinder

from ..identify import OnlineOptions
from .session import (ESTIMATOR_NICE_AHEAD, ESTIMATOR_NICE_BEHIND, Estimator, LockstepSimulator,
                      PipelinedEstimator, ProcessEstimator)

__all__ = ["SessionParts", "assemble_session"]


@dataclass(frozen=True)
class SessionParts:
    estimator: Estimator
    simulator: LockstepSimulator | None  # None: no viewer reads the model's traces
    realtime: int | None  # the acquisition's real-time priority; None: a replay, ordinary priority


def assemble_session(cyl: Cylinder, sample_period: float, options: OnlineOptions, *, live: bool, pipelined: bool,
                     viewer: bool) -> SessionParts:
    """The estimator and the lock-step model of a session: `live` a rig (acquired at real-time
    priority where the OS grants it), else a replay; `pipelined` a replay as fast as possible;
    `viewer` whether anything reads the model's traces."""
    # the lock-step model's traces are for the viewer: without one nothing reads them, and
    # they cost a replay about a fifth of its time. Replayed as fast as possible, the estimates
    # reach the model a window after their data (PipelinedEstimator): it runs on from each
    # for up to two windows before it restarts
    lag = 2 * options.window_s if pipelined else 0.0
    simulator = (LockstepSimulator(cyl, resync_s=max(2.0, lag + 0.5), history_s=max(10.0, lag + 2.0))
                 if viewer else None)
    # a live rig is acquired at real-time priority where the OS grants it; the estimator
    # then runs ahead of ordinary work (below acquisition), else behind acquisition
    realtime = HOST_PRIORITY if live else None
    # two threads for the estimator's model where nothing real-time can suffer from them
    two = dataclasses.replace(options, threads=min(2, os.cpu_count() or 1))
    if pipelined:
        estimator: Estimator = PipelinedEstimator(cyl, sample_period, two)
    else:
        ahead = realtime is not None and realtime_available()
        estimator = ProcessEstimator(cyl, sample_period, two if ahead else options,
                                     nice=ESTIMATOR_NICE_AHEAD if ahead else ESTIMATOR_NICE_BEHIND)
    return SessionParts(estimator, simulator, realtime)
