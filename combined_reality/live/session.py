"""The streaming pipeline: source -> lock-step simulation -> online estimator -> sinks.

A source is any rig (hw.rig.Rig): serial, CAN, the in-process virtual rig, or a recorded
run replayed at real time or as fast as possible. The session reads a sample, asks the
experiment program for the next command (live rigs only), records the row at once, and
hands blocks of rows to the lock-step simulation, the estimator and the sinks. The
estimator runs in its own process when acquisition must never wait for it, or inline when
replaying as fast as possible.
"""
from __future__ import annotations

import array
import gc
import math
import multiprocessing as mp
import os
import queue
import signal
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Protocol, Sequence

import numpy as np
from threadpoolctl import threadpool_limits

from hw.protocol import EventLimiter
from hw.realtime import make_normal, take_host_priority
from hw.rig import Rig, Sample, Status
from hw.virtual_rig import VirtualRig
from sim.compiled import NumpyCall, shooting_functions
from sim.cylinder import Cylinder
from sim.extension import Effect
from sim.plant import plant_for

from ..files import Run, RunRecorder, measured_value
from ..files.plausibility import COMMAND_LIMIT
from ..identify import MovingHorizonEstimator, OnlineEstimate, OnlineOptions
from .console import Console
from .messages import pending
from .monitor import SessionMonitor


class EndOfRun(Exception):
    """A finite source (a replayed file) has no more samples."""


# ------------------------------------------------------------------ sources

_REPLAY_BLOCK = 4096  # rows a replay turns into Python floats at a time


class ReplayRig(Rig):
    """A recorded run as a rig: samples at their recorded times (scaled by `speed`), or as
    fast as possible (speed = inf). Commands sent to it are ignored: it reports the
    recorded command as the one applied."""

    def __init__(self, run: Run, speed: float = 1.0):
        self.run, self.speed = run, speed
        self.k = 0
        self._wall0 = None
        # Python floats a block of rows at a time: indexing numpy arrays sample by sample cost a
        # tenth of a fast replay, the whole run as tuples 230 bytes a sample (138 MB on 600 s)
        self._ps = run.ps if run.ps is not None else np.full(run.n, np.nan)
        self._rows: list[tuple[float, ...]] = []
        self._row0 = 0

    def start(self) -> None:
        self._wall0 = time.perf_counter()

    def read(self, timeout: float | None = None) -> Sample | None:
        r, k = self.run, self.k
        if k >= r.n:
            raise EndOfRun()
        if math.isfinite(self.speed):
            due = self._wall0 + (r.t[k] - r.t[0]) / self.speed
            delay = due - time.perf_counter()
            if timeout is not None and delay > timeout:  # a long pause in the file: like a quiet rig
                time.sleep(timeout)
                return None
            if delay > 0:
                time.sleep(delay)
        self.k += 1
        if k - self._row0 >= len(self._rows):
            b = min(r.n, k + _REPLAY_BLOCK)
            self._rows = list(zip(*(a[k:b].tolist() for a in (r.t, r.u, r.x, r.p1, r.p2, self._ps))))
            self._row0 = k
        t, u, x, p1, p2, ps = self._rows[k - self._row0]
        return Sample(t=t, x=x, p1=p1, p2=p2, ps=ps if math.isfinite(ps) else None,  # an empty cell: not measured
                      u_applied=u)

    def send(self, u: float) -> None:
        pass

    def stop(self) -> None:
        pass


class PacedRig(Rig):
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

class Estimator(Protocol):
    """The online estimator as the session sees it, wherever it runs: InlineEstimator in the
    calling thread, PipelinedEstimator in a worker thread, ProcessEstimator in its own process."""

    error: str | None  # why it stopped estimating (the session keeps acquiring); None while it works

    def add(self, rows: np.ndarray) -> None:
        """Take a block of rows: t, u, x, p1, p2, lost_before (6, n)."""
        ...

    def poll(self) -> list[OnlineEstimate]:
        """The estimates due since the last poll, in order."""
        ...

    def finish(self, timeout: float = 30.0, cancelled: Callable[[], bool] = ...) -> list[OnlineEstimate]:
        """Take in every row added (for at most `timeout` s, or until `cancelled()`): the last estimates."""
        ...

    def close(self) -> None: ...


class InlineEstimator:
    """The moving-horizon estimator in the calling thread (replay as fast as possible).

    With `catch_up`, it updates once half a window of new data is there: the same data enter
    the estimate with a fifth of the updates, each a single Gauss-Newton iteration on a
    window it mostly knows, and a change of the rig is tested every half window. The window
    grows to one and a half before the oldest whole window leaves it (OnlineOptions.hold_s):
    the arrival cost takes in whole windows, as when whole windows were slid."""

    error: str | None = None  # never set: a failure here is the caller's exception

    def __init__(self, cyl: Cylinder, sample_period: float, options: OnlineOptions, effects: Sequence[Effect] = (),
                 catch_up: bool = True):
        if catch_up:
            options = replace(options, hold_s=max(options.hold_s, 1.5 * options.window_s))
        self.mhe = MovingHorizonEstimator(cyl, sample_period, options, effects)
        self.catch_up = catch_up

    def add(self, rows: np.ndarray) -> None:
        self.mhe.add(*rows[:5], lost_before=rows[5])

    def poll(self, final: bool = False) -> list[OnlineEstimate]:
        out = []
        while self.mhe.ready() and (final or not self.catch_up or self.mhe.backlog >= self.mhe.N // 2
                                    or not out and not self.mhe.started):
            out.append(self.mhe.update())
        return out

    def finish(self, timeout: float = 30.0, cancelled: Callable[[], bool] = lambda: False) -> list[OnlineEstimate]:
        self.mhe.flush()
        return self.poll(final=True)

    def close(self) -> None:
        pass


class PipelinedEstimator:
    """The moving-horizon estimator in a worker thread, one window behind the rows: replay as
    fast as possible on two cores (the compiled model and numpy release the GIL, so one
    window's update runs while the next window's rows are read, recorded and simulated).

    Deterministic whatever the machine's speed: the thread updates exactly as InlineEstimator
    with catch_up does, and an estimate is handed out once the rows sent reach the end of the
    block that made it due plus one window (poll waits for the thread if it is behind)."""

    def __init__(self, cyl: Cylinder, sample_period: float, options: OnlineOptions, effects: Sequence[Effect] = ()):
        self._inline = InlineEstimator(cyl, sample_period, options, effects, catch_up=True)
        self.lag = self._inline.mhe.N  # rows
        self._inbox: queue.SimpleQueue = queue.SimpleQueue()
        self._cond = threading.Condition()
        self._sent = 0
        self._taken = 0  # rows the thread has taken in, with the updates they made due
        self._due: list[tuple[int, OnlineEstimate]] = []  # (rows taken when due, estimate), in order
        self._finished = False
        self.error: str | None = None
        self._thread = threading.Thread(target=self._work, name="combined-reality-estimator", daemon=True)
        self._thread.start()

    def _work(self) -> None:
        # one BLAS thread, as in the estimator process: its own threads would compete with this
        # one and the session's for two cores
        with threadpool_limits(1):
            while True:
                msg = self._inbox.get()
                if msg is None:
                    return
                try:
                    if msg is _FINISH:
                        out = self._inline.finish()
                    else:
                        self._inline.add(msg)
                        out = self._inline.poll()
                except Exception as exc:  # reported to the session, which keeps acquiring
                    with self._cond:
                        self.error = f"{type(exc).__name__}: {exc}"
                        self._cond.notify_all()
                    return
                with self._cond:
                    if msg is _FINISH:
                        self._finished = True
                    else:
                        self._taken += msg.shape[1]
                    self._due.extend((self._taken, e) for e in out)
                    self._cond.notify_all()

    def add(self, rows: np.ndarray) -> None:
        self._sent += rows.shape[1]
        self._inbox.put(np.array(rows, float))

    def _take(self, upto: float) -> list[OnlineEstimate]:
        i = 0
        while i < len(self._due) and self._due[i][0] <= upto:
            i += 1
        out = [e for _, e in self._due[:i]]
        del self._due[:i]
        return out

    def poll(self) -> list[OnlineEstimate]:
        target = self._sent - self.lag
        with self._cond:
            self._cond.wait_for(lambda: self._taken >= target or self.error is not None)
            return self._take(target)

    def finish(self, timeout: float = 30.0, cancelled: Callable[[], bool] = lambda: False) -> list[OnlineEstimate]:
        self._inbox.put(_FINISH)
        deadline = time.monotonic() + timeout
        with self._cond:
            while not (self._finished or self.error is not None) and not cancelled():
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._cond.wait(min(0.1, left))
            return self._take(math.inf)

    def close(self) -> None:
        self._inbox.put(None)
        self._thread.join(timeout=1.0)  # a daemon: an update still running ends with the process


_FINISH = object()  # PipelinedEstimator's inbox: flush and finish

# The estimator's nice increment. Behind acquisition and the link where acquisition has no
# real-time priority (they share the time-sharing scheduler); ahead of ordinary work where
# acquisition runs under SCHED_FIFO (it then cannot be delayed by the estimator, and the
# estimate keeps its update rate beside other work: with two busy processes on 2 cores an
# update at nice 0 got about 2/3 of a core, p95 ~75 ms against a 50 ms budget). Raising the
# priority needs root, CAP_SYS_NICE or a nice limit (limits.conf); without, it stays at nice 0.
ESTIMATOR_NICE_BEHIND = 10
ESTIMATOR_NICE_AHEAD = -10


def set_estimator_priority(nice: int) -> int:
    """Apply the nice increment `nice` to the calling process where the OS allows it (a
    negative one needs root or CAP_SYS_NICE); the nice value it then runs at."""
    try:
        return os.nice(nice)
    except OSError:
        return os.nice(0)


def _estimator_main(cyl, sample_period, options, effects, inbox, outbox, parent: int, nice: int) -> None:
    """The estimator process: take rows, update whenever a window is due, send estimates.
    It ends with its parent, even one killed outright (no orphan keeps computing)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the session's: it ends this process
    try:
        set_estimator_priority(nice)
        # one BLAS thread: OpenBLAS's own threads spin for work and, on a busy machine, take
        # twice the time of the one they would help (3 % of samples lost: update p50 73 -> 32 ms)
        threadpool_limits(1)
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
                    mhe.flush()
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
                 start_timeout: float = 120.0, nice: int = ESTIMATOR_NICE_BEHIND):
        """`nice`: the estimator process's nice increment (ESTIMATOR_NICE_BEHIND when
        acquisition shares the time-sharing scheduler with it, ESTIMATOR_NICE_AHEAD when
        acquisition runs at real-time priority)."""
        ctx = mp.get_context("spawn")
        self.inbox, self.outbox = ctx.Queue(), ctx.Queue()
        self.proc = ctx.Process(target=_estimator_main, name="combined-reality-estimator", daemon=True,
                                args=(cyl, sample_period, options, tuple(effects), self.inbox, self.outbox,
                                      os.getpid(), nice))
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
        for kind, value in pending(self.outbox):
            if kind == "estimate":
                out.append(value)
            elif kind == "error":
                self.error = value
        return out

    def finish(self, timeout: float = 30.0, cancelled: Callable[[], bool] = lambda: False) -> list[OnlineEstimate]:
        """Let the estimator take in everything sent so far (for at most `timeout`, or until
        `cancelled()`); its last estimates."""
        out = self.poll()
        if self.error or not self.proc.is_alive():
            return out
        self.inbox.put("finish")
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not cancelled():
            kind, value = self._get(min(0.1, max(0.01, deadline - time.monotonic())))
            if kind == "estimate":
                out.append(value)
            elif kind in ("done", "error") or (kind is None and not self.proc.is_alive()):
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
        self.plant = plant = plant_for(cyl, "command", effects)
        sf = shooting_functions(plant, 1, ())
        self.B = block
        # evaluated through buffers: a DM call costs more than the 20 steps it runs
        self._acc = NumpyCall(sf.step.mapaccum("lockstep", block, [0], [0]))  # states after each of B steps
        self._friction = NumpyCall(plant.friction.map(block))
        self.p = np.array(plant.parameter_vector(cyl), float)
        self.resync_s, self.history_s = resync_s, history_s
        self.state: np.ndarray | None = None  # at the last row seen
        self._t_sync = -math.inf
        self._pending: tuple[float, np.ndarray] | None = None  # (t, state) of the newest estimate
        self._hist = np.empty((3, 4 * block))  # recent rows (t, u, x): the first _n_hist columns
        self._n_hist = 0
        ix = plant.state_names.index
        self._out = [ix("x"), ix("p1"), ix("p2"), ix("v")]
        self._measured = (math.nan, math.nan, math.nan)  # the last measured x, p1, p2

    def set_estimate(self, e: OnlineEstimate) -> None:
        self.p = np.asarray(e.params, float)
        self._pending = (e.t, np.asarray(e.state, float))

    def _run(self, s0: np.ndarray, u: np.ndarray, h: np.ndarray) -> np.ndarray:
        """States after each step of holding u[i] for h[i], from s0: (nx, len(u))."""
        B, out = self.B, np.empty((self.plant.nx, len(u)))
        P = self.p[:, None]  # a column: NumpyCall gives it to every step of the block
        for a in range(0, len(u), B):
            m = min(B, len(u) - a)
            U, H = np.zeros(B), np.zeros(B)  # zero-length steps pad the block, leaving the state alone
            U[:m], H[:m] = u[a:a + m], h[a:a + m]
            X = self._acc(s0, U[None], U[None], P, H[None])[0]
            out[:, a:a + m] = X[:, :m]
            s0 = X[:, m - 1]
        return out

    def _remember(self, t: np.ndarray, u: np.ndarray, x: np.ndarray) -> np.ndarray:
        """The rows of at least the last history_s with this block's last, as a view (the
        buffer is compacted when full: a copy per block cost more than the block's simulation)."""
        n, h = len(t), self._hist
        if self._n_hist + n > h.shape[1]:
            keep = np.flatnonzero(h[0, :self._n_hist] >= t[-1] - self.history_s)
            kept = h[:, keep[0]:self._n_hist] if len(keep) else h[:, :0]
            if kept.shape[1] + n > h.shape[1] // 2:  # room for as many rows again before the next compaction
                h = np.empty((3, 2 * (kept.shape[1] + n)))
            h[:, :kept.shape[1]] = kept.copy()
            self._hist, self._n_hist = h, kept.shape[1]
        h[:, self._n_hist:self._n_hist + n] = (t, u, x)
        self._n_hist += n
        return h[:, :self._n_hist]

    def _nearest_measured(self, *values: float) -> tuple[float, float, float]:
        """(x, p1, p2) with the last measured value standing in for one not measured now."""
        out = tuple(v if math.isfinite(v) else last for v, last in zip(values, self._measured))
        self._measured = tuple(v if math.isfinite(v) else last for v, last in zip(out, self._measured))
        return tuple(v if math.isfinite(v) else 0.0 for v in out)

    def advance(self, rows: np.ndarray) -> np.ndarray:
        """Simulated (x, p1, p2, v, friction) at each row's time: (5, n), n <= block."""
        t, u, x, p1, p2 = rows
        n, nx = len(t), self.plant.nx
        hist = self._remember(t, u, x)
        if self._pending is not None and self.state is not None:
            te, se = self._pending
            i = int(np.searchsorted(hist[0], te - 1e-9))
            if (i < hist.shape[1] and abs(hist[0, i] - te) < 1e-6 and hist[0, i] <= t[0] - 1e-12
                    and te >= t[-1] - self.history_s):
                j = hist.shape[1] - n  # rows before this block: carry the estimate up to the last of them
                hs = np.diff(hist[0, i:j + 1])[: j - i - 1] if j - i > 1 else np.empty(0)
                self.state = self._run(se, hist[1, i:j - 1], hs)[:, -1] if len(hs) else se
                self._t_sync = te
            self._pending = None
        states = np.empty((nx, n))
        k = 0
        while k < n:
            measured = math.isfinite(x[k]) and math.isfinite(p1[k]) and math.isfinite(p2[k])
            stale = self.state is None or t[k] - self._t_sync >= self.resync_s or not np.all(np.isfinite(self.state))
            if stale and (measured or self.state is None or not np.all(np.isfinite(self.state))):
                # no estimate lately: start again from the measured state (velocity from a
                # quadratic through the last measured positions; the nearest measured values
                # stand in for a channel not measured until one is)
                j = hist.shape[1] - n + k
                ja = max(0, j - 19)
                tt, xx = hist[0, ja:j + 1] - hist[0, j], hist[2, ja:j + 1]
                ok = np.isfinite(xx)
                v = float(np.polyfit(tt[ok], xx[ok], 2)[1]) if ok.sum() >= 4 else 0.0
                states[:, k] = self.plant.initial_state(self.cyl, *self._nearest_measured(x[k], p1[k], p2[k]), v)
                self._t_sync = t[k]
                self.state = states[:, k]
                self._last = (t[k], u[k])
                k += 1
                continue
            # this row and the rest of the block in one call, up to a resynchronisation: each
            # row is the step from the row before it, holding that row's command
            m = 1
            while k + m < n and t[k + m] - self._t_sync < self.resync_s:
                m += 1
            t_from = np.r_[self._last[0], t[k:k + m - 1]]
            u_held = np.r_[self._last[1], u[k:k + m - 1]]
            states[:, k:k + m] = self._run(self.state, u_held, t[k:k + m] - t_from)
            self.state = states[:, k + m - 1]
            self._last = (t[k + m - 1], u[k + m - 1])
            k += m
        S = np.zeros((nx, self.B))
        S[:, :n] = states
        Uf = np.zeros(self.B)
        Uf[:n] = u
        F = self._friction(S, Uf[None], self.p[:, None])[0].ravel()[:n]
        return np.vstack([states[self._out], F[None]])


# ------------------------------------------------------------------ sinks

class Sink(Protocol):
    def rows(self, rows: np.ndarray, sim: np.ndarray | None) -> None: ...
    def estimate(self, e: OnlineEstimate) -> None: ...
    def note(self, t: float, text: str) -> None:
        """What the session judged of the rig at data time `t` (a sink may ignore it)."""
        ...
    def close(self) -> None: ...


class ConsoleSink:
    """The session's status line: session time, sample rate, link counters, the latest
    estimate with its standard deviation, and with a monitor whether the model explains the
    rig and the last change (times from the session's first sample, not the rig's clock)."""

    def __init__(self, console: Console, counters: Callable[[], dict] | None = None,
                 monitor: SessionMonitor | None = None):
        self.console, self.counters, self.monitor = console, counters, monitor
        self._t0: float | None = None
        self._e: OnlineEstimate | None = None
        self._rate = (time.monotonic(), 0, 0.0)  # (wall, samples, rate) of the last rate update
        self._n = 0

    def rows(self, rows: np.ndarray, sim: np.ndarray) -> None:
        if self._t0 is None:
            self._t0 = float(rows[0, 0])
        self._n += rows.shape[1]
        now = time.monotonic()
        wall, n, rate = self._rate
        if now - wall >= 1.0:
            self._rate = (now, self._n, (self._n - n) / (now - wall))
        self.console.status(self._line(float(rows[0, -1])))

    def _line(self, t: float) -> str:
        parts = [f"t {t - self._t0:6.1f} s", f"{self._rate[2]:5.0f} samples/s"]
        if self.counters:
            parts += [f"{k} {v}" for k, v in self.counters().items()]
        if self._e is not None:
            parts.append("  ".join(f"{n} {v:.5g} ± {self._e.std[n]:.2g}" for n, v in self._e.values.items())
                         + f"  σ {self._e.sigma:.2f}")
        else:
            parts.append("estimate: waiting for the first window")
        m = self.monitor
        if m is not None and m.explained is not None:
            parts.append("model explains the rig" if m.trusted else "MODEL DOES NOT EXPLAIN THE RIG: estimate untrusted")
            if m.changes:
                parts.append(f"changed at {m.changes[-1].t - m.t0:.1f} s")
            if m.drifts and m.drifts[-1]["t_end"] is None:
                parts.append("drifting")
        return " | ".join(parts)

    def estimate(self, e: OnlineEstimate) -> None:
        self._e = e

    def note(self, t: float, text: str) -> None:
        pass  # the session says its judgements on the console itself

    def close(self) -> None:
        self.console.close()


# ------------------------------------------------------------------ the session

@dataclass
class SessionResult:
    run: Run  # every sample received
    estimates: list[OnlineEstimate]
    stop_reason: str
    counters: dict
    events: list[str] = field(default_factory=list)
    t0: float = 0.0  # rig time of the first sample: session times are rig times minus this
    monitor: SessionMonitor = field(default_factory=SessionMonitor)  # what the session judged of the rig

    @property
    def final(self) -> OnlineEstimate | None:
        return self.estimates[-1] if self.estimates else None

    def document(self, options: OnlineOptions, wall_s: float, link_events: Sequence[str] = (),
                 no_estimate: str | None = None) -> dict:
        """live's and replay's JSON document (docs/formats.md): the last estimate (none where
        `no_estimate` says why the recording cannot determine the parameters), the solver's
        figures, the link's counters, every event, the history and the monitor's judgement."""
        final = None if no_estimate else self.final
        walls = np.array([e.wall_s for e in self.estimates]) * 1e3
        out = {"params": {}, "fit": {}, "solver": {
            "status": "online" if final else "no_estimate", "method": "moving-horizon multiple shooting",
            **({"reason": no_estimate} if no_estimate else {}), "explains_run": self.monitor.trusted,
            "updates": len(self.estimates), "window_s": options.window_s, "wall_s": round(wall_s, 3),
            "update_ms_p50": float(np.percentile(walls, 50)) if len(walls) else None,
            "update_ms_p95": float(np.percentile(walls, 95)) if len(walls) else None,
            "n_samples": int(self.run.n), "stop_reason": self.stop_reason, "rig_time_at_start": self.t0},
            "link": self.counters, "events": self.events + list(link_events),
            # t: s since the session's first sample; t_rig: the rig's clock (the recording's t)
            "history": [{"t": e.t - self.t0, "t_rig": e.t, "values": e.values, "std": e.std, "sigma": e.sigma,
                         **({"drift": e.drift.rate} if e.drift else {})} for e in self.estimates],
            "monitor": self.monitor.to_json()}
        if final:
            out["params"] = {n: {"value": final.values[n], "std": final.std[n], "unit": final.units[n]}
                             for n in final.values}
            out["fit"] = {**final.rmse, "sigma": final.sigma, "window": list(final.window)}
        return out


class _Recording:
    """Every sample the session takes, in order: the file (opened with the first sample, with
    a ps column if the rig measures supply pressure then) and the columns of the Run."""

    def __init__(self, path, comments: Sequence[str], event: Callable[[str], None]):
        self.path, self.comments, self.event = path, comments, event
        self.recorder: RunRecorder | None = None
        # t, u, x, p1, p2, ps as machine doubles (8 bytes a value; a list of floats took 32: 690 MB an hour)
        self.cols = [array.array("d") for _ in range(6)]
        self._ps_unrecorded = False

    def append(self, t: float, u: float, x: float, p1: float, p2: float, ps: float | None) -> None:
        if self.path is not None and self.recorder is None:
            self.recorder = RunRecorder(self.path, with_ps=ps is not None, comments=self.comments)
        if self.recorder is not None:
            if ps is not None and not self.recorder.with_ps and not self._ps_unrecorded:
                self._ps_unrecorded = True
                self.event(f"the rig reports supply pressure from t = {t:.3f} s (rig clock) on; the recording "
                           "began without it and leaves it out")
            self.recorder.append(t, u, x, p1, p2, ps if self.recorder.with_ps else None, checked=True)
        for c, v in zip(self.cols, (t, u, x, p1, p2, math.nan if ps is None else ps)):
            c.append(v)

    def close(self) -> None:
        if self.recorder is not None:
            self.recorder.close()

    def run(self) -> Run:
        c = [np.frombuffer(col, float) if len(col) else np.empty(0) for col in self.cols]  # views, no copies
        ps = c[5] if len(c[5]) and not np.all(np.isnan(c[5])) else None
        return Run(t=c[0], u=c[1], x=c[2], p1=c[3], p2=c[4], ps=ps)




def run_session(cyl: Cylinder, rig: Rig, *, estimator: Estimator, program=None, duration: float | None = None,
                record_to: str | os.PathLike | None = None, record_comments: Sequence[str] = (),
                sinks: Sequence[Sink] = (), simulator: LockstepSimulator | None = None,
                on_event: Callable[[str], None] | None = None, block: int = 20,
                give_up_s: float = 3.0, expected_period: float | None = None,
                stop: Callable[[], str | None] | None = None, finish_timeout_s: float = 30.0,
                realtime: int | None = None, monitor: SessionMonitor | None = None,
                on_judgement: Callable[[str], None] | None = None) -> SessionResult:
    """Acquire until `duration` of rig time, the end of a replayed run, a rig that stays
    silent for `give_up_s`, Ctrl-C, or `stop()` returning a reason (checked at least every
    0.1 s: a signal handler sets it). Every sample received is recorded the moment it
    arrives, in order, also the ones still queued when acquisition stops; a channel the rig
    did not measure (missing or not finite) is an empty cell. After a stop the estimator gets
    at most 0.1 s to finish (the session ends within a second), else `finish_timeout_s`.
    With `realtime`, acquisition (this thread and the rig's reader) runs under SCHED_FIFO
    at that priority where the OS grants it: other processes then cannot delay the answer
    to a sample. `monitor` judges every estimate (validity, changes of the rig); what it says
    joins the events and goes to `on_judgement` (else on_event) and to every sink's
    `note(t, text)`."""
    session = _Session(estimator, sinks, simulator, monitor if monitor is not None else SessionMonitor(),
                       on_event, on_judgement, block, expected_period, record_to, record_comments)
    # a full garbage collection can pause the loop for tens of milliseconds, long enough for
    # the rig's watchdog: collect now and keep what exists out of later collections
    gc.collect()
    gc.freeze()
    rig.start()
    taken = session.take_priority(rig, realtime)
    stats = None
    try:
        reason, stopped = session.acquire(rig, program, duration, give_up_s, stop)
    except KeyboardInterrupt:
        reason, stopped = "interrupted (Ctrl-C)", True
    finally:
        try:
            stats = session.stop_rig(rig)
        finally:
            gc.unfreeze()
            session.rec.close()
            if taken:
                make_normal()
    if stopped:
        session.event(f"{reason}: valve centred, recording closed")
    # a signal while the estimator finishes ends that too (the session ends within a second)
    session.finish(0.1 if stopped else finish_timeout_s, cancelled=lambda: stop is not None and stop() is not None)
    if stats is not None:  # the link's counters; "samples" stays the rows taken (the recording's, the run's)
        session.counters.update({("received" if k == "samples" else k): v for k, v in vars(stats).items()
                                 if isinstance(v, (int, float))})
    return SessionResult(run=session.rec.run(), estimates=session.estimates, stop_reason=reason,
                         counters=session.counters, events=session.events,
                         t0=0.0 if session.t0 is None else session.t0, monitor=session.monitor)


class _Session:
    """One session while it runs: the samples taken (recorded, and queued in blocks for the
    model, the estimator and the sinks), the estimates, the counters and what was said."""

    def __init__(self, estimator: Estimator, sinks: Sequence[Sink], simulator: LockstepSimulator | None,
                 monitor: SessionMonitor, on_event: Callable[[str], None] | None,
                 on_judgement: Callable[[str], None] | None, block: int, expected_period: float | None,
                 record_to: str | os.PathLike | None, record_comments: Sequence[str]):
        self.estimator, self.sinks, self.simulator, self.monitor = estimator, sinks, simulator, monitor
        self.on_event, self.on_judgement = on_event, on_judgement
        self.block, self.expected_period = block, expected_period
        self.rec = _Recording(record_to, record_comments, self.event)
        self.events: list[str] = []
        # what may come with every sample (a sensor that dropped out) is said once a second at most
        self.per_sample = EventLimiter(1.0)
        self.pending: list[tuple] = []
        self.estimates: list[OnlineEstimate] = []
        self.counters = {"samples": 0, "gaps": 0, "estimates": 0, "incomplete": 0, "invalid": 0, "rig_overruns": 0}
        self.t0: float | None = None
        self.t_prev: float | None = None
        self.seq_prev: int | None = None
        self.dt_nominal: float | None = None
        self.first_dts: list[float] = []

    def event(self, msg: str) -> None:
        self.events.append(msg)
        if self.on_event:
            self.on_event(msg)

    def sample_event(self, key: str, msg: str) -> None:
        self.per_sample.say(key, msg)
        for line in self.per_sample.pop_lines():
            self.event(line)

    def take_priority(self, rig: Rig, realtime: int | None) -> bool:
        """Whether acquisition runs under SCHED_FIFO (and gives it back at the end)."""
        if realtime is None:
            return False
        taken, why = take_host_priority(rig, realtime)
        if why is not None:
            self.event(f"acquisition runs without real-time priority ({why}): on a busy machine the answers to "
                       "samples come late more often (give this user an rtprio limit to change that)")
        return taken

    def acquire(self, rig: Rig, program, duration: float | None, give_up_s: float,
                stop: Callable[[], str | None] | None) -> tuple[str, bool]:
        """Read, answer and take samples until the session ends: (why, whether it was stopped)."""
        last_sample_wall = time.monotonic()
        while True:
            why = stop() if stop is not None else None
            if why:
                return why, True
            try:
                s = rig.read(timeout=0.1)
            except EndOfRun:
                return "end of the recorded run", False
            if s is None:
                silent = time.monotonic() - last_sample_wall
                if silent >= give_up_s:
                    self.event(f"rig silent for {silent:.1f} s; stopping (the recording holds every sample received)")
                    return f"no samples for {silent:.1f} s: the rig has gone", False
                continue
            last_sample_wall = time.monotonic()
            if self.t0 is not None and program is not None:
                rig.send(program.command(s.t - self.t0, s.x))
            elif program is not None:
                rig.send(program.command(0.0, s.x))
            if self.take_sample(s) and duration is not None and s.t - self.t0 >= duration:
                return "duration reached", False

    def stop_rig(self, rig: Rig):
        """Stop the rig and take what arrived but was not read yet (nothing received is lost);
        the link's counters as the recording closes: they and the recording tell the same."""
        rig.stop()
        for s in rig.drain():
            self.take_sample(s)
        return rig.stats

    def finish(self, timeout: float, cancelled: Callable[[], bool]) -> None:
        """The last block to the model and the estimator, its last estimates, the sinks closed."""
        self.flush_block()
        for e in self.estimator.finish(timeout, cancelled=cancelled):
            self.take(e)
        if self.estimator.error:
            self.event(f"online estimator failed: {self.estimator.error}")
        for s in self.sinks:
            s.close()

    def flush_block(self) -> None:
        if not self.pending:
            return
        rows_all = np.array(self.pending).T  # t, u, x, p1, p2, lost_before
        rows = rows_all[:5]
        self.pending.clear()
        self.estimator.add(rows_all)
        sim = None
        if self.simulator is not None:
            sim = self.simulator.advance(rows)
        for s in self.sinks:
            s.rows(rows, sim)
        for e in self.estimator.poll():
            self.take(e)

    def take(self, e: OnlineEstimate) -> None:
        self.estimates.append(e)
        self.counters["estimates"] += 1
        if self.simulator is not None:
            self.simulator.set_estimate(e)
        self.monitor.t0 = self.t0
        judged = self.monitor.take(e)
        for s in self.sinks:
            s.estimate(e)
        for msg in judged:
            self.events.append(msg)
            (self.on_judgement or self.on_event or (lambda m: None))(msg)
            for s in self.sinks:
                s.note(e.t, msg)

    def take_sample(self, s: Sample) -> bool:
        """Record one sample and queue it for the model; False if it cannot be a row."""
        if (not (math.isfinite(s.t) and math.isfinite(s.u_applied)) or abs(s.u_applied) > COMMAND_LIMIT
                or (self.t_prev is not None and s.t <= self.t_prev)):
            # a row needs its time (after the one before) and the command the valve held
            self.counters["invalid"] += 1
            self.sample_event("invalid", f"a sample without a valid time or command (t = {s.t!r}, "
                                         f"u = {s.u_applied!r}) cannot be a row of the run; left out")
            return False
        if self.t0 is None:
            self.t0 = s.t
        lost_before = self.lost_before(s)
        self.t_prev, self.seq_prev = s.t, s.seq
        x, p1, p2, ps = self.measured(s)
        if s.status and s.status & Status.OVERRUN:  # a healthy sample skips the (slow) flag arithmetic
            self.counters["rig_overruns"] += 1
        self.rec.append(s.t, s.u_applied, x, p1, p2, None if math.isnan(ps) else ps)
        self.counters["samples"] += 1
        self.pending.append((s.t, s.u_applied, x, p1, p2, float(lost_before)))
        if len(self.pending) >= self.block:
            self.flush_block()
        return True

    def lost_before(self, s: Sample) -> bool:
        """Whether samples were lost before `s`: by the rig's sequence numbers where it numbers
        them (exact), else by a step of more than 1.9 sampling periods (the median of the first
        50 steps, said when it is not the expected one)."""
        if self.t_prev is None:
            return False
        dt = s.t - self.t_prev
        first_dts = self.first_dts
        if len(first_dts) < 50:
            first_dts.append(dt)
            self.dt_nominal = float(np.median(first_dts))
            expected = self.expected_period
            if len(first_dts) == 50 and expected and abs(self.dt_nominal / expected - 1) > 0.02:
                self.event(f"the rig samples every {self.dt_nominal * 1e3:.4g} ms, not every {expected * 1e3:.4g} "
                           "ms as expected (--rate): the estimator's windows are that much longer or shorter")
        lost = False
        if s.seq is not None and self.seq_prev is not None:
            lost = s.seq != self.seq_prev + 1  # the rig numbers its samples: exact
        elif len(first_dts) == 50:
            lost = dt > 1.9 * self.dt_nominal  # at least one period without a sample
        self.counters["gaps"] += lost
        return lost

    def measured(self, s: Sample) -> tuple[float, float, float, float]:
        """(x, p1, p2, ps), NaN where not measured: missing, not finite, or beyond any reading
        (a sensor or link fault); a sample without x, p1 or p2 is said (once a second at most)."""
        x, p1, p2, ps = (measured_value(n, v) for n, v in (("x", s.x), ("p1", s.p1), ("p2", s.p2), ("ps", s.ps)))
        if not (math.isfinite(x) and math.isfinite(p1) and math.isfinite(p2)):
            self.counters["incomplete"] += 1
            missing = ", ".join(n if getattr(s, n) is None or not math.isfinite(getattr(s, n))
                                else f"{n} (read {getattr(s, n):.4g}, not physical)"
                                for n, v in (("x", x), ("p1", p1), ("p2", p2)) if not math.isfinite(v))
            self.sample_event("incomplete", f"sample at t = {s.t - self.t0:.3f} s: {missing} not measured "
                                            "(recorded as an empty cell)")
        return x, p1, p2, ps
