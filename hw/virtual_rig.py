"""The virtual rig: the nominal plant (plus switched-on effects as truth) with white sensor noise.

It is built from the same compiled plant as the identifier, integrated with a much
tighter tolerance (TRUTH_OPTIONS) so that identification tests include the
identifier's own discretisation error instead of reproducing it.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from sim.compiled import VectorCall, shooting_functions
from sim.cylinder import Cylinder
from sim.effects import Effect
from sim.integrator import TRUTH_OPTIONS, IntegratorOptions
from sim.plant import plant_for

from .rig import Rig, Sample, bounded


class VirtualRig(Rig):
    """An in-process rig: `read()` advances the plant by one sample period with the held command."""

    def __init__(self, cyl: Cylinder, effects: Sequence[Effect] = (), *, rate: float = 1000.0, seed: int = 0,
                 x0: float | None = None, noise: bool = True, integrator: IntegratorOptions = TRUTH_OPTIONS,
                 progress=None):
        self.cyl = cyl
        self.effects = tuple(effects)
        self.plant = plant_for(cyl, "command", self.effects)
        self.params = np.array(self.plant.parameter_vector(cyl))
        self.funcs = shooting_functions(self.plant, 1, (), integrator, progress=progress)
        self._step = VectorCall(self.funcs.step)  # called once per sample: no per-call conversions
        self.dt = 1.0 / rate
        self.rng = np.random.default_rng(seed)
        self.noise = noise
        L = cyl.geometry.stroke
        x_start = 0.5 * L if x0 is None else x0
        # at rest, valve centred, chambers balanced so the piston holds still: the
        # acceleration is linear in p1 at v = 0, so one evaluation of the plant finds p1
        p2 = 0.5 * (cyl.supply.pressure + cyl.supply.atmosphere)
        probe = self.plant.initial_state(cyl, x_start, p2, p2)
        accel = float(self.plant.rhs(probe, 0.0, self.params)[self.plant.state_names.index("v")])
        p1 = p2 - accel * cyl.mechanics.moving_mass / cyl.geometry.area_cap
        self.state = np.array(self.plant.initial_state(cyl, x_start, p1, p2), float)
        names = self.plant.state_names
        self._ix, self._ip1, self._ip2 = names.index("x"), names.index("p1"), names.index("p2")
        self.k = 0  # sample counter: t = k * dt without accumulated rounding
        self.u = 0.0  # the command latched at the last tick, held until the next one
        self._u_sent = 0.0
        self._t_shift = 0.0  # time gained or lost by advance() periods that differ from dt
        self._started = False

    @property
    def true_state(self) -> dict[str, float]:
        return dict(zip(self.plant.state_names, self.state.tolist()))

    def start(self) -> None:
        self._started = True

    def send(self, u: float) -> None:
        self._u_sent = bounded(u)

    def read(self, timeout: float | None = None) -> Sample:
        return self.advance(self.dt)

    def advance(self, dt: float) -> Sample:
        """Like read(), over a period of `dt` seconds: a real-time rig ticks with jitter."""
        t, x, p1, p2 = self.integrate(dt)
        # like a rig's firmware: the latest command is latched at the tick and reported with
        # the sample, so a sample's u_applied is what the valve holds until the next tick
        self.u = self._u_sent
        return Sample(t=t, x=x, p1=p1, p2=p2, u_applied=self.u)

    def integrate(self, dt: float) -> tuple[float, float, float, float]:
        """Advance the plant by `dt` seconds with the latched command and sample the sensors:
        (t, x, p1, p2). Latches nothing: firmware checks the sample, then calls latch()."""
        if self._started:
            # a stretched period (a busy host's firmware overran) in steps of about one period:
            # the integrator refines a step 32-fold at most, too little for 28 ms
            n = max(1, round(dt / self.dt))
            for _ in range(n):
                self.state = self._step(self.state, self.u, self.u, self.params, dt / n)
            self.k += 1
            self._t_shift += dt - self.dt  # exactly 0.0 for read(): t stays k * dt
            if not math.isfinite(self.state.sum()):  # a NaN or an infinity anywhere (cheaper per sample)
                raise RuntimeError(f"virtual rig: the plant diverged at t = {self.k * self.dt + self._t_shift:.3f} s")
        else:
            self._started = True
        state = self.state
        x, p1, p2 = float(state[self._ix]), float(state[self._ip1]), float(state[self._ip2])
        if self.noise:
            sen = self.cyl.sensors
            x += sen.position_noise * self.rng.standard_normal()
            p1 += sen.pressure_noise * self.rng.standard_normal()
            p2 += sen.pressure_noise * self.rng.standard_normal()
        return self.k * self.dt + self._t_shift, x, p1, p2

    def latch(self, u: float) -> None:
        """Latch `u` (bounded) now: the valve holds it until the next tick."""
        self.u = self._u_sent = bounded(u)

    def stop(self) -> None:
        self.u = self._u_sent = 0.0
