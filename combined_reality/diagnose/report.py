"""The human report of a diagnosis: one self-contained HTML file (inline CSS, plots as
embedded PNG), written for an engineer, not a statistician.

    write_report(diagnosis, "diagnosis.html", png_dir="plots/")

Contents: the verdict in one sentence, the inputs, the ranking of the candidate effects
(and the best pair), plots of the validation error (over time, against velocity and
position, measured vs simulated traces, where the error lies, which subsystem carries
it), and the whiteness test and regressor screen as small tables with a line each on how
to read them. Units for people: um for position errors, mm for positions along the
stroke, kPa for pressures, mm/s for velocities; the Diagnosis itself stays in SI.

The diagnosis in words (diagnose.text) is shared with the console and the Rerun view;
matplotlib is imported only when plots are drawn.
"""
from __future__ import annotations

import math

import numpy as np

from ..identify import MIN_REGION_FRACTION
from ..report.figures import new_figure, png_bytes, wrap_lines
from ..report.html import CSS, escape, img_tag, write_html_and_plots
from ..report.text import finite, pct, sig, um
from .text import effect_description, friction_text, headline, params_text, subsystem_value, z_text
from .where import whiteness

__all__ = ["write_report", "render_report"]

_SCATTER_MAX = 4000  # points per series in the scatter plots
_LINE_MAX = 8000  # points per line in the whole-run trace plots

# colours: measured, nominal model, model with the verdict's effect
_C_MEAS, _C_NOM, _C_EFF = "#222222", "#1f77b4", "#e8590c"


# ------------------------------------------------------------------ numbers for people


# ------------------------------------------------------------------ the verdict in words


# ------------------------------------------------------------------ plots


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
    fig = new_figure(10, 5.6 if two else 3.4)
    axes = fig.subplots(2 if two else 1, 1, sharex=True, squeeze=False)[:, 0]
    ax = axes[0]
    ax.axhspan(-2 * noise, 2 * noise, color="#dddddd", zorder=0, label=_band_label(noise))
    ax.plot(t, base.residual[ix] * 1e6, color=_C_NOM, lw=0.8,
            label=f"nominal model (RMSE {um(base.rmse('x'))})")
    if two:
        ax.plot(t, bestval.residual[_x_index(bestval)] * 1e6, color=_C_EFF, lw=0.8,
                label=f"with {d.verdict} (RMSE {um(bestval.rmse('x'))})")
    ax.set_title("Position error over time on VALID (each segment simulated from its own start)", fontsize=10)
    ax.legend(loc="upper right", fontsize=8, framealpha=0.9)
    ax.set_ylabel("position error (um)\nmeasured − simulated")
    if two:
        ax2 = axes[1]
        ax2.axhspan(-2 * noise, 2 * noise, color="#dddddd", zorder=0, label=_band_label(noise))
        ax2.plot(t, bestval.residual[_x_index(bestval)] * 1e6, color=_C_EFF, lw=0.6,
                 label=f"with {d.verdict} (RMSE {um(bestval.rmse('x'))})")
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
    return f"± 2 × sensor noise ({sig(noise_um, 2)} um): pure noise stays inside 95 % of the time"


def _scatter(ax, xvals, val, color, label, band: bool = False) -> None:
    r = val.residual[_x_index(val)]
    idx = np.flatnonzero(np.isfinite(r) & np.isfinite(xvals))
    idx = idx[::_stride(len(idx), _SCATTER_MAX)]
    ax.scatter(xvals[idx], r[idx] * 1e6, s=3, color=color, alpha=0.5, lw=0, rasterized=True,
               label=f"{label} (RMSE {um(val.rmse('x'))})")
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
    fig = new_figure(5, 5.6 if two else 3.4)
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
    fig = new_figure(11, 7.8)
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
    fig = new_figure(10, row_height * max(n, 1) + extra)
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
        txt = f"×{c:.2f}" if finite(c) else "×?"
        txt += f"   RMSE {um(r.get('rmse_x', math.nan))}"
        if has_after and "rmse_x_after" in r:
            txt += f" → {um(r['rmse_x_after'])}"
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


def _plot_subsystems(d):
    rows = list(d.subsystems or [])
    fig, ax = _bar_figure(len(rows), 0.75, 1.3, "no subsystem split")
    if not rows:
        return fig
    y = np.arange(len(rows))[::-1]
    ratio = np.array([r["rmse"] / r["floor"] if finite(r.get("rmse")) and finite(r.get("floor")) and r["floor"] > 0
                      else math.nan for r in rows])
    colors = ["#2b8a3e" if r.get("within_noise") else ("#f08c00" if np.isfinite(q) and q < 1.5 else "#c92a2a")
              for r, q in zip(rows, ratio)]
    ax.barh(y, np.nan_to_num(ratio, nan=0.0), height=0.45, color=colors)
    ax.axvline(1, color="#222222", lw=1, ls="--")
    shown = ratio[np.isfinite(ratio) & (ratio > 0)]
    hi = max(float(shown.max()) if shown.size else 1.0, 1.5)
    log = hi > 20
    if log:
        ax.set_xscale("log")
        ax.set_xlim(min(0.5, 0.5 * float(shown.min())), hi * 2)
    else:
        ax.set_xlim(0, hi * 1.15)
    ax.text(1, -0.55, " noise floor", fontsize=8, va="bottom")
    # each bar's figures above it, from the left edge: at the bar's end they ran out of the axes
    # (a large ratio) or over the labels (a ratio below the axis start)
    above = ax.get_yaxis_transform()  # x in axes fractions, y in data
    labels = []
    for yi, r in zip(y, rows):
        labels.append("\n".join(wrap_lines(r.get("subsystem", "?"), 46)))
        if "error" in r:
            txt = f"failed: {r['error']}"[:100]
        else:
            rm, fl = subsystem_value(r)
            txt = (f"RMSE {rm} (floor {fl}); " + ("within noise" if r.get("within_noise") else
                                                  f"{pct(r.get('share_of_error', math.nan))} of the excess error"))
        ax.text(0.005, yi + 0.25, txt, va="bottom", fontsize=8, transform=above,
                bbox={"facecolor": "white", "edgecolor": "none", "alpha": 0.8, "pad": 0.5})
    ax.set_yticks(y, labels, fontsize=8)
    ax.set_ylim(-0.6, len(rows) - 0.25)
    ax.set_xlabel("validation RMSE / noise floor" + (" (log scale)" if log else "")
                  + ". Green: within the noise; amber: < 1.5 × the floor; red: above")
    ax.set_title("Which part of the model carries the gap (nominal model)", fontsize=10)
    ax.grid(axis="x", alpha=0.3)
    return fig


# ------------------------------------------------------------------ HTML


def _run_rows(label: str, run) -> str:
    src = getattr(run, "source", None)
    try:
        per = run.sample_period
        rate = f", {sig(1.0 / per)} Hz"
    except (ValueError, ZeroDivisionError):
        rate = ""
    return (f"<tr><th>{escape(label)}</th><td>{escape(src) if src else '<i>in memory (no file)</i>'}</td>"
            f"<td>{run.duration:.2f} s, {run.n} samples{rate}</td></tr>")


def _inputs_html(d) -> str:
    cyl, b, o = d.cylinder, d.baseline, d.options
    g = cyl.geometry
    src = getattr(cyl, "source", None)
    fr = friction_text(b.get("friction") or {}, b.get("friction_std") or {})
    nseg = len(d.base_validation.segments)
    return f"""
<table>
<tr><th>cylinder</th><td>{escape(cyl.name)}<br><span class="small">{escape(src) if src else 'in memory (no file)'}</span></td>
<td>bore {g.bore * 1e3:g} mm, stroke {g.stroke * 1e3:g} mm; sensor noise {um(cyl.sensors.position_noise)},
{sig(cyl.sensors.pressure_noise / 1e3)} kPa</td></tr>
{_run_rows("TRAIN (fits the models)", d.train)}
{_run_rows("VALID (scores them)", d.valid)}
<tr><th>validation</th><td colspan="2">{nseg} segments of about {sig(o.horizon_s)} s, each simulated
open loop with the recorded command from its own fitted start (nothing of VALID enters the models)</td></tr>
<tr><th>nominal model</th><td colspan="2">friction identified on TRAIN: {escape(fr)}<br>
position error of the fit on TRAIN {um(b.get('rmse_x_train'))}; on VALID {um(b.get('rmse_x_validation'))} in position,
{sig(b.get('rmse_p1_validation', math.nan) / 1e3)} kPa in p1, {sig(b.get('rmse_p2_validation', math.nan) / 1e3)} kPa
in p2: {sig(b.get('normalized_rms'))} × the sensor noise over all outputs (1 = a perfect model)</td></tr>
<tr><th>verdict rule</th><td colspan="2">a candidate is significant when its gain on VALID is beyond what sensor
noise could produce (z ≥ {sig(o.min_z, 2)}) and the all-output error shrinks by {pct(o.min_shrink)} or more; ranked by that shrink less
{pct(o.penalty_per_param)} per added parameter</td></tr>
</table>"""


def _breakable(word: str) -> str:
    """A status word (`worse_than_nominal`) that may wrap after its underscores: unbroken, it
    pushed the ranking table past the page."""
    return escape(word).replace("_", "_<wbr>")


def _candidate_row(c, rank, verdict: str, ncols: int) -> str:
    mark = '<span class="yes">✓</span>' if c.significant else '<span class="no">–</span>'
    cls = "verdict" if c.effect == verdict else ("failed" if c.error else "")
    params = "<br>".join(escape(p) for p in params_text(c, "\n", bounds=True).split("\n") if p) or "–"
    vstat = c.validation.status if c.validation is not None else "converged"
    vnote = f"<br><span class=\"small\">start fit on VALID: {_breakable(vstat)}</span>" if vstat != "converged" else ""
    fr = escape(friction_text(c.friction or {})) or "–"
    out = (f'<tr class="{cls}"><td class="num">{rank}</td><td><b>{escape(c.effect)}</b><br>'
           f'<span class="small">{escape(effect_description(c.effect))}</span></td>'
           f'<td class="num">{pct(c.shrink)}</td><td class="num">{pct(c.shrink_all)}</td>'
           f'<td class="num">{z_text(c.z)}</td><td>{mark}</td>'
           f'<td class="num">{um(c.rmse_x_validation)}</td>'
           f'<td>{params}</td><td class="small">{fr}</td>'
           f'<td>{_breakable(c.status)}{vnote}<br><span class="small">{c.wall_s:.1f} s</span></td></tr>')
    if c.error:  # the screen's reason is no error of the tool
        note = "small" if c.status in ("no_gain_on_train", "screened_out", "not_validated", "falls_short") else "err"
        out += f'<tr class="failed"><td></td><td colspan="{ncols - 1}" class="{note}">{escape(c.error)}</td></tr>'
    return out


_RANK_HEAD = ("#", "effect", "shrink of x", "shrink, all outputs", "z", "significant", "x error on VALID",
              "identified parameters (± std)", "friction re-identified", "fit")


def _ranking_html(d) -> str:
    n = len(_RANK_HEAD)
    head = "".join(f"<th>{escape(h)}</th>" for h in _RANK_HEAD)
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
could produce (above {sig(d.options.min_z, 2)}: not luck). <b>friction re-identified</b>: Fc, Fv, kp refitted with
the effect. <b>fit</b>: how the identification on TRAIN ended; <code>no_gain_on_train</code>: the effect fits TRAIN no
better than the nominal model and was not validated (the fast screen); <code>screened_out</code>: its gain on
TRAIN is under {d.options.screen_share:.0%} of the best candidate's, not validated either; <code>not_validated</code>:
a candidate that fits TRAIN better closed the gap on VALID to near the noise first (validations run in the order of
the TRAIN fit); <code>worse_than_nominal</code>: the fit ended
worse on TRAIN than the nominal model it contains (a local minimum) and was not validated; <code>falls_short</code>
(the pair): for 6 iterations in a row its fit explained under {d.options.pair_give_up:.0%} of what the pair would need
on TRAIN to change the verdict, and it was given up, not validated; these, failed fits and
models whose simulation of VALID diverged have no shrink and no z (n/a). <b>start fit on VALID</b> (shown when it
did not converge): how the worst fit of a validation segment's initial state ended; the model's parameters stay as
identified on TRAIN, and a segment fit that stops early can only make the model look worse.</p>{pair}"""


def _regions_sentence(d) -> str:
    regs = [r for r in (d.regions or []) if finite(r.get("concentration"))
            and r.get("fraction_of_samples", 0.0) >= MIN_REGION_FRACTION]
    if not regs:
        return ""
    top = max(regs, key=lambda r: r["concentration"])
    if top["concentration"] < 1.3:
        return ("The error is spread evenly over the operating regimes: no regime holds more than 1.3 × its share "
                "of the samples.")
    hot = [r for r in regs if r["concentration"] >= 1.3][:3]
    return "Most concentrated: " + "; ".join(
        f"{r['where']} ({pct(r.get('share_of_error'))} of the error in {pct(r.get('fraction_of_samples'))} of "
        f"the samples)" for r in hot) + "."


def _whiteness_rows(d) -> list[tuple[str, dict]]:
    rows = [("nominal model", d.whiteness)] if d.whiteness else []
    best = d.best
    if best is not None:  # the verdict is significant, hence validated
        val = best.validation
        rows.append((f"with {best.effect}", whiteness(val.residual[_x_index(val)])))
    return rows


def _whiteness_html(d) -> str:
    rows = _whiteness_rows(d)
    if not rows:
        return "<p>not computed</p>"
    yes, no = '<span class="yes">yes: random</span>', "<b>no: structured</b>"
    body = "".join(
        f"<tr><td>{escape(label)}</td><td class=\"num\">{sig(w.get('ljung_box_q'))}</td><td class=\"num\">"
        f"{w.get('lags', '')}</td><td class=\"num\">{sig(w.get('p_value'), 2)}</td><td class=\"num\">"
        f"{sig(w.get('acf_1'), 2)}</td><td>{yes if w.get('white') else no}"
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
        f"<tr><td>{escape(c.get('regressor', '?'))}</td><td>{escape(c.get('hints', ''))}</td><td class=\"num\">"
        f"{sig(c.get('r'), 2)}</td><td>{bar.format(min(1.0, abs(c.get('r') or 0)) * 120)}</td></tr>" for c in cs)
    return f"""
<table><tr><th>signal</th><th>hints at</th><th>r</th><th>|r|</th></tr>{rows}</table>
<p class="explain">A quick screen: how strongly the nominal model's equation errors (force balance and chamber pressures,
at the measured signals) follow a signal that each effect would add (r from −1 to 1; 0 = unrelated). A large |r|
points at that effect, but only the re-identification in the ranking above decides.</p>"""


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
    return {k: png_bytes(f()) for k, f in makers.items()}


def _unphysical_note(d) -> str:
    """A sentence when the nominal model's simulation of VALID leaves the physical range: the
    nominal model has no end stops (docs/model.md), so a model that far off runs past them."""
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
    lines = headline(d, strong=lambda s: f"<b>{escape(s)}</b>", esc=escape)
    head_cls = "headline" + (" none" if d.best is None else "")
    img = {k: img_tag(v, alt) for (k, alt) in _PLOTS if (v := plots.get(k)) is not None}
    has = d.best is not None
    after = f" and with {escape(d.verdict)} (orange)" if has else ""
    unphysical = _unphysical_note(d)
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{escape(title)}</title>
<meta name="viewport" content="width=device-width, initial-scale=1"><style>{CSS}</style></head><body>
<h1>{escape(title)}</h1>
<div class="{head_cls}">{''.join(f'<p>{s}</p>' for s in lines)}</div>
<p class="small">Verdict: <code>{escape(d.verdict)}</code>. Errors are measured − simulated on VALID, a run the models never
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
{escape(_regions_sentence(d))}</p>
{img.get("e_regions", "")}

<h2>Which subsystem carries it</h2>
<p class="explain">The piston's force balance alone (driven by the measured pressures, so valve and chamber errors
cannot leak in) and the chamber pressures of the whole model, each against the error it would show if the model were
perfect (its noise floor).</p>
{img.get("f_subsystems", "")}

<h2>Is what is left random? (whiteness of the nominal model's position error)</h2>{_whiteness_html(d)}

<h2>Which signals the errors follow (regressor screen)</h2>{_correlations_html(d.correlations)}

<p class="small">combined_reality diagnosis{f', {d.wall_s:.1f} s' if finite(getattr(d, 'wall_s', None)) else ''}.</p>
</body></html>
"""


def write_report(diagnosis, path, *, title: str | None = None, png_dir=None) -> None:
    """Write the report of `diagnosis` to `path` as one self-contained HTML file
    (atomically); with `png_dir`, also every plot as a PNG there."""
    plots = _make_plots(diagnosis)
    write_html_and_plots(path, render_report(diagnosis, title=title, plots=plots), plots, png_dir)


