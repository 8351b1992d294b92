"""Before any fit, in well under a second, from the data alone: can these runs belong to this
cylinder file, and can they determine the chosen parameters? Every subcommand that takes a
run and a cylinder calls `preflight` first; what it is sure of is refused in one sentence
naming the likely cause and its fix (RunFormatError or ConfigError: bad input, exit status
2), what it is not sure of comes back as notes to show.

Against the cylinder file (files.checks): the geometry the run's header names, the stroke
(millimetres, another origin, a longer stroke), the pressures against the atmosphere and the
supply (gauge chambers, a gauge supply). From the motion (here, they need its derivatives):

- the pressure force against the motion: friction opposes the motion, so the force that
  p1 A1 - p2 A2 leaves beyond m a (and a constant) has the sign of the velocity. Reversed,
  either p1 and p2 are swapped or the position runs the other way;
- each chamber against the command: while u > 0 the valve fills chamber 1 and empties
  chamber 2 (u < 0 the reverse). Over windows of 20 ms, the chambers' air (p^(1/kappa) V)
  grows and shrinks with the command's sign; reversed, the command's sign is inverted (or,
  with the force reversed too, tells swapped chambers from a reversed position);
- the chambers at rest with the valve centred sit near the valve's null pressure, 0.6 to
  0.75 of the way from the atmosphere to the supply on every cylinder and valve tried:
  far below, the pressures may be gauge; far above, the file's supply may be (a note only:
  a valve may hold them elsewhere).

Can the runs determine the parameters? A fit on a run that cannot (no motion, one direction
only, one speed, one pressure difference) still "converges", to numbers that mean nothing;
this says which parameter and why instead.

- Fc (Coulomb) needs motion in both directions: in one, it is a constant force like a load,
  the mounting angle or a pressure-sensor offset;
- Fv (viscous) needs motion at different speeds;
- kp (seal pressure) needs motion at different |p1 - p2|, not changing in step with the speed
  when Fv is estimated too.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from sim.cylinder import Cylinder

from ..files import Run, RunFormatError, split_at_gaps
from ..files.checks import GAUGE_FIX, check_run_shape, check_supply, run_name
from .smoothing import fill_missing, savgol_kernels, velocity_estimate

__all__ = ["MotionSummary", "motion_summary", "check_determinable", "Preflight", "preflight", "direction_figures"]

FRICTION = ("Fc", "Fv", "kp")
_MIN_MOTION_S = 0.05  # s of motion per direction that Fc needs at least
_MIN_SPEED_RATIO = 1.5  # fastest / slowest decile of the moving speeds that Fv needs at least
_TOGETHER = 0.98  # |r| of speed and |p1 - p2| above which kp and Fv cannot be told apart


@dataclass(frozen=True)
class MotionSummary:
    moving_speed: float  # m/s: faster than this counts as motion
    time_extending: float  # s
    time_retracting: float  # s
    position_range: float  # m
    speeds: np.ndarray  # |v| of the moving samples, m/s
    dp: np.ndarray  # |p1 - p2| at the moving samples, Pa


def motion_summary(cyl: Cylinder, runs: Sequence[Run]) -> MotionSummary:
    threshold = max(5.0 * cyl.friction.v_smooth, 2e-3)
    ext = ret = 0.0
    lo, hi = np.inf, -np.inf
    speeds, dps = [], []
    for piece in (p for r in runs for p in split_at_gaps(r)):
        if piece.n < 3:
            continue
        finite = np.isfinite(piece.x)  # a channel not measured at a sample is NaN
        if finite.sum() < 3:
            continue
        t, x = piece.t[finite], piece.x[finite]
        v = velocity_estimate(t, x)
        dt = np.gradient(t)
        ext += float(dt[v > threshold].sum())
        ret += float(dt[v < -threshold].sum())
        lo, hi = min(lo, float(x.min())), max(hi, float(x.max()))
        moving = np.abs(v) > threshold
        speeds.append(np.abs(v[moving]))
        dps.append(np.abs(piece.p1[finite] - piece.p2[finite])[moving])
    cat = (lambda a: np.concatenate(a) if a else np.empty(0))
    dp = cat(dps)
    ok = np.isfinite(dp)
    return MotionSummary(moving_speed=threshold, time_extending=ext, time_retracting=ret,
                         position_range=max(0.0, hi - lo) if np.isfinite(hi) else 0.0,
                         speeds=cat(speeds)[ok], dp=dp[ok])


def check_determinable(cyl: Cylinder, runs: Sequence[Run], estimate: Sequence[str]) -> None:
    """Refuse (RunFormatError: bad input, exit status 2) runs that cannot determine the
    friction parameters in `estimate`, naming the parameter and why."""
    wanted = [n for n in FRICTION if n in estimate]
    if not wanted or not runs:
        return
    names = [str(r.source.name) if r.source is not None else "the run" for r in runs]
    who = f"{names[0]}: this run" if len(names) == 1 else f"{', '.join(names)}: these runs"
    m = motion_summary(cyl, runs)
    moving = m.time_extending + m.time_retracting
    if moving < _MIN_MOTION_S:
        raise RunFormatError(f"{who} cannot determine {', '.join(wanted)}: the piston does not move (faster than "
                             f"{m.moving_speed * 1e3:.3g} mm/s for {moving:.3g} s in all, position range "
                             f"{m.position_range * 1e6:.4g} um); friction shows only in motion.")
    if "Fc" in wanted and min(m.time_extending, m.time_retracting) < _MIN_MOTION_S:
        only = "extending" if m.time_extending > m.time_retracting else "retracting"
        raise RunFormatError(f"{who} cannot determine Fc: the piston moves only while {only} "
                             f"({m.time_extending:.3g} s extending, {m.time_retracting:.3g} s retracting); in one "
                             "direction Coulomb friction cannot be told from a constant force (load, mounting angle, a "
                             "pressure-sensor offset), so record moves both ways or leave Fc out of --estimate.")
    lo, hi = np.percentile(m.speeds, [10, 90]) if m.speeds.size else (0.0, 0.0)
    if "Fv" in wanted and hi < _MIN_SPEED_RATIO * lo:
        raise RunFormatError(f"{who} cannot determine Fv: the piston moves at nearly one speed ({lo * 1e3:.3g} to "
                             f"{hi * 1e3:.3g} mm/s for 80 % of the motion); viscous friction grows with speed, so "
                             "record moves at different speeds or leave Fv out of --estimate.")
    if "kp" in wanted:
        dlo, dhi = np.percentile(m.dp, [10, 90]) if m.dp.size else (0.0, 0.0)
        if dhi - dlo < max(10.0 * cyl.sensors.pressure_noise, 0.05 * dhi):
            raise RunFormatError(f"{who} cannot determine kp: while the piston moves, |p1 - p2| stays between "
                                 f"{dlo / 1e3:.4g} and {dhi / 1e3:.4g} kPa (80 % of the motion); the seal-pressure "
                                 "term needs motion at different pressure differences, so vary the load or the "
                                 "supply, or leave kp out of --estimate.")
        if "Fv" in wanted and m.speeds.size > 2 and np.std(m.speeds) > 0 and np.std(m.dp) > 0:
            r = float(np.corrcoef(m.speeds, m.dp)[0, 1])
            if abs(r) > _TOGETHER:
                raise RunFormatError(f"{who} cannot determine kp and Fv apart: speed and |p1 - p2| changed together "
                                     f"(correlation {r:.4f}), so friction growing with one cannot be told from "
                                     "friction growing with the other; record moves where they vary independently, "
                                     "or estimate only one of them.")


# ------------------------------------------------------------------ the preflight

_HALF = 15  # Savitzky-Golay half window for velocity and acceleration (31 ms at 1 kHz)
_WINDOW_S = 0.02  # the windows over which the chambers' air is compared with the command
_KAPPA = 1.4
_SURE_T = 4.0  # |t| of the friction's sign beyond which the force balance is sure
_AGREE, _DISAGREE = 0.75, 0.25  # share of the chambers' air that moved with the command
_MIN_EVIDENCE = 20  # windows with the valve open, moving samples / 100: below, no verdict
_REST_LOW, _REST_HIGH = 0.5, 0.85  # the null pressure's place between atmosphere and supply, noted beyond


@dataclass(frozen=True)
class Preflight:
    """What the preflight found: notes to show (what it was not sure of), and per run the
    figures its verdicts rest on (direction_figures)."""
    notes: tuple[str, ...] = ()
    figures: tuple[dict, ...] = field(default=(), repr=False)


def preflight(cyl: Cylinder, runs: Sequence[Run], estimate: Sequence[str] = (),
              held_out: Sequence[Run] = ()) -> Preflight:
    """Check that every run (those fitted, then those `held_out` of the fit, e.g. a validation
    run) can belong to `cyl` (files.checks: channels, header, stroke, gauge chambers; the
    motion's directions; then the supply, which needs the directions right) and, with
    `estimate`, that the fitted runs can determine those parameters (check_determinable).
    Raises RunFormatError / ConfigError on what it is sure of; returns the notes."""
    notes: list[str] = []
    figures = []
    for run in (*runs, *held_out):
        notes += check_run_shape(run, cyl)
        fig = direction_figures(run, cyl)
        figures.append(fig)
        notes += _judge_directions(run, cyl, fig)
        notes += check_supply(run, cyl)
    if estimate:
        check_determinable(cyl, runs, estimate)
    return Preflight(notes=tuple(dict.fromkeys(notes)), figures=tuple(figures))


def _pieces(run: Run) -> list[Run]:
    """Gap-free pieces long enough to differentiate, with channels not measured filled in (an
    estimate for these statistics only)."""
    out = []
    for piece in split_at_gaps(run):
        if piece.n < 4 * _HALF + 10:
            continue
        filled = {n: fill_missing(piece.t, getattr(piece, n)) for n in ("x", "p1", "p2")}
        if all(np.isfinite(v).all() for v in filled.values()):
            out.append(replace(piece, **filled))
    return out


def _smooth(y: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    s, d1, d2 = savgol_kernels(_HALF)
    valid = lambda k: np.convolve(y, k, mode="valid")  # noqa: E731
    return valid(s), valid(d1) / dt, valid(d2) / dt ** 2


def _block_t(z: np.ndarray, per: int) -> float:
    """The mean of z over its standard error from blocks of `per` samples (z is correlated
    over about a window)."""
    nb = len(z) // per
    if nb < 3:
        return math.nan
    means = z[:nb * per].reshape(nb, per).mean(axis=1)
    sd = float(means.std(ddof=1))
    return float(means.mean() / (sd / math.sqrt(nb))) if sd > 0 else math.copysign(math.inf, float(means.mean()))


def direction_figures(run: Run, cyl: Cylinder) -> dict:
    """The figures of the direction checks for one run: `friction_t` (the friction left by the
    pressure force beyond m a and a constant, along the motion, over its standard error: well
    positive when p1, p2 and x are the right way round), `agree` (share of the chambers' air
    that moved with the command's sign, 1 when u, p1 and p2 are the right way round; the same
    with p1 and p2 swapped back: `agree_swapped`, with the position reversed:
    `agree_reversed`) and `rest` (where the chambers rest between atmosphere and supply)."""
    g, pa, ps = cyl.geometry, cyl.supply.atmosphere, cyl.supply.pressure
    A1, A2 = g.area_cap, g.area_rod
    vth = max(5 * cyl.friction.v_smooth, 2e-3)
    rows, air, rest = [], {"agree": [0.0, 0.0], "agree_swapped": [0.0, 0.0], "agree_reversed": [0.0, 0.0]}, []
    windows = 0
    for piece in _pieces(run):
        dt = piece.sample_period
        x, v, a = _smooth(piece.x, dt)
        p1, p2 = _smooth(piece.p1, dt)[0], _smooth(piece.p2, dt)[0]
        u = piece.u[_HALF:-_HALF]
        F = A1 * p1 - A2 * p2 - pa * (A1 - A2)
        inside = (x > 0.03 * g.stroke) & (x < 0.97 * g.stroke)  # end stops push too
        moving = (np.abs(v) > vth) & inside
        rows.append(np.column_stack([F, a, np.sign(v), v])[moving])
        held = (np.abs(v) < 2e-3) & (np.abs(u) < 0.1) & inside
        rest.append(((A1 * p1 + A2 * p2) / (A1 + A2))[held])
        W = max(2, int(round(_WINDOW_S / dt)))
        for key, (q1, q2, xx) in (("agree", (piece.p1, piece.p2, piece.x)),
                                  ("agree_swapped", (piece.p2, piece.p1, piece.x)),
                                  ("agree_reversed", (piece.p1, piece.p2, g.stroke - piece.x))):
            pos, tot, n_open = _air_with_command(piece.u, xx, q1, q2, cyl, W)
            air[key][0] += pos
            air[key][1] += tot
            if key == "agree":
                windows += n_open
    out = {"friction_t": math.nan, "agree": math.nan, "agree_swapped": math.nan, "agree_reversed": math.nan,
           "rest": math.nan}
    if windows >= _MIN_EVIDENCE:
        for key, (pos, tot) in air.items():
            out[key] = pos / tot if tot > 0 else math.nan
    X = np.vstack(rows) if rows else np.empty((0, 4))
    if len(X) >= 100 * _MIN_EVIDENCE:
        # F = m a + friction(v) + F0; the friction left beyond m a and F0, along the motion
        A = np.column_stack([X[:, 1], X[:, 2], X[:, 3], np.ones(len(X))])
        coef = np.linalg.lstsq(A, X[:, 0], rcond=None)[0]
        along = (X[:, 0] - coef[0] * X[:, 1] - coef[3]) * X[:, 2]
        out["friction_t"] = _block_t(along, 100)
    held = np.concatenate(rest) if rest else np.empty(0)
    if held.size >= 500:
        out["rest"] = float(np.median((held - pa) / (ps - pa)))
    return out


def _air_with_command(u, x, p1, p2, cyl: Cylinder, W: int) -> tuple[float, float, int]:
    """Over windows of W samples: how much of the chambers' air change went the way the
    command drives it (chamber 1 gains and chamber 2 loses for u > 0), weighted by the
    command; (agreeing, total, windows with the valve open)."""
    g = cyl.geometry
    xc = np.clip(x, 0.0, g.stroke)
    m1 = np.maximum(p1, 1.0) ** (1 / _KAPPA) * (g.dead_volume_cap + g.area_cap * xc)
    m2 = np.maximum(p2, 1.0) ** (1 / _KAPPA) * (g.dead_volume_rod + g.area_rod * (g.stroke - xc))
    n = len(u)
    if n < 3 * W + 10:
        return 0.0, 0.0, 0
    starts = np.arange(3, n - W - 3, W)
    ends = starts + W

    def at(y):  # mean of 5 samples around each window end (the sensor noise)
        c = np.concatenate([[0.0], np.cumsum(y)])
        return (c[ends + 3] - c[ends - 2]) / 5 - (c[starts + 3] - c[starts - 2]) / 5

    d1, d2 = at(m1), at(m2)
    cu = np.concatenate([[0.0], np.cumsum(u)])
    U = (cu[ends] - cu[starts]) / W
    s1, s2 = np.median(np.abs(d1)), np.median(np.abs(d2))
    if not (s1 > 0 and s2 > 0):
        return 0.0, 0.0, 0
    z = U * (d1 / s1 - d2 / s2)
    return float(np.maximum(z, 0.0).sum()), float(np.abs(z).sum()), int(np.sum(np.abs(U) > 0.01))


def _judge_directions(run: Run, cyl: Cylinder, f: dict) -> list[str]:
    """Refuse what the direction figures are sure of, naming the cause and the fix; notes for
    what they only suggest."""
    name = run_name(run)
    t, agree = f["friction_t"], f["agree"]
    notes = []
    if t <= -_SURE_T:
        force = (f"the pressure force p1 A1 - p2 A2 pushes the piston against its motion (friction would have to "
                 f"push it along: t = {t:.3g})")
        if f["agree_swapped"] >= _AGREE and not f["agree_reversed"] >= _AGREE:
            raise RunFormatError(f"{name}: p1 and p2 look swapped: {force}, and the chambers fill the way the command "
                                 f"drives them only with p1 and p2 exchanged; p1 is the cap side (the chamber that "
                                 f"extends the piston): swap the columns p1 and p2 (or their sources in the import "
                                 f"map).")
        if f["agree_reversed"] >= _AGREE and not f["agree_swapped"] >= _AGREE:
            raise RunFormatError(f"{name}: the position looks reversed: {force}, and the chambers follow the command "
                                 f"only with the position measured from the other end; x must grow as the piston "
                                 f"extends from 0 (fully retracted): use the stroke minus the position (a negative "
                                 f"scale for x in the import map), or, if the command's sign and p1/p2 are both "
                                 f"swapped, fix those.")
        raise RunFormatError(f"{name}: {force}: p1 and p2 are swapped or the position runs the other way; p1 is the "
                             f"cap side and x grows as the piston extends from 0 (fully retracted).")
    if agree <= _DISAGREE and t >= _SURE_T:
        raise RunFormatError(f"{name}: the command's sign looks inverted: where the command says fill, the chamber "
                             f"empties ({100 * (1 - agree):.0f} % of the chambers' air moved against the command's "
                             f"sign), while the pressure force and the motion agree; u > 0 must open the supply to "
                             f"p1 (extend): invert the command (u -> -u, or a negative span for u in the import map).")
    if t < _SURE_T / 2 and math.isfinite(t):
        notes.append(f"{name}: the pressure force barely explains the motion's direction (friction along the motion "
                     f"at t = {t:.2g}); check that p1 is the cap side and x grows as the piston extends")
    if agree < _AGREE:
        notes.append(f"{name}: only {agree:.0%} of the chambers' air moved the way the command drives it; check the "
                     f"command's sign, that p1 is the cap side and that x grows as the piston extends")
    rest = f["rest"]
    if rest < _REST_LOW:
        notes.append(f"{name}: at rest the chambers sit {rest:.2f} of the way from the atmosphere to the supply "
                     f"({cyl.supply.atmosphere:g} to {cyl.supply.pressure:g} Pa), where a centred valve holds them "
                     f"near 0.6 to 0.75: if the pressures are gauge, {GAUGE_FIX}")
    elif rest > _REST_HIGH:
        notes.append(f"{name}: at rest the chambers sit {rest:.2f} of the way from the atmosphere to the supply "
                     f"({cyl.supply.atmosphere:g} to {cyl.supply.pressure:g} Pa of "
                     f"{cyl.source or 'the cylinder file'}), "
                     f"where a centred valve holds them near 0.6 to 0.75: if the file's supply is gauge, give it "
                     f"absolute (gauge + {cyl.supply.atmosphere:g} Pa)")
    return notes
