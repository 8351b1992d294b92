"""The report of a calibration: one self-contained HTML page. Beside what identify's page
shows (the fit of every run, its errors, the friction law), what calibration adds: the
values against the cylinder file's, the valve characteristic found per direction with its
band (± 2 standard deviations) and the openings the runs did not reach, the stages, the
calibrated model on VALID (a run no fit saw), and what the runs could not determine with
what to record for it.

    write_calibration_report(cal, start, runs, "calibration.html", validation=val)
"""
from __future__ import annotations

import math
from dataclasses import replace
from typing import Sequence

import numpy as np

from sim.cylinder import OPENING_GRID, Cylinder, flow_levels_at

from ..files import Run, run_name
from ..identify import Validation
from ..identify.report import C_MEAS, C_P2, C_SIM, C_SIM2, fit_plots, fit_sections, render_page
from ..report.figures import new_figure, png_bytes
from ..report.html import escape, img_tag, write_html_and_plots
from ..report.text import sig, um
from .identifiability import MIN_COVERAGE, grouped
from .stages import Calibration, validation_figures

__all__ = ["write_calibration_report"]

_DIRECTIONS = (("extend", "u > 0, extending"), ("retract", "u < 0, retracting"))


def _curve(levels: tuple[float, ...], overlap: float, u: np.ndarray) -> np.ndarray:
    """C / sonic_conductance at the commands |u| (closed within the overlap)."""
    s = np.clip((u - overlap) / (1.0 - overlap), 0.0, 1.0)
    return np.where(u <= overlap, 0.0, np.array(flow_levels_at(OPENING_GRID, tuple(levels), s)))


def _valve_figure(cal: Calibration, start: Cylinder):
    """Per direction: the characteristic found with its ± 2 std band (through the levels ± 2
    std), the file's, and the openings too few samples reached (shaded)."""
    v, v0 = cal.cylinder.valve, start.valve
    params = cal.result.params
    cov = cal.identifiability.coverage
    u = np.linspace(0.0, 1.0, 401)
    fig = new_figure(10, 3.6)
    axes = fig.subplots(1, 2, sharey=True)
    for ax, (d, label) in zip(axes, _DIRECTIONS):
        levels = getattr(v, f"flow_{d}")
        overlap = getattr(v, f"overlap_{d}")
        std = [params[f"flow_{d}_{k + 1}"].std if f"flow_{d}_{k + 1}" in params else 0.0 for k in range(len(levels))]
        std = [s if math.isfinite(s) else 0.0 for s in std]
        lo = tuple(max(a - 2 * s, 0.0) for a, s in zip(levels, std))
        hi = tuple(a + 2 * s for a, s in zip(levels, std))
        lo = tuple(np.maximum.accumulate(lo))  # a characteristic never falls
        hi = tuple(np.maximum.accumulate(hi))
        ax.fill_between(u, _curve(lo, overlap, u), _curve(hi, overlap, u), color=C_SIM, alpha=0.2, lw=0,
                        label="± 2 standard deviations")
        ax.plot(u, _curve(levels, overlap, u), color=C_SIM, lw=1.6, label="calibrated")
        ax.plot(u, _curve(getattr(v0, f"flow_{d}"), getattr(v0, f"overlap_{d}"), u), color=C_MEAS, lw=1.0, ls="--",
                label="the cylinder file's")
        # openings (beyond the overlap) that too few samples reached: the curve follows its neighbours there
        first = True
        for k, (a, b) in enumerate(zip((0.0, *OPENING_GRID[:-1]), OPENING_GRID)):
            if cov.get(f"flow_{d}_{k + 1}", 1.0) < MIN_COVERAGE:
                ua, ub = overlap + a * (1 - overlap), overlap + b * (1 - overlap)
                ax.axvspan(ua, ub, color="#ffe8cc", zorder=0, lw=0,
                           label="not reached by the runs (follows its neighbours)" if first else None)
                first = False
        if overlap > 0:
            ax.axvline(overlap, color=C_SIM2, lw=0.8, ls=":", label=f"overlap {overlap:.3f}")
        ax.set_title(f"{d} ({label})", fontsize=9)
        ax.set_xlabel("|command| (fraction of full opening)")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", fontsize=8, framealpha=0.9)
    axes[0].set_ylabel("C / sonic_conductance")
    return fig


def _validation_figure(val: Validation, valid: Run, noise_x: float):
    """VALID: measured and simulated (each segment from its own fitted start), and the position
    error."""
    o = list(val.outputs)
    t = valid.t - valid.t[0]
    fig = new_figure(10, 6.4)
    ax_x, ax_p, ax_r = fig.subplots(3, 1, sharex=True)
    k = max(1, len(t) // 8000)
    sim = {n: val.simulated[o.index(n)] for n in o}
    ax_x.plot(t[::k], valid.x[::k] * 1e3, color=C_MEAS, lw=0.9, label="measured")
    ax_x.plot(t[::k], sim["x"][::k] * 1e3, color=C_SIM, lw=0.9, ls="--", label="calibrated model")
    ax_x.set_ylabel("position (mm)")
    for n, cm, cs in (("p1", C_MEAS, C_SIM), ("p2", C_P2, C_SIM2)):
        ax_p.plot(t[::k], getattr(valid, n)[::k] / 1e3, color=cm, lw=0.9, label=f"{n} measured")
        ax_p.plot(t[::k], sim[n][::k] / 1e3, color=cs, lw=0.9, ls="--", label=f"{n} calibrated model")
    ax_p.set_ylabel("pressure (kPa abs.)")
    r = val.residual[o.index("x")] * 1e6
    ax_r.axhspan(-2 * noise_x * 1e6, 2 * noise_x * 1e6, color="#dddddd", zorder=0,
                 label=f"± 2 × sensor noise ({sig(noise_x * 1e6, 2)} um)")
    ax_r.plot(t[::k], r[::k], color=C_SIM, lw=0.7, label=f"measured − simulated (RMSE {um(val.rmse('x'))})")
    ax_r.axhline(0, color="#555555", lw=0.5)
    ax_r.set_ylabel("position error (um)")
    for a, _b in val.segments[1:]:
        for ax in (ax_x, ax_p, ax_r):
            ax.axvline(t[a], color="#999999", lw=0.5, ls=":", zorder=0)
    for ax in (ax_x, ax_p, ax_r):
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize=8, framealpha=0.9, ncols=4)
    ax_r.set_xlabel("time on VALID (s); dotted: starts of the segments, each simulated from its own fitted start")
    return fig


def _stages_html(cal: Calibration) -> str:
    def seen(s: dict) -> str:  # the data a stage saw, where the stages started from a share of it
        return f" (on {s['data_s']:.0f} s of the data)" if "data_s" in s else ""

    rows = "".join(f"<tr><td>{escape(s['stage'] + seen(s))}</td><td>{escape(s['drive'])}</td>"
                   f"<td>{escape(s['status'])}</td>"
                   f"<td class=\"num\">{s['iterations']}</td><td class=\"num\">{s['wall_s']:.1f} s</td>"
                   f"<td class=\"num\">{s['residual_sigma']:.3g} ×</td></tr>" for s in cal.stages)
    return (f"<table><tr><th>stage</th><th>driven by</th><th>status</th><th>iterations</th><th>time</th>"
            f"<th>residual (sensor noise)</th></tr>{rows}</table><p class=\"explain\">The piston's force balance "
            "driven by the measured pressures and the valve and chambers driven by the measured motion, then the "
            "force balance once more through the command-driven model with that valve, start the whole model, driven "
            "by the command alone.</p>")


def _identifiability_html(cal: Calibration) -> str:
    ident = cal.identifiability
    parts = []
    if ident.undetermined:
        items = "".join(f"<li><code>{escape(u['name'])}</code>: {escape(u['why'])}; to determine it, record "
                        f"{escape(u['advice'])}.</li>" for u in grouped(ident.undetermined))
        parts.append(f"<p>Not determined by these runs, and what to record for it:</p><ul>{items}</ul>")
    if ident.correlated:
        items = "".join(f"<li><code>{escape(c['a'])}</code> and <code>{escape(c['b'])}</code> (correlation "
                        f"{c['r']:+.2f})</li>" for c in ident.correlated)
        parts.append("<p>Not separated by these runs (their estimates trade off against each other):</p>"
                     f"<ul>{items}</ul>")
    if not parts:
        parts.append("<p>Every calibrated parameter is determined by these runs.</p>")
    if ident.effects:
        items = "".join(f"<li><code>{escape(e['effect'])}</code> from {escape(e['from'])}: {escape(e['found'])}; "
                        f"record {escape(e['needs'])}.</li>" for e in ident.effects)
        parts.append("<p>Effects these runs hold too little of what tells them from a calibrated quantity:</p>"
                     f"<ul>{items}</ul>")
    return "".join(parts)


def write_calibration_report(cal: Calibration, start: Cylinder, runs: Sequence[Run], path, *,
                             valid: Run | None = None, validation: Validation | None = None,
                             inputs: Sequence[str] = (), png_dir=None, figures: dict | None = None) -> None:
    """The page of a calibration (module docstring), written atomically; with `png_dir`, every
    plot as a PNG there too. `figures`: validation_figures of `validation`, where made already."""
    result = cal.result
    plots = fit_plots(result, runs)
    named = plots.named()
    named["valve"] = png_bytes(_valve_figure(cal, start))
    s = result.solver
    ok = result.explains_run
    box = [f"The calibrated model explains the runs to {s['residual_sigma']:.2f} × the sensor noise." if ok and
           not cal.misfit else (f"Not explained: {cal.misfit}." if ok else
           f"Even calibrated, the model does not explain the runs: the residual is {s['residual_sigma']:.3g} × the "
           "sensor noise; an effect the model lacks is at work (combined-reality diagnose --calibrate finds it and "
           "calibrates with it).")]
    if validation is not None:
        box.append(f"On VALID, a run no fit saw: {validation.normalized_rms():.2f} × the sensor noise (position RMSE "
                   f"{um(validation.rmse('x'))}).")
        if figures is None and valid is not None:
            figures = validation_figures(cal.cylinder, valid, val=validation, train=runs)
        if figures and figures["caveat"]:
            box.append(figures["caveat"])
    lacking = grouped(cal.identifiability.undetermined)
    if cal.start_share is not None:
        box.append(f"The stages started from {cal.start_share[0]:.0f} s of the {cal.start_share[1]:.0f} s of data "
                   "(stretches spread over it); the whole model was then fitted to all of it.")
    box.append(f"Solver: {s['status']}; {cal.wall_s:.0f} s in all. "
               + (f"What these runs could not determine: {', '.join(u['name'] for u in lacking)} (below, with what to "
                  "record)." if lacking else "Every calibrated parameter is determined by these runs."))
    nd = {u["name"]: f"not determined: {u['why']}" for u in cal.identifiability.undetermined}
    flow = {n: e for n, e in result.params.items() if n.startswith("flow_")}
    shown = replace(result, params={n: e for n, e in result.params.items() if n not in flow})  # flow: the curve
    sections = fit_sections(shown, runs, plots, start={n: start.value(n) for n in result.params},
                            start_label="the file's value", not_determined=nd)
    sections[0] = ("The calibrated values against the cylinder file's", sections[0][1])
    sections.insert(1, ("The valve characteristic per direction", img_tag(named["valve"], "valve characteristic")
                        + f"<p class=\"explain\">The conductance of each path over the file's sonic conductance "
                          f"({start.valve.sonic_conductance:.4g} m³/(s·Pa)) against the command; the band is ± 2 "
                          f"standard deviations of the {len(flow)} levels calibrated. Shaded: openings that fewer than "
                          f"{MIN_COVERAGE:.1%} of the samples reached.</p>"))
    sections.insert(2, ("Not determined, and what to record", _identifiability_html(cal)))
    sections.insert(3, ("The stages", _stages_html(cal)))
    if valid is not None and validation is not None:
        named["validation"] = png_bytes(_validation_figure(validation, valid, cal.cylinder.sensors.position_noise))
        sections.append((f"The calibrated model on VALID ({run_name(valid)})",
                         img_tag(named["validation"], "validation traces")
                         + "<p class=\"explain\">VALID was not fitted: each segment is simulated from an initial "
                           "state fitted to it, with the calibrated parameters.</p>"))
    footer = (f"combined-reality calibrate; cylinder file {start.source or '-'}; runs: "
              + ", ".join(str(p) for p in inputs or [run_name(r) for r in runs]))
    html = render_page(f"Calibrated: {cal.cylinder.name}", box, ok, sections, footer)
    write_html_and_plots(path, html, named, png_dir)
