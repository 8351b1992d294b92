"""The static friction-velocity map (the friction of industrial pneumatic actuators, seed 004,
and Trentini et al.'s Karnopp/least-squares friction fit, seed 000): per direction its points
(points: from runs; tables: from points tables), the stick band, the linear fit and every
model's fit (fits), and the quantities the points confound.

Breakaway rows are not sliding points: every fit and the stick band's dv use the sliding
points only (so that RMSE, R^2 and AICc of all models refer to the same points); the
breakaway rows fix Fs of karnopp, cvs, cvs_delta and lugre (seed 004: Fs from the rest end
of the map, then the Stribeck velocity fitted to the sliding points), with their standard
error. Breakaways detected in runs feed the stick band and karnopp only.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable, Mapping, Sequence

import numpy as np

from sim.friction_models import DIRECTIONS, FRICTION_MODELS

from ..progress import counter
from .fits import LinearFit, ModelFit, fit_curve, fit_model, linear_fit, predicted
from .points import Breakaway, MapPoint
from .specs import FIT_SPECS, NOMINAL_LAW, PARSIMONY, FrictionMapError, TooFewPointsError

__all__ = ["StickBand", "Confounding", "confounded_quantities", "DirectionMap", "FrictionMap", "build_map"]


# families whose Fs is the breakaway force itself (no load or pressure terms): breakaway rows fix it
_FS_FROM_BREAKAWAY_ROWS = frozenset({"cvs", "lugre"})


@dataclass(frozen=True)
class StickBand:
    """Where one direction sticks: no steady sliding below dv (Karnopp's band, seed 000's
    minimum speed), and the breakaway forces: single ones seen in runs, and the rows of
    breakaway tables (each the mean of `count` trials with their standard deviation F_std)."""

    direction: str
    dv: float | None  # m/s: slowest steady sliding speed
    at_detector_limit: bool  # dv is the detector's min_speed: the true band may be narrower
    breakaway: tuple[float, ...]  # N, magnitudes (runs)
    stuck_speed: float | None  # m/s (runs)
    stuck_time: float | None  # s in all runs, either direction
    breakaway_rows: tuple[tuple[float, float, int], ...] = ()  # (mean |F| N, std N or NaN, trials) of tables

    def _groups(self) -> list[tuple[float, float, int]]:
        """(mean, std, count) of every source; a row without its spread counts as one value."""
        return [(f, 0.0, 1) for f in self.breakaway] + \
            [(m, s, n) if math.isfinite(s) else (m, 0.0, 1) for m, s, n in self.breakaway_rows]

    @property
    def breakaway_count(self) -> int:
        return sum(n for *_, n in self._groups())

    @property
    def breakaway_mean(self) -> float | None:
        g = self._groups()
        return sum(m * n for m, _, n in g) / self.breakaway_count if g else None

    @property
    def breakaway_std(self) -> float | None:
        """Sample standard deviation of all trials, pooled exactly from the groups' means and spreads."""
        N = self.breakaway_count
        if N < 2:
            return None
        mean = self.breakaway_mean
        ss = sum((n - 1) * s * s + n * (m - mean) ** 2 for m, s, n in self._groups())
        return math.sqrt(ss / (N - 1))

    def to_json(self) -> dict:
        return {"dv": self.dv, "at_detector_limit": self.at_detector_limit, "stuck_speed": self.stuck_speed,
                "stuck_time_s": self.stuck_time,
                "breakaway": {"count": self.breakaway_count, "mean": self.breakaway_mean, "std": self.breakaway_std,
                              "max": max(self.breakaway) if self.breakaway else None,
                              "forces": list(self.breakaway),
                              "rows": [{"mean": m, "std": s, "count": n} for m, s, n in self.breakaway_rows]}}


@dataclass(frozen=True)
class Confounding:
    """Two quantities of a direction's points that changed together: a friction term growing
    with one cannot be told from one growing with the other."""

    first: str  # "speed", "dp", "pc", "load"
    second: str
    r: float  # correlation over the sliding points

    def sentence(self, direction: str) -> str:
        return (f"{_QUANTITY_WORDS[self.first]} and {_QUANTITY_WORDS[self.second]} changed together in the "
                f"{direction} points (r = {self.r:.3f}), so friction growing with one is hard to tell from friction "
                f"growing with the other; their terms are reported only where the points still determine them")

    def to_json(self) -> dict:
        return {"quantities": [self.first, self.second], "r": self.r}


_QUANTITY_WORDS = {"speed": "speed", "dp": "|p1 - p2|", "pc": "the counter pressure", "load": "the normal load"}
_CONFOUNDED = 0.9  # |r| from which two quantities count as changed together


def confounded_quantities(points: Sequence[MapPoint]) -> tuple[Confounding, ...]:
    """Pairs of speed, dp, pc, load that changed together over the sliding points (|r| >= 0.9)."""
    slide = [p for p in points if not p.breakaway]
    if len(slide) < 3:
        return ()
    series = {"speed": np.abs([p.v for p in slide])}
    for key in ("dp", "pc", "load"):
        vals = np.array([getattr(p, key) for p in slide], float)
        if np.all(np.isfinite(vals)):
            series[key] = vals
    series = {k: v for k, v in series.items() if np.std(v) > 1e-12 * max(1.0, float(np.mean(np.abs(v))))}
    names = list(series)
    out = []
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            r = float(np.corrcoef(series[a], series[b])[0, 1])
            if abs(r) >= _CONFOUNDED:
                out.append(Confounding(a, b, r))
    return tuple(out)


@dataclass(frozen=True)
class DirectionMap:
    direction: str
    points: tuple[MapPoint, ...]
    stick_band: StickBand
    linear: LinearFit | None
    fits: Mapping[str, ModelFit]
    skipped: Mapping[str, str]  # model -> why it was not fitted
    confounded: tuple[Confounding, ...] = ()

    @property
    def best(self) -> str | None:
        """Among the fits that may be preferred (every parameter determined, a sound curve), the
        simplest whose AICc lies within PARSIMONY of the lowest: the fewest parameters, then the
        product's own law (cv_dp), then the lower AICc. A parameter must buy more than
        PARSIMONY AICc units (a likelihood ratio of e^2, about 7.4) to be preferred, and another
        law as many over the nominal one. None without a preferable fit."""
        ranked = {n: f for n, f in self.fits.items() if f.preferable and f.aicc is not None}
        if not ranked:
            return None
        lowest = min(f.aicc for f in ranked.values())
        order = list(FIT_SPECS)
        near = [n for n, f in ranked.items() if f.aicc <= lowest + PARSIMONY]
        return min(near, key=lambda n: (len(ranked[n].free), n != NOMINAL_LAW, ranked[n].aicc,
                                        order.index(n) if n in order else len(order)))

    def to_json(self) -> dict:
        return {"models": {k: f.to_json() for k, f in self.fits.items()},
                "best": self.best, "confounded": [c.to_json() for c in self.confounded],
                "notes": [c.sentence(self.direction) for c in self.confounded],
                "linear": self.linear.to_json() if self.linear else None,
                "points": [p.to_json() for p in self.points], "stick_band": self.stick_band.to_json(),
                "skipped": dict(self.skipped)}


@dataclass(frozen=True)
class FrictionMap:
    directions: Mapping[str, DirectionMap]

    def combined(self) -> dict[str, dict]:
        """Per model fitted in both directions: its full parameter set (model names, the
        class defaults where the map gives no value) and the spec string for
        sim.friction_models.parse_friction_spec."""
        out = {}
        for name in FIT_SPECS:
            fits = [d.fits.get(name) for d in self.directions.values()]
            if any(f is None for f in fits):
                continue
            cls = FRICTION_MODELS[fits[0].family]
            values = {k: v for f in fits for k, v in f.model_values().items()}
            defaults = [k for k in cls.PARAMS if k not in values and k not in cls.CONDITIONS]
            full = {k: values.get(k, cls.defaults()[k]) for k in cls.PARAMS}
            out[name] = {"family": cls.name, "params": full, "defaults_used": defaults,
                         "spec": f"{cls.name}:" + ",".join(f"{k}={v:.6g}" for k, v in full.items())}
        return out

    def to_json(self) -> dict:
        return {"directions": {k: d.to_json() for k, d in self.directions.items()}, "models": self.combined()}


def build_map(points: Sequence[MapPoint], models: Sequence[str] | None = None,
              breakaways: Sequence[Breakaway] = (), stuck_speed: float | None = None,
              stuck_time: float | None = None, min_speed: float | None = None,
              strict: bool = False, progress: Callable[[str], None] | None = None) -> FrictionMap:
    """Fit the models (default: all of FIT_SPECS) to each direction's points; `progress`
    hears of each fit done (of models x directions).

    strict: a model that cannot be fitted (too few points, missing conditions) is an
    error; otherwise it is skipped with the reason."""
    names = list(models) if models else list(FIT_SPECS)
    unknown = [m for m in names if m not in FIT_SPECS]
    if unknown:
        raise FrictionMapError(f"unknown model {', '.join(unknown)} (known: {', '.join(FIT_SPECS)}).")
    dirs = {}
    tick = counter(progress, "model fits", len(names) * len(DIRECTIONS))
    for direction in DIRECTIONS:
        pts = tuple(sorted((p for p in points if p.direction == direction), key=lambda p: abs(p.v)))
        slide = [p for p in pts if not p.breakaway]
        forces = tuple(b.force for b in breakaways if b.direction == direction)
        rows = tuple((abs(p.F), p.F_std, p.count) for p in pts if p.breakaway)
        dv = abs(slide[0].v) if slide else None
        band = StickBand(direction=direction, dv=dv,
                         at_detector_limit=bool(dv is not None and min_speed is not None and dv < 1.2 * min_speed),
                         breakaway=forces, stuck_speed=stuck_speed, stuck_time=stuck_time, breakaway_rows=rows)
        fits, skipped = {}, {}
        linear = None
        try:
            linear = linear_fit(pts) if slide else None
        except TooFewPointsError:
            pass
        for name in names:
            try:
                if not slide:
                    what = "no points" if not pts else "no points but breakaway rows (no sliding points)"
                    raise TooFewPointsError(f"the {direction} direction has {what}, so {name} cannot be fitted.")
                fixed, why = {}, {}
                if FIT_SPECS[name].family == "karnopp":
                    # the band is where no steady sliding was seen; every point lies on the sliding branch
                    fixed["dv"] = float(np.nextafter(dv, 0.0))
                    why["dv"] = "the stick band: slowest steady sliding speed (not fitted)"
                    fixed["Fs"] = band.breakaway_mean if band.breakaway_count else math.nan
                    why["Fs"] = (f"mean of {band.breakaway_count} breakaway forces (not fitted)" if band.breakaway_count
                                 else "no breakaway observed: not determined")
                rows_only = replace(band, breakaway=())  # the breakaway table's rows
                if FIT_SPECS[name].family in _FS_FROM_BREAKAWAY_ROWS and rows_only.breakaway_count:
                    fixed["Fs"] = rows_only.breakaway_mean
                    why["Fs"] = (f"mean of {rows_only.breakaway_count} breakaway forces of the breakaway table "
                                 f"(not fitted)")
                fit = fit_model(pts, name, fixed, why)
                if FIT_SPECS[name].family == "karnopp":
                    fit = _fs_from_breakaways(fit, band)
                elif "Fs" in fixed:
                    fit = _fs_from_breakaways(fit, rows_only)
                fits[name] = _assess(fit, pts)
            except FrictionMapError as e:
                if strict:
                    raise
                skipped[name] = str(e)
            if tick:
                tick()
        dirs[direction] = DirectionMap(direction=direction, points=pts, stick_band=band, linear=linear,
                                       fits=fits, skipped=skipped, confounded=confounded_quantities(pts))
    return FrictionMap(directions=dirs)


# how far beyond the points' forces a fitted curve may go (in spreads of those forces)
_RANGE_MARGIN = 0.5


def _assess(fit: ModelFit, points: Sequence[MapPoint]) -> ModelFit:
    """What is wrong with the fitted curve as a whole: between the slowest and the fastest point
    it leaves the range of the points' forces (by more than half their spread), or its static
    level lies below its Coulomb level."""
    problems = list(fit.problems)
    slide = [p for p in points if not p.breakaway]
    curve = fit_curve(fit, points)
    if curve is not None and slide:
        s = DIRECTIONS[fit.direction][1]
        if FIT_SPECS[fit.model].needs():  # a curve of the points' pressures or loads: the model at the points
            mag = s * predicted(fit, slide)
        else:
            vv, FF = curve
            speeds = np.abs([p.v for p in slide])
            inside = (np.abs(vv) >= speeds.min()) & (np.abs(vv) <= speeds.max())  # where there are points
            mag = s * FF[inside] if inside.any() else s * FF
        forces = np.abs([p.F for p in points])
        spread = max(float(np.ptp(forces)), 0.1 * float(np.mean(forces)))
        low, high = float(forces.min()) - _RANGE_MARGIN * spread, float(forces.max()) + _RANGE_MARGIN * spread
        if np.any(~np.isfinite(mag)) or mag.min() < low or mag.max() > high:
            problems.append(f"the fitted curve leaves the data's range ({float(np.nanmin(mag)):.3g} to "
                            f"{float(np.nanmax(mag)):.3g} N against points of {forces.min():.3g} to "
                            f"{forces.max():.3g} N)")
    Fs, Fc = fit.params.get("Fs"), fit.params.get("Fc")
    if Fs is not None and Fc is not None and Fs < Fc * (1 - 1e-3):
        problems.append(f"the static level Fs = {Fs:.3g} N lies below the Coulomb level Fc = {Fc:.3g} N")
    return replace(fit, problems=tuple(problems)) if problems != list(fit.problems) else fit


def _fs_from_breakaways(fit: ModelFit, band: StickBand) -> ModelFit:
    """An Fs fixed at the mean breakaway force: its standard error and interval, or a flag."""
    std, ci, flags = dict(fit.std), dict(fit.ci95), list(fit.flags)
    if band.breakaway_count:
        m = band.breakaway_count
        se = band.breakaway_std / math.sqrt(m) if band.breakaway_std is not None else None
        std["Fs"] = se
        if se is not None:
            from scipy.stats import t as student_t

            h = float(student_t.ppf(0.975, m - 1)) * se
            ci["Fs"] = (band.breakaway_mean - h, band.breakaway_mean + h)
            if band.breakaway_std > 0.3 * band.breakaway_mean:
                flags.append({"param": "Fs", "reason": f"the {m} breakaway forces scatter widely (standard "
                                                       f"deviation {band.breakaway_std:.3g} N about "
                                                       f"{band.breakaway_mean:.3g} N): the piston hardly sticks, or "
                                                       f"is driven too fast to show it"})
        else:
            flags.append({"param": "Fs", "reason": "a single breakaway: no spread to judge it by"})
        Fc = fit.params.get("Fc")
        if Fc is not None and band.breakaway_mean < Fc:
            flags.append({"param": "Fs", "reason": f"the breakaway forces (mean {band.breakaway_mean:.3g} N) lie "
                                                   f"below the Coulomb level {Fc:.3g} N: the piston creeps rather "
                                                   f"than sticks"})
    else:
        flags.append({"param": "Fs", "reason": "no breakaway observed (the piston never stuck and then slid); "
                                               "a map of steady speeds cannot show static friction"})
    return replace(fit, std=std, ci95=ci, flags=tuple(flags))
