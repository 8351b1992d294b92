"""The streaming pipeline: source -> lock-step simulation -> online estimator -> sinks.

A source is any rig (hw.rig.Rig): serial, CAN, the in-process virtual rig, or a recorded
run replayed at real time or as fast as possible. The session reads a sample, asks the
experiment program for the next command (live rigs only), records the row at once, and
hands blocks of rows to the lock-step simulation, the estimator and the sinks. The
estimator runs in its own process when acquisition must never wait for it, or inline when
replaying as fast as possible.
"""
from __future__ import annotations

import gc
import math
import multiprocessing as mp
import os
import queue
import time
from dataclasses import dataclass, field
from typing import Callable, Protocol, Sequence

import numpy as np

from hw.rig import Rig, Sample
from hw.virtual_rig import VirtualRig
from sim.compiled import shooting_functions
from sim.cylinder import Cylinder
from sim.extension import Effect
from sim.plant import build_plant

from ..files import Run, RunRecorder
from ..identify import MovingHorizonEstimator, OnlineEstimate, OnlineOptions


class EndOfRun(Exception):
    """A finite source (a replayed file) has no more samples."""


# ------------------------------------------------------------------ sources

class ReplayRig:
    """A recorded run as a rig: samples at their recorded times (scaled by `speed`), or as
    fast as possible (speed = inf). Commands sent to it are ignored: it reports the
    recorded command as the one applied."""

    def __init__(self, run: Run, speed: float = 1.0):
        self.run, self.speed = run, speed
        self.k = 0
        self._wall0 = None

    def start(self) -> None:
        self._wall0 = time.perf_counter()

    def read(self, timeout: float | None = None) -> Sample:
        r, k = self.run, self.k
        if k >= r.n:
            raise EndOfRun()
        if math.isfinite(self.speed):
            due = self._wall0 + (r.t[k] - r.t[0]) / self.speed
            delay = due - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
        self.k += 1
        return Sample(t=float(r.t[k]), x=float(r.x[k]), p1=float(r.p1[k]), p2=float(r.p2[k]),
                      ps=None if r.ps is None else float(r.ps[k]), u_applied=float(r.u[k]))

    def send(self, u: float) -> None:
        pass

    def stop(self) -> None:
        pass


class PacedRig:
    """The in-process virtual rig held to its own clock, so a live session runs in real time."""

    def __init__(self, rig: VirtualRig):
        self.rig = rig
        self._wall0 = None

    def start(self) -> None:
        self.rig.start()
        self._wall0 = time.perf_counter()

    def read(self, timeout: float | None = None) -> Sample:
        s = self.rig.read()
        delay = self._wall0 + s.t - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        return s

    def send(self, u: float) -> None:
        self.rig.send(u)

    def stop(self) -> None:
        self.rig.stop()


# ------------------------------------------------------------------ estimators

class InlineEstimator:
    """The moving-horizon estimator in the calling thread (replay as fast as possible).

    With `catch_up`, it waits until a whole window of new data is there and slides by that
    window: the same data enter the estimate with a tenth of the updates."""

    def __init__(self, cyl: Cylinder, sample_period: float, options: OnlineOptions, effects: Sequence[Effect] = (),
                 catch_up: bool = True):
        self.mhe = MovingHorizonEstimator(cyl, sample_period, options, effects)
        self.catch_up = catch_up

    def add(self, rows: np.ndarray) -> None:
        self.mhe.add(*rows[:5], lost_before=rows[5])

    def poll(self, final: bool = False) -> list[OnlineEstimate]:
        out = []
        while self.mhe.ready() and (final or not self.catch_up or self.mhe.backlog >= self.mhe.N
                                    or not out and not self.mhe.started):
            out.append(self.mhe.update())
        return out

    def finish(self, timeout: float = 30.0) -> list[OnlineEstimate]:
        return self.poll(final=True)

    def close(self) -> None:
        pass


def _estimator_main(cyl, sample_period, options, effects, inbox, outbox, parent: int) -> None:
    """The estimator process: take rows, update whenever a window is due, send estimates.
    It ends with its parent, even one killed outright (no orphan keeps computing)."""
    try:
        try:
            os.nice(10)  # best effort: acquisition and the rig's link come first on a busy machine
        except OSError:
            pass
        mhe = MovingHorizonEstimator(cyl, sample_period, options, effects)
        outbox.put(("ready", None))
        finishing = False
        while True:
            if os.getppid() != parent:
                outbox.cancel_join_thread()  # nobody reads any more: exit without flushing
                return
            try:
                msg = inbox.get(timeout=0.05)
            except queue.Empty:
                msg = None
            while msg is not None:
                if isinstance(msg, str):  # "finish"
                    finishing = True
                else:
                    mhe.add(*msg[:5], lost_before=msg[5])
                try:
                    msg = inbox.get_nowait()
                except queue.Empty:
                    msg = None
            while mhe.ready():
                outbox.put(("estimate", mhe.update()))
                if not finishing:
                    break  # look at the inbox again: newer data shortens the catch-up
            if finishing and not mhe.ready():
                outbox.put(("done", None))
                return
    except Exception as exc:  # reported to the session, which keeps acquiring
        outbox.put(("error", f"{type(exc).__name__}: {exc}"))


class ProcessEstimator:
    """The moving-horizon estimator in its own process: acquisition never waits for it."""

    def __init__(self, cyl: Cylinder, sample_period: float, options: OnlineOptions, effects: Sequence[Effect] = (),
                 start_timeout: float = 120.0):
        ctx = mp.get_context("spawn")
        self.inbox, self.outbox = ctx.Queue(), ctx.Queue()
        self.proc = ctx.Process(target=_estimator_main, name="combined-reality-estimator", daemon=True,
                                args=(cyl, sample_period, options, tuple(effects), self.inbox, self.outbox, os.getpid()))
        self.proc.start()
        self.error: str | None = None
        kind, _ = self._get(start_timeout)
        if kind != "ready":
            self.close()
            raise RuntimeError(f"the estimator process did not start: {self.error or 'no answer'}")

    def _get(self, timeout: float):
        try:
            kind, value = self.outbox.get(timeout=timeout)
        except queue.Empty:
            return None, None
        if kind == "error":
            self.error = value
        return kind, value

    def add(self, rows: np.ndarray) -> None:
        self.inbox.put(np.ascontiguousarray(rows))

    def poll(self) -> list[OnlineEstimate]:
        out = []
        while True:
            try:
                kind, value = self.outbox.get_nowait()
            except queue.Empty:
                return out
            if kind == "estimate":
                out.append(value)
            elif kind == "error":
                self.error = value

    def finish(self, timeout: float = 30.0) -> list[OnlineEstimate]:
        """Let the estimator take in everything sent so far; its last estimates."""
        out = self.poll()
        if self.error or not self.proc.is_alive():
            return out
        self.inbox.put("finish")
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            kind, value = self._get(max(0.01, deadline - time.monotonic()))
            if kind == "estimate":
                out.append(value)
            elif kind in ("done", "error", None):
                break
        return out

    def close(self) -> None:
        if self.proc.is_alive():
            self.proc.terminate()
        self.proc.join(timeout=5)


# ------------------------------------------------------------------ lock-step simulation

class LockstepSimulator:
    """The model fed with the very command the rig applied, sample by sample, with the latest
    estimated parameters. Each online estimate also resynchronises it: the estimator's state
    at the end of its window is carried forward through the rows since then, so the gap to
    the measurement is the model's own prediction error over the last update period.
    Without estimates for `resync_s` it restarts from the measured state instead. Blocks of
    up to `block` rows go through one call of the compiled step, accumulated."""

    def __init__(self, cyl: Cylinder, effects: Sequence[Effect] = (), resync_s: float = 2.0, block: int = 20,
                 history_s: float = 10.0):
        self.cyl = cyl
        self.plant = plant = build_plant("command", effects)
        sf = shooting_functions(plant, 1, ())
        self.B = block
        self._acc = sf.step.mapaccum("lockstep", block, [0], [0])  # states after each of B steps
        self._friction = plant.friction.map(block)
        self.p = np.array(plant.parameter_vector(cyl), float)
        self.resync_s, self.history_s = resync_s, history_s
        self.state: np.ndarray | None = None  # at the last row seen
        self._t_sync = -math.inf
        self._pending: tuple[float, np.ndarray] | None = None  # (t, state) of the newest estimate
        self._hist = np.empty((3, 0))  # recent rows (t, u, x)
        ix = plant.state_names.index
        self._out = [ix("x"), ix("p1"), ix("p2"), ix("v")]

    def set_estimate(self, e: OnlineEstimate) -> None:
        self.p = np.asarray(e.params, float)
        self._pending = (e.t, np.asarray(e.state, float))

    def _run(self, s0: np.ndarray, u: np.ndarray, h: np.ndarray) -> np.ndarray:
        """States after each step of holding u[i] for h[i], from s0: (nx, len(u))."""
        B, out = self.B, np.empty((self.plant.nx, len(u)))
        P = np.tile(self.p[:, None], (1, B))
        for a in range(0, len(u), B):
            m = min(B, len(u) - a)
            U, H = np.zeros(B), np.zeros(B)  # zero-length steps pad the block, leaving the state alone
            U[:m], H[:m] = u[a:a + m], h[a:a + m]
            X = np.asarray(self._acc(s0, U[None], U[None], P, H[None]))
            out[:, a:a + m] = X[:, :m]
            s0 = X[:, m - 1]
        return out

    def advance(self, rows: np.ndarray) -> np.ndarray:
        """Simulated (x, p1, p2, v, friction) at each row's time: (5, n), n <= block."""
        t, u, x, p1, p2 = rows
        n, nx = len(t), self.plant.nx
        hist = np.hstack([self._hist, np.vstack([t, u, x])])
        hist = hist[:, hist[0] >= t[-1] - self.history_s]
        if self._pending is not None and self.state is not None:
            te, se = self._pending
            i = int(np.searchsorted(hist[0], te - 1e-9))
            if i < hist.shape[1] and abs(hist[0, i] - te) < 1e-6 and hist[0, i] <= t[0] - 1e-12:
                j = hist.shape[1] - n  # rows before this block: carry the estimate up to the last of them
                hs = np.diff(hist[0, i:j + 1])[: j - i - 1] if j - i > 1 else np.empty(0)
                self.state = self._run(se, hist[1, i:j - 1], hs)[:, -1] if len(hs) else se
                self._t_sync = te
            self._pending = None
        states = np.empty((nx, n))
        k = 0
        while k < n:
            if self.state is None or t[k] - self._t_sync >= self.resync_s or not np.all(np.isfinite(self.state)):
                # no estimate lately: start again from the measured state (velocity from a
                # quadratic through the last samples)
                j = hist.shape[1] - n + k
                ja = max(0, j - 19)
                v = float(np.polyfit(hist[0, ja:j + 1] - hist[0, j], hist[2, ja:j + 1], 2)[1]) if j - ja >= 3 else 0.0
                states[:, k] = self.plant.initial_state(self.cyl, x[k], p1[k], p2[k], v)
                self._t_sync = t[k]
            else:
                h = t[k] - self._last[0]
                states[:, k] = self._run(self.state, np.array([self._last[1]]), np.array([h]))[:, 0]
            self.state = states[:, k]
            self._last = (t[k], u[k])
            k += 1
            # the rest of the block in one call, up to a resynchronisation
            m = 0
            while k + m < n and t[k + m] - self._t_sync < self.resync_s:
                m += 1
            if m:
                states[:, k:k + m] = self._run(self.state, u[k - 1:k - 1 + m], t[k:k + m] - t[k - 1:k - 1 + m])
                self.state = states[:, k + m - 1]
                self._last = (t[k + m - 1], u[k + m - 1])
                k += m
        self._hist = hist
        S = np.zeros((nx, self.B))
        S[:, :n] = states
        Uf = np.zeros(self.B)
        Uf[:n] = u
        F = np.asarray(self._friction(S, Uf[None], np.tile(self.p[:, None], (1, self.B)))).ravel()[:n]
        return np.vstack([states[self._out], F[None]])


# ------------------------------------------------------------------ sinks

class Sink(Protocol):
    def rows(self, rows: np.ndarray, sim: np.ndarray) -> None: ...
    def estimate(self, e: OnlineEstimate) -> None: ...
    def close(self) -> None: ...


class ConsoleSink:
    """One progress line per `every_s` of rig time on stderr."""

    def __init__(self, print_fn: Callable[[str], None], every_s: float = 1.0, counters: Callable[[], dict] | None = None):
        self.print, self.every_s, self.counters = print_fn, every_s, counters
        self._t_last = -math.inf
        self._e: OnlineEstimate | None = None

    def rows(self, rows: np.ndarray, sim: np.ndarray) -> None:
        t = rows[0, -1]
        if t - self._t_last < self.every_s:
            return
        self._t_last = t
        line = f"  t = {t:7.2f} s"
        if self._e is not None:
            line += "  " + "  ".join(f"{n} = {v:.4g} ± {self._e.std[n]:.2g}" for n, v in self._e.values.items())
            line += f"  σ = {self._e.sigma:.2f}"
        if self.counters:
            c = self.counters()
            line += "  " + "  ".join(f"{k} {v}" for k, v in c.items())
        self.print(line)

    def estimate(self, e: OnlineEstimate) -> None:
        self._e = e

    def close(self) -> None:
        pass


# ------------------------------------------------------------------ the session

@dataclass
class SessionResult:
    run: Run  # every sample received
    estimates: list[OnlineEstimate]
    stop_reason: str
    counters: dict
    events: list[str] = field(default_factory=list)

    @property
    def final(self) -> OnlineEstimate | None:
        return self.estimates[-1] if self.estimates else None


def run_session(cyl: Cylinder, rig: Rig, *, estimator, program=None, duration: float | None = None,
                record_to: str | os.PathLike | None = None, record_comments: Sequence[str] = (),
                sinks: Sequence[Sink] = (), simulator: LockstepSimulator | None = None,
                on_event: Callable[[str], None] | None = None, block: int = 20,
                give_up_s: float = 3.0, expected_period: float | None = None) -> SessionResult:
    """Acquire until `duration` of rig time, the end of a replayed run, a rig that stays
    silent for `give_up_s`, or Ctrl-C; every sample is recorded the moment it arrives (the
    file is opened with the first sample, with a `ps` column if the rig measures it)."""
    events: list[str] = []

    def event(msg: str) -> None:
        events.append(msg)
        if on_event:
            on_event(msg)

    cols: list[list[float]] = [[] for _ in range(6)]  # t, u, x, p1, p2, ps
    pending: list[tuple] = []
    estimates: list[OnlineEstimate] = []
    counters = {"samples": 0, "gaps": 0, "estimates": 0}
    t0 = None
    t_prev = seq_prev = None
    dt_nominal = None
    first_dts: list[float] = []
    reason = "duration reached"
    last_sample_wall = time.monotonic()

    def flush_block() -> None:
        if not pending:
            return
        rows_all = np.array(pending).T  # t, u, x, p1, p2, lost_before
        rows = rows_all[:5]
        pending.clear()
        estimator.add(rows_all)
        sim = None
        if simulator is not None:
            sim = simulator.advance(rows)
        for s in sinks:
            s.rows(rows, sim)
        for e in estimator.poll():
            take(e)

    def take(e: OnlineEstimate) -> None:
        estimates.append(e)
        counters["estimates"] += 1
        if simulator is not None:
            simulator.set_estimate(e)
        for s in sinks:
            s.estimate(e)

    # a full garbage collection can pause the loop for tens of milliseconds, long enough for
    # the rig's watchdog: collect now and keep what exists out of later collections
    gc.collect()
    gc.freeze()
    recorder: RunRecorder | None = None
    rig.start()
    try:
        while True:
            try:
                s = rig.read(timeout=0.1)
            except EndOfRun:
                reason = "end of the recorded run"
                break
            if s is None:
                silent = time.monotonic() - last_sample_wall
                if silent >= give_up_s:
                    reason = f"no samples for {silent:.1f} s: the rig has gone"
                    event(f"rig silent for {silent:.1f} s; stopping (the recording holds every sample received)")
                    break
                continue
            last_sample_wall = time.monotonic()
            if t0 is None:
                t0 = s.t
                if record_to is not None:
                    recorder = RunRecorder(record_to, with_ps=s.ps is not None, comments=record_comments)
            if program is not None:
                rig.send(program.command(s.t - t0, s.x))
            lost_before = False
            if t_prev is not None:
                dt = s.t - t_prev
                if dt <= 0:
                    event(f"sample at t = {s.t:.6f} s does not advance the rig clock; dropped")
                    continue
                if len(first_dts) < 50:
                    first_dts.append(dt)
                    dt_nominal = float(np.median(first_dts))
                    if len(first_dts) == 50 and expected_period and abs(dt_nominal / expected_period - 1) > 0.02:
                        event(f"the rig samples every {dt_nominal * 1e3:.4g} ms, not every {expected_period * 1e3:.4g} ms "
                              "as expected (--rate): the estimator's windows are that much longer or shorter")
                if s.seq is not None and seq_prev is not None:
                    lost_before = s.seq != seq_prev + 1  # the rig numbers its samples: exact
                elif len(first_dts) == 50:
                    lost_before = dt > 1.9 * dt_nominal  # at least one period without a sample
                counters["gaps"] += lost_before
            t_prev, seq_prev = s.t, s.seq
            ps = s.ps if s.ps is not None and math.isfinite(s.ps) else None
            if recorder is not None:
                recorder.append(s.t, s.u_applied, s.x, s.p1, s.p2, s.ps if recorder.with_ps else None)
            for c, v in zip(cols, (s.t, s.u_applied, s.x, s.p1, s.p2, ps if ps is not None else math.nan)):
                c.append(v)
            counters["samples"] += 1
            pending.append((s.t, s.u_applied, s.x, s.p1, s.p2, float(lost_before)))
            if len(pending) >= block:
                flush_block()
            if duration is not None and s.t - t0 >= duration:
                break
    except KeyboardInterrupt:
        reason = "interrupted (Ctrl-C)"
        event("interrupted: valve centred, recording closed")
    finally:
        try:
            rig.stop()
        finally:
            gc.unfreeze()
            if recorder is not None:
                recorder.close()
    flush_block()
    for e in estimator.finish():
        take(e)
    if getattr(estimator, "error", None):
        event(f"online estimator failed: {estimator.error}")
    for s in sinks:
        s.close()
    n = len(cols[0])
    ps_col = np.array(cols[5]) if n and not np.all(np.isnan(cols[5])) else None
    run = Run(t=np.array(cols[0]), u=np.array(cols[1]), x=np.array(cols[2]), p1=np.array(cols[3]),
              p2=np.array(cols[4]), ps=ps_col)
    stats = getattr(rig, "stats", None)
    if stats is not None:
        counters.update({k: v for k, v in vars(stats).items() if isinstance(v, (int, float))})
    return SessionResult(run=run, estimates=estimates, stop_reason=reason, counters=counters, events=events)
