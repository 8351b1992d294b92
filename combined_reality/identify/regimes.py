"""The operating regimes of a run (direction, speed bands, reversals, stroke zones, valve near
centre, high flow, time spans), the share of a validation's position error in each (regions),
and those where it gathers that the fitting runs held too little of (untaught_regions): shared
by the diagnosis (where the gap lies) and calibrate (how far its VALID can be trusted)."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from sim.cylinder import Cylinder

from ..files import Run
from .smoothing import velocity_estimate
from .validation import Validation

__all__ = ["FAILS_CONCENTRATION", "MIN_REGION_FRACTION", "TRUSTED_VALID", "misses_valid", "operating_regions",
           "regions", "untaught_regions"]


def operating_regions(cyl: Cylinder, run: Run) -> dict[str, np.ndarray]:
    """Boolean masks of the operating regimes of a run: direction, speed bands, reversals,
    stroke zones, valve near centre, high flow, time spans."""
    v = velocity_estimate(run.t, run.x)
    L = cyl.geometry.stroke
    moving = np.abs(v) > 0.005
    sgn = np.sign(np.where(moving, v, 0.0))
    nz = np.flatnonzero(sgn)
    rev = np.zeros(run.n, bool)
    if len(nz) > 1:
        flips = nz[1:][sgn[nz[1:]] != sgn[nz[:-1]]]
        w = max(1, int(round(0.02 / run.sample_period)))
        for i in flips:
            rev[max(0, i - w):i + w] = True
    t_rel = (run.t - run.t[0]) / max(run.duration, 1e-12)
    masks = {
        "extension (v > 5 mm/s)": v > 0.005,
        "retraction (v < -5 mm/s)": v < -0.005,
        "near-zero speed (|v| < 5 mm/s)": ~moving,
        "slow (5-50 mm/s)": moving & (np.abs(v) < 0.05),
        "fast (> 50 mm/s)": np.abs(v) >= 0.05,
        "reversals (within 20 ms)": rev,
        "stroke: first third": run.x < L / 3,
        "stroke: middle third": (run.x >= L / 3) & (run.x < 2 * L / 3),
        "stroke: last third": run.x >= 2 * L / 3,
        "valve near centre (|u| < 0.05)": np.abs(run.u) < 0.05,
        "high flow (|u| > 0.5)": np.abs(run.u) > 0.5,
    }
    for q in range(4):
        masks[f"time: quarter {q + 1}"] = (t_rel >= q / 4) & ((t_rel < (q + 1) / 4) if q < 3 else (t_rel <= 1))
    return masks


MIN_REGION_FRACTION = 0.01  # a regime with fewer samples is listed, never singled out


def regions(cyl: Cylinder, run: Run, base: Validation, best: Validation | None = None) -> list[dict]:
    """Where the validation position error lies: share of the squared error per operating
    regime, how over-represented it is (share / fraction of samples), and the position RMSE
    there before and (with the verdict's effect) after; most concentrated first, regimes
    with under MIN_REGION_FRACTION of the samples last."""
    r = base.residual[base.outputs.index("x")]
    ok = np.isfinite(r)
    e2 = np.where(ok, r, 0.0) ** 2
    total = float(e2.sum()) or 1.0
    out = []
    for where, m in operating_regions(cyl, run).items():
        m = m & ok
        frac = float(m.sum()) / max(int(ok.sum()), 1)
        if frac == 0:
            continue
        share = float(e2[m].sum()) / total
        row = {"where": where, "share_of_error": share, "fraction_of_samples": frac,
               "concentration": share / frac, "rmse_x": float(np.sqrt(e2[m].mean()))}
        if best is not None:
            row["rmse_x_after"] = best.rmse("x", m)
        out.append(row)
    # a regime of a handful of samples can look concentrated by chance: those last
    return sorted(out, key=lambda r: (r["fraction_of_samples"] < MIN_REGION_FRACTION, -r["concentration"]))


# a model whose normalized RMS on VALID stays within this (x the sensor noise) matches the rig
# there; beyond it its predictions carry a caveat (misses_valid)
TRUSTED_VALID = 2.0

# a regime holding this many times its share of the samples' squared position error on VALID is
# where the model fails (untaught_regions)
FAILS_CONCENTRATION = 2.0


def untaught_regions(cyl: Cylinder, train: Sequence[Run], valid: Run, val: Validation) -> list[dict]:
    """The operating regimes (not the time spans: TRAIN has its own) where `val`'s position error
    on VALID is concentrated (FAILS_CONCENTRATION, in at least MIN_REGION_FRACTION of the
    samples), each with its share of VALID's samples and of TRAIN's (all its runs): {where,
    concentration, share_of_error, valid_fraction, train_fraction, taught}, most concentrated
    first. `taught` is False where TRAIN holds under half VALID's share of the regime: there the
    fit saw too little of what VALID asks of the model."""
    seen = [operating_regions(cyl, run) for run in train]
    n_train = sum(run.n for run in train)
    out = []
    for row in regions(cyl, valid, val):
        where, frac = row["where"], row["fraction_of_samples"]
        if where.startswith("time:") or frac < MIN_REGION_FRACTION or row["concentration"] < FAILS_CONCENTRATION:
            continue
        trained = sum(int(s[where].sum()) for s in seen) / n_train if n_train else 0.0
        out.append({"where": where, "concentration": row["concentration"], "share_of_error": row["share_of_error"],
                    "valid_fraction": frac, "train_fraction": trained, "taught": bool(trained >= 0.5 * frac)})
    return out  # in regions' order: most concentrated first


def misses_valid(who: str, nrms: float, where: Sequence[dict] | None, within: float = TRUSTED_VALID) -> str:
    """The sentence for a model (`who`: "the calibrated model", ...) that misses VALID by `nrms` x
    the noise, beyond `within`: its predictions are no match, and where its error gathers
    (`where`: untaught_regions; None where not looked for), the regimes TRAIN showed it too
    little of (the runs' fault: a TRAIN that goes there pins it) apart from those TRAIN showed as
    much as VALID (the model lacks something there); or that no regime holds it."""
    def listed(rows: list[dict], with_train: bool) -> str:
        return ", ".join(f"{r['where']} ({r['concentration']:.2g} × its share of the samples"
                         + (f"; VALID spends {r['valid_fraction']:.1%} of its samples there, "
                            f"TRAIN {r['train_fraction']:.1%}" if with_train else "") + ")" for r in rows[:2])

    text = (f"Do not take its predictions for the rig's: {who} still misses VALID by {nrms:.3g} × the sensor noise "
            f"over all outputs (a model that matches stays within {within:g} ×)")
    if where is None:
        return text + "."
    if not where:
        return text + (f"; its position error is spread over the run (no regime holds {FAILS_CONCENTRATION:g} × its "
                       "share of the samples or more): the model is off throughout, not where TRAIN did not go.")
    untaught = [r for r in where if not r["taught"]]
    taught = [r for r in where if r["taught"]]
    if untaught:
        text += (f"; its position error gathers at {listed(untaught, True)}: TRAIN showed the model too little of "
                 "that, so what decides it there is not calibrated (a TRAIN run that goes there more, a longer "
                 "calibration run, would pin it)")
    if taught:
        text += (f"{'; also' if untaught else '; its position error gathers'} at {listed(taught, False)}, which TRAIN "
                 "showed as much as VALID: the model still lacks something there (an effect, or another form of "
                 "one)")
    return text + "."
