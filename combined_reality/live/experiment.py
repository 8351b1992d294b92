"""Run an experiment program on any rig and collect the run; `simulate_run` does so on the
virtual rig as fast as the CPU allows (the simulator of `simulate`, the batch and the demo)."""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from hw.rig import Rig
from hw.virtual_rig import VirtualRig
from sim.cylinder import Cylinder
from sim.extension import Effect

from ..files import Run
from .programs import PositionProgram


def run_program(rig: Rig, program, n_samples: int, progress: Callable[[int], None] | None = None) -> Run:
    """Read a sample, decide the command, send it; each row records the command the rig held from that tick."""
    t = np.empty(n_samples)
    u = np.empty(n_samples)
    x = np.empty(n_samples)
    p1 = np.empty(n_samples)
    p2 = np.empty(n_samples)
    rig.start()
    try:
        for k in range(n_samples):
            s = rig.read()
            cmd = program.command(s.t, s.x)
            rig.send(cmd)
            t[k], u[k], x[k], p1[k], p2[k] = s.t, s.u_applied, s.x, s.p1, s.p2
            if progress and k % 1000 == 0:
                progress(k)
    finally:
        rig.stop()
    return Run(t=t, u=u, x=x, p1=p1, p2=p2)


def simulate_run(cyl: Cylinder, duration: float, seed: int, rate: float = 1000.0, effects: Sequence[Effect] = (),
                 noise: bool = True, progress: Callable[[str], None] | None = None) -> Run:
    """A run of the virtual rig under closed-loop position control (steps, ramps, sines):
    the cylinder file's friction and `effects` are the truth, sensors add white noise."""
    rig = VirtualRig(cyl, effects, rate=rate, seed=seed, noise=noise, progress=progress)
    program = PositionProgram(cyl, duration, seed=seed)
    n = int(round(duration * rate))
    report = (lambda k: progress(f"  simulated {k / rate:5.1f} / {duration:g} s")) if progress else None
    return run_program(rig, program, n, progress=report if progress and n > 5000 else None)
