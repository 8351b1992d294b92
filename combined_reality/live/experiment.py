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
from ..progress import Step
from .programs import PositionProgram


def run_program(rig: Rig, program, n_samples: int, progress: Callable[[int], None] | None = None,
                lost: np.ndarray | None = None) -> Run:
    """Read a sample, decide the command, send it; each row records the command the rig held
    from that tick. `lost` (one flag per sample) loses samples on the way to the host: they
    are neither recorded nor answered, so the rig holds the last command it got."""
    t = np.empty(n_samples)
    u = np.empty(n_samples)
    x = np.empty(n_samples)
    p1 = np.empty(n_samples)
    p2 = np.empty(n_samples)
    rig.start()
    try:
        for k in range(n_samples):
            s = rig.read()
            t[k], u[k], x[k], p1[k], p2[k] = s.t, s.u_applied, s.x, s.p1, s.p2
            if lost is not None and lost[k]:
                continue
            cmd = program.command(s.t, s.x)
            rig.send(cmd)
            if progress and k % 1000 == 0:
                progress(k)
    finally:
        rig.stop()
    run = Run(t=t, u=u, x=x, p1=p1, p2=p2)
    if lost is not None:
        run = Run(t=t[~lost], u=u[~lost], x=x[~lost], p1=p1[~lost], p2=p2[~lost])
    return run


def simulate_run(cyl: Cylinder, duration: float, seed: int, rate: float = 1000.0, effects: Sequence[Effect] = (),
                 noise: bool = True, progress: Callable[[str], None] | None = None, drop: float = 0.0) -> Run:
    """A run of the virtual rig under closed-loop position control (steps, ramps, sines):
    the cylinder file's friction and `effects` are the truth, sensors add white noise. With
    `drop`, each sample is lost on a lossy link with that probability (never the first):
    the run holds the samples that arrived."""
    rig = VirtualRig(cyl, effects, rate=rate, seed=seed, noise=noise, progress=progress)
    program = PositionProgram(cyl, duration, seed=seed)
    n = int(round(duration * rate))
    report = (lambda k: progress(Step(f"  simulated {k / rate:5.1f} / {duration:g} s", "s simulated", k / rate,
                                      duration))) if progress else None
    lost = None
    if drop:
        lost = np.random.default_rng([seed, 7]).random(n) < drop
        lost[0] = False
    return run_program(rig, program, n, progress=report if progress and n > 5000 else None, lost=lost)
