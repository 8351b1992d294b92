"""Rerun logging of a diagnosis: VALID as measured, as the nominal model simulates it and
as the model with the verdict's effect does, the residuals before and after, the verdict
and the ranking as text, and where the error lies as bar charts.

    rec = open_recording("save", "diagnosis.rrd")        # combined_reality.visual
    log_diagnosis(diagnosis, rec)

Entity paths (SI units like combined_reality/visual.py; the timeline `time` is VALID's own
clock). `nominal` is the model identified on TRAIN without effects, `verdict` the model
with the verdict's effect (absent when the verdict is `none`):
  diagnosis/position/measured, diagnosis/position/nominal, diagnosis/position/verdict  m
  diagnosis/pressure/p1/measured, .../p1/nominal, .../p1/verdict; p2 likewise         Pa
  diagnosis/residual/x/nominal, diagnosis/residual/x/verdict; p1, p2 likewise          measured - simulated
  diagnosis/command/u                                                                  1
  diagnosis/velocity                                                                   m/s (estimate)
  diagnosis/segment          number of the validation segment (steps at each new start)
  diagnosis/summary          TextDocument (markdown): verdict, inputs, ranking, pair, subsystems, whiteness
  diagnosis/regions/share_of_error, diagnosis/regions/fraction_of_samples
                             BarChart, one bar per region in the order of diagnosis/regions/labels
  diagnosis/regions/labels   TextDocument (markdown): the regions, their shares and RMSE before/after
Simulated values and residuals exist only inside the validation segments.
"""
from __future__ import annotations

import math

import numpy as np
import rerun as rr

from ..report.text import pct, sig, um
from .text import friction_text, headline, params_text, subsystem_value, z_text

__all__ = ["log_diagnosis", "summary_markdown", "regions_markdown"]

ROOT = "diagnosis"
_COLORS = {"measured": (34, 34, 34), "nominal": (31, 119, 180), "verdict": (232, 89, 12)}
_RANK_HEAD = ["| # | effect | shrink x | shrink all | z | significant | x error | parameters | fit |",
              "|---|---|---|---|---|---|---|---|---|"]


def _md(s: str) -> str:
    """Escape the characters markdown tables and emphasis would eat."""
    return str(s).replace("|", "\\|").replace("*", "\\*").replace("_", "\\_")


def summary_markdown(d) -> str:
    """The verdict, the inputs, the ranking (and pair), the subsystem split and the
    whiteness test as markdown."""
    b = d.baseline
    lines = ["# Diagnosis: " + _md(d.cylinder.name), ""]
    lines += [" ".join(headline(d, strong=lambda s: f"**{_md(s)}**", esc=_md)), ""]
    src = lambda r: _md(r.source) if getattr(r, "source", None) else "in memory"  # noqa: E731
    lines += [
        "## Inputs", "",
        f"- cylinder: {_md(d.cylinder.name)} ({_md(d.cylinder.source) if d.cylinder.source else 'in memory'})",
        f"- TRAIN: {src(d.train)}, {d.train.duration:.2f} s",
        f"- VALID: {src(d.valid)}, {d.valid.duration:.2f} s, {len(d.base_validation.segments)} segments of about "
        f"{sig(d.options.horizon_s)} s",
        f"- nominal friction (TRAIN): {_md(friction_text(b.get('friction') or {}, b.get('friction_std') or {}))}",
        f"- nominal model on VALID: x {um(b.get('rmse_x_validation'))}, "
        f"all outputs {sig(b.get('normalized_rms'))} x the sensor noise",
        "", "## Ranking", "", *_RANK_HEAD,
    ]

    def row(c, rank) -> str:
        fit = _md(c.status) + (f": {_md(c.error)}" if c.error else "")
        name = f"**{_md(c.effect)}**" if c.effect == d.verdict else _md(c.effect)
        return (f"| {rank} | {name} | {pct(c.shrink)} | {pct(c.shrink_all)} | {z_text(c.z)} | "
                f"{'yes' if c.significant else 'no'} | {um(c.rmse_x_validation)} | "
                f"{_md(params_text(c, '; ', bounds=True)) or '-'} | {fit} |")

    lines += [row(c, i + 1) for i, c in enumerate(d.ranking)]
    if d.pair is not None:
        lines += ["", "Best pair (shrink and z against the nominal model; significant = better than the verdict "
                  "alone):", "", *_RANK_HEAD, row(d.pair, "pair")]
    if d.subsystems:
        lines += ["", "## Subsystems (nominal model)", "", "| part | RMSE | floor | share of the excess |",
                  "|---|---|---|---|"]
        for r in d.subsystems:
            if "error" in r:
                lines.append(f"| {_md(r.get('subsystem', '?'))} | failed: {_md(r['error'])} | | |")
                continue
            rmse, floor = subsystem_value(r)
            lines.append(f"| {_md(r.get('subsystem', '?'))} | {rmse} | {floor} | "
                         + ("within noise" if r.get("within_noise") else pct(r.get("share_of_error"))) + " |")
    w = d.whiteness or {}
    if w:
        lines += ["", "## Whiteness of the nominal model's position error", "",
                  f"Ljung-Box Q {sig(w.get('ljung_box_q'))} over {w.get('lags', '?')} lags, p = "
                  f"{sig(w.get('p_value'), 2)}, lag-1 autocorrelation {sig(w.get('acf_1'), 2)}: "
                  + ("random like noise." if w.get("white") else "structured (p < 0.001): the model misses something.")]
    return "\n".join(lines) + "\n"


def regions_markdown(d) -> str:
    has_after = d.best is not None
    lines = ["Where the nominal model's position error lies (bar i of the charts = row i):", "",
             "| bar | region | share of error | share of samples | concentration | RMSE"
             + (" before -> after |" if has_after else " |"),
             "|---|---|---|---|---|---|"]
    for i, r in enumerate(d.regions or []):
        rm = um(r.get("rmse_x"))
        if has_after and "rmse_x_after" in r:
            rm += f" -> {um(r['rmse_x_after'])}"
        c = r.get("concentration", math.nan)
        lines.append(f"| {i} | {_md(r.get('where', '?'))} | {pct(r.get('share_of_error'))} | "
                     f"{pct(r.get('fraction_of_samples'))} | {c:.2f} | {rm} |")
    return "\n".join(lines) + "\n"


def _send(rec, path: str, t: np.ndarray, values: np.ndarray) -> None:
    ok = np.isfinite(values)
    if not ok.any():
        return
    rec.send_columns(path, indexes=[rr.TimeColumn("time", duration=t[ok])],
                     columns=rr.Scalars.columns(scalars=np.asarray(values[ok], dtype=float)))


def _style(rec, path: str, name: str, kind: str) -> None:
    rec.log(path, rr.SeriesLines(names=name, colors=_COLORS[kind]), static=True)


def log_diagnosis(diagnosis, rec: rr.RecordingStream) -> None:
    """Log `diagnosis` to the recording `rec` (see the module docstring for the paths)."""
    d = diagnosis
    run, base = d.valid, d.base_validation
    best = d.best
    bestval = best.validation if best is not None else None
    t = np.asarray(run.t, dtype=float)
    effect = d.verdict

    rec.log(f"{ROOT}/summary", rr.TextDocument(summary_markdown(d), media_type=rr.MediaType.MARKDOWN), static=True)

    models = [("nominal", "nominal model", base)]
    if bestval is not None:
        models.append(("verdict", f"with {effect}", bestval))
    for out in base.outputs:
        path = f"{ROOT}/position" if out == "x" else f"{ROOT}/pressure/{out}"
        _style(rec, f"{path}/measured", f"{out} measured", "measured")
        _send(rec, f"{path}/measured", t, getattr(run, out))
        for key, label, val in models:
            if out not in val.outputs:
                continue
            i = list(val.outputs).index(out)
            _style(rec, f"{path}/{key}", f"{out} {label}", key)
            _send(rec, f"{path}/{key}", t, val.simulated[i])
            _style(rec, f"{ROOT}/residual/{out}/{key}", f"{out} residual, {label}", key)
            _send(rec, f"{ROOT}/residual/{out}/{key}", t, val.residual[i])
    _send(rec, f"{ROOT}/command/u", t, run.u)
    _send(rec, f"{ROOT}/velocity", t, np.asarray(d.velocity, dtype=float))
    seg = np.full(run.n, np.nan)
    for k, (a, b) in enumerate(base.segments):
        seg[a:b] = k
    _send(rec, f"{ROOT}/segment", t, seg)

    regs = list(d.regions or [])
    if regs:
        rec.log(f"{ROOT}/regions/share_of_error",
                rr.BarChart(np.array([r.get("share_of_error", math.nan) for r in regs], dtype=float),
                            color=(201, 42, 42)), static=True)
        rec.log(f"{ROOT}/regions/fraction_of_samples",
                rr.BarChart(np.array([r.get("fraction_of_samples", math.nan) for r in regs], dtype=float),
                            color=(173, 181, 189)), static=True)
        rec.log(f"{ROOT}/regions/labels", rr.TextDocument(regions_markdown(d), media_type=rr.MediaType.MARKDOWN),
                static=True)
