"""Safe experiment programs: what the valve is asked to do during a run.

The built-in program is closed-loop position control on the *measured* position along
a seeded sequence of steps, constant-speed ramps in both directions and sines, with a
small dither on the command. Commands are bounded and the reference stays within soft
stroke limits; near a limit the command can only push back into the stroke.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim.cylinder import Cylinder
from sim.flow import R_AIR, RHO0, T0
from sim.inputs import read_checked, shorten

from ..files.plausibility import COMMAND_LIMIT

COMMAND_FILE_MAX_BYTES = 64 << 20  # a command file: hours of commands at 1 kHz

@dataclass(frozen=True)
class ProgramOptions:
    u_max: float = 0.8  # command bound
    margin: float = 0.1  # soft stroke limits as a fraction of the stroke
    dither: float = 0.03  # standard deviation of the command dither
    bandwidth_hz: float = 4.0  # position-loop crossover


def _reference_segments(L: float, duration: float, rng: np.random.Generator,
                        kinds: tuple[str, ...] = ("step", "ramp", "sine")):
    """(t_end, kind, params) segments filling `duration`; positions within [0.15L, 0.85L]."""
    lo, hi = 0.15 * L, 0.85 * L
    kinds = list(kinds)
    segs = []
    t = 0.0
    x = 0.5 * L
    while t < duration:
        kind = kinds[rng.integers(len(kinds))]
        if kind == "step":
            target = rng.uniform(lo, hi)
            T = rng.uniform(0.5, 1.0)
            segs.append((t, t + T, "step", (target,)))
            x = target
        elif kind == "ramp":
            target = hi if x < 0.5 * L else lo
            T = abs(target - x) / (L * rng.choice([0.25, 0.5, 1.0, 2.0, 3.0]))
            T = max(T, 0.2)
            segs.append((t, t + T, "ramp", (x, target)))
            x = target
            segs.append((t + T, t + T + 0.3, "step", (x,)))
            T += 0.3
        else:
            amp = rng.uniform(0.1, 0.3) * L
            centre = float(np.clip(x, lo + amp, hi - amp))
            f = rng.choice([0.5, 1.0, 1.5, 2.5])
            T = round(rng.uniform(1.0, 2.0) * f) / f or 1.0 / f
            segs.append((t, t + T, "sine", (centre, amp, f, x)))
            x = centre
        t += T
    return segs


class PositionProgram:
    """Closed-loop position control along a seeded reference; call `command(t, x_measured)`."""

    def __init__(self, cyl: Cylinder, duration: float, seed: int = 0, options: ProgramOptions = ProgramOptions(),
                 kinds: tuple[str, ...] = ("step", "ramp", "sine")):
        self.cyl = cyl
        self.opts = options
        self.rng = np.random.default_rng(seed + 7919)
        L = cyl.geometry.stroke
        self.L = L
        self.segments = _reference_segments(L, duration, np.random.default_rng(seed), kinds)
        # velocity per unit command near mid-pressure: choked flow at full opening into
        # a chamber at ~70 % of supply; the loop gain follows from the crossover
        g = cyl.geometry
        v_per_u = cyl.valve.sonic_conductance * RHO0 * math.sqrt(T0 / cyl.supply.temperature) * R_AIR \
            * cyl.supply.temperature / (0.7 * g.area_cap)
        self.kp = 2 * math.pi * options.bandwidth_hz / v_per_u
        self.kff = 1.0 / v_per_u
        self._i = 0

    def reference(self, t: float) -> tuple[float, float]:
        while self._i < len(self.segments) - 1 and t >= self.segments[self._i][1]:
            self._i += 1
        t0, t1, kind, par = self.segments[self._i]
        if kind == "step":
            return par[0], 0.0
        if kind == "ramp":
            a, b = par
            s = min(max((t - t0) / (t1 - t0), 0.0), 1.0)
            return a + (b - a) * s, (b - a) / (t1 - t0) if s < 1.0 else 0.0
        centre, amp, f, x_from = par
        w = 2 * math.pi * f
        # blend from the previous position into the sine over its first quarter period
        blend = min((t - t0) * f * 4, 1.0)
        r = centre + amp * math.sin(w * (t - t0))
        return x_from + (r - x_from) * blend, amp * w * math.cos(w * (t - t0)) * blend

    def command(self, t: float, x_meas: float) -> float:
        r, rdot = self.reference(t)
        lo, hi = self.opts.margin * self.L, (1 - self.opts.margin) * self.L
        r = min(max(r, lo), hi)
        u = self.kp * (r - x_meas) + self.kff * rdot + self.opts.dither * self.rng.standard_normal()
        return guarded(u, x_meas, self.L, self.opts)


def guarded(u: float, x_meas: float, L: float, opts: ProgramOptions) -> float:
    """A command within the bound that, past a soft stroke limit, can only push back into the stroke."""
    u = 0.0 if math.isnan(u) else max(-opts.u_max, min(opts.u_max, float(u)))
    lo = opts.margin * L
    if x_meas < 0.5 * lo:
        u = max(u, 0.05)
    elif x_meas > L - 0.5 * lo:
        u = min(u, -0.05)
    return u


class HeldCommandProgram:
    """Open loop: command u[i] held from t[i] until t[i+1] (the last one to the end); the
    bound and the soft stroke limits still apply, on the measured position."""

    def __init__(self, t: np.ndarray, u: np.ndarray, cyl: Cylinder, options: ProgramOptions = ProgramOptions()):
        self.t, self.u = np.asarray(t, float), np.asarray(u, float)
        self.L, self.opts = cyl.geometry.stroke, options

    def command(self, t: float, x_meas: float) -> float:
        i = max(int(np.searchsorted(self.t, t, side="right")) - 1, 0)
        return guarded(self.u[i], x_meas, self.L, self.opts)


def pulse_program(cyl: Cylinder, duration: float, seed: int = 0,
                  options: ProgramOptions = ProgramOptions()) -> HeldCommandProgram:
    """Alternating pulses of random height and length, with rests between them."""
    rng = np.random.default_rng(seed)
    starts, levels = [], []
    sign, t = 1.0, 0.0
    while t < duration:
        on, rest = rng.uniform(0.05, 0.3), rng.uniform(0.2, 0.6)
        starts += [t, t + on]
        levels += [sign * rng.uniform(0.1, options.u_max), 0.0]
        t, sign = t + on + rest, -sign
    return HeldCommandProgram(np.array(starts), np.array(levels), cyl, options)


def command_file_program(path, cyl: Cylinder, options: ProgramOptions = ProgramOptions()) -> HeldCommandProgram:
    """Commands from a CSV file with columns t and u (u within [-1, 1]: a command beyond is
    refused, never bounded silently; the program's own bound still applies)."""
    try:
        text = read_checked(path, "a command file", ValueError, COMMAND_FILE_MAX_BYTES).decode("utf-8-sig")
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not UTF-8 text (a command file is a CSV with columns t and u).") from None
    rows = [(n, ln) for n, ln in enumerate(text.splitlines(), 1) if ln.strip() and not ln.lstrip().startswith("#")]
    if not rows:
        raise ValueError(f"{path}: holds no commands (a command file is a CSV with columns t and u).")
    names = [c.strip() for c in rows[0][1].split(",")]
    if "t" not in names or "u" not in names:
        raise ValueError(f"{path}: a command file needs columns t and u (found "
                         f"{shorten(', '.join(names)) or 'none'}).")
    t, u = np.empty(len(rows) - 1), np.empty(len(rows) - 1)
    for k, (n, line) in enumerate(rows[1:]):
        cells = line.split(",")
        if len(cells) != len(names):
            raise ValueError(f"{path}, line {n}: {len(cells)} cells, but the header has {len(names)} columns.")
        for arr, j in ((t, names.index("t")), (u, names.index("u"))):
            try:
                arr[k] = float(cells[j])
            except ValueError:
                raise ValueError(f"{path}, line {n}: {shorten(cells[j].strip())!r} is not a number.") from None
    if not t.size:
        raise ValueError(f"{path}: no commands after the header.")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(u)) and np.all(np.diff(t) > 0)):
        raise ValueError(f"{path}: times must be finite and increasing, commands finite.")
    beyond = np.flatnonzero(np.abs(u) > COMMAND_LIMIT)
    if beyond.size:
        i = int(beyond[0])
        raise ValueError(f"{path}: u = {u[i]:g} at t = {t[i]:g} s is outside [-1, 1] (the valve's opening as a "
                         "fraction of full opening; not percent or volts).")
    return HeldCommandProgram(t, u, cyl, options)


class CalibrationProgram:
    """What calibration needs, safely: creeping openings through the valve's overlap in both
    directions (open loop, stopped well before the soft limits), moves into both end stops at a
    bounded speed and command with a hold there (the exhausting chamber settles at atmosphere,
    the filling one at supply: the sensors' offsets; at the ends the dead volumes show), and
    open-loop pulses of growing command (the flow characteristic up to full opening, the mass)
    and closed-loop steps, ramps and sines at several positions and speeds (the flow
    characteristic at small openings, the critical ratio). Call `command(t, x_measured)`."""

    END_SPEED = 0.05  # m/s: the reference's speed into an end stop (a gentle landing) ...
    END_TRAVEL = 2.0  # s: ... or, on a long stroke, fast enough to cross it in this time, at most
    END_SPEED_MAX = 0.15  # m/s
    END_COMMAND = 0.35  # command bound while driving into and holding at an end
    END_HOLD = 1.5  # s at the end stop
    CREEP_RATE = 0.15  # 1/s: how fast the open-loop command grows while creeping
    CREEP_MAX = 0.3  # the creep's largest command

    def __init__(self, cyl: Cylinder, duration: float, seed: int = 0, options: ProgramOptions = ProgramOptions()):
        self.L, self.opts = cyl.geometry.stroke, options
        self.closed = PositionProgram(cyl, duration, seed, options)
        L = self.L
        # (start, end, kind, sign, level): cycles of creeping out and in, both end stops, pulses
        # of growing command, then position control; its reference runs underneath throughout
        self.phases: list[tuple[float, float, str, float, float]] = []
        self.end_speed = min(max(self.END_SPEED, L / self.END_TRAVEL), self.END_SPEED_MAX)
        travel = 1.1 * L / self.end_speed + self.END_HOLD
        # a pulse's length: a sixth of the stroke at the speed its command gives
        v_per_u = 1.0 / self.closed.kff
        t, cycle = 1.0, 0
        while t < duration:
            s = 1.0 if cycle % 2 == 0 else -1.0
            plan = [("creep", 2.0, s, 0.0), ("settle", 0.8, s, 0.0), ("end", travel, s, 0.0), ("settle", 1.0, s, 0.0),
                    ("creep", 2.0, -s, 0.0), ("settle", 0.8, s, 0.0), ("end", travel, -s, 0.0),
                    ("settle", 1.0, s, 0.0)]
            for level in (0.25, 0.45, 0.65, options.u_max):
                for sign in (s, -s):
                    plan += [("pulse", min(0.3, L / 6 / (v_per_u * level)), sign, level), ("settle", 0.6, s, 0.0)]
            plan.append(("position", 5.0, s, 0.0))
            for kind, length, sign, level in plan:
                self.phases.append((t, t + length, kind, sign, level))
                t += length
            cycle += 1
        self._i = -1
        self._x0 = 0.5 * self.L  # where the current phase started
        self._creep_done = False

    def command(self, t: float, x_meas: float) -> float:
        i = self._i
        while i < len(self.phases) - 1 and t >= self.phases[i + 1][0]:
            i += 1
        if i != self._i:
            self._i, self._x0, self._creep_done = i, x_meas, False
        if i < 0:
            return self.closed.command(t, x_meas)
        t0, _t1, kind, sign, level = self.phases[i]
        L = self.L
        if kind == "end":  # no soft limit: the end stop is the limit, approached at end_speed
            # the reference goes on beyond the end, so that the held command opens the valve
            # decisively (up to END_COMMAND) and the chambers settle at supply and atmosphere
            target = 1.5 * L if sign > 0 else -0.5 * L
            r = self._x0 + sign * self.end_speed * (t - t0)
            r = min(r, target) if sign > 0 else max(r, target)
            u = self.closed.kp * (r - x_meas) + (self.closed.kff * sign * self.end_speed if r != target else 0.0)
            return max(-self.END_COMMAND, min(self.END_COMMAND, u))
        if kind == "creep":  # open loop from mid-stroke; stops well inside the soft limits
            if (x_meas - 0.5 * L) * sign > 0.25 * L:
                self._creep_done = True
            u = 0.0 if self._creep_done else sign * min(self.CREEP_RATE * (t - t0), self.CREEP_MAX)
            return guarded(u, x_meas, L, self.opts)
        if kind == "pulse":  # open loop, from mid-stroke
            return guarded(sign * level, x_meas, L, self.opts)
        if kind == "settle":  # back to mid-stroke under position control
            u = self.closed.kp * (0.5 * L - x_meas)
            return guarded(u, x_meas, L, self.opts)
        return self.closed.command(t, x_meas)


PROGRAMS = {"mixed": ("step", "ramp", "sine"), "steps": ("step",), "ramps": ("ramp",), "sines": ("sine",),
            "pulses": None, "calibration": None}


def make_program(name: str, cyl: Cylinder, duration: float, seed: int = 0, options: ProgramOptions = ProgramOptions()):
    """A built-in program by name (mixed, steps, ramps, sines, pulses, calibration) or `file:PATH`
    (t,u CSV)."""
    if name.startswith("file:"):
        return command_file_program(name[5:], cyl, options)
    if name not in PROGRAMS:
        raise ValueError(f"unknown program '{name}' (available: {', '.join(PROGRAMS)}, file:PATH).")
    if name == "pulses":
        return pulse_program(cyl, duration, seed, options)
    if name == "calibration":
        return CalibrationProgram(cyl, duration, seed, options)
    return PositionProgram(cyl, duration, seed, options, PROGRAMS[name])
