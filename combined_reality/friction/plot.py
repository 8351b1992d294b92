"""The friction map drawn (matplotlib, imported when it draws): the points with their friction
spread, breakaway rows apart, the stick band and every fitted curve, both directions."""
from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np

from sim.friction_models import DIRECTIONS

from ..files import atomic_write
from .fits import fit_curve, predicted
from .map import FrictionMap
from .specs import FIT_SPECS, FrictionMapError

__all__ = ["plot_map"]


def plot_map(fmap: FrictionMap, path: str | os.PathLike[str], title: str = "") -> None:
    """The map (points with their friction spread, breakaway rows apart) and every fitted curve, both
    directions (a model of the points' pressures or loads as its value at each point); the
    friction axis spans the points (a curve that runs off beyond them is cut)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise FrictionMapError("--plot needs matplotlib, which is not installed (pip install matplotlib).") from None
    fig, ax = plt.subplots(figsize=(9, 6))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    F_all, labelled = [0.0], set()
    for direction, d in fmap.directions.items():
        for static, marker, label in ((False, "o", "points"), (True, "^", "breakaway")):
            pts = [p for p in d.points if p.breakaway == static]
            if not pts:
                continue
            v = np.array([p.v for p in pts])
            F = np.array([p.F for p in pts])
            err = np.array([p.F_std for p in pts])
            F_all.extend((F - np.nan_to_num(err)).tolist() + (F + np.nan_to_num(err)).tolist())
            ax.errorbar(v * 1e3, F, yerr=np.where(np.isfinite(err), err, 0.0), fmt=marker, color="k", ms=4,
                        capsize=2, label=None if label in labelled else label)
            labelled.add(label)
        if d.stick_band.dv is not None:
            s = DIRECTIONS[direction][1]
            ax.axvspan(0, s * d.stick_band.dv * 1e3, color="0.9", zorder=0,
                       label="stick band" if direction == "extension" else None)
        for name, fit in d.fits.items():
            i = list(FIT_SPECS).index(name)  # one colour (and style) per model in both directions
            # the best bold, fits that may not be preferred (parameters not determined, an unsound curve) faint
            style = {"color": colours[i % len(colours)], "label": name if direction == "extension" else None,
                     "alpha": 1.0 if fit.preferable else 0.35, "lw": 2.5 if name == d.best else 1.2}
            if FIT_SPECS[name].needs():
                # the curve depends on the points' pressures or loads: the model at each point, not one line
                pts = [p for p in d.points if not p.breakaway]
                at = predicted(fit, pts)
                ax.plot([p.v * 1e3 for p in pts], at, "x" if i < len(colours) else "+", ms=6, ls="none", **style)
                continue
            curve = fit_curve(fit, d.points)
            if curve is None:
                continue
            vv, FF = curve
            ax.plot(vv * 1e3, FF, ls="-" if i < len(colours) else "--", **style)
    lo, hi = min(F_all), max(F_all)
    ax.set_ylim(lo - 0.15 * (hi - lo), hi + 0.15 * (hi - lo))
    ax.axhline(0, color="0.5", lw=0.5)
    ax.axvline(0, color="0.5", lw=0.5)
    ax.set_xlabel("velocity v [mm/s]")
    ax.set_ylabel("friction F [N]")
    ax.set_title((title or "static friction map") + "\nbold: the best fit; faint: fits not to be preferred")
    ax.legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()  # written atomically, as every output (a failed plot leaves no half file)
    fig.savefig(buf, dpi=120, format=Path(path).suffix.lstrip(".").lower() or "png")
    plt.close(fig)
    atomic_write(path, buf.getvalue())
