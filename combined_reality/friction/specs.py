"""What the friction map offers, as data: the fits it can make (FitSpec, FIT_SPECS), how
segments of a run are recognised (SegmentOptions), the plot formats, and the map's errors.
Free of the numerics, so that the command line can state them without importing the map.
The seed papers the fits come from: seed 000 (Trentini et al., Karnopp friction by least
squares), seed 003 (Romeo et al., static models with load terms), seed 004 (friction of
industrial pneumatic actuators)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

from ..errors import InputError

__all__ = ["FrictionMapError", "PointsFormatError", "TooFewPointsError", "SegmentOptions", "FitSpec", "FIT_SPECS",
           "NOMINAL_LAW", "PARSIMONY", "PLOT_FORMATS", "DYNAMIC_SPECS"]


class FrictionMapError(InputError):
    """A map that cannot be made from the given input; the message is one sentence (exit status 2)."""


class PointsFormatError(FrictionMapError):
    """A points table that cannot be used; the message names file, line and column."""


class TooFewPointsError(FrictionMapError):
    """Fewer points in a direction than a model needs (one more than its free parameters)."""


@dataclass(frozen=True)
class SegmentOptions:
    """How constant-velocity segments and sticking are recognised in a run.

    Velocity trend = the velocity averaged over min_duration. A segment is a stretch of
    at least min_duration in which the trend is at least min_speed, changes by at most
    `spread` of itself over min_duration, has a standard deviation of at most `spread` of
    its mean, and the piston slides throughout (|v| >= stuck speed at every sample).
    Faster fluctuations around the trend (valve dither, control noise) are allowed: the
    point is their mean, and v_std, F_std report them.
    """

    min_duration: float = 0.05  # s
    min_speed: float = 2e-3  # m/s
    spread: float = 0.2  # relative
    stuck_speed: float | None = None  # m/s; default 3 x the velocity noise the position sensor implies
    stuck_duration: float = 0.02  # s: sticking lasts at least this long
    newton_half: int = 15  # half-width (samples) of the Savitzky-Golay derivatives of friction_from_newton

    def __post_init__(self) -> None:
        for name in ("min_duration", "min_speed", "spread", "stuck_duration"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise FrictionMapError(f"{name} must be a positive number, not {value}.")
        if self.stuck_speed is not None and not (math.isfinite(self.stuck_speed) and 0 < self.stuck_speed):
            raise FrictionMapError(f"stuck_speed must be a positive number, not {self.stuck_speed}.")

    def stuck_threshold(self, position_noise: float, dt: float) -> float:
        """Below this speed the piston counts as stuck: the option, or 3 x the noise of the
        Savitzky-Golay velocity (sigma_x / (dt sqrt(sum j^2))), at most half of min_speed."""
        if self.stuck_speed is not None:
            return self.stuck_speed
        half = self.newton_half  # sum of j^2 over -half..half
        noise = position_noise / (dt * math.sqrt(half * (half + 1) * (2 * half + 1) / 3))
        return min(max(3.0 * noise, 1e-5), 0.5 * self.min_speed)


@dataclass(frozen=True)
class FitSpec:
    """A fit of the map: a model family with some base parameters held fixed."""

    name: str
    family: str  # key of sim.friction_models.FRICTION_MODELS
    fixed: Mapping[str, float]
    description: str
    # the operating conditions the points must carry (None: all of the family's); a condition
    # of the family left out is 0 in the curve, and its parameters are held at 0 by `fixed`
    conditions: tuple[str, ...] | None = None

    def needs(self) -> tuple[str, ...]:
        from sim.friction_models import FRICTION_MODELS

        return FRICTION_MODELS[self.family].CONDITIONS if self.conditions is None else self.conditions


FIT_SPECS: dict[str, FitSpec] = {s.name: s for s in (
    FitSpec("cv", "cv", {}, "Coulomb-viscous: Fc + B v (seeds 000, 003)"),
    FitSpec("karnopp", "karnopp", {}, "Karnopp: Fc + B v above the stick band dv, Fs from breakaways"),
    FitSpec("threlfall", "threlfall", {}, "Threlfall: exponential rise to Fc within ve, plus B v"),
    FitSpec("cvs", "cvs", {"delta": 2.0}, "static-Coulomb-Stribeck-viscous, exponent 2 (seed 004 Eq. 3)"),
    FitSpec("cvs_delta", "cvs", {}, "static-Coulomb-Stribeck-viscous with a free exponent"),
    FitSpec("lugre", "lugre", {}, "LuGre static curve (Stribeck, exponent 2); sigma0, sigma1 are dynamic"),
    FitSpec("cv_load", "cv_load", {}, "Coulomb-viscous with normal-load terms (seed 003 Eq. 5)"),
    FitSpec("cvs_load", "cvs_load", {}, "Stribeck with normal-load terms (seed 003 Eq. 8)"),
    FitSpec("belforte", "belforte", {}, "pressure-dependent (Belforte, seed 004 Eq. 2)"),
    FitSpec("belforte_dp", "belforte", {"K3": 0.0}, "Belforte without the counter-pressure term (points with dp only)",
            conditions=("dp",)),
    FitSpec("cv_dp", "cv_dp", {}, "the product's own law per direction: (Fc + kp dp) + Fv v"),
    FitSpec("efficiency", "efficiency", {}, "friction proportional to dp (seed 004 Eq. 1, the efficiency factor)"),
)}

NOMINAL_LAW = "cv_dp"  # the product's own friction law (sim/plant.py), per direction
PARSIMONY = 4.0  # AICc units a parameter more, or another law than the nominal one, must gain to be preferred
PLOT_FORMATS = ("png", "pdf", "svg", "eps", "ps", "jpg", "jpeg", "tif", "tiff", "webp")  # --plot's suffixes
# models whose dynamic identification is offered (the map's "cvs_delta" is cvs with a free exponent)
DYNAMIC_SPECS: tuple[str, ...] = ("cv", "karnopp", "threlfall", "cvs", "cvs_delta", "lugre", "cv_load",
                                  "cvs_load", "belforte", "cv_dp")
