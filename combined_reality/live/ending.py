"""How a live or replayed session ends: whether its recording gives an estimate at all
(`identify`'s rules), the final estimate's residual on `identify`'s own measure where the model
did not explain the rig, the lines that say it all, and the exit status.

A window's residual sigma (the monitor's) and `identify`'s are the same quantity over different
horizons: a window re-fits its own start every 2 s, `identify` simulates a whole run from one
start, and a model that is off accumulates error over a run. Where the session ends with the
model not explaining the rig, it therefore also states `identify`'s figure for its final
estimate: the residual sigma with the estimate held and only the run's states fitted, over the
data the estimate stands for (since the last change of the rig, at most the last `RUN_SIGMA_S`
seconds: bounded work at the end of an hour-long session).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..errors import CombinedRealityError
from ..files import Run, RunFormatError
from ..identify import IdentifyOptions, OnlineEstimate, check_determinable, identify, not_determined
from .monitor import WHAT_TO_DO, RunSigma, SessionMonitor, change_message, drift_message
from .session import SessionResult

__all__ = ["RUN_SIGMA_S", "SessionEnd", "conclude_session", "final_run_sigma", "session_verdict"]

RUN_SIGMA_S = 60.0  # s of recording, at most, that the final estimate's run residual is taken over

# samples of a recording that the end of a session looks at, at most (its motion, for the
# determinability rules: 0.1 s on a 2-core machine; an hour at 1 kHz whole took 20 s)
_CHECKED_SAMPLES = 20_000


@dataclass(frozen=True)
class SessionEnd:
    no_estimate: str | None  # why the recording gives no estimate, or None
    trusted: bool  # the model explained the rig at the end
    run_sigma: RunSigma | None  # where it did not: identify's figure for the final estimate

    def status(self, result: SessionResult, replayed: bool) -> int:
        """The exit status: a replay ends as `identify` ends on its run (1 where the model does
        not explain it, 2 where the run cannot determine the parameters); a live session 0, its
        recording being complete, or 1 where no sample came."""
        if result.stop_reason.startswith("no samples"):
            return 1
        if replayed and result.estimates:
            return 1 if not self.trusted else 2 if self.no_estimate is not None else 0
        return 0

    def lines(self, result: SessionResult) -> list[str]:
        """What the session says at its end: the estimate (or why there is none), whether the
        model explains the rig, the changes and drifts it found."""
        final, out = result.final, []
        if self.no_estimate is None:
            out.append(f"online estimate at t = {final.t - result.t0:.2f} s of the session ({len(result.estimates)} "
                       f"updates, residual σ = {final.sigma:.2f} × noise)"
                       + ("" if self.trusted else ", NOT TO BE TRUSTED") + ":")
            out += [f"  {n:4s} = {v:.6g} ± {final.std[n]:.2g} {final.units[n]}" for n, v in final.values.items()]
        else:
            out.append(f"no estimate: {self.no_estimate}")
        if not self.trusted:
            out.append(f"the model does not explain the rig (residual {final.sigma:.3g} × the sensor noise): the "
                       f"estimate is not to be trusted; {WHAT_TO_DO}.")
        if self.run_sigma is not None:
            r = self.run_sigma
            out.append(f"  over t = {r.t_start:.1f} to {r.t_end:.1f} s simulated from one start, as identify does, the "
                       f"last estimate leaves {r.sigma:.3g} × the sensor noise")
        out += [f"  {change_message(c, final.units if final else {}, result.t0)}" for c in result.monitor.changes]
        out += [f"  {drift_message(d)}" for d in result.monitor.drifts]
        return out


def conclude_session(result: SessionResult, names: Sequence[str], cyl) -> SessionEnd:
    """The session's end judged, and `identify`'s figure kept in the monitor (its JSON)."""
    no_estimate = session_verdict(result.run, result.final, names, cyl)
    trusted = result.monitor.trusted
    run_sigma = None
    if not trusted and result.final is not None:
        run_sigma = final_run_sigma(result.run, result.final, cyl, result.monitor)
        result.monitor.run_sigma = run_sigma
    return SessionEnd(no_estimate, trusted, run_sigma)


def final_run_sigma(run: Run, final: OnlineEstimate, cyl, monitor: SessionMonitor) -> RunSigma | None:
    """`identify`'s residual sigma of the final estimate (held, only the states fitted) over
    the recording since the rig's last change, at most the last RUN_SIGMA_S s; None where the
    stretch cannot be simulated (too short, or `identify` refuses it)."""
    t_from = max(float(run.t[-1]) - RUN_SIGMA_S, max((c.t for c in monitor.changes), default=-math.inf))
    piece = run.slice(int(np.searchsorted(run.t, t_from)))
    try:
        res = identify(cyl.with_values(final.values), [piece], IdentifyOptions(estimate=()))
    except (CombinedRealityError, ValueError):
        return None
    sigma = res.solver["residual_sigma"]
    if not math.isfinite(sigma):
        return None
    return RunSigma(float(sigma), float(piece.t[0]) - monitor.t0, float(piece.t[-1]) - monitor.t0)


def session_verdict(run: Run, final: OnlineEstimate | None, names: Sequence[str], cyl) -> str | None:
    """Why the session ends with no estimate (identify's rules: a run that cannot determine
    the parameters, a parameter that is not determined), or None."""
    if final is None:
        return "fewer samples than one estimation window"
    step = -(-run.n // _CHECKED_SAMPLES)  # a long session is judged on every step-th sample
    if step > 1:
        run = Run(t=run.t[::step], u=run.u[::step], x=run.x[::step], p1=run.p1[::step], p2=run.p2[::step])
    try:
        check_determinable(cyl, [run], names)
    except RunFormatError as e:
        return str(e).removeprefix("the run: ")
    loose = not_determined({n: final.values.get(n, math.nan) for n in names}, final.std)
    if loose:
        return (f"{', '.join(loose)} not determined: the standard deviation is as large as the value "
                f"({', '.join(f'{n} = {final.values.get(n, math.nan):.3g} ± {final.std.get(n, math.nan):.2g}' for n in loose)})")
    return None
