"""Whether the validation residual is white (where the gap lies by operating regime:
identify.regimes.regions)."""
from __future__ import annotations

import numpy as np


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
