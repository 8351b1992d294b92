"""Rerun logging of a session: measured vs simulated traces, the command, residuals,
parameter estimates with confidence bands over time, and friction against velocity.

Entity paths (SI units; the timeline `time` is the rig clock):
  position/measured, position/simulated                     m
  pressure/p1/measured, pressure/p1/simulated, p2 likewise  Pa
  command/u                                                  1
  residual/x, residual/p1, residual/p2                       measured - simulated
  params/NAME/value, params/NAME/upper, params/NAME/lower    estimate and +-2 sigma band
  fit/sigma                                                  residual RMS in noise units
  friction/measured  Points2D (v, F) from Newton's law with measured pressures, last window
  friction/model     LineStrips2D, the identified friction curve at the window's mean |p1-p2|
"""
from __future__ import annotations

import numpy as np
import rerun as rr

from sim.cylinder import Cylinder
from sim.plant import build_plant

from ..files import Run
from ..identify import OnlineEstimate, friction_from_newton


class RerunSink:
    """A session sink that logs to a Rerun recording (see the entity paths above)."""

    def __init__(self, rec: rr.RecordingStream, cyl: Cylinder, window_s: float = 2.0):
        self.rec, self.cyl, self.window_s = rec, cyl, window_s
        self._plant = build_plant("command")
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
        self._log_friction(e)

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

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()
