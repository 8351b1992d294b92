"""The report of a fit: one self-contained HTML page (inline CSS, plots as embedded PNG) of
what `identify` found, for an engineer: whether the model explains the runs, the estimates,
measured against simulated for each run (the whole run and its worst second), the errors
against time, velocity and position, the friction law found beside the friction Newton's
law gives with the measured pressures, and the solver's iterations. `calibrate` builds its
page from the same parts (calibrate.report).

    write_fit_report(result, runs, "identify.html", not_determined=[...])

matplotlib is imported only when plots are drawn; the result itself stays SI."""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..files import Run, run_name, split_at_gaps
from ..report.figures import new_figure, png_bytes
from ..report.html import CSS, escape, img_tag, write_html_and_plots
from ..report.text import format_value, sig, um
from .newton import friction_from_newton
from .offline import MISMATCH, IdentifyResult

__all__ = ["FitPlots", "fit_pieces", "fit_plots", "fit_sections", "render_page", "write_fit_report",
           "C_MEAS", "C_SIM", "C_P2", "C_SIM2"]

_LINE_MAX = 8000  # points per line in whole-run plots
_SCATTER_MAX = 5000  # points per scatter series
_RUNS_SHOWN = 3  # runs drawn one by one (all runs enter the scatter plots and tables)
C_MEAS, C_SIM, C_P2, C_SIM2 = "#222222", "#1f77b4", "#868e96", "#e8590c"


def _stride(n: int, cap: int) -> int:
    return max(1, int(math.ceil(n / cap)))


def fit_pieces(runs: Sequence[Run], result: IdentifyResult) -> list[Run]:
    """The runs as the fit saw them, one per simulated trace: cut at lost samples (and, in the
    pressure drive, where a pressure was not measured), as identify cuts them."""
    if len(result.simulated) == len(runs):
        return list(runs)
    channels = ("p1", "p2") if result.drive == "pressure" else ()
    pieces = [q for r in runs for q in split_at_gaps(r, channels=channels) if q.n >= 3]
    if len(pieces) != len(result.simulated):
        raise ValueError(f"{len(pieces)} pieces of the runs for {len(result.simulated)} simulated traces")
    return pieces


@dataclass(frozen=True)
class _Trace:
    """One source run's measured and simulated signals, pieces joined with a gap between."""
    name: str
    t: np.ndarray
    meas: dict[str, np.ndarray]
    sim: dict[str, np.ndarray]


def _traces(runs: Sequence[Run], result: IdentifyResult) -> list[_Trace]:
    out: dict[str, dict] = {}
    for piece, sim in zip(fit_pieces(runs, result), result.simulated):
        key = run_name(piece)
        d = out.setdefault(key, {"t": [], "meas": {n: [] for n in ("x", "p1", "p2")},
                                 "sim": {n: [] for n in result.output_names}})
        gap = [np.nan] if d["t"] else []
        d["t"].append(np.r_[gap, piece.t])
        for n in ("x", "p1", "p2"):
            d["meas"][n].append(np.r_[gap, getattr(piece, n)])
        for i, n in enumerate(result.output_names):
            d["sim"][n].append(np.r_[gap, sim[i]])
    return [_Trace(name=k, t=np.concatenate(d["t"]), meas={n: np.concatenate(v) for n, v in d["meas"].items()},
                   sim={n: np.concatenate(v) for n, v in d["sim"].items()}) for k, d in out.items()]


def _sub(t: np.ndarray, *ys: np.ndarray, cap: int = _LINE_MAX):
    k = _stride(len(t), cap)
    return (t[::k], *(y[::k] for y in ys))


def _worst_window(tr: _Trace, width_s: float = 1.0) -> tuple[float, float]:
    """The stretch of `width_s` with the largest mean squared position error."""
    r = tr.meas["x"] - tr.sim.get("x", tr.meas["x"])
    ok = np.isfinite(r) & np.isfinite(tr.t)
    if ok.sum() < 10:
        return float(np.nanmin(tr.t)), float(np.nanmin(tr.t)) + width_s
    t, e = tr.t[ok], r[ok] ** 2
    dt = float(np.median(np.diff(t)))
    w = max(1, int(width_s / dt))
    if len(e) <= w:
        return float(t[0]), float(t[-1])
    c = np.r_[0.0, np.cumsum(e)]
    i = int(np.argmax(c[w:] - c[:-w]))
    return float(t[i]), float(t[min(i + w, len(t) - 1)])


def _trace_figure(tr: _Trace, noise_x: float, window: tuple[float, float] | None = None):
    """Position, pressures and the position error over time: measured (dark) and simulated."""
    has_x, has_p = "x" in tr.sim, "p1" in tr.sim
    rows = (2 if has_x else 0) + (1 if has_p else 0)
    fig = new_figure(10 if window is None else 10, 1.9 * rows + 0.6)
    axes = list(fig.subplots(rows, 1, sharex=True, squeeze=False)[:, 0])
    t = tr.t
    sel = np.ones(len(t), bool) if window is None else (t >= window[0]) & (t <= window[1])
    t0 = float(np.nanmin(tr.t))
    ts = t[sel] - t0
    cap = _LINE_MAX if window is None else 100000
    if has_x:
        ax = axes.pop(0)
        tt, xm, xs = _sub(ts, tr.meas["x"][sel], tr.sim["x"][sel], cap=cap)
        ax.plot(tt, xm * 1e3, color=C_MEAS, lw=0.9, label="measured")
        ax.plot(tt, xs * 1e3, color=C_SIM, lw=0.9, ls="--", label="simulated")
        ax.set_ylabel("position (mm)")
        ax.legend(loc="upper right", fontsize=8, framealpha=0.9, ncols=2)
    if has_p:
        ax = axes.pop(0)
        tt, a, b, c, d = _sub(ts, tr.meas["p1"][sel], tr.sim["p1"][sel], tr.meas["p2"][sel], tr.sim["p2"][sel],
                              cap=cap)
        ax.plot(tt, a / 1e3, color=C_MEAS, lw=0.9, label="p1 measured")
        ax.plot(tt, b / 1e3, color=C_SIM, lw=0.9, ls="--", label="p1 simulated")
        ax.plot(tt, c / 1e3, color=C_P2, lw=0.9, label="p2 measured")
        ax.plot(tt, d / 1e3, color=C_SIM2, lw=0.9, ls="--", label="p2 simulated")
        ax.set_ylabel("pressure (kPa abs.)")
        ax.legend(loc="upper right", fontsize=8, framealpha=0.9, ncols=4)
    if has_x:
        ax = axes.pop(0)
        tt, r = _sub(ts, (tr.meas["x"] - tr.sim["x"])[sel], cap=cap)
        ax.axhspan(-2 * noise_x * 1e6, 2 * noise_x * 1e6, color="#dddddd", zorder=0,
                   label=f"± 2 × sensor noise ({sig(noise_x * 1e6, 2)} um)")
        ax.plot(tt, r * 1e6, color=C_SIM, lw=0.7, label="measured − simulated")
        ax.axhline(0, color="#555555", lw=0.5)
        ax.set_ylabel("position error (um)")
        ax.legend(loc="upper right", fontsize=8, framealpha=0.9, ncols=2)
    for ax in fig.axes:
        ax.grid(alpha=0.3)
    fig.axes[-1].set_xlabel("time (s)" + ("" if window is None else f" from t = {window[0] - t0:.2f} s of the run"))
    return fig


def _scatter(ax, x, y, color, label) -> None:
    ok = np.flatnonzero(np.isfinite(x) & np.isfinite(y))
    ok = ok[::_stride(len(ok), _SCATTER_MAX)]
    ax.scatter(x[ok], y[ok], s=3, color=color, alpha=0.45, lw=0, rasterized=True, label=label)


def _residual_figure(traces: list[_Trace], noise: dict[str, float]):
    """The position error against time, velocity and position (all runs), and the pressure
    errors against time."""
    from .smoothing import velocity_estimate

    has_x, has_p = "x" in traces[0].sim, "p1" in traces[0].sim
    rows = int(has_x) + int(has_p)
    fig = new_figure(10, 3.3 * rows)
    gs = fig.add_gridspec(rows, 3)
    if has_x:
        ax_t, ax_v, ax_x = (fig.add_subplot(gs[0, k]) for k in range(3))
        band = 2 * noise["x"] * 1e6
        for ax in (ax_t, ax_v, ax_x):
            ax.axhspan(-band, band, color="#dddddd", zorder=0)
            ax.axhline(0, color="#555555", lw=0.5)
        t_off = 0.0
        for tr in traces:
            r = (tr.meas["x"] - tr.sim["x"]) * 1e6
            t = tr.t - np.nanmin(tr.t) + t_off
            _scatter(ax_t, t, r, C_SIM, None)
            t_off = float(np.nanmax(t)) + 0.5
            fin = np.isfinite(tr.t) & np.isfinite(tr.meas["x"])
            v = np.full(len(t), np.nan)
            if fin.sum() > 50:
                v[fin] = velocity_estimate(tr.t[fin], tr.meas["x"][fin])
            _scatter(ax_v, v * 1e3, r, C_SIM, None)
            _scatter(ax_x, tr.meas["x"] * 1e3, r, C_SIM, None)
        ax_t.set_title("position error over time", fontsize=9)
        ax_t.set_xlabel("time (s; runs one after another)")
        ax_t.set_ylabel("measured − simulated (um)")
        ax_v.set_title("against velocity", fontsize=9)
        ax_v.set_xlabel("velocity (mm/s)")
        ax_x.set_title("against position", fontsize=9)
        ax_x.set_xlabel("position (mm)")
    if has_p:
        ax = fig.add_subplot(gs[rows - 1, :])
        band = 2 * noise["p"] / 1e3
        ax.axhspan(-band, band, color="#dddddd", zorder=0, label="± 2 × sensor noise")
        t_off = 0.0
        for k, tr in enumerate(traces):
            t = tr.t - np.nanmin(tr.t) + t_off
            _scatter(ax, t, (tr.meas["p1"] - tr.sim["p1"]) / 1e3, C_MEAS, "p1" if k == 0 else None)
            _scatter(ax, t, (tr.meas["p2"] - tr.sim["p2"]) / 1e3, C_SIM2, "p2" if k == 0 else None)
            t_off = float(np.nanmax(t)) + 0.5
        ax.axhline(0, color="#555555", lw=0.5)
        ax.set_title("pressure errors over time", fontsize=9)
        ax.set_xlabel("time (s; runs one after another)")
        ax.set_ylabel("measured − simulated (kPa)")
        leg = ax.legend(loc="upper right", fontsize=8, markerscale=4, framealpha=0.9)
        for h in leg.legend_handles:
            h.set_alpha(1)
    for ax in fig.axes:
        ax.grid(alpha=0.3)
    return fig


def _friction_figure(result: IdentifyResult, runs: Sequence[Run]):
    """The friction law found (the nominal law Fc + Fv v + kp |p1 - p2|, at the runs' pressure
    differences) beside the friction Newton's law gives with the measured pressures."""
    cyl = result.cylinder
    f = cyl.friction
    vs, Fs, Ls, dps = [], [], [], []
    for r in runs:
        idx, v, F = friction_from_newton(cyl, r)
        if len(idx):
            dp = np.abs(r.p1[idx] - r.p2[idx])
            vs.append(v), Fs.append(F), dps.append(dp)
            Ls.append((f.Fc + f.kp * dp) * np.tanh(v / f.v_smooth) + f.Fv * v)
    if not vs:
        return None
    v, F, L, dp = (np.concatenate(a) for a in (vs, Fs, Ls, dps))
    fig = new_figure(10, 4.0)
    ax = fig.subplots()
    _scatter(ax, v * 1e3, F, "#adb5bd", "from Newton's law with the measured pressures (each sample)")
    _scatter(ax, v * 1e3, L, C_SIM, "the law found, at each sample's |p1 − p2|")
    lo, hi = np.percentile(dp, [10, 90])
    grid = np.linspace(np.percentile(v, 0.5), np.percentile(v, 99.5), 400)
    for q, ls in ((lo, ":"), (hi, "-")):
        ax.plot(grid * 1e3, (f.Fc + f.kp * q) * np.tanh(grid / f.v_smooth) + f.Fv * grid, color=C_SIM2, lw=1.2, ls=ls,
                label=f"the law found at |p1 − p2| = {q / 1e3:.0f} kPa")
    extra = [e.name for e in result.effects]
    ax.set_title("Friction against velocity: Fc + Fv v + kp |p1 − p2|, opposing the motion"
                 + (f" (the model also has {', '.join(extra)}, not drawn)" if extra else ""), fontsize=9)
    ax.set_xlabel("velocity (mm/s)")
    ax.set_ylabel("friction (N)")
    span = np.percentile(np.abs(L), 99.5) * 1.6 + 1.0
    ax.set_ylim(-span, span)
    vlo, vhi = np.percentile(v, [0.5, 99.5]) * 1e3
    ax.set_xlim(vlo - 0.1 * (vhi - vlo), vhi + 0.1 * (vhi - vlo))
    ax.axhline(0, color="#555555", lw=0.5)
    ax.grid(alpha=0.3)
    leg = ax.legend(loc="upper left", fontsize=8, markerscale=4, framealpha=0.9)
    for h in leg.legend_handles:
        h.set_alpha(1)
    return fig


def _iterations_figure(result: IdentifyResult):
    hist = result.solver.get("history") or []
    if len(hist) < 2:
        return None
    fig = new_figure(5, 2.8)
    ax = fig.subplots()
    it = [h["iteration"] for h in hist]
    ax.semilogy(it, [h["cost"] for h in hist], "o-", color=C_SIM, ms=3, lw=1)
    ax.set_xlabel("iteration")
    ax.set_ylabel("cost (weighted squared errors / 2)")
    ax.set_title("The solver's iterations", fontsize=9)
    ax.grid(alpha=0.3, which="both")
    return fig


@dataclass(frozen=True)
class FitPlots:
    """The plots of a fit, as PNG bytes: per run its traces and its worst second, the errors,
    the friction law, the iterations."""
    traces: tuple[tuple[str, bytes, bytes], ...]  # (run, whole run, worst second)
    residuals: bytes
    friction: bytes | None
    iterations: bytes | None

    def named(self) -> dict[str, bytes]:
        out = {}
        for k, (_, whole, worst) in enumerate(self.traces):
            out[f"run{k + 1}_traces"], out[f"run{k + 1}_worst"] = whole, worst
        out["residuals"] = self.residuals
        if self.friction:
            out["friction"] = self.friction
        if self.iterations:
            out["iterations"] = self.iterations
        return out


def fit_plots(result: IdentifyResult, runs: Sequence[Run]) -> FitPlots:
    cyl = result.cylinder
    noise = {"x": cyl.sensors.position_noise, "p": cyl.sensors.pressure_noise}
    traces = _traces(runs, result)
    drawn = []
    for tr in traces[:_RUNS_SHOWN]:
        whole = png_bytes(_trace_figure(tr, noise["x"]))
        worst = png_bytes(_trace_figure(tr, noise["x"], _worst_window(tr)))
        drawn.append((tr.name, whole, worst))
    fr = _friction_figure(result, runs) if "x" in result.output_names else None
    it = _iterations_figure(result)
    return FitPlots(traces=tuple(drawn), residuals=png_bytes(_residual_figure(traces, noise)),
                    friction=png_bytes(fr) if fr is not None else None,
                    iterations=png_bytes(it) if it is not None else None)


def _estimates_html(result: IdentifyResult, start: dict[str, float], start_label: str,
                    not_determined: dict[str, str]) -> str:
    rows = []
    for n, e in result.params.items():
        nd = not_determined.get(n)
        value = "not determined" if nd and not math.isfinite(e.std) else format_value(e.value, e.std, e.unit)
        note = "; ".join(x for x in (("at a bound of its range" if e.at_bound else ""), nd or "") if x)
        cls = ' class="failed"' if nd else ""
        rows.append(f"<tr{cls}><td><code>{escape(n)}</code></td>"
                    f"<td class=\"num\">{escape(value)}</td><td class=\"num\">"
                    f"{escape(format_value(start.get(n, e.initial), None, e.unit))}</td><td>{escape(note)}</td></tr>")
    return (f"<table><tr><th>parameter</th><th>estimate ± std</th><th>{escape(start_label)}</th><th>note</th></tr>"
            + "".join(rows) + "</table>")


def _rmse_text(output: str, rmse: float) -> str:
    return um(rmse) if output == "x" else f"{sig(rmse)} Pa"


def _fit_table_html(result: IdentifyResult, runs: Sequence[Run]) -> str:
    names = result.output_names
    head = "".join(f"<th>RMSE {escape(n)}</th>" for n in names)
    by_run: dict[str, list[dict]] = {}
    for piece, f in zip(fit_pieces(runs, result), result.fit_per_run):
        by_run.setdefault(run_name(piece), []).append(f)
    rows = []
    for name, fits in by_run.items():
        cells = []
        for n in names:
            vals = [f.get(f"rmse_{n}") for f in fits if f.get(f"rmse_{n}") is not None]
            rms = math.sqrt(sum(v * v for v in vals) / len(vals)) if vals else math.nan
            cells.append(_rmse_text(n, rms))
        pieces = f" ({len(fits)} pieces)" if len(fits) > 1 else ""
        rows.append(f"<tr><td>{escape(Path(name).name)}{pieces}</td>"
                    + "".join(f"<td class=\"num\">{escape(c)}</td>" for c in cells) + "</tr>")
    pooled = "".join(f'<td class="num"><b>{escape(_rmse_text(n, result.fit[f"rmse_{n}"]))}</b></td>' for n in names)
    rows.append(f"<tr><td><b>all runs</b></td>{pooled}</tr>")
    return f"<table><tr><th>run</th>{head}</tr>{''.join(rows)}</table>"


def headline(result: IdentifyResult) -> tuple[list[str], bool]:
    """Sentences of the page's box, and whether the model explains the runs."""
    s = result.solver
    sigma = s["residual_sigma"]
    ok = result.explains_run
    lines = [f"The model explains the runs to {sigma:.2f} × the sensor noise." if ok else
             f"The model does not explain the runs: the residual is {sigma:.3g} × the sensor noise (above "
             f"{MISMATCH:g})."]
    lines.append(f"Solver: {s['status']} after {s['iterations']} iterations, {s['wall_s']:.1f} s, {result.drive} "
                 f"drive, {s['n_samples']} samples.")
    if not ok:
        lines.append("The values below describe a misfit: if the cylinder file's valve, dead volumes, mass or sensor "
                     "offsets are guesses, calibrate them (combined-reality calibrate); if an effect the model lacks "
                     "is at work, diagnose it (combined-reality diagnose).")
    return lines, ok


def fit_sections(result: IdentifyResult, runs: Sequence[Run], plots: FitPlots, *, start: dict[str, float],
                 start_label: str, not_determined: dict[str, str]) -> list[tuple[str, str]]:
    """(heading, html) of the fit's sections: estimates, fit per run, traces, errors, friction,
    iterations."""
    sections = [("Estimates", _estimates_html(result, start, start_label, not_determined)
                 + "<p class=\"explain\">The standard deviation is the larger of the Gauss-Newton and the "
                   "cluster-robust one (errors correlated in time).</p>"),
                ("The fit, run by run", _fit_table_html(result, runs)
                 + "<p class=\"explain\">Each run simulated in one piece from its identified initial state with the "
                   "recorded command; a perfect model leaves the sensor noise.</p>")]
    for name, whole, worst in plots.traces:
        sections.append((f"Measured and simulated: {Path(name).name}",
                         img_tag(whole, f"measured and simulated signals of {name}")
                         + "<p class=\"explain\">The second where the position error is largest:</p>"
                         + img_tag(worst, f"the worst second of {name}")))
    total = len({run_name(p) for p in fit_pieces(runs, result)})
    if total > len(plots.traces):
        sections[-1] = (sections[-1][0], sections[-1][1] + f"<p class=\"small\">{total - len(plots.traces)} more "
                                                           "runs enter the tables and the plots below.</p>")
    sections.append(("The errors against time, velocity and position", img_tag(plots.residuals, "errors")
                     + "<p class=\"explain\">Grey: ± 2 × the sensor noise, where pure noise stays 95 % of the time. "
                       "An error that bunches at low speed or at reversals points at friction, one that grows with "
                       "speed at the valve, one that follows the position at the chamber volumes or friction along "
                       "the stroke.</p>"))
    if plots.friction:
        sections.append(("The friction law found", img_tag(plots.friction, "friction against velocity")
                         + "<p class=\"explain\">Grey: the friction each sample implies by Newton's law with the "
                           "measured pressures and the moving mass of the file (noisy: it differentiates the "
                           "position twice); blue: the law found, at that sample's pressure difference.</p>"))
    if plots.iterations:
        sections.append(("The solver", img_tag(plots.iterations, "cost per iteration")))
    return sections


def render_page(title: str, box: list[str], ok: bool, sections: list[tuple[str, str]], footer: str = "") -> str:
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{escape(title)}</title>
<meta name="viewport" content="width=device-width, initial-scale=1"><style>{CSS}</style></head><body>
<h1>{escape(title)}</h1>
<div class="headline{' none' if ok else ''}">{''.join(f'<p>{escape(s)}</p>' for s in box)}</div>
{''.join(f'<h2>{escape(h)}</h2>{body}' for h, body in sections)}
<p class="small">{escape(footer)}</p>
</body></html>
"""


def write_fit_report(result: IdentifyResult, runs: Sequence[Run], path, *, inputs: Sequence[str] = (),
                     not_determined: dict[str, str] | None = None, png_dir=None) -> None:
    """The page of an identification (module docstring), written atomically; with `png_dir`,
    every plot as a PNG there too. `not_determined`: parameter -> what to record for it."""
    plots = fit_plots(result, runs)
    nd = not_determined or {}
    box, ok = headline(result)
    sections = fit_sections(result, runs, plots, start={n: e.initial for n, e in result.params.items()},
                            start_label="start", not_determined=nd)
    if nd:
        items = "".join(f"<li><code>{escape(n)}</code>: {escape(why)}</li>" for n, why in nd.items())
        sections.insert(1, ("Not determined by these runs", f"<ul>{items}</ul>"))
    cyl = result.cylinder
    footer = (f"combined-reality identify; cylinder file {cyl.source or '-'}; runs: "
              + ", ".join(str(p) for p in inputs or [run_name(r) for r in runs]))
    html = render_page(f"Identified: {cyl.name}", box, ok, sections, footer)
    write_html_and_plots(path, html, plots.named(), png_dir)
