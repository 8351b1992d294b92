"""The human report of a diagnosis: one self-contained HTML file (inline CSS, plots as
embedded PNG), written for an engineer, not a statistician.

    write_report(diagnosis, "diagnosis.html", png_dir="plots/")

Contents: the verdict in one sentence, the inputs, the ranking of the candidate effects
(and the best pair), plots of the validation error (over time, against velocity and
position, measured vs simulated traces, where the error lies, which subsystem carries
it), and the whiteness test and regressor screen as small tables with a line each on how
to read them. Units for people: um for position errors, mm for positions along the
stroke, kPa for pressures, mm/s for velocities; the Diagnosis itself stays in SI.

The text helpers (`headline`, `format_value` and the small formatters) are shared with the
Rerun logging (`diagnose_rerun`); matplotlib is imported only when plots are drawn.
"""
from __future__ import annotations

import base64
import html
import io
import math
from pathlib import Path
from typing import Callable

import numpy as np

from sim.cylinder import PARAMETERS

from .diagnose import MIN_REGION_FRACTION
from .identify import at_bounds

__all__ = ["write_report", "render_report", "headline", "format_value"]

_SCATTER_MAX = 4000  # points per series in the scatter plots
_LINE_MAX = 8000  # points per line in the whole-run trace plots
_WITHIN_NOISE = 1.2  # all-output RMS in noise units below which the nominal model "fits"

# colours: measured, nominal model, model with the verdict's effect
_C_MEAS, _C_NOM, _C_EFF = "#222222", "#1f77b4", "#e8590c"


# ------------------------------------------------------------------ numbers for people

def _finite(v) -> bool:
    try:
        return v is not None and math.isfinite(float(v))
    except (TypeError, ValueError):
        return False


def _sig(v: float, digits: int = 3) -> str:
    """A number to `digits` significant digits, without exponent for ordinary magnitudes."""
    if not _finite(v):
        return "n/a"
    v = float(v)
    if v == 0:
        return "0"
    mag = math.floor(math.log10(abs(v)))
    if mag < -3 or mag >= 6:
        return f"{v:.{digits - 1}e}"
    return f"{v:.{max(0, digits - 1 - mag)}f}"


def _um(m: float) -> str:
    return f"{_sig(float(m) * 1e6)} um" if _finite(m) else "n/a"


def _pct(s: float) -> str:
    if not _finite(s):
        return "n/a"
    s = 100.0 * float(s)
    return f"{s:.1f} %" if 99 <= abs(s) < 100 or abs(s) < 1 else f"{s:.0f} %"


# the parameters' SI units, shown in the unit an engineer reads them in
_DISPLAY_UNITS: dict[str, tuple[str, float]] = {
    "N/Pa": ("N/bar", 1e5),
    "m/s": ("mm/s", 1e3),
    "m^3/(s Pa)": ("m³/(s·Pa)", 1.0),
    "W/(m^2 K)": ("W/(m²·K)", 1.0),
    "1": ("", 1.0),
}


def _display_unit(unit: str, value: float) -> tuple[str, float]:
    if unit == "s":
        return ("ms", 1e3) if abs(value) < 1 else ("s", 1.0)
    if unit == "m":
        return ("um", 1e6) if abs(value) < 1e-3 else ("mm", 1e3)
    if unit.startswith("1 "):  # "1 (of L)" and the like
        return unit[2:], 1.0
    return _DISPLAY_UNITS.get(unit, (unit, 1.0))


def _param_info(effect: str, name: str):
    """ParamInfo of `name` (a parameter of `effect`, or `effect.param` for a pair) or None."""
    from sim.effects import EFFECTS

    if "." in name:
        effect, name = name.split(".", 1)
    cls = EFFECTS.get(effect)
    return cls.PARAMS.get(name) if cls is not None else None


def format_value(value: float, std: float | None, unit: str) -> str:
    """`1.41580 ms ± 0.00032 ms`: the value to the precision its standard deviation (2
    significant digits) supports, at least 3 and at most 6 significant digits, in a unit
    for people."""
    if not _finite(value):
        return "n/a"
    value = float(value)
    u, k = _display_unit(unit, value)
    v = value * k
    s = float(std) * k if _finite(std) and float(std) > 0 else None
    sfx = f" {u}" if u else ""
    if v == 0:
        return f"0{sfx}" + (f" ± {_sig(s, 2)}{sfx}" if s is not None else "")
    mag = math.floor(math.log10(abs(v)))
    if mag < -3 or mag >= 6:
        vs = f"{v:.{3 if s is None else min(5, max(2, mag - math.floor(math.log10(s)) + 1))}e}"
        return vs + sfx + (f" ± {s:.1e}{sfx}" if s is not None else "")
    if s is None:
        return f"{v:.{max(0, 3 - mag)}f}{sfx}"
    ms = math.floor(math.log10(s))
    if ms >= 6 or ms < mag - 5:
        # the std of an undetermined (1e26) or a degenerate (1e-34) fit: no 26-digit integer, no 35
        # decimals; the value to 3 significant digits, or to the 6 it is at most given with
        return f"{v:.{max(0, (2 if ms >= 6 else 5) - mag)}f}{sfx} ± {s:.1e}{sfx}"
    ds = max(0, 1 - ms)
    dv = min(max(max(0, 2 - mag), ds), max(0, 5 - mag))
    return f"{v:.{dv}f}{sfx} ± {s:.{ds}f}{sfx}"


def _at_bound(v: float, info) -> bool:
    if info is None or not _finite(v):
        return False
    return bool(at_bounds(v, info.lower, info.upper))


def _params_text(c, sep: str = ", ", bounds: bool = False) -> str:
    """`tau = 1.416 ms ± 0.0003 ms, share = ...`; with `bounds`, a parameter the fit left at
    a bound of its range is marked (its std then means little)."""
    parts = []
    for n, v in (c.params or {}).items():
        info = _param_info(c.effect, n)
        std = (c.std or {}).get(n)
        if info is not None and _finite(std) and std > info.upper - info.lower:
            # a std wider than the whole range says the data do not determine the parameter
            txt = f"{n} = {format_value(v, None, info.unit)} (not determined by the data)"
        else:
            txt = f"{n} = {format_value(v, std, info.unit if info else '')}"
        if bounds and _at_bound(v, info):
            txt += " (at its bound)"
        parts.append(txt)
    return sep.join(parts)


def _friction_text(fr: dict, std: dict | None = None) -> str:
    return ", ".join(f"{n} = {format_value(fr[n], (std or {}).get(n), PARAMETERS[n].unit)}"
                     + (" (at its bound 0)" if fr[n] == 0 else "") for n in ("Fc", "Fv", "kp") if n in fr)


def _effect_description(name: str) -> str:
    from sim.effects import EFFECTS

    if "+" in name:
        return " and ".join(_effect_description(n) for n in name.split("+"))
    cls = EFFECTS.get(name)
    return cls.description if cls is not None else ""


# ------------------------------------------------------------------ the verdict in words

def headline(d, strong: Callable[[str], str] = lambda s: s, esc: Callable[[str], str] = lambda s: s) -> list[str]:
    """The verdict in plain sentences (the first one is the headline). `strong` marks the
    effect word (HTML <b>, markdown **), `esc` escapes the rest."""
    b = d.baseline
    noise_x = b["noise"]["x"]
    before = b.get("rmse_x_validation", math.nan)
    nrms = b.get("normalized_rms", math.nan)
    best = d.best
    out = []
    if best is not None:
        after = best.rmse_x_validation
        params = _params_text(best)
        out.append(esc("The gap is best explained by ") + strong(best.effect)
                   + esc(f" ({_effect_description(best.effect)}): with it, the validation position error shrinks by "
                         f"{_pct(best.shrink)} ({_um(before)} → {_um(after)})" + (f"; {params}." if params else ".")))
        meaning = [f"{n} is the {info.description}" for n in best.params if (info := _param_info(best.effect, n))]
        if meaning:  # a_coulomb or share mean nothing to a reader without it
            out.append(esc("Its parameters: " + "; ".join(meaning) + "."))
        rest = best.validation.normalized_rms()  # the verdict is significant, hence validated
        if rest < _WITHIN_NOISE:
            out.append(esc(f"What remains is at the sensor noise ({_sig(rest)} × the noise over all outputs; "
                           f"it was {_sig(nrms)} ×)."))
        else:
            out.append(esc(f"Part of the gap remains: {_sig(rest)} × the sensor noise over all outputs "
                           f"(it was {_sig(nrms)} ×; 1 would be a perfect model)."))
        others = [c.effect for c in d.ranking if c.significant and c.effect != best.effect]
        if others:
            out.append(esc("Other candidates that also help significantly (usually by imitating part of the same "
                           "error): " + ", ".join(others) + "."))
        p = d.pair
        if p is not None:
            if p.significant:
                out.append(esc("Together with the runner-up, ") + strong(p.effect)
                           + esc(f" shrinks the position error by {_pct(p.shrink)} (to {_um(p.rmse_x_validation)}), "
                                 "significantly better than the verdict alone: both effects are likely present."))
            elif p.status == "failed":
                out.append(esc("The pair ") + strong(p.effect) + esc(" could not be fitted."))
            elif not _finite(p.shrink):  # screened out on TRAIN, or its simulation of VALID diverged
                out.append(esc("The pair ") + strong(p.effect)
                           + esc(f" was not scored on VALID: {p.error or p.status}."))
            else:
                out.append(esc("The pair ") + strong(p.effect) + esc(
                    " is not significantly better than the verdict alone "
                    f"(position error {_um(p.rmse_x_validation)})."))
        return out
    tried = [c.effect for c in d.ranking]
    if _finite(nrms) and nrms < _WITHIN_NOISE:
        out.append(esc(f"The nominal model already fits VALID to within the sensor noise (position error {_um(before)}"
                       f" with {_um(noise_x)} sensor noise; all outputs {_sig(nrms)} × the noise): ") + strong("none")
                   + esc(" of the candidate effects improves it significantly."))
    else:
        out.append(esc(f"No candidate effect explains the gap: the nominal model misses VALID by {_um(before)} in "
                       f"position ({_sig(nrms)} × the sensor noise over all outputs), and none of the "
                       f"{len(tried)} candidates tried removes a significant part of it (verdict ") + strong("none")
                   + esc("). See where the error lies below, and consider effects that were not tried."))
    if tried:
        out.append(esc("Candidates tried: " + ", ".join(tried) + "."))
    screened = [c.effect for c in d.ranking if c.status == "no_gain_on_train"]
    if screened and screened == tried:
        out.append(esc("None of them fits TRAIN better than the nominal model, so none was validated (the fast "
                       "screen)."))
    elif screened:
        out.append(esc("Not validated, as they fit TRAIN no better than the nominal model (the fast screen): "
                       + ", ".join(screened) + "."))
    return out


# ------------------------------------------------------------------ plots

def _new_figure(w: float, h: float):
    from matplotlib.figure import Figure

    return Figure(figsize=(w, h), dpi=100, layout="constrained")


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return buf.getvalue()


def _stride(n: int, cap: int) -> int:
    return max(1, int(math.ceil(n / cap)))


def _mark_segments(ax, t, segments, t0: float, tmin: float | None = None, tmax: float | None = None) -> None:
    for a, _b in segments[1:]:
        ts = t[a] - t0
        if (tmin is None or ts >= tmin) and (tmax is None or ts <= tmax):
            ax.axvline(ts, color="#999999", lw=0.6, ls=":", zorder=0)


def _x_index(val) -> int:
    return list(val.outputs).index("x")


def _plot_residual_time(d, bestval):
    base = d.base_validation
    t = d.valid.t - d.valid.t[0]
    ix = _x_index(base)
    noise = float(base.noise[ix]) * 1e6
    two = bestval is not None
    fig = _new_figure(10, 5.6 if two else 3.4)
    axes = fig.subplots(2 if two else 1, 1, sharex=True, squeeze=False)[:, 0]
    ax = axes[0]
    ax.axhspan(-2 * noise, 2 * noise, color="#dddddd", zorder=0, label=_band_label(noise))
    ax.plot(t, base.residual[ix] * 1e6, color=_C_NOM, lw=0.8,
            label=f"nominal model (RMSE {_um(base.rmse('x'))})")
    if two:
        ax.plot(t, bestval.residual[_x_index(bestval)] * 1e6, color=_C_EFF, lw=0.8,
                label=f"with {d.verdict} (RMSE {_um(bestval.rmse('x'))})")
    ax.set_title("Position error over time on VALID (each segment simulated from its own start)", fontsize=10)
    ax.legend(loc="upper right", fontsize=8, framealpha=0.9)
    ax.set_ylabel("position error (um)\nmeasured − simulated")
    if two:
        ax2 = axes[1]
        ax2.axhspan(-2 * noise, 2 * noise, color="#dddddd", zorder=0, label=_band_label(noise))
        ax2.plot(t, bestval.residual[_x_index(bestval)] * 1e6, color=_C_EFF, lw=0.6,
                 label=f"with {d.verdict} (RMSE {_um(bestval.rmse('x'))})")
        ax2.set_ylabel(f"with {d.verdict} only:\nposition error (um)")
        ax2.legend(loc="upper right", fontsize=8, framealpha=0.9)
        ax2.set_title(f"The error left with {d.verdict}, at its own scale", fontsize=9)
    for a in axes:
        _mark_segments(a, d.valid.t, base.segments, d.valid.t[0])
        a.axhline(0, color="#555555", lw=0.5)
        a.grid(alpha=0.3)
    axes[-1].set_xlabel("time on VALID (s); dotted lines: starts of the validation segments")
    axes[-1].set_xlim(t[0], t[-1])
    return fig


def _band_label(noise_um: float) -> str:
    return f"± 2 × sensor noise ({_sig(noise_um, 2)} um): pure noise stays inside 95 % of the time"


def _scatter(ax, xvals, val, color, label, band: bool = False) -> None:
    r = val.residual[_x_index(val)]
    idx = np.flatnonzero(np.isfinite(r) & np.isfinite(xvals))
    idx = idx[::_stride(len(idx), _SCATTER_MAX)]
    ax.scatter(xvals[idx], r[idx] * 1e6, s=3, color=color, alpha=0.5, lw=0, rasterized=True,
               label=f"{label} (RMSE {_um(val.rmse('x'))})")
    noise = float(val.noise[_x_index(val)]) * 1e6
    ax.axhspan(-2 * noise, 2 * noise, color="#dddddd", zorder=0,
               label="± 2 × sensor noise" if band else None)
    ax.axhline(0, color="#555555", lw=0.5)
    ax.grid(alpha=0.3)
    leg = ax.legend(loc="upper right", fontsize=8, markerscale=4, framealpha=0.9, handletextpad=0.2)
    for h in leg.legend_handles:
        h.set_alpha(1)


def _plot_scatter(d, bestval, xvals, xlabel, title, xlim=None):
    two = bestval is not None
    fig = _new_figure(5, 5.6 if two else 3.4)
    axes = fig.subplots(2 if two else 1, 1, sharex=True, squeeze=False)[:, 0]
    _scatter(axes[0], xvals, d.base_validation, _C_NOM, "nominal model", band=not two)
    axes[0].set_ylabel("position error (um)")
    axes[0].set_title(title, fontsize=10)
    if two:
        _scatter(axes[1], xvals, bestval, _C_EFF, f"with {d.verdict}", band=True)
        axes[1].set_ylabel(f"with {d.verdict}, own scale:\nposition error (um)")
    axes[-1].set_xlabel(xlabel)
    if xlim is not None:
        axes[-1].set_xlim(*xlim)
    return fig


def _plot_residual_vs_velocity(d, bestval):
    return _plot_scatter(d, bestval, np.asarray(d.velocity) * 1e3, "velocity (mm/s)", "Position error against velocity")


def _plot_residual_vs_position(d, bestval):
    L = d.cylinder.geometry.stroke * 1e3
    return _plot_scatter(d, bestval, d.valid.x * 1e3, "piston position along the stroke (mm)",
                         "Position error against position", (-0.02 * L, 1.02 * L))


def _plot_traces(d, bestval):
    base = d.base_validation
    run = d.valid
    t = run.t - run.t[0]
    # the nominal model's worst segment by its validation cost (all outputs, noise-weighted)
    seg = base.segments[int(np.argmax(base.segment_cost))] if base.segments else None
    rows = [("x", "position (mm)", 1e3), ("p1", "p1, cap side\n(kPa abs)", 1e-3),
            ("p2", "p2, rod side\n(kPa abs)", 1e-3)]
    rows = [r for r in rows if r[0] in base.outputs]
    fig = _new_figure(11, 7.8)
    axes = fig.subplots(len(rows) + 1, 2, sharex="col", height_ratios=[1.3, 1, 1, 0.8])
    step = _stride(run.n, _LINE_MAX)
    whole = slice(None, None, step)
    if seg is not None:
        a, b = seg
        pad = max(1, (b - a) // 20)
        zoom = slice(max(0, a - pad), min(run.n, b + pad))
    else:
        zoom = slice(None)
    for col, (sl, title) in enumerate(((whole, "whole VALID run"),
                                       (zoom, "zoom: the nominal model's worst segment"
                                        + (f", {t[seg[0]]:.2f} to {t[seg[1] - 1]:.2f} s" if seg else "")))):
        for row, (name, label, k) in enumerate(rows):
            ax = axes[row, col]
            ax.plot(t[sl], getattr(run, name)[sl] * k, color=_C_MEAS, lw=1.6 if col else 1.0, label="measured")
            io_ = list(base.outputs).index(name)
            ax.plot(t[sl], base.simulated[io_][sl] * k, color=_C_NOM, lw=0.9, label="nominal model")
            if bestval is not None and name in bestval.outputs:
                ax.plot(t[sl], bestval.simulated[list(bestval.outputs).index(name)][sl] * k, color=_C_EFF, lw=0.9,
                        ls="--", label=f"with {d.verdict}")
            if col == 0:
                ax.set_ylabel(label)
            ax.grid(alpha=0.3)
            if row == 0:
                ax.set_title(title, fontsize=10)
        # the position error under the traces: at the scale of the stroke it is invisible
        ax = axes[len(rows), col]
        ix = _x_index(base)
        ax.plot(t[sl], base.residual[ix][sl] * 1e6, color=_C_NOM, lw=0.9)
        if bestval is not None:
            ax.plot(t[sl], bestval.residual[_x_index(bestval)][sl] * 1e6, color=_C_EFF, lw=0.9)
        ax.axhline(0, color="#555555", lw=0.5)
        ax.grid(alpha=0.3)
        if col == 0:
            ax.set_ylabel("position error\n(um)")
        ax.set_xlabel("time on VALID (s)")
        lo, hi = t[sl][0], t[sl][-1]
        for r in range(len(rows) + 1):
            _mark_segments(axes[r, col], run.t, base.segments, run.t[0], lo, hi)
        ax.set_xlim(lo, hi)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside upper center", ncol=3, fontsize=9, frameon=False)
    return fig


def _bar_figure(n: int, row_height: float, extra: float, empty: str):
    """A figure of one horizontal bar axes for `n` rows; with none, it says `empty`."""
    fig = _new_figure(10, row_height * max(n, 1) + extra)
    ax = fig.add_subplot()
    if not n:
        ax.text(0.5, 0.5, empty, ha="center", va="center", transform=ax.transAxes)
        ax.set_axis_off()
    return fig, ax


def _plot_regions(d, has_after: bool):
    regs = list(d.regions or [])
    fig, ax = _bar_figure(len(regs), 0.36, 1.4, "no regions")
    if not regs:
        return fig
    y = np.arange(len(regs))[::-1]
    share = np.array([r.get("share_of_error", math.nan) for r in regs]) * 100
    frac = np.array([r.get("fraction_of_samples", math.nan) for r in regs]) * 100
    h = 0.38
    ax.barh(y + h / 2, share, height=h, color="#c92a2a", label="share of the squared position error (%)")
    ax.barh(y - h / 2, frac, height=h, color="#adb5bd", label="share of the samples (%)")
    ax.set_yticks(y, [r.get("where", "?") for r in regs], fontsize=8.5)
    top = float(np.nanmax(np.concatenate([share, frac])))
    ax.set_xlim(0, top * 1.55 + 1)
    for yi, r, s, f in zip(y, regs, share, frac):
        c = r.get("concentration", math.nan)
        txt = f"×{c:.2f}" if _finite(c) else "×?"
        txt += f"   RMSE {_um(r.get('rmse_x', math.nan))}"
        if has_after and "rmse_x_after" in r:
            txt += f" → {_um(r['rmse_x_after'])}"
        ax.text(max(s, f) + top * 0.02, yi, txt, va="center", fontsize=8)
    ax.set_xlabel("% (regions overlap: each group — direction, speed, stroke, valve, time — adds up to 100 %)")
    # below the axes: inside, it hid the figures of whichever row ran under it
    fig.legend(*ax.get_legend_handles_labels(), loc="outside lower center", ncol=2, fontsize=8, frameon=False)
    ax.set_title("Where the nominal model's position error lies, most concentrated first\n"
                 "(× = share of error / share of samples; RMSE there: "
                 + (f"nominal → with {d.verdict})" if has_after else "nominal model)"), fontsize=9.5)
    ax.grid(axis="x", alpha=0.3)
    ax.set_ylim(-0.7, len(regs) - 0.3)
    return fig


def _subsystem_value(r: dict) -> tuple[str, str]:
    unit = r.get("unit", "")
    if unit == "m":
        return _um(r.get("rmse")), _um(r.get("floor"))
    if unit == "Pa":
        f = lambda v: f"{_sig(float(v) / 1e3)} kPa" if _finite(v) else "n/a"  # noqa: E731
        return f(r.get("rmse")), f(r.get("floor"))
    return f"{_sig(r.get('rmse'))} {unit}", f"{_sig(r.get('floor'))} {unit}"


def _plot_subsystems(d):
    rows = list(d.subsystems or [])
    fig, ax = _bar_figure(len(rows), 0.75, 1.3, "no subsystem split")
    if not rows:
        return fig
    y = np.arange(len(rows))[::-1]
    ratio = np.array([r["rmse"] / r["floor"] if _finite(r.get("rmse")) and _finite(r.get("floor")) and r["floor"] > 0
                      else math.nan for r in rows])
    colors = ["#2b8a3e" if r.get("within_noise") else ("#f08c00" if np.isfinite(q) and q < 1.5 else "#c92a2a")
              for r, q in zip(rows, ratio)]
    ax.barh(y, np.nan_to_num(ratio, nan=0.0), height=0.45, color=colors)
    ax.axvline(1, color="#222222", lw=1, ls="--")
    finite = ratio[np.isfinite(ratio) & (ratio > 0)]
    hi = max(float(finite.max()) if finite.size else 1.0, 1.5)
    log = hi > 20
    if log:
        ax.set_xscale("log")
        ax.set_xlim(min(0.5, 0.5 * float(finite.min())), hi * 2)
    else:
        ax.set_xlim(0, hi * 1.15)
    ax.text(1, -0.55, " noise floor", fontsize=8, va="bottom")
    # each bar's figures above it, from the left edge: at the bar's end they ran out of the axes
    # (a large ratio) or over the labels (a ratio below the axis start)
    above = ax.get_yaxis_transform()  # x in axes fractions, y in data
    labels = []
    for yi, r in zip(y, rows):
        labels.append("\n".join(_wrap(r.get("subsystem", "?"), 46)))
        if "error" in r:
            txt = f"failed: {r['error']}"[:100]
        else:
            rm, fl = _subsystem_value(r)
            txt = (f"RMSE {rm} (floor {fl}); " + ("within noise" if r.get("within_noise") else
                                                  f"{_pct(r.get('share_of_error', math.nan))} of the excess error"))
        ax.text(0.005, yi + 0.25, txt, va="bottom", fontsize=8, transform=above,
                bbox={"facecolor": "white", "edgecolor": "none", "alpha": 0.8, "pad": 0.5})
    ax.set_yticks(y, labels, fontsize=8)
    ax.set_ylim(-0.6, len(rows) - 0.25)
    ax.set_xlabel("validation RMSE / noise floor" + (" (log scale)" if log else "")
                  + ". Green: within the noise; amber: < 1.5 × the floor; red: above")
    ax.set_title("Which part of the model carries the gap (nominal model)", fontsize=10)
    ax.grid(axis="x", alpha=0.3)
    return fig


def _wrap(s: str, width: int) -> list[str]:
    import textwrap

    return textwrap.wrap(s, width) or [s]


# ------------------------------------------------------------------ HTML

_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,Helvetica,Arial,sans-serif;max-width:1150px;margin:1.5em auto;
padding:0 1em;color:#212529;line-height:1.45}
h1{font-size:1.5em;margin-bottom:.2em}h2{font-size:1.2em;margin-top:1.8em;border-bottom:1px solid #dee2e6}
.headline{font-size:1.15em;background:#f1f3f5;border-left:5px solid #e8590c;padding:.7em 1em;margin:1em 0}
.headline.none{border-left-color:#2b8a3e}.headline p{margin:.3em 0}.headline p:first-child{font-weight:600}
table{border-collapse:collapse;margin:.5em 0;font-size:.9em}
th,td{border:1px solid #dee2e6;padding:.3em .55em;text-align:left;vertical-align:top}
th{background:#f8f9fa}td.num{text-align:right;font-variant-numeric:tabular-nums;white-space:nowrap}
tr.verdict td{background:#fff4e6}tr.failed td{color:#868e96}td.err{color:#c92a2a;font-family:monospace;font-size:.9em}
.small{font-size:.85em;color:#495057}.explain{font-size:.9em;color:#495057;margin:.3em 0 1em}
img{max-width:100%;height:auto;display:block;margin:.6em 0}
.yes{color:#2b8a3e;font-weight:700}.no{color:#adb5bd}
code{background:#f1f3f5;padding:0 .2em}
"""


def _e(s) -> str:
    return html.escape(str(s))


def _run_rows(label: str, run) -> str:
    src = getattr(run, "source", None)
    try:
        per = run.sample_period
        rate = f", {_sig(1.0 / per)} Hz"
    except (ValueError, ZeroDivisionError):
        rate = ""
    return (f"<tr><th>{_e(label)}</th><td>{_e(src) if src else '<i>in memory (no file)</i>'}</td>"
            f"<td>{run.duration:.2f} s, {run.n} samples{rate}</td></tr>")


def _inputs_html(d) -> str:
    cyl, b, o = d.cylinder, d.baseline, d.options
    g = cyl.geometry
    src = getattr(cyl, "source", None)
    fr = _friction_text(b.get("friction") or {}, b.get("friction_std") or {})
    nseg = len(d.base_validation.segments)
    return f"""
<table>
<tr><th>cylinder</th><td>{_e(cyl.name)}<br><span class="small">{_e(src) if src else 'in memory (no file)'}</span></td>
<td>bore {g.bore * 1e3:g} mm, stroke {g.stroke * 1e3:g} mm; sensor noise {_um(cyl.sensors.position_noise)},
{_sig(cyl.sensors.pressure_noise / 1e3)} kPa</td></tr>
{_run_rows("TRAIN (fits the models)", d.train)}
{_run_rows("VALID (scores them)", d.valid)}
<tr><th>validation</th><td colspan="2">{nseg} segments of about {_sig(o.horizon_s)} s, each simulated
open loop with the recorded command from its own fitted start (nothing of VALID enters the models)</td></tr>
<tr><th>nominal model</th><td colspan="2">friction identified on TRAIN: {_e(fr)}<br>
position error of the fit on TRAIN {_um(b.get('rmse_x_train'))}; on VALID {_um(b.get('rmse_x_validation'))} in position,
{_sig(b.get('rmse_p1_validation', math.nan) / 1e3)} kPa in p1, {_sig(b.get('rmse_p2_validation', math.nan) / 1e3)} kPa
in p2: {_sig(b.get('normalized_rms'))} × the sensor noise over all outputs (1 = a perfect model)</td></tr>
<tr><th>verdict rule</th><td colspan="2">a candidate is significant when its gain on VALID is beyond what sensor
noise could produce (z ≥ {_sig(o.min_z, 2)}) and the all-output error shrinks by {_pct(o.min_shrink)} or more; ranked by that shrink less
{_pct(o.penalty_per_param)} per added parameter</td></tr>
</table>"""


def _z_text(z) -> str:
    """The z statistic of a candidate's validation gain; n/a when it was not validated."""
    return f"{float(z):.1f}" if _finite(z) else "n/a"


def _breakable(word: str) -> str:
    """A status word (`worse_than_nominal`) that may wrap after its underscores: unbroken, it
    pushed the ranking table past the page."""
    return _e(word).replace("_", "_<wbr>")


def _candidate_row(c, rank, verdict: str, ncols: int) -> str:
    sig = '<span class="yes">✓</span>' if c.significant else '<span class="no">–</span>'
    cls = "verdict" if c.effect == verdict else ("failed" if c.error else "")
    params = "<br>".join(_e(p) for p in _params_text(c, "\n", bounds=True).split("\n") if p) or "–"
    vstat = c.validation.status if c.validation is not None else "converged"
    vnote = f"<br><span class=\"small\">start fit on VALID: {_breakable(vstat)}</span>" if vstat != "converged" else ""
    fr = _e(_friction_text(c.friction or {})) or "–"
    out = (f'<tr class="{cls}"><td class="num">{rank}</td><td><b>{_e(c.effect)}</b><br>'
           f'<span class="small">{_e(_effect_description(c.effect))}</span></td>'
           f'<td class="num">{_pct(c.shrink)}</td><td class="num">{_pct(c.shrink_all)}</td>'
           f'<td class="num">{_z_text(c.z)}</td><td>{sig}</td>'
           f'<td class="num">{_um(c.rmse_x_validation)}</td>'
           f'<td>{params}</td><td class="small">{fr}</td>'
           f'<td>{_breakable(c.status)}{vnote}<br><span class="small">{c.wall_s:.1f} s</span></td></tr>')
    if c.error:  # the screen's reason is no error of the tool
        note = "small" if c.status == "no_gain_on_train" else "err"
        out += f'<tr class="failed"><td></td><td colspan="{ncols - 1}" class="{note}">{_e(c.error)}</td></tr>'
    return out


_RANK_HEAD = ("#", "effect", "shrink of x", "shrink, all outputs", "z", "significant", "x error on VALID",
              "identified parameters (± std)", "friction re-identified", "fit")


def _ranking_html(d) -> str:
    n = len(_RANK_HEAD)
    head = "".join(f"<th>{_e(h)}</th>" for h in _RANK_HEAD)
    rows = "".join(_candidate_row(c, i + 1, d.verdict, n) for i, c in enumerate(d.ranking))
    pair = ""
    if d.pair is not None:
        pair = ("<h3>The best pair</h3><p class=\"explain\">The verdict's effect and the runner-up fitted together; "
                "shrink and z are against the nominal model, as above, but significant here means significantly "
                "better than the verdict alone.</p>"
                f"<table><tr>{head}</tr>{_candidate_row(d.pair, '', d.verdict, n)}</table>")
    return f"""
<table><tr>{head}</tr>{rows}</table>
<p class="explain"><b>shrink of x</b>: the share of the position error on VALID that disappears once the effect is added
and re-identified on TRAIN (100 % = all of it, negative = worse). <b>shrink, all outputs</b>: the same for position and
both pressures together, each in units of its sensor noise. <b>z</b>: how far the gain lies beyond what sensor noise
could produce (above {_sig(d.options.min_z, 2)}: not luck). <b>friction re-identified</b>: Fc, Fv, kp refitted with
the effect. <b>fit</b>: how the identification on TRAIN ended; <code>no_gain_on_train</code>: the effect fits TRAIN no
better than the nominal model and was not validated (the fast screen); <code>worse_than_nominal</code>: the fit ended
worse on TRAIN than the nominal model it contains (a local minimum) and was not validated; these, failed fits and
models whose simulation of VALID diverged have no shrink and no z (n/a). <b>start fit on VALID</b> (shown when it
did not converge): how the worst fit of a validation segment's initial state ended; the model's parameters stay as
identified on TRAIN, and a segment fit that stops early can only make the model look worse.</p>{pair}"""


def _regions_sentence(d) -> str:
    regs = [r for r in (d.regions or []) if _finite(r.get("concentration"))
            and r.get("fraction_of_samples", 0.0) >= MIN_REGION_FRACTION]
    if not regs:
        return ""
    top = max(regs, key=lambda r: r["concentration"])
    if top["concentration"] < 1.3:
        return ("The error is spread evenly over the operating regimes: no regime holds more than 1.3 × its share "
                "of the samples.")
    hot = [r for r in regs if r["concentration"] >= 1.3][:3]
    return "Most concentrated: " + "; ".join(
        f"{r['where']} ({_pct(r.get('share_of_error'))} of the error in {_pct(r.get('fraction_of_samples'))} of "
        f"the samples)" for r in hot) + "."


def _whiteness_rows(d) -> list[tuple[str, dict]]:
    rows = [("nominal model", d.whiteness)] if d.whiteness else []
    best = d.best
    if best is not None:  # the verdict is significant, hence validated
        from .diagnose import whiteness

        val = best.validation
        rows.append((f"with {best.effect}", whiteness(val.residual[_x_index(val)])))
    return rows


def _whiteness_html(d) -> str:
    rows = _whiteness_rows(d)
    if not rows:
        return "<p>not computed</p>"
    yes, no = '<span class="yes">yes: random</span>', "<b>no: structured</b>"
    body = "".join(
        f"<tr><td>{_e(label)}</td><td class=\"num\">{_sig(w.get('ljung_box_q'))}</td><td class=\"num\">"
        f"{w.get('lags', '')}</td><td class=\"num\">{_sig(w.get('p_value'), 2)}</td><td class=\"num\">"
        f"{_sig(w.get('acf_1'), 2)}</td><td>{yes if w.get('white') else no}"
        f"</td></tr>" for label, w in rows)
    return f"""
<table><tr><th>position error of</th><th>Ljung-Box Q</th><th>lags</th><th>p-value</th><th>lag-1 autocorrelation</th>
<th>white (like noise)?</th></tr>{body}</table>
<p class="explain">Are the position errors on VALID (sampled every 10 ms) random like sensor noise, or do they follow a
pattern? A p-value below 0.001 means a pattern: the model misses something systematic. A lag-1 autocorrelation near 1
means the error changes slowly, as a model error does; near 0, it jumps from sample to sample like noise.</p>"""


def _correlations_html(cs: list[dict]) -> str:
    if not cs:
        return "<p>not computed (too few moving samples)</p>"
    bar = '<div style="background:#868e96;height:.8em;width:{:.0f}px"></div>'
    rows = "".join(
        f"<tr><td>{_e(c.get('regressor', '?'))}</td><td>{_e(c.get('hints', ''))}</td><td class=\"num\">"
        f"{_sig(c.get('r'), 2)}</td><td>{bar.format(min(1.0, abs(c.get('r') or 0)) * 120)}</td></tr>" for c in cs)
    return f"""
<table><tr><th>signal</th><th>hints at</th><th>r</th><th>|r|</th></tr>{rows}</table>
<p class="explain">A quick screen: how strongly the nominal model's equation errors (force balance and chamber pressures,
at the measured signals) follow a signal that each effect would add (r from −1 to 1; 0 = unrelated). A large |r|
points at that effect, but only the re-identification in the ranking above decides.</p>"""


def _img(png: bytes, alt: str) -> str:
    return f'<img alt="{_e(alt)}" src="data:image/png;base64,{base64.b64encode(png).decode("ascii")}">'


_PLOTS = (
    ("a_residual_time", "Position error over time"),
    ("b_residual_velocity", "Position error against velocity"),
    ("c_residual_position", "Position error against position"),
    ("d_traces", "Measured and simulated signals"),
    ("e_regions", "Where the error lies"),
    ("f_subsystems", "Which subsystem carries the gap"),
)


def _make_plots(d) -> dict[str, bytes]:
    best = d.best
    bestval = best.validation if best is not None else None
    makers = {
        "a_residual_time": lambda: _plot_residual_time(d, bestval),
        "b_residual_velocity": lambda: _plot_residual_vs_velocity(d, bestval),
        "c_residual_position": lambda: _plot_residual_vs_position(d, bestval),
        "d_traces": lambda: _plot_traces(d, bestval),
        "e_regions": lambda: _plot_regions(d, bestval is not None),
        "f_subsystems": lambda: _plot_subsystems(d),
    }
    return {k: _png(f()) for k, f in makers.items()}


def _unphysical_note(d) -> str:
    """A sentence when the nominal model's simulation of VALID leaves the physical range: the
    nominal model has no end stops (MODEL.md), so a model that far off runs past them."""
    sim = d.base_validation.simulated
    o = d.base_validation.outputs
    x = sim[o.index("x")]
    p = np.concatenate([sim[o.index(n)] for n in ("p1", "p2") if n in o] or [np.zeros(0)])
    out_x = bool(np.any((x < 0) | (x > d.cylinder.geometry.stroke)))
    out_p = bool(np.any(p <= 0))
    if not (out_x or out_p):
        return ""
    what = " and ".join(w for w, f in (("past the ends of the stroke", out_x), ("below zero pressure", out_p)) if f)
    return (f" The nominal model's simulation runs {what}: the nominal model has no end stops and nothing keeps its "
            "pressures physical, so a model this far off leaves the range a real cylinder stays in.")


def render_report(diagnosis, *, title: str | None = None, plots: dict[str, bytes] | None = None) -> str:
    """The report as one HTML string (plots drawn unless given)."""
    d = diagnosis
    plots = _make_plots(d) if plots is None else plots
    title = title or f"Why the simulation differs: {d.cylinder.name}"
    lines = headline(d, strong=lambda s: f"<b>{_e(s)}</b>", esc=_e)
    head_cls = "headline" + (" none" if d.best is None else "")
    img = {k: _img(v, alt) for (k, alt) in _PLOTS if (v := plots.get(k)) is not None}
    has = d.best is not None
    after = f" and with {_e(d.verdict)} (orange)" if has else ""
    unphysical = _unphysical_note(d)
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{_e(title)}</title>
<meta name="viewport" content="width=device-width, initial-scale=1"><style>{_CSS}</style></head><body>
<h1>{_e(title)}</h1>
<div class="{head_cls}">{''.join(f'<p>{s}</p>' for s in lines)}</div>
<p class="small">Verdict: <code>{_e(d.verdict)}</code>. Errors are measured − simulated on VALID, a run the models never
saw while fitting; "nominal" is the model with friction identified on TRAIN, without any added effect.</p>

<h2>Inputs</h2>{_inputs_html(d)}

<h2>Candidate effects, best first</h2>{_ranking_html(d)}

<h2>The position error on VALID</h2>
<p class="explain">The nominal model (blue){after}. A perfect model leaves only sensor noise, which stays inside
the grey band 95 % of the time.</p>
{img.get("a_residual_time", "")}
<p class="explain">Against velocity and position: an error that bunches at low speed or at reversals points at friction
(stiction, friction with memory); one that grows with speed at valve timing or flow; one that depends on the position
at friction along the stroke or the chamber volumes.</p>
<div style="display:flex;gap:1%;flex-wrap:wrap"><div style="flex:1 1 49%">{img.get("b_residual_velocity", "")}</div>
<div style="flex:1 1 49%">{img.get("c_residual_position", "")}</div></div>

<h2>Measured and simulated signals</h2>
<p class="explain">Left the whole run, right the segment where the nominal model is worst; the bottom row is the position
error, which is too small to see against the stroke.{unphysical}</p>
{img.get("d_traces", "")}

<h2>Where the error lies</h2>
<p class="explain">For each operating regime: its share of the nominal model's squared position error (red) against
its share of the samples (grey). A regime with much more error than samples (large ×) is where the model is wrong.
{_e(_regions_sentence(d))}</p>
{img.get("e_regions", "")}

<h2>Which subsystem carries it</h2>
<p class="explain">The piston's force balance alone (driven by the measured pressures, so valve and chamber errors
cannot leak in) and the chamber pressures of the whole model, each against the error it would show if the model were
perfect (its noise floor).</p>
{img.get("f_subsystems", "")}

<h2>Is what is left random? (whiteness of the nominal model's position error)</h2>{_whiteness_html(d)}

<h2>Which signals the errors follow (regressor screen)</h2>{_correlations_html(d.correlations)}

<p class="small">combined_reality diagnosis{f', {d.wall_s:.1f} s' if _finite(getattr(d, 'wall_s', None)) else ''}.</p>
</body></html>
"""


def write_report(diagnosis, path, *, title: str | None = None, png_dir=None) -> None:
    """Write the report of `diagnosis` to `path` as one self-contained HTML file
    (atomically); with `png_dir`, also every plot as a PNG there."""
    plots = _make_plots(diagnosis)
    write_html_and_plots(path, render_report(diagnosis, title=title, plots=plots), plots, png_dir)


def write_html_and_plots(path, html_text: str, plots: dict[str, bytes], png_dir=None) -> None:
    """A report's HTML file (atomically) and, with `png_dir`, its plots as NAME.png there."""
    from .cli import _write_text_atomic

    if png_dir is not None:
        png_dir = Path(png_dir)
        png_dir.mkdir(parents=True, exist_ok=True)
        for name, data in plots.items():
            (png_dir / f"{name}.png").write_bytes(data)
    _write_text_atomic(path, html_text)
