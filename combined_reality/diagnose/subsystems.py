"""Which part of the model carries the gap: the nominal model's equation errors per subsystem
(the piston force balance by the method of the Karnopp/LS friction fit (seed 000), the chamber
pressures), the split of the validation error among the force balance and the chambers, and
the correlations of the equation errors with regressors the candidates' physics would add."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from sim.compiled import plant_columns
from sim.cylinder import Cylinder

from ..files import Run
from ..identify import (IdentificationError, IdentifyOptions, Validation, derivative_kernels, equation_error_friction,
                        friction_from_newton, identify, savgol_kernels, validate)
from .options import DiagnoseOptions


def _rmse(r: np.ndarray) -> float:
    r = r[np.isfinite(r)]
    return float(np.sqrt(np.mean(r * r))) if r.size else math.nan


def equation_errors(nominal: Cylinder, run: Run, half: int = 15) -> dict[str, np.ndarray]:
    """Equation errors of the nominal model at the measured signals (seed 000's method), each
    subsystem on its own:

    force  friction implied by Newton's law with the measured pressures minus the nominal
           friction law refitted to it by linear least squares (so a dynamic fit distorted
           by an unmodelled pneumatic effect does not blame the friction law) (N);
    p1, p2 the measured pressure derivatives minus the nominal chamber equations (valve and
           chambers) evaluated at the smoothed measured state and the command (Pa/s).
    Derivatives and smoothing are Savitzky-Golay over +-`half` samples; the model's chamber
    rates, which follow the command sample by sample, are smoothed by the same filter."""
    from sim.plant import plant_for


    idx, v, F = friction_from_newton(nominal, run, half)
    if len(idx) == 0:
        return {}
    fitted = equation_error_friction(nominal, [run], half)
    fr = nominal.with_values(fitted).friction if fitted else nominal.friction
    dp = np.abs(run.p1[idx] - run.p2[idx])
    eF = F - ((fr.Fc + fr.kp * dp) * np.tanh(v / fr.v_smooth) + fr.Fv * v)
    k0, k1, _ = savgol_kernels(half)
    full = {n: np.convolve(getattr(run, n), k0, mode="same") for n in ("x", "p1", "p2")}
    v_full = np.convolve(run.x, k1, mode="same") / run.sample_period
    dt = run.sample_period
    plant = plant_for(nominal, "command")
    p = np.array(plant.parameter_vector(nominal))
    # the command changes every sample: smooth the model's rates with the same filter as the
    # measured derivative, so both see the same bandwidth
    states = np.vstack([full["p1"], full["p2"], full["x"], v_full])
    rhs_full = plant_columns(plant)(states, run.u[None, :], p)
    rhs = np.vstack([np.convolve(rhs_full[i], k0, mode="same")[idx] for i in range(2)])
    out = {"index": idx, "v": v, "force": eF}
    for i, name in enumerate(("p1", "p2")):
        out[name] = np.convolve(getattr(run, name), k1, mode="same")[idx] / dt - rhs[i]  # (idx: whole windows)
    return out


def subsystem_split(cyl: Cylinder, nominal: Cylinder, train: Run, valid: Run, base_val: Validation,
                    opts: DiagnoseOptions, segments, seed: int = 0) -> list[dict]:
    """Which part of the model carries the gap.

    - the piston force balance (friction, mass) alone: the pressure drive, driven by the
      MEASURED pressures, identified on TRAIN and scored on VALID like the whole model. Its
      floor is not the sensor noise (the noisy measured pressures drive it), so the same
      score on the nominal model's own simulation of VALID with sensor noise added (a
      parametric bootstrap) gives it;
    - the chamber pressures (valve and chambers) in the whole model's validation, with the
      valve near centre (chambers: leakage, heat; a valve that should be shut) and open
      (valve characteristic, timing, supply); their floor is the pressure sensor noise.
    `excess` is (rmse / floor)^2 - 1, the error variance above the floor in units of it;
    `share_of_error` divides the summed excess among the parts."""
    rows = []
    label = "piston force balance (friction, mass), driven by the measured pressures"
    try:
        # one thread: diagnose runs it in a process beside the candidate fits
        mech = identify(cyl, [train], IdentifyOptions(drive="pressure", threads=1, restart_misfit=False))
        mval = validate(mech.cylinder, (), valid, opts.horizon_s, drive="pressure", segments=segments)
        rng = np.random.default_rng(seed)
        sen, sim = cyl.sensors, base_val.simulated
        fake = replace(valid, x=sim[0] + rng.normal(0, sen.position_noise, valid.n),
                       p1=sim[1] + rng.normal(0, sen.pressure_noise, valid.n),
                       p2=sim[2] + rng.normal(0, sen.pressure_noise, valid.n))
        floor = validate(nominal, (), fake, opts.horizon_s, drive="pressure", segments=segments).rmse("x")
        rows.append({"subsystem": label, "output": "x", "rmse": mval.rmse("x"), "floor": floor, "unit": "m",
                     "fraction_of_samples": 1.0})
    except IdentificationError as e:
        rows.append({"subsystem": label, "error": str(e)})
    centre = np.abs(valid.u) < 0.05
    for label, m in (("chamber pressures, valve near centre (chambers, leakage, heat)", centre),
                     ("chamber pressures, valve open (valve characteristic, timing, supply)", ~centre)):
        if m.any():
            r = np.concatenate([base_val.residual[base_val.outputs.index(o)][m] for o in ("p1", "p2")])
            rows.append({"subsystem": label, "output": "p1, p2", "rmse": _rmse(r),
                         "floor": float(cyl.sensors.pressure_noise), "unit": "Pa",
                         "fraction_of_samples": float(m.mean())})
    for r in rows:
        ok = "rmse" in r and math.isfinite(r["rmse"]) and r["floor"] > 0
        r["excess"] = max(0.0, (r["rmse"] / r["floor"]) ** 2 - 1) if ok else 0.0
        r["within_noise"] = bool(r["excess"] < 0.1)
    total = sum(r["excess"] for r in rows)
    for r in rows:
        r["share_of_error"] = r["excess"] / total if total > 0 else 0.0
    return rows


# regressors that each candidate's physics would add to the force or pressure equations
_REGRESSOR_EFFECTS = {
    "stribeck (sign(v) exp(-(v/10 mm/s)^2))": "stiction",
    "direction (sign(v))": "friction_asymmetry",
    "position along the stroke": "friction_position",
    "pressure difference (p1 - p2)": "leakage",
    "command rate (du/dt)": "valve_delay",
    "valve near centre (u, |u| < 0.1)": "valve_deadzone",
    "supply draw (|u| ps)": "supply_droop",
}


def regressor_correlations(nominal: Cylinder, run: Run) -> list[dict]:
    """Fast screen: correlation of the nominal model's equation errors (equation_errors, with
    the friction refitted by equation error on this run so that a distorted dynamic fit
    does not leak into the force error) with regressors the candidates' physics would add.
    Reported, never deciding. There is no regressor for `mass` or the effects with their own
    states: the acceleration correlates with the force error on clean runs too (the derivative
    filter's lag), so it hints at nothing."""
    ee = equation_errors(nominal, run)
    if not ee or len(ee["index"]) < 100:
        return []
    idx, v = ee["index"], ee["v"]
    half = 15
    k1, _ = derivative_kernels(half)
    dt = run.sample_period
    g = nominal.geometry
    V1 = g.dead_volume_cap + g.area_cap * run.x[idx]
    V2 = g.dead_volume_rod + g.area_rod * (g.stroke - run.x[idx])
    # chamber errors as volume-weighted rates (mass flow equivalents), net into chamber 1
    e12 = ee["p1"] * V1 - ee["p2"] * V2
    u = run.u[idx]
    du = np.convolve(run.u, k1, mode="same")[idx] / dt
    moving = np.abs(v) > 0.005
    xi = run.x[idx] / g.stroke
    eF = ee["force"]
    regs = {
        "stribeck (sign(v) exp(-(v/10 mm/s)^2))": (eF, np.sign(v) * np.exp(-(v / 0.01) ** 2)),
        "direction (sign(v))": (eF, np.sign(v) * moving),
        "position along the stroke": (eF, np.sign(v) * (xi - 0.5) * moving),
        "pressure difference (p1 - p2)": (e12, -(run.p1[idx] - run.p2[idx])),
        "command rate (du/dt)": (e12, -du),
        "valve near centre (u, |u| < 0.1)": (e12, -u * (np.abs(u) < 0.1)),
        "supply draw (|u| ps)": (ee["p1"] * V1 + ee["p2"] * V2, -np.abs(u)),
    }
    out = []
    step = max(1, int(round(0.005 / dt)))  # decimate: neighbouring samples share the filter
    for name, (e, r_) in regs.items():
        e, r_ = e[::step], r_[::step]
        ok = np.isfinite(e) & np.isfinite(r_)
        e, r_ = e[ok] - e[ok].mean(), r_[ok] - r_[ok].mean()
        den = math.sqrt(float(e @ e) * float(r_ @ r_))
        r = float(e @ r_) / den if den > 0 else 0.0
        out.append({"regressor": name, "hints": _REGRESSOR_EFFECTS[name], "r": r, "n": int(len(e))})
    return sorted(out, key=lambda d: -abs(d["r"]))
