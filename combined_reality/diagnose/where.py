"""Where the gap lies: the operating regimes of a run (direction, speed bands, reversals,
stroke zones, valve near centre, high flow, time spans), the share of the validation position
error in each, and whether the residual is white."""
from __future__ import annotations

import numpy as np

from sim.cylinder import Cylinder

from ..files import Run
from ..identify import Validation, velocity_estimate


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


# a regime holding this many times its share of the samples' squared position error on VALID is
# where the model fails (untaught_regions)
FAILS_CONCENTRATION = 2.0


def untaught_regions(cyl: Cylinder, train: Run, valid: Run, val: Validation) -> list[dict]:
    """The operating regimes (not the time spans: TRAIN has its own) where `val`'s position error
    on VALID is concentrated (FAILS_CONCENTRATION, in at least MIN_REGION_FRACTION of the
    samples), each with its share of VALID's samples and of TRAIN's: {where, concentration,
    share_of_error, valid_fraction, train_fraction, taught}, most concentrated first. `taught` is
    False where TRAIN holds under half VALID's share of the regime: there the calibration saw too
    little of what VALID asks of the model."""
    r = val.residual[val.outputs.index("x")]
    ok = np.isfinite(r)
    e2 = np.where(ok, r, 0.0) ** 2
    total = float(e2.sum())
    if total <= 0:
        return []
    seen = operating_regions(cyl, train)
    out = []
    for where, m in operating_regions(cyl, valid).items():
        if where.startswith("time:"):
            continue
        m = m & ok
        frac = float(m.sum()) / max(int(ok.sum()), 1)
        if frac < MIN_REGION_FRACTION:
            continue
        share = float(e2[m].sum()) / total
        if share / frac < FAILS_CONCENTRATION:
            continue
        trained = float(seen[where].mean()) if train.n else 0.0
        out.append({"where": where, "concentration": share / frac, "share_of_error": share, "valid_fraction": frac,
                    "train_fraction": trained, "taught": bool(trained >= 0.5 * frac)})
    return sorted(out, key=lambda row: -row["concentration"])


def whiteness(resid: np.ndarray, lags: int = 20, decimate: int = 10) -> dict:
    """Ljung-Box statistic of a residual (decimated, to 10 ms at 1 kHz, where sensor noise no
    longer dominates) and its first autocorrelation; `white` at the 0.1 % level."""
    from scipy.special import chdtrc  # chi2's survival function, without scipy.stats's 0.6 s import

    r = resid[np.isfinite(resid)][::decimate]
    r = r - r.mean()
    n = len(r)
    den = float(r @ r) or 1.0
    acf = np.array([float(r[:-k] @ r[k:]) / den for k in range(1, min(lags, n - 1) + 1)])
    q = n * (n + 2) * float(np.sum(acf ** 2 / (n - np.arange(1, len(acf) + 1))))
    p = float(chdtrc(len(acf), q)) if len(acf) else 1.0
    return {"ljung_box_q": q, "lags": len(acf), "p_value": p, "acf_1": float(acf[0]) if len(acf) else 0.0,
            "white": bool(p > 1e-3)}
