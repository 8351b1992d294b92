"""Static friction test procedures on any rig: breakaway force and constant-speed sweep.

Both drive anything that satisfies `hw.rig.Rig` (the in-process virtual rig, a rig on a
serial port or on CAN) and never ask which. They answer every sample with a command, so
a wire rig hears from the host all along, and record every sample the moment it arrives
(RunRecorder: a crash leaves a valid run file).

- `breakaway_test`: from rest, the net pneumatic force is raised along a slow ramp, in
  closed loop on the measured pressures ("pressure raised slowly until motion starts"),
  until the piston moves; repeated per direction. The breakaway force is the peak of the
  smoothed net force before motion was detected (docs/procedures.md: why, and its bias).
- `speed_sweep`: strokes at constant speed under closed-loop velocity control; one point
  (mean velocity, mean friction from Newton's law with the measured pressures) from the
  steady part of each stroke.

Safety: every command is bounded, soft stroke limits apply on the measured position
(`excitation.guarded`, and each move stays inside the working range itself), every phase
has a time limit, and the valve is centred at the end, on Ctrl-C and on any error
(`Rig.stop`). A rig that never moves, stops answering or reads a position outside the
stroke ends the procedure with a one-sentence `ProcedureError`.
"""
from __future__ import annotations

import gc
import math
import time
from collections import deque
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

from hw.realtime import make_normal, take_host_priority
from hw.rig import Rig, RigError, Sample, Status
from sim.cylinder import Cylinder
from sim.flow import G, KAPPA, R_AIR, RHO0, T0
from sim.plant import build_plant

from ..errors import ToolFailure
from ..files import Run, RunRecorder, atomic_write
from ..identify import friction_from_newton
from ..live import ProgramOptions, guarded

__all__ = ["ProcedureError", "SafetyOptions", "BreakawayOptions", "SweepOptions", "BreakawayTrial",
           "DirectionSummary", "BreakawayResult", "SweepPoint", "SweepResult", "breakaway_test", "speed_sweep",
           "target_speeds", "default_speed_range", "steady_speed", "fast_velocity", "net_force", "force_limits",
           "write_points", "DIRECTION_NAMES", "TABLE_COLUMNS"]

Progress = Callable[[str], None]
DIRECTION_NAMES = {1: "extension", -1: "retraction"}
# the points table of the friction-map command: v,F required (SI, signed: v > 0 extension, F the
# sign of v), then the spreads, the samples averaged, the pressure conditions, and breakaway
# (1: a breakaway force, which the map must not fit as a sliding point; 0: a sliding point)
TABLE_COLUMNS = ("v", "F", "F_std", "v_std", "count", "dp", "pc", "breakaway")
_HALF = 15  # half-window of friction_from_newton's Savitzky-Golay derivatives (its default)


class ProcedureError(ToolFailure, RuntimeError):
    """The procedure cannot go on (the rig does not move, does not answer, leaves the stroke); one
    sentence (exit status 1)."""


def _keep_partial(e: BaseException, result: "SweepResult | BreakawayResult") -> None:
    """What a procedure measured before it failed or was interrupted rides on the exception
    (`partial`), for the caller to write out: nothing measured is lost."""
    e.partial = result  # type: ignore[attr-defined]


# ------------------------------------------------------------------ options

@dataclass(frozen=True)
class SafetyOptions:
    u_max: float = 0.8  # command bound
    margin: float = 0.1  # soft stroke limits: moves stay this fraction of the stroke away from each end
    read_timeout_s: float = 1.0  # a rig silent this long ends the procedure

    def __post_init__(self) -> None:
        if not 0 < self.u_max <= 1:
            raise ValueError(f"u_max must lie in (0, 1], not {self.u_max:g}")
        if not 0.02 <= self.margin <= 0.3:
            raise ValueError(f"margin must lie between 0.02 and 0.3 of the stroke, not {self.margin:g}")
        if not self.read_timeout_s > 0:
            raise ValueError(f"read_timeout_s must be positive, not {self.read_timeout_s:g}")


def _check_directions(directions: tuple[int, ...]) -> None:
    if not directions or any(d not in (1, -1) for d in directions) or len(set(directions)) != len(directions):
        raise ValueError(f"directions must be (1,), (-1,), (1, -1) or (-1, 1), not {directions}")


@dataclass(frozen=True)
class BreakawayOptions:
    trials: int = 15  # per direction (the seeds' apparatus: 15)
    directions: tuple[int, ...] = (1, -1)  # 1 = extension, -1 = retraction; trials alternate between them
    force_rate: float = 20.0  # N/s: slope of the net-force ramp
    start: float = 0.5  # where each trial starts, fraction of the stroke
    rest_s: float = 0.3  # valve centred, piston at rest, before each ramp
    v_detect: float = 0.01  # m/s: motion = filtered velocity beyond this ...
    x_detect: float = 0.3e-3  # m: ... and this far from where the ramp started
    force_limit: float | None = None  # N; default: 90 % of the net force the supply can give
    u_max: float = 0.3  # command bound during the ramp (a slow ramp needs little flow)
    smooth_s: float = 0.02  # s: centred moving average of the net force before its peak is taken
    safety: SafetyOptions = SafetyOptions()

    def __post_init__(self) -> None:
        if isinstance(self.trials, bool) or not (isinstance(self.trials, int) and self.trials >= 1):
            raise ValueError(f"trials must be a whole number >= 1, not {self.trials}")
        _check_directions(self.directions)
        if not (self.force_rate > 0 and math.isfinite(self.force_rate)):
            raise ValueError(f"force_rate must be a positive number of N/s, not {self.force_rate}")
        if not 0.2 <= self.start <= 0.8:
            raise ValueError(f"start must lie between 0.2 and 0.8 of the stroke, not {self.start:g}")
        if not (self.v_detect > 0 and self.x_detect > 0):
            raise ValueError("v_detect and x_detect must be positive")
        if self.force_limit is not None and not (self.force_limit > 0 and math.isfinite(self.force_limit)):
            raise ValueError(f"force_limit must be a positive number of N, not {self.force_limit}")
        if not 0 < self.u_max <= 1:
            raise ValueError(f"u_max must lie in (0, 1], not {self.u_max:g}")
        if not self.smooth_s > 0:
            raise ValueError(f"smooth_s must be positive, not {self.smooth_s:g}")


@dataclass(frozen=True)
class SweepOptions:
    speeds: int = 8  # target speeds per direction, log-spaced from v_min to v_max
    v_min: float | None = None  # m/s; default v_max / 20
    v_max: float | None = None  # m/s; default default_speed_range(cyl)
    directions: tuple[int, ...] = (1, -1)  # strokes alternate between them at each speed
    accel: float = 20.0  # m/s^2: ramp of the speed reference at the start of a stroke ...
    decel: float = 10.0  # m/s^2: ... and at its end
    settle_s: float = 0.1  # s the piston slides at the target speed before the steady part starts
    max_stroke_s: float = 5.0  # slow strokes only travel what this takes at their speed
    min_samples: int = 50  # a shorter steady part gives no point
    max_speed_spread: float = 0.25  # a point whose speed varies more (std / mean) is not steady
    # nor one whose speed drops below this share of its mean anywhere: the piston all but stopped
    # (stick-slip), where friction is static, not the sliding map (a stroke at 23 % spread that
    # nearly stopped read 1.6 % low beside two busy processes)
    min_speed_ratio: float = 0.25
    rest_s: float = 0.3  # valve centred between strokes
    # strokes per target at most: one that gives no steady point is run again from its start end
    # (a busy host's late commands make a stroke ring now and then, not every time)
    attempts: int = 2
    bandwidth_hz: float = 5.0  # outer velocity loop (PI, critically damped on the moving mass)
    force_bandwidth_hz: float = 40.0  # inner net-force loop: above the air-spring resonance, to damp it
    safety: SafetyOptions = SafetyOptions()

    def __post_init__(self) -> None:
        if isinstance(self.speeds, bool) or not (isinstance(self.speeds, int) and self.speeds >= 1):
            raise ValueError(f"speeds must be a whole number >= 1, not {self.speeds}")
        if isinstance(self.attempts, bool) or not (isinstance(self.attempts, int) and self.attempts >= 1):
            raise ValueError(f"attempts must be a whole number >= 1, not {self.attempts}")
        _check_directions(self.directions)
        for name in ("v_min", "v_max"):
            v = getattr(self, name)
            if v is not None and not (v > 0 and math.isfinite(v)):
                raise ValueError(f"{name} must be a positive number of m/s, not {v}")
        if self.v_min is not None and self.v_max is not None and self.v_min > self.v_max:
            raise ValueError(f"v_min ({self.v_min:g} m/s) must not exceed v_max ({self.v_max:g} m/s)")
        for name in ("accel", "decel", "settle_s", "max_stroke_s", "max_speed_spread", "bandwidth_hz",
                     "force_bandwidth_hz"):
            v = getattr(self, name)
            if not (v > 0 and math.isfinite(v)):
                raise ValueError(f"{name} must be a positive number, not {v}")
        if not 0 <= self.min_speed_ratio < 1:
            raise ValueError(f"min_speed_ratio must lie in [0, 1), not {self.min_speed_ratio}")


def late_commands(counters: Mapping[str, float]) -> str:
    """"N of M commands reached the rig after its next sample" when more than 1 % did (a wire
    rig's session counters; the loops then act a sample later than designed), else ""."""
    late, sent = int(counters.get("commands_late", 0)), int(counters.get("commands_sent", 0))
    return f"{late} of {sent} commands reached the rig after its next sample" if sent and late > 0.01 * sent else ""


# ------------------------------------------------------------------ results

@dataclass(frozen=True)
class BreakawayTrial:
    direction: int  # 1 extension, -1 retraction
    trial: int  # 1-based, per direction
    F: float  # N, signed: the breakaway force (peak of the smoothed net force before motion was detected)
    F_detect: float  # N, smoothed net force when motion was detected
    F_start: float  # N, net force when the ramp started (the preload left by positioning)
    rate: float  # N/s, signed: slope of the net force over the 0.3 s before the peak
    t_start: float  # s, rig time: ramp start ...
    t_break: float  # ... force peak (motion onset) ...
    t_detect: float  # ... motion detected
    x_start: float  # m
    creep: float  # m, signed: displacement from the ramp start to the force peak (pre-sliding, creep)
    v_break: float  # m/s, signed: velocity at the force peak (creep or pre-sliding speed; centred estimate)
    dp: float  # Pa, |p1 - p2| at the force peak (seal friction grows with it: kp)
    pc: float  # Pa gauge, counter pressure at the peak (p2 - pa extending, p1 - pa retracting)


@dataclass(frozen=True)
class DirectionSummary:
    direction: int
    mean: float  # N, signed
    std: float  # N, sample standard deviation (0 for one trial)
    values: tuple[float, ...]  # N, every trial, signed
    v: float  # m/s, signed: mean velocity at breakaway (never 0: its sign is the direction)
    v_std: float
    dp: float  # Pa, mean |p1 - p2| at breakaway
    pc: float  # Pa gauge, mean counter pressure at breakaway


@dataclass(frozen=True, eq=False)
class BreakawayResult:
    trials: tuple[BreakawayTrial, ...]
    summary: tuple[DirectionSummary, ...]
    run: Run  # every sample of the procedure
    counters: dict  # session health: samples, longest host pause, rig status counts, link statistics
    options: BreakawayOptions

    def direction(self, d: int) -> DirectionSummary:
        return next(s for s in self.summary if s.direction == d)

    def table(self) -> list[dict[str, float]]:
        """Rows of the points table, one per direction: the static end of the map (TABLE_COLUMNS)."""
        return [{"v": s.v, "F": s.mean, "F_std": s.std, "v_std": s.v_std, "count": len(s.values), "dp": s.dp,
                 "pc": s.pc, "breakaway": 1} for s in sorted(self.summary, key=lambda s: s.v)]

    def to_json(self) -> dict:
        return {"procedure": "breakaway", "options": asdict(self.options),
                "directions": {DIRECTION_NAMES[s.direction]: {"mean": s.mean, "std": s.std, "n": len(s.values),
                                                              "values": list(s.values), "v": s.v, "v_std": s.v_std,
                                                              "dp": s.dp, "pc": s.pc} for s in self.summary},
                "trials": [asdict(t) for t in self.trials], "session": self.counters}


@dataclass(frozen=True)
class SweepPoint:
    direction: int
    target: float  # m/s, signed target speed
    v: float  # m/s, signed mean velocity over the steady part
    F: float  # N, signed mean friction over it (Newton's law with the measured pressures)
    v_std: float  # m/s
    F_std: float  # N
    F_sem: float  # N, standard error of F (the derivative noise is correlated in time)
    n: int  # samples in the steady part
    t_start: float  # s, rig time of the steady part
    t_end: float
    x_start: float  # m
    x_end: float
    u_mean: float  # mean command over the steady part
    dp: float  # Pa, mean |p1 - p2| over it (seal friction grows with it: kp)
    pc: float  # Pa gauge, mean counter pressure (p2 - pa extending, p1 - pa retracting)
    steady: bool  # speed spread within max_speed_spread and never near rest; else stick-slip or ringing


@dataclass(frozen=True, eq=False)
class SweepResult:
    points: tuple[SweepPoint, ...]  # every stroke that gave a point, steady or not
    skipped: tuple[dict, ...]  # strokes that gave none, with the reason
    run: Run
    counters: dict
    options: SweepOptions
    retried: tuple[dict, ...] = ()  # attempts that gave no steady point and were run again, with the reason

    def table(self) -> list[dict[str, float]]:
        """Rows of the points table (TABLE_COLUMNS): the steady points, in order of v."""
        return [{"v": p.v, "F": p.F, "F_std": p.F_std, "v_std": p.v_std, "count": p.n, "dp": p.dp, "pc": p.pc,
                 "breakaway": 0} for p in sorted(self.points, key=lambda p: p.v) if p.steady]

    def to_json(self) -> dict:
        return {"procedure": "sweep", "options": asdict(self.options), "points": [asdict(p) for p in self.points],
                "skipped": list(self.skipped), "retried": list(self.retried), "session": self.counters}


def write_points(path, rows: Sequence[Mapping[str, float]], comments: Sequence[str] = (),
                 columns: Sequence[str] = TABLE_COLUMNS) -> None:
    """The points table, atomically: `#` comment lines, the header (v,F first), one row per point."""
    if tuple(columns[:2]) != ("v", "F"):
        raise ValueError(f"a points table starts with the columns v,F, not {','.join(columns[:2])}")
    lines = [f"# {line}".rstrip() for text in comments for line in (text.splitlines() or [""])]
    lines.append(",".join(columns))
    lines += [",".join(str(int(r[c])) if c in ("count", "breakaway") else repr(float(r[c])) for c in columns)
              for r in rows]
    atomic_write(Path(path), ("\n".join(lines) + "\n").encode("utf-8"))


# ------------------------------------------------------------------ cylinder quantities

def net_force(cyl: Cylinder, p1, p2):
    """Net pneumatic force minus the weight along the axis, N (docs/model.md's piston equation without
    friction and inertia): what friction holds while the piston is at rest."""
    g, m = cyl.geometry, cyl.mechanics
    A1, A2 = g.area_cap, g.area_rod
    return p1 * A1 - p2 * A2 - cyl.supply.atmosphere * (A1 - A2) - m.moving_mass * G * math.sin(m.angle)


def force_limits(cyl: Cylinder) -> tuple[float, float]:
    """The most net force the supply can give: (extension > 0, retraction < 0), N."""
    g, s = cyl.geometry, cyl.supply
    weight = cyl.mechanics.moving_mass * G * math.sin(cyl.mechanics.angle)
    return (s.pressure - s.atmosphere) * g.area_cap - weight, -(s.pressure - s.atmosphere) * g.area_rod - weight


def _phi(r: float, b: float) -> float:
    """ISO 6358 flow function (without docs/model.md's laminar end: for controller gains only)."""
    if r <= b:
        return 1.0
    a = min((r - b) / (1 - b), 1.0)
    return math.sqrt(1 - a * a)


def _velocity_per_command(cyl: Cylinder) -> float:
    """Piston speed per unit command near mid-pressure (as excitation.PositionProgram): choked
    flow at full opening into a chamber at ~70 % of supply."""
    return cyl.valve.sonic_conductance * RHO0 * math.sqrt(T0 / cyl.supply.temperature) * R_AIR \
        * cyl.supply.temperature / (0.7 * cyl.geometry.area_cap)


def _volumes(cyl: Cylinder, x: float) -> tuple[float, float]:
    g = cyl.geometry
    x = min(max(x, 0.0), g.stroke)
    return g.dead_volume_cap + g.area_cap * x, g.dead_volume_rod + g.area_rod * (g.stroke - x)


def _force_gain(cyl: Cylinder, x: float, p1: float, p2: float, sign: int) -> float:
    """dF/dt per unit command (N/s) with the valve opened in direction `sign`, from the valve
    flows at the measured pressures (the net force changes as g |u| - K v)."""
    g, T = cyl.geometry, cyl.supply.temperature
    b = cyl.valve.critical_ratio
    A1, A2 = g.area_cap, g.area_rod
    V1, V2 = _volumes(cyl, x)
    k = KAPPA * R_AIR * T * cyl.valve.sonic_conductance * RHO0 * math.sqrt(T0 / T)
    ps, pa = cyl.supply.pressure, cyl.supply.atmosphere
    # floor at 5 % of the flow function: near saturation the gain collapses, the bound takes over
    if sign > 0:  # supply -> 1, 2 -> exhaust
        fill = ps * max(_phi(p1 / ps, b), 0.05) * A1 / V1
        vent = max(p2, pa) * max(_phi(pa / max(p2, pa), b), 0.05) * A2 / V2
    else:  # supply -> 2, 1 -> exhaust
        fill = ps * max(_phi(p2 / ps, b), 0.05) * A2 / V2
        vent = max(p1, pa) * max(_phi(pa / max(p1, pa), b), 0.05) * A1 / V1
    return k * (fill + vent)


def _air_stiffness(cyl: Cylinder, x: float, p1: float, p2: float) -> float:
    """K in N/m: the two closed chambers as adiabatic springs (dF/dt = -K v at a centred valve)."""
    g, pa = cyl.geometry, cyl.supply.atmosphere
    V1, V2 = _volumes(cyl, x)
    return KAPPA * (max(p1, pa) * g.area_cap ** 2 / V1 + max(p2, pa) * g.area_rod ** 2 / V2)


def default_speed_range(cyl: Cylinder, safety: SafetyOptions = SafetyOptions()) -> tuple[float, float]:
    """(v_min, v_max), m/s: v_max crosses the working travel in 0.4 s (at most 0.5 m/s and half of
    what the valve gives at the command bound); v_min = v_max / 20."""
    travel = (1 - 2 * safety.margin) * cyl.geometry.stroke
    v_max = min(travel / 0.4, 0.5, 0.5 * safety.u_max * _velocity_per_command(cyl))
    return v_max / 20.0, v_max


def target_speeds(cyl: Cylinder, options: SweepOptions) -> np.ndarray:
    """The target speeds (positive, ascending): log-spaced from v_min to v_max (one: v_max)."""
    v_max = options.v_max if options.v_max is not None else default_speed_range(cyl, options.safety)[1]
    v_min = options.v_min if options.v_min is not None else v_max / 20.0
    if v_min > v_max:
        raise ValueError(f"v_min ({v_min:g} m/s) must not exceed v_max ({v_max:g} m/s)")
    return np.geomspace(v_min, v_max, options.speeds) if options.speeds > 1 else np.array([v_max])


# ------------------------------------------------------------------ the session with the rig

class _Driver:
    """One streaming session: every command bounded and guarded, every sample recorded at once,
    a filtered velocity (least-squares slope) and net force kept up to date."""

    def __init__(self, rig: Rig, cyl: Cylinder, safety: SafetyOptions, record_to, comments: Sequence[str],
                 progress: Progress | None, velocity_window: int = 15, force_window: int = 20,
                 fast_force_window: int = 4, realtime: int | None = None):
        self.rig, self.cyl, self.safety, self.realtime = rig, cyl, safety, realtime
        self._made_realtime = False
        self.L = cyl.geometry.stroke
        self.lo, self.hi = safety.margin * self.L, (1 - safety.margin) * self.L  # the working range
        self._guard = ProgramOptions(u_max=safety.u_max, margin=safety.margin)
        self.record_to, self.comments, self.progress = record_to, tuple(comments), progress
        self.recorder: RunRecorder | None = None
        self.cols: list[list[float]] = [[] for _ in range(6)]  # t, u, x, p1, p2, ps
        self._tw: deque[float] = deque(maxlen=velocity_window)
        self._xw: deque[float] = deque(maxlen=velocity_window)
        self._fw: deque[float] = deque(maxlen=force_window)
        self._nfast = fast_force_window
        self.v = 0.0  # m/s, filtered (lags by half its window)
        self.F = 0.0  # N, filtered net force: quiet, for detection and start values
        self.F_fast = 0.0  # N, lightly filtered net force: little lag, for the force loops
        self.s: Sample | None = None
        self.watchdog_samples = 0
        self.rig_limit_samples = 0
        self.longest_pause = 0.0  # s of wall time between two commands (a wire rig's watchdog trips at 50 ms)
        self._sent_at = math.inf
        self.plant = build_plant("pressure")  # for friction_from_newton, built once

    # -------------------------------------------------------------- session

    def __enter__(self) -> "_Driver":
        # a full garbage collection can pause the loop for tens of ms (a wire rig's watchdog
        # trips at 50 ms): collect now and keep what exists out of later collections
        gc.collect()
        gc.freeze()
        try:
            self.rig.start()
            if self.realtime is not None:  # the loop answers every sample: late answers make strokes ring
                self._made_realtime, why = take_host_priority(self.rig, self.realtime)
                if why is not None:
                    self.say(f"the loop runs without real-time priority ({why}): on a busy machine its commands "
                             "reach the rig late more often")
            self._take(self._read())
        except BaseException:
            self._close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self._close()

    def _close(self) -> None:
        try:
            self.rig.stop()  # centres the valve
        finally:
            if self._made_realtime:
                make_normal()
            gc.unfreeze()
            if self.recorder is not None:
                self.recorder.close()

    def counters(self) -> dict:
        out = {"samples": self.n, "longest_host_pause_s": round(self.longest_pause, 4),
               "watchdog_samples": self.watchdog_samples, "rig_soft_limit_samples": self.rig_limit_samples}
        stats = self.rig.stats
        if stats is not None:
            out.update({k: v for k, v in vars(stats).items() if isinstance(v, (int, float))})
        return out

    def warn_if_unhealthy(self, what: str) -> None:
        if self.watchdog_samples:
            self.say(f"warning: the rig's watchdog centred the valve for {self.watchdog_samples} samples (the host "
                     f"answered too late, longest pause {self.longest_pause * 1e3:.0f} ms): check the {what}")
        late = late_commands(self.counters())
        if late:
            self.say(f"warning: {late} (a busy host or "
                     f"link): check the {what}")

    def say(self, msg: str) -> None:
        if self.progress:
            self.progress(msg)

    # -------------------------------------------------------------- one sample

    @property
    def n(self) -> int:
        return len(self.cols[0])

    @property
    def t(self) -> float:
        return self.s.t

    @property
    def x(self) -> float:
        return self.s.x

    def step(self, u: float) -> Sample:
        """Send u (bounded, soft stroke limits on the measured position) and take the next sample."""
        self.rig.send(guarded(u, self.s.x, self.L, self._guard))
        now = time.perf_counter()
        self.longest_pause = max(self.longest_pause, now - self._sent_at)
        self._sent_at = now
        self._take(self._read())
        return self.s

    def hold(self, duration: float) -> None:
        """Valve centred for `duration` s of rig time (the rig keeps hearing from the host)."""
        t_end = self.t + duration
        while self.t < t_end:
            self.step(0.0)

    def force_command(self, F_ref: float, k_F: float, *, rate_ff: float = 0.0, v_ff: float = 0.0) -> float:
        """The command that makes the net force change as rate_ff + k_F (F_ref - F) while the
        piston moves at v_ff: the inner loop of both procedures. The air springs' K v_ff is fed
        forward and the valve gain divided out (feedback linearisation)."""
        s = self.s
        want = rate_ff + _air_stiffness(self.cyl, s.x, s.p1, s.p2) * v_ff + k_F * (F_ref - self.F_fast)
        return want / _force_gain(self.cyl, s.x, s.p1, s.p2, 1 if want >= 0 else -1)

    def _read(self) -> Sample:
        for _ in range(1000):
            s = self.rig.read(timeout=self.safety.read_timeout_s)
            if s is None:
                raise ProcedureError(f"no sample from the rig for {self.safety.read_timeout_s:g} s: "
                                     "the rig or its link has stopped")
            if self.s is None or s.t > self.s.t:
                return s
            # a sample that does not advance the rig clock cannot go into a run file: skip it
        raise ProcedureError(f"the rig's clock stands still at t = {self.s.t:.6f} s (1000 samples in a row)")

    def _take(self, s: Sample) -> None:
        L = self.L
        if not (math.isfinite(s.x) and -0.05 * L <= s.x <= 1.05 * L):
            raise ProcedureError(f"the position reads {s.x:.4g} m, outside the stroke 0 to {L:g} m of the cylinder "
                                 "file: wrong cylinder, wrong unit or a sensor fault")
        if s.status & Status.SUPPLY_FAULT:
            raise ProcedureError("the rig reports a supply fault (supply pressure missing or low)")
        self.watchdog_samples += bool(s.status & Status.WATCHDOG)
        self.rig_limit_samples += bool(s.status & Status.SOFT_LIMIT)
        if self.recorder is None and self.record_to is not None:
            self.recorder = RunRecorder(self.record_to, with_ps=s.ps is not None, comments=self.comments)
        if self.recorder is not None:
            self.recorder.append(s.t, s.u_applied, s.x, s.p1, s.p2, s.ps if self.recorder.with_ps else None)
        ps = s.ps if s.ps is not None and math.isfinite(s.ps) else math.nan
        for c, val in zip(self.cols, (s.t, s.u_applied, s.x, s.p1, s.p2, ps)):
            c.append(val)
        self.s = s
        self._tw.append(s.t)
        self._xw.append(s.x)
        self._fw.append(net_force(self.cyl, s.p1, s.p2))
        self.F = sum(self._fw) / len(self._fw)
        k = min(self._nfast, len(self._fw))
        self.F_fast = sum(self._fw[-i] for i in range(1, k + 1)) / k
        if len(self._tw) >= 3:
            tc = np.asarray(self._tw) - s.t
            tc -= tc.mean()
            self.v = float(tc @ np.asarray(self._xw) / (tc @ tc))  # least-squares slope

    def run(self, i0: int = 0, i1: int | None = None) -> Run:
        c = self.cols
        i1 = self.n if i1 is None else i1
        ps = np.array(c[5][i0:i1])
        return Run(t=np.array(c[0][i0:i1]), u=np.array(c[1][i0:i1]), x=np.array(c[2][i0:i1]),
                   p1=np.array(c[3][i0:i1]), p2=np.array(c[4][i0:i1]),
                   ps=None if np.all(np.isnan(ps)) else ps)

    # -------------------------------------------------------------- moves

    def reposition(self, x_target: float) -> None:
        """Closed-loop position control to x_target (inside the working range) along a reference
        at a moderate speed, then the valve centred; an error if the piston does not get there."""
        vpu = _velocity_per_command(self.cyl)
        kp = 2 * math.pi * 4.0 / vpu  # 4 Hz position loop, as the excitation programs
        tol = 0.01 * self.L
        speed = min(0.1, 0.5 * (self.hi - self.lo))
        x_target = min(max(x_target, self.lo + tol), self.hi - tol)
        r = min(max(self.x, self.lo), self.hi)
        t0 = t_last = self.t
        err0 = abs(x_target - self.x)
        still_since = None
        while self.t - t0 < 5.0:
            if abs(x_target - self.x) > err0 + 0.05 * self.L:
                raise ProcedureError(f"the piston runs away from the position it is sent to ({x_target:.4g} m, it is at "
                                     f"{self.x:.4g} m): is the valve or the position sensor wired the other way round?")
            dt, t_last = self.t - t_last, self.t
            rdot = 0.0
            if abs(x_target - r) > speed * dt:
                rdot = math.copysign(speed, x_target - r)
                r += rdot * dt
            else:
                r = x_target
            if r == x_target and abs(self.x - x_target) < tol and abs(self.v) < 0.05 * speed:
                still_since = self.t if still_since is None else still_since
                if self.t - still_since >= 0.05:
                    break
            else:
                still_since = None
            self.step(kp * (r - self.x) + rdot / vpu)
        self.step(0.0)
        if not (self.lo - tol <= self.x <= self.hi + tol):
            raise ProcedureError(f"the piston did not come into the working range {self.lo:.4g} to {self.hi:.4g} m "
                                 f"within 5 s (it is at {self.x:.4g} m): is it blocked, or the supply off?")


# ------------------------------------------------------------------ breakaway

def breakaway_test(rig: Rig, cyl: Cylinder, options: BreakawayOptions = BreakawayOptions(), *,
                   record_to=None, record_comments: Sequence[str] = (), progress: Progress | None = None,
                   realtime: int | None = None) -> BreakawayResult:
    """The breakaway force per direction: `trials` ramps of the net force from rest until the piston moves.
    `realtime`: the SCHED_FIFO priority of the loop (hw.realtime) for a rig at its own clock; None
    for one that waits for the host (it would never let go of the CPU)."""
    opts = options
    limits = force_limits(cyl)
    x0 = opts.start * cyl.geometry.stroke
    trials: list[BreakawayTrial] = []
    with _Driver(rig, cyl, opts.safety, record_to, record_comments, progress, realtime=realtime) as d:
        try:
            for k in range(opts.trials):
                for direction in opts.directions:
                    d.reposition(x0)
                    d.hold(opts.rest_s)
                    supply = limits[0] if direction > 0 else limits[1]
                    limit = opts.force_limit if opts.force_limit is not None else 0.9 * abs(supply)
                    i0, i_det = _force_ramp(d, direction, limit, opts)
                    d.hold(0.1)  # valve centred: the closed chambers brake the piston
                    trial = _breakaway_trial(d, direction, k + 1, i0, i_det, opts)
                    trials.append(trial)
                    d.say(f"breakaway {DIRECTION_NAMES[direction]:10s} {k + 1}/{opts.trials}: {trial.F:+8.3f} N "
                          f"(at detection {trial.F_detect:+.3f} N, {1e3 * (trial.t_detect - trial.t_break):.0f} ms "
                          f"later; ramp {trial.rate:+.3g} N/s, creep {trial.creep * 1e3:+.2f} mm)")
            d.reposition(x0)
        except (ProcedureError, RigError, KeyboardInterrupt) as e:
            _keep_partial(e, _breakaway_result(trials, d.run(), d.counters(), opts))
            raise
        d.warn_if_unhealthy("trials")
        run, counters = d.run(), d.counters()
    return _breakaway_result(trials, run, counters, opts)


def _breakaway_result(trials: list[BreakawayTrial], run: Run, counters: dict,
                      opts: BreakawayOptions) -> BreakawayResult:
    """The trials and, for each direction that has any, their summary."""
    summary = []
    for direction in opts.directions:
        mine = [t for t in trials if t.direction == direction]
        if not mine:
            continue
        vals = np.array([t.F for t in mine])
        # the speed at the peak: creep or pre-sliding, near zero; signed by the direction (a noisy
        # estimate of a near-zero speed may come out with the other sign) and never exactly 0,
        # so that the points table says the direction
        vb = np.array([direction * max(abs(t.v_break), 1e-6) for t in mine])
        summary.append(DirectionSummary(direction, float(vals.mean()), _sample_std(vals), tuple(vals.tolist()),
                                        v=float(vb.mean()), v_std=_sample_std(vb),
                                        dp=float(np.mean([t.dp for t in mine])), pc=float(np.mean([t.pc for t in mine]))))
    return BreakawayResult(tuple(trials), tuple(summary), run, counters, opts)


def _sample_std(x: np.ndarray) -> float:
    return float(x.std(ddof=1)) if len(x) > 1 else 0.0


def _force_ramp(d: _Driver, direction: int, limit: float, opts: BreakawayOptions) -> tuple[int, int]:
    """Raise the net force along the ramp until motion is detected: (index of the ramp start,
    index of the detection)."""
    i0 = d.n - 1
    F_ref = d.F
    x0 = d.x
    # slow force loop: the ramp rate and the creep (K v) are fed forward, the loop only trims
    k_F = 2 * math.pi * 2.0
    t_last = d.t
    t_limit = d.t + abs(direction * limit - F_ref) / opts.force_rate + 2.0
    F_best = direction * d.F
    while True:
        if direction * d.v > opts.v_detect and direction * (d.x - x0) > opts.x_detect:
            return i0, d.n - 1
        if direction * (d.x - x0) < -0.02 * d.L:
            raise _wrong_way(direction)
        if not (d.lo <= d.x <= d.hi):
            raise ProcedureError(f"the piston crept out of the working range (x = {d.x:.4g} m) before it broke "
                                 f"away in {DIRECTION_NAMES[direction]}")
        F_best = max(F_best, direction * d.F)
        if d.t > t_limit:
            raise ProcedureError(f"no breakaway in {DIRECTION_NAMES[direction]}: the piston did not move up to "
                                 f"{F_best:.1f} N of net force (limit {limit:.1f} N): is it blocked, or the "
                                 "supply off?")
        dt, t_last = d.t - t_last, d.t
        F_ref = direction * min(direction * F_ref + opts.force_rate * dt, limit)
        u = d.force_command(F_ref, k_F, rate_ff=direction * opts.force_rate, v_ff=d.v)
        d.step(max(-opts.u_max, min(opts.u_max, u)))


def _wrong_way(direction: int) -> ProcedureError:
    return ProcedureError(f"the piston moved against the {DIRECTION_NAMES[direction]} it was driven to: is the valve "
                          "or the position sensor wired the other way round?")


def _smooth(y: np.ndarray, n: int) -> np.ndarray:
    """Centred moving average over n samples (shorter windows at the ends)."""
    n = max(1, min(n, len(y)))
    c = np.concatenate([[0.0], np.cumsum(y)])
    i = np.arange(len(y))
    a, b = np.maximum(i - n // 2, 0), np.minimum(i + n - n // 2, len(y))
    return (c[b] - c[a]) / (b - a)


def _breakaway_trial(d: _Driver, direction: int, trial: int, i0: int, i_det: int,
                     opts: BreakawayOptions) -> BreakawayTrial:
    """The breakaway force of one ramp: the peak of the smoothed net force up to the detection.

    Once the piston moves, its chamber expands and the friction falls from its static level,
    so the net force stops rising: its peak marks the motion onset, whereas the force at
    detection depends on how fast the piston then runs (docs/procedures.md)."""
    c = d.cols
    t = np.array(c[0][i0:i_det + 1])
    F = net_force(d.cyl, np.array(c[3][i0:i_det + 1]), np.array(c[4][i0:i_det + 1]))
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1e-3
    Fs = _smooth(F, int(round(opts.smooth_s / dt)) | 1)
    j = int(np.argmax(direction * Fs))
    a = int(np.searchsorted(t, t[j] - 0.3))
    rate = float(np.polyfit(t[a:j + 1] - t[j], F[a:j + 1], 1)[0]) if j - a >= 10 else math.nan
    # around the peak (the samples after the detection are there: the valve was held centred)
    k = i0 + j
    near = slice(max(k - 10, 0), min(k + 11, d.n))
    tn, xn = np.array(c[0][near]), np.array(c[2][near])
    v_break = float(np.polyfit(tn - tn.mean(), xn, 1)[0])  # least-squares slope, centred on the peak
    p1n, p2n = np.array(c[3][near]), np.array(c[4][near])
    pc = float(np.mean((p2n if direction > 0 else p1n) - d.cyl.supply.atmosphere))
    return BreakawayTrial(direction=direction, trial=trial, F=float(Fs[j]), F_detect=float(Fs[-1]),
                          F_start=float(Fs[0]), rate=rate, t_start=float(t[0]), t_break=float(t[j]),
                          t_detect=float(t[-1]), x_start=float(c[2][i0]), creep=float(xn.mean()) - float(c[2][i0]),
                          v_break=v_break, dp=float(np.mean(np.abs(p1n - p2n))), pc=pc)


# ------------------------------------------------------------------ constant-speed sweep

def speed_sweep(rig: Rig, cyl: Cylinder, options: SweepOptions = SweepOptions(), *, record_to=None,
                record_comments: Sequence[str] = (), progress: Progress | None = None,
                realtime: int | None = None) -> SweepResult:
    """One friction point per target speed and direction, from strokes at constant speed
    (`realtime` as for `breakaway_test`)."""
    opts = options
    speeds = target_speeds(cyl, opts)
    points: list[SweepPoint] = []
    skipped: list[dict] = []
    retried: list[dict] = []  # attempts run again, with why
    with _Driver(rig, cyl, opts.safety, record_to, record_comments, progress, realtime=realtime) as d:
        start_end = {1: d.lo, -1: d.hi}
        try:
            d.reposition(start_end[opts.directions[0]])
            d.hold(opts.rest_s)
            for k, v_target in enumerate(speeds.tolist()):
                for direction in opts.directions:
                    head = f"sweep {DIRECTION_NAMES[direction]:10s} {v_target:.4g} m/s ({k + 1}/{len(speeds)}):"
                    for attempt in range(1, opts.attempts + 1):
                        if len(opts.directions) == 1 or attempt > 1:  # back to this direction's start
                            d.reposition(start_end[direction])
                            d.hold(opts.rest_s)
                        point, why, repeatable = _sweep_attempt(d, direction, v_target, points, opts)
                        last = attempt == opts.attempts or not repeatable or (point is not None and point.steady)
                        if not last:
                            why = why or "unsteady (stick-slip or ringing)"
                            retried.append({"direction": direction, "target": direction * v_target,
                                            "attempt": attempt, "reason": why})
                            d.say(f"{head} attempt {attempt} gave no steady point ({why}): once more")
                            continue
                        if point is None:
                            skipped.append({"direction": direction, "target": direction * v_target, "reason": why})
                            d.say(f"{head} no point, {why}")
                        else:
                            points.append(point)
                            d.say(f"{head} v = {point.v:+.4g} ± {point.v_std:.2g} m/s, F = {point.F:+.4g} ± "
                                  f"{point.F_sem:.2g} N ({point.n} samples)"
                                  + ("" if point.steady else "; unsteady (stick-slip or ringing): left out of the "
                                                             "points table"))
                        break
        except (ProcedureError, RigError, KeyboardInterrupt) as e:
            _keep_partial(e, SweepResult(tuple(points), tuple(skipped), d.run(), d.counters(), opts, tuple(retried)))
            raise
        d.warn_if_unhealthy("strokes")
        run, counters = d.run(), d.counters()
    return SweepResult(tuple(points), tuple(skipped), run, counters, opts, tuple(retried))


def _sweep_attempt(d: _Driver, direction: int, v_target: float, points: Sequence[SweepPoint],
                   opts: SweepOptions) -> tuple[SweepPoint | None, str, bool]:
    """One stroke and its point (or why none, and whether another attempt can help)."""
    # the friction expected: the nearest point measured so far in this direction, else the
    # cylinder file's values (the loop's integral does the rest)
    done = [p for p in points if p.direction == direction and p.steady]
    if done:
        F_ff = abs(min(done, key=lambda p: abs(abs(p.v) - v_target)).F)
    else:
        F_ff = d.cyl.friction.Fc + d.cyl.friction.Fv * v_target
    seg = _stroke(d, direction, v_target, F_ff, opts)
    d.hold(opts.rest_s)
    return _sweep_point(d, direction, v_target, seg, opts)


@dataclass(frozen=True)
class _Stroke:
    i_start: int  # first sample of the stroke
    i_steady: int  # first sample of the steady part (-1: never steady)
    i_brake: int  # first sample of the deceleration
    i_end: int
    cruised: bool  # the speed reference reached the target before braking
    i_cruise: int = -1  # first sample at the target speed (-1: never reached)


def _stroke(d: _Driver, direction: int, v_target: float, F_ff: float, opts: SweepOptions) -> _Stroke:
    """One stroke at constant speed: the speed reference ramps up, holds, and ramps down before the
    working range ends.

    Cascade: the outer PI on the filtered velocity sets a net-force reference (feed-forward: the
    expected friction plus M times the reference acceleration); the inner force loop
    (`_Driver.force_command`, the air springs' K v fed forward) damps the air-spring resonance,
    which a velocity loop alone cannot do on a lightly damped cylinder: it rings into stick-slip."""
    cyl = d.cyl
    M = cyl.mechanics.moving_mass
    i_start = d.n - 1
    x_end = d.hi if direction > 0 else d.lo
    ramps = v_target ** 2 / (2 * opts.accel) + v_target ** 2 / (2 * opts.decel)
    if direction * (x_end - d.x) > v_target * opts.max_stroke_s + ramps:  # slow: only the travel it needs
        x_end = d.x + direction * (v_target * opts.max_stroke_s + ramps)
    wv = 2 * math.pi * opts.bandwidth_hz
    kp_v, ki_v = 2 * M * wv, M * wv * wv  # velocity loop critically damped on the mass
    k_F = 2 * math.pi * opts.force_bandwidth_hz
    F_lo, F_hi = sorted(force_limits(cyl))
    slew = 2.0 * (F_hi - F_lo)  # N/s
    lag = 0.01  # s: the filtered velocity lags by half its window; brake that much earlier
    v_ref = integ = 0.0
    F_cmd = d.F_fast
    phase = "accel"
    i_steady = i_brake = i_cruise = -1
    cruised, stuck, released = False, True, False
    t0 = t_last = t_cruise = t_moving = d.t
    x0 = d.x
    t_limit = d.t + opts.max_stroke_s + 3.0 + 2 * v_target / min(opts.accel, opts.decel)
    while True:
        dt, t_last = d.t - t_last, d.t
        remaining = direction * (x_end - d.x)
        v_meas = direction * d.v
        v_brake = max(v_ref, v_meas)
        if phase != "decel" and remaining <= v_brake ** 2 / (2 * opts.decel) + v_brake * lag:
            phase, i_brake = "decel", d.n - 1
        a_ref = 0.0
        if phase == "accel":
            v_ref = min(v_ref + opts.accel * dt, v_target)
            a_ref = opts.accel
            if v_ref >= v_target:
                phase, t_cruise, cruised, i_cruise = "cruise", d.t, True, d.n - 1
        elif phase == "cruise":
            if i_steady < 0 and not stuck and d.t - max(t_cruise, t_moving) >= opts.settle_s:
                i_steady = d.n - 1
        else:
            v_ref = max(v_ref - opts.decel * dt, 0.0)
            a_ref = -opts.decel
            if v_ref == 0.0 or remaining <= 0:
                break
        if direction * (d.x - x0) < -0.02 * d.L:
            raise _wrong_way(direction)
        # blocked: after 2 s less than 1 mm, or for a slow target a quarter of the reference's travel
        if d.t - t0 > 2.0 and direction * (d.x - x0) < min(1e-3, 0.25 * v_target * (d.t - t0)):
            raise ProcedureError(f"the piston did not move in {DIRECTION_NAMES[direction]} within 2 s "
                                 f"(command {d.s.u_applied:+.2f}): is it blocked, or the supply off?")
        if d.t > t_limit:
            break
        if stuck and v_meas > 0.5 * v_ref > 0:
            stuck, t_moving = False, d.t
        elif not stuck and v_meas < 0.25 * v_ref:
            stuck = True
        if not (stuck or released) and d.t - t_moving >= 0.02:
            # broken free for good: what the integral built up while stuck was stiction, not the
            # sliding friction; kept, it would overshoot the speed for a long time
            integ, released = min(integ, 0.0), True
        e = v_ref - v_meas
        F_ref = direction * (F_ff + M * a_ref + kp_v * e + integ)
        if F_lo < F_ref < F_hi:  # integrate only while the reference is reachable (no wind-up)
            integ += ki_v * e * dt
        # slew-limited: from rest the force reference flips sign, and a jump would kick the piston
        # loose before the loop is in control
        F_cmd += min(max(min(max(F_ref, F_lo), F_hi) - F_cmd, -slew * dt), slew * dt)
        d.step(d.force_command(F_cmd, k_F, v_ff=direction * v_ref))
    return _Stroke(i_start, i_steady, i_brake if i_brake >= 0 else d.n - 1, d.n - 1, cruised, i_cruise)


def _standard_error(y: np.ndarray, block: int) -> float:
    """Standard error of the mean of a series with correlated noise: the larger of the white-noise
    figure and batch means (blocks of >= `block` samples, 5 to 10 of them, when there are enough)."""
    white = float(y.std() / math.sqrt(len(y)))
    nb = min(10, len(y) // block)
    if nb < 5:
        return white
    means = np.array([b.mean() for b in np.array_split(y[: nb * (len(y) // nb)], nb)])
    return max(white, float(means.std(ddof=1) / math.sqrt(nb)))


def steady_speed(v: np.ndarray, direction: int, opts: SweepOptions, v_fast: np.ndarray | None = None) -> bool:
    """Whether a stroke's velocity samples slid steadily: spread within max_speed_spread of the mean
    speed, and never below min_speed_ratio of it (a near stop is stick-slip). `v_fast`, a velocity
    with less lag and smoothing than `v` (`fast_velocity`), is where a near stop is looked for: a
    stick-slip at the air-spring resonance hides in the friction's 31-sample derivative."""
    speed = abs(float(np.mean(v)))
    low = np.min(direction * (v if v_fast is None or not len(v_fast) else v_fast))
    return bool(speed > 0 and np.std(v) <= opts.max_speed_spread * speed and low >= opts.min_speed_ratio * speed)


def fast_velocity(x: np.ndarray, dt: float, noise: float, speed: float) -> np.ndarray:
    """Least-squares slope of the positions `x` (m, evenly sampled every `dt` s) over the shortest
    odd window, 5 samples at least, whose noise (position noise `noise`, m) stays within 5 % of
    `speed`; at most the friction's own derivative window. One value per whole window."""
    n = 5
    while n < 2 * _HALF + 1 and noise * math.sqrt(12.0 / (n * (n * n - 1))) / dt > 0.05 * speed:
        n += 2
    if len(x) < n:
        return np.empty(0)
    j = np.arange(n) - n // 2
    return np.convolve(x, (j / (j @ j))[::-1], mode="valid") / dt


def _sweep_point(d: _Driver, direction: int, v_target: float, seg: _Stroke,
                 opts: SweepOptions) -> tuple[SweepPoint | None, str, bool]:
    """The stroke's point: friction from Newton's law with the measured pressures, over its steady
    part; else why not, and whether running it again can help (not when the travel is too short)."""
    if seg.i_steady < 0:
        if seg.cruised:
            return None, (f"the piston never slid for {opts.settle_s:g} s without sticking (stick-slip: the speed "
                          "is too low for this friction)"), True
        return None, "the stroke is too short to reach this speed (lower --vmax)", False
    # the derivative window must not reach into the braking: it would smear the deceleration into
    # the steady part and bias the mean friction by M times a share of it
    i_end = seg.i_brake - _HALF - 5
    if i_end - seg.i_steady < opts.min_samples:
        short = f"the steady part is too short ({max(i_end - seg.i_steady, 0)} samples < {opts.min_samples})"
        # had the piston slid from the moment the reference reached the target, would it have
        # been long enough? Then it stuck or rang first (a busy host), and another stroke may do
        settle = int(round(opts.settle_s / float(np.median(np.diff(d.cols[0][seg.i_start:seg.i_end + 1])))))
        if seg.i_cruise >= 0 and i_end - (seg.i_cruise + settle) >= opts.min_samples:
            return None, f"{short}: the piston stuck or rang after reaching the target speed", True
        return None, f"{short}: lower --vmax", False
    a, b = max(seg.i_start - _HALF, 0), min(seg.i_end + _HALF, d.n)
    run = d.run(a, b)
    idx, v, F = friction_from_newton(d.cyl, run, _HALF, plant=d.plant)
    keep = (idx >= seg.i_steady - a) & (idx < i_end - a)
    v, F, sel = v[keep], F[keep], idx[keep]
    if len(v) < opts.min_samples or np.median(v) * direction <= 0:
        return None, "the piston did not move in the commanded direction", True
    v_mean = float(v.mean())
    # the fast velocity over the steady part, piece by piece between lost samples
    pieces = np.split(sel, np.flatnonzero(np.diff(run.t[sel]) > 1.5 * run.sample_period) + 1)
    v_fast = np.concatenate([fast_velocity(run.x[q[0]:q[-1] + 1], run.sample_period, d.cyl.sensors.position_noise,
                                           abs(v_mean)) for q in pieces])
    return SweepPoint(direction=direction, target=direction * v_target, v=v_mean, F=float(F.mean()),
                      v_std=float(v.std()), F_std=float(F.std()), F_sem=_standard_error(F, 4 * _HALF + 2),
                      n=int(len(v)), t_start=float(run.t[sel[0]]), t_end=float(run.t[sel[-1]]),
                      x_start=float(run.x[sel[0]]), x_end=float(run.x[sel[-1]]), u_mean=float(run.u[sel].mean()),
                      dp=float(np.abs(run.p1[sel] - run.p2[sel]).mean()),
                      pc=float(((run.p2[sel] if direction > 0 else run.p1[sel]) - d.cyl.supply.atmosphere).mean()),
                      steady=steady_speed(v, direction, opts, v_fast)), "", True
