"""A candidate effect: its figures (Candidate), its identification starts (neutral from the
nominal optimum, its defaults, its alternatives), what every fit of it starts from and is
compared with (NominalFit), and how a validated candidate is scored against a baseline (shrink,
z, significance, the share of the gap it explains)."""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from sim.cylinder import Cylinder
from sim.effects import EFFECTS, Effect, make_effect

from ..identify import Validation, validation_gain
from .options import DiagnoseOptions


@dataclass
class Candidate:
    effect: str  # a vocabulary word, or "a+b" for a pair
    shrink: float = math.nan
    rmse_x_validation: float = math.nan
    params: dict[str, float] = field(default_factory=dict)
    std: dict[str, float] = field(default_factory=dict)
    score: float = -math.inf
    status: str = "failed"
    shrink_all: float = math.nan
    z: float = math.nan
    significant: bool = False
    friction: dict[str, float] = field(default_factory=dict)
    train_cost: float = math.nan
    iterations: int = 0
    start: int = 0
    wall_s: float = 0.0
    error: str | None = None
    validation: Validation | None = field(default=None, repr=False)
    effects: tuple[Effect, ...] = field(default=(), repr=False)
    nodes: np.ndarray | None = field(default=None, repr=False)  # TRAIN node states of the fit
    cylinder: Cylinder | None = field(default=None, repr=False)  # the fitted model, for its validation
    calibration: dict | None = None  # with DiagnoseOptions.calibrate: how the candidate was calibrated

    @property
    def n_params(self) -> int:
        return len(self.params)

    def to_json(self) -> dict:
        out = {"effect": self.effect, "shrink": self.shrink, "rmse_x_validation": self.rmse_x_validation,
               "params": self.params, "std": self.std, "score": self.score, "significant": self.significant,
               "shrink_all": self.shrink_all, "z": self.z, "status": self.status,
               "friction": self.friction, "iterations": self.iterations, "start": self.start,
               "wall_s": round(self.wall_s, 3)}
        if self.validation is not None:
            out["rmse_p1_validation"] = self.validation.rmse("p1")
            out["rmse_p2_validation"] = self.validation.rmse("p2")
            out["normalized_rms_validation"] = self.validation.normalized_rms()
        if self.error:
            out["error"] = self.error
        if self.calibration is not None:
            out["calibration"] = self.calibration
        return out


NESTED_START = 0  # the start index of "the nominal optimum with the effect at its neutral value"


def neutral_start(name: str) -> Effect:
    """The candidate at its neutral value (the nominal model to rounding; a value below the
    identification range, heat_transfer's h = 0, at that range's bound), shapes at defaults."""
    cls = EFFECTS[name]
    return make_effect(name, {k: min(max(v, cls.PARAMS[k].lower), cls.PARAMS[k].upper)
                              for k, v in cls.NEUTRAL.items()})


def has_nested_start(name: str) -> bool:
    """Whether the candidate's neutral value lies inside its identification range: heat
    exchange's (h = 0) does not, and from the range's bound its fit only creeps."""
    cls = EFFECTS[name]
    return all(cls.PARAMS[k].lower <= v <= cls.PARAMS[k].upper for k, v in cls.NEUTRAL.items())


def candidate_starts(name: str) -> list[Effect]:
    """The identification starts of a candidate: neutral from the nominal optimum (start 0:
    a fit from there can only improve on the nominal model), its defaults from the cylinder
    file (start 1), then its alternatives."""
    cls = EFFECTS[name]
    return [neutral_start(name), make_effect(name)] + [make_effect(name, s) for s in cls.STARTS]


def held_shapes(name: str) -> list[dict[str, float]]:
    """The values of the held shapes (FREED_LAST) of each alternative start that sets them: a
    held shape does not move until the rest has converged, so each of its basins needs starts
    of its own (a rational Stribeck curve is not reached from the exponential one)."""
    cls = EFFECTS[name]
    return [held for s in cls.STARTS if (held := {p: v for p, v in s.items() if p in cls.FREED_LAST})]


def shapes_label(held: dict[str, float]) -> str:
    return ", ".join(f"{p}={v:g}" for p, v in held.items())


@dataclass
class NominalFit:
    """What every candidate fit starts from and is compared with: the cylinder file (the
    friction start of the default and alternative starts comes from the equation-error
    prefit, as for the nominal fit: a nominal fit distorted by a strong effect is a poor
    start), the nominal optimum (friction and node states: the nested start), the nominal
    fit's TRAIN cost and its validation."""

    config: Cylinder
    optimum: Cylinder
    nodes: np.ndarray | None
    train_cost: float
    validation: Validation
    noise_cost: float = math.nan  # the TRAIN cost of a model at the sensor noise
    # the TRAIN cost a fit from here must get under within IdentifyOptions.give_up_after
    # iterations (NaN: the train cost itself, plus min_train_gain of it)
    give_up_above: float = math.nan


def score_candidate(c: Candidate, base: Validation, base_rmse_x: float, opts: DiagnoseOptions) -> None:
    """A validated candidate's figures against the baseline `base` (shrink, z, significance,
    score), in place; one whose simulation of VALID diverges is marked so."""
    if c.validation is None or not c.validation.normalized_rms() < 1e6 * base.normalized_rms():
        if c.validation is not None:
            c.status, c.error = "diverged", ("the re-identified model's simulation of VALID diverges (not finite, "
                                             "or a million times the nominal model's error)")
        return
    c.shrink = 1.0 - c.rmse_x_validation / base_rmse_x
    c.shrink_all, c.z = validation_gain(base, c.validation)
    c.significant = bool(c.z >= opts.min_z and c.shrink_all >= opts.min_shrink)
    c.score = c.shrink_all - opts.penalty_per_param * c.n_params


def explained_share(base: Validation, cand: Validation | None) -> float:
    """The share of the nominal model's excess error variance (above the sensor noise, over all
    outputs) that a candidate removes on VALID: 1 = down to the noise, 0 = nothing."""
    if cand is None:
        return math.nan
    b2, c2 = base.normalized_rms() ** 2, cand.normalized_rms() ** 2
    return (b2 - c2) / (b2 - 1.0) if b2 > 1.0 else math.nan


def gain_over(ref: Validation, cand: Validation | None, opts: DiagnoseOptions) -> bool:
    """Whether `cand` improves VALID significantly over `ref` (min_z and min_shrink)."""
    if cand is None:
        return False
    shrink, z = validation_gain(ref, cand)
    return z >= opts.min_z and shrink >= opts.min_shrink


def closes_gap(c: Candidate, base: Validation, base_rmse_x: float, opts: DiagnoseOptions) -> bool:
    """Whether one fit (of one start) leaves VALID significantly better and near the noise
    (`closed_gap`): then no further start can change the verdict much. Scored on a copy."""
    c = copy.copy(c)
    score_candidate(c, base, base_rmse_x, opts)
    return near_noise(c, opts)


def near_noise(c: Candidate, opts: DiagnoseOptions) -> bool:
    """A scored candidate that is significant and leaves VALID within `closed_gap` x the noise."""
    return bool(c.significant and c.validation.normalized_rms() < opts.closed_gap)


def departure_z(c: Candidate, effects: Sequence[str] | None = None) -> float:
    """How far the candidate's effect lies from the nominal plant: the largest |value - neutral| /
    std over its effects' NEUTRAL parameters (nan where no such parameter has a finite std);
    `effects`: only these of a pair's."""
    zs = []
    for name in effects if effects is not None else c.effect.split("+"):
        for k, neutral in EFFECTS[name].NEUTRAL.items():
            key = k if k in c.params else f"{name}.{k}"
            v, sd = c.params.get(key), c.std.get(key)
            if v is not None and sd is not None and math.isfinite(sd) and sd > 0:
                zs.append(abs(v - neutral) / sd)
    return max(zs, default=math.nan)
