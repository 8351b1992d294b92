"""Run an experiment program on any rig and collect the run (on the virtual rig offline:
combined_reality.simulation.simulate_run)."""
from __future__ import annotations

from typing import Callable

import numpy as np

from hw.rig import Rig

from ..files import Run


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

