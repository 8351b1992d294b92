"""Rerun logging of a session: measured vs simulated traces, the command, residuals,
parameter estimates with confidence bands over time, and friction against velocity.

`RerunProcessSink` does the logging in a process of its own: encoding and sending cost the
acquisition loop nothing, and a viewer that does not start, hangs or goes away (Rerun then
waits in native code, deaf to signals) can hold up only that process, which the session
ends when it ends.

Entity paths (SI units; the timeline `time` is the rig clock):
  position/measured, position/simulated                     m
  pressure/p1/measured, pressure/p1/simulated, p2 likewise  Pa
  command/u                                                  1
  residual/x, residual/p1, residual/p2                       measured - simulated
  params/NAME/value, params/NAME/upper, params/NAME/lower    estimate and +-2 sigma band
  fit/sigma                                                  residual RMS in noise units
  fit/mismatch_limit                                         above it the model does not explain the rig
  events/changes     TextLog at each detected change's located time (the change in words)
  events/monitor     TextLog of what the session judged, when it said so (validity, changes, drift)
  friction/measured  Points2D (v, F) from Newton's law with measured pressures, last window
  friction/model     LineStrips2D, the identified friction curve at the window's mean |p1-p2|
"""
from __future__ import annotations

import multiprocessing as mp
import os
import queue
import signal
import time
from typing import Callable

import numpy as np
import rerun as rr

from sim.cylinder import Cylinder
from sim.plant import build_plant, plant_for

from ..files import Run
from ..identify import MISMATCH, OnlineEstimate, friction_from_newton
from ..report.rerun import close_recording, display_available, open_recording
from .messages import pending
from .monitor import change_message


class RerunSink:
    """A session sink that logs to a Rerun recording (see the entity paths above)."""

    def __init__(self, rec: rr.RecordingStream, cyl: Cylinder, window_s: float = 2.0):
        self.rec, self.cyl, self.window_s = rec, cyl, window_s
        self._plant = plant_for(cyl, "command")
        self._pressure_plant = build_plant("pressure")
        self._buf = np.empty((5, 0))

    def rows(self, rows: np.ndarray, sim: np.ndarray | None) -> None:
        t, u, x, p1, p2 = rows
        idx = [rr.TimeColumn("time", duration=t)]
        send = self.rec.send_columns
        send("position/measured", indexes=idx, columns=rr.Scalars.columns(scalars=x))
        send("pressure/p1/measured", indexes=idx, columns=rr.Scalars.columns(scalars=p1))
        send("pressure/p2/measured", indexes=idx, columns=rr.Scalars.columns(scalars=p2))
        send("command/u", indexes=idx, columns=rr.Scalars.columns(scalars=u))
        if sim is not None:
            for name, meas, s in (("x", x, sim[0]), ("p1", p1, sim[1]), ("p2", p2, sim[2])):
                path = "position/simulated" if name == "x" else f"pressure/{name}/simulated"
                send(path, indexes=idx, columns=rr.Scalars.columns(scalars=s))
                send(f"residual/{name}", indexes=idx, columns=rr.Scalars.columns(scalars=meas - s))
        self._buf = np.hstack([self._buf, rows])
        keep = int(np.searchsorted(self._buf[0], self._buf[0, -1] - self.window_s))
        self._buf = self._buf[:, keep:]

    def estimate(self, e: OnlineEstimate) -> None:
        rec = self.rec
        rec.set_time("time", duration=e.t)
        for n, v in e.values.items():
            s = e.std[n]
            rec.log(f"params/{n}/value", rr.Scalars(v))
            if np.isfinite(s):
                rec.log(f"params/{n}/upper", rr.Scalars(v + 2 * s))
                rec.log(f"params/{n}/lower", rr.Scalars(v - 2 * s))
        rec.log("fit/sigma", rr.Scalars(e.sigma))
        rec.log("fit/mismatch_limit", rr.Scalars(MISMATCH))
        self._log_friction(e)
        if e.change is not None:  # marked on the time line where it happened
            rec.set_time("time", duration=e.change.t)
            rec.log("events/changes", rr.TextLog(change_message(e.change, e.units), level=rr.TextLogLevel.WARN))

    def note(self, t: float, text: str) -> None:
        self.rec.set_time("time", duration=t)
        self.rec.log("events/monitor", rr.TextLog(text, level=rr.TextLogLevel.INFO))

    def _log_friction(self, e: OnlineEstimate) -> None:
        b = self._buf
        if b.shape[1] < 100:
            return
        run = Run(t=b[0], u=b[1], x=b[2], p1=b[3], p2=b[4])
        idx, v, F = friction_from_newton(self.cyl, run, plant=self._pressure_plant)
        if len(idx):
            step = max(1, len(idx) // 400)
            self.rec.log("friction/measured", rr.Points2D(np.column_stack([v[::step], F[::step]]), radii=0.5))
        vmax = max(float(np.max(np.abs(v))) if len(idx) else 0.0, 0.05)
        grid = np.linspace(-vmax, vmax, 201)
        plant = self._plant
        dp = float(np.mean(np.abs(b[3] - b[4])))
        states = np.zeros((plant.nx, len(grid)))
        names = plant.state_names
        states[names.index("p1")] = 3e5 + dp
        states[names.index("p2")] = 3e5
        states[names.index("x")] = 0.5 * self.cyl.geometry.stroke
        states[names.index("v")] = grid
        curve = np.asarray(plant.friction.map(len(grid))(states, np.zeros((1, len(grid))),
                                                        np.tile(e.params[:, None], (1, len(grid))))).ravel()
        self.rec.log("friction/model", rr.LineStrips2D([np.column_stack([grid, curve])]))

    def close(self, timeout_s: float = 2.0) -> bool:
        """False if the data could not be delivered (a viewer that went away)."""
        return close_recording(self.rec, timeout_s)


def _rerun_main(mode: str, target: str | None, fallback: str | None, cyl: Cylinder, window_s: float, inbox, outbox,
                parent: int, hurry) -> None:
    """The sink process: open the recording (a viewer that cannot start: the fallback file),
    log what arrives, flush at "close". It ends with its parent, even one killed outright."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the session's: it ends this process
    try:
        sink = RerunSink(open_recording(mode, target, fallback=fallback, say=lambda m: outbox.put(("say", m))),
                         cyl, window_s)
        while True:
            try:
                msg = inbox.get(timeout=0.5)
            except queue.Empty:
                if os.getppid() != parent:
                    return
                continue
            kind, value = msg
            if hurry.is_set():  # a stopped session: what is still queued is dropped, the view closed
                kind = "close"
            if kind == "rows":
                sink.rows(*value)
            elif kind == "estimate":
                sink.estimate(value)
            elif kind == "note":
                sink.note(*value)
            else:  # "close"
                ok = sink.close()
                outbox.put(("closed", ok))
                return
    except Exception as exc:  # said by the session, which goes on without the view
        outbox.put(("error", f"{type(exc).__name__}: {exc}"))


class RerunProcessSink:
    """A RerunSink in its own process (see the module's docstring). `close` waits for the
    view to be complete (a file, a viewer that takes the data) or at most `close_timeout_s`."""

    def __init__(self, mode: str, target: str | None, cyl: Cylinder, window_s: float = 2.0, *,
                 fallback: str | os.PathLike | None = None, say: Callable[[str], None] | None = None):
        ctx = mp.get_context("spawn")
        self.inbox, self.outbox = ctx.Queue(), ctx.Queue()
        self._hurry = ctx.Event()
        self.say = say or (lambda m: None)
        self.proc = ctx.Process(target=_rerun_main, name="combined-reality-rerun", daemon=True,
                                args=(mode, target, None if fallback is None else str(fallback), cyl, window_s,
                                      self.inbox, self.outbox, os.getpid(), self._hurry))
        self.proc.start()
        self.failed = False
        self.close_timeout_s = 60.0  # how long close() lets the view finish (see hurry)
        # a file cannot hang; a viewer can
        self._to_file = mode == "save" or (mode == "spawn" and not display_available())

    def hurry(self) -> None:
        """The session was stopped (it ends within a second): what the view has not logged yet
        is dropped, and a file gets 0.4 s to be closed complete, a viewer 0.2 s to take the
        data."""
        self.close_timeout_s = 0.4 if self._to_file else 0.2
        self._hurry.set()

    def rows(self, rows: np.ndarray, sim: np.ndarray | None) -> None:
        self._poll()
        if not self.failed:
            self.inbox.put(("rows", (rows, sim)))

    def estimate(self, e: OnlineEstimate) -> None:
        if not self.failed:
            self.inbox.put(("estimate", e))

    def note(self, t: float, text: str) -> None:
        if not self.failed:
            self.inbox.put(("note", (t, text)))

    def _poll(self) -> bool | None:
        """Pass on what the sink process said; its "closed" answer, if any."""
        for kind, value in pending(self.outbox):
            if kind == "say":
                self.say(value)
            elif kind == "error":
                self.failed = True
                self.say(f"Rerun view failed ({value}); the session goes on without it")
            elif kind == "closed":
                if not value:
                    self.say("the Rerun viewer did not take the last data (it went away)")
                return value
        return None

    def close(self) -> None:
        """Let the view finish (for at most close_timeout_s), then end the process whatever it does."""
        closed = None
        if self.proc.is_alive() and not self.failed:
            self.inbox.put(("close", None))
            deadline = time.monotonic() + self.close_timeout_s
            while closed is None and self.proc.is_alive() and time.monotonic() < deadline:
                closed = self._poll()
                self.proc.join(0.05)
            if closed is None:
                closed = self._poll()
            if closed is None and not self.failed:
                self.say(f"the Rerun view was not finished within {self.close_timeout_s:g} s; ended")
        self.inbox.cancel_join_thread()  # what the process did not take is dropped, not waited for
        if self.proc.is_alive():
            self.proc.kill()
        self.proc.join(1.0)
