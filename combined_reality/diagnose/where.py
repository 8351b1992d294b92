"""Where the gap lies: the share of the validation position error in each operating regime of
the run (identify.regimes), and whether the residual is white."""
from __future__ import annotations

import numpy as np

from sim.cylinder import Cylinder

from ..files import Run
from ..identify import MIN_REGION_FRACTION, Validation, operating_regions


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
