"""Offline simulation: a run of the virtual rig under the built-in closed-loop position
program, as fast as the CPU allows (the runs of `simulate`, the batch and the demo)."""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from hw.virtual_rig import VirtualRig
from sim.cylinder import Cylinder
from sim.extension import Effect

from .files import Run
from .live.experiment import run_program
from .live.programs import PositionProgram
from .progress import Step

__all__ = ["simulate_run"]


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
