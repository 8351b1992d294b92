"""The comparison report of a batch identification: one self-contained HTML file (inline
CSS, plots as embedded PNG) that compares many cylinders, after seed 004 ("Study of the
friction behavior in industrial pneumatic actuators").

    write_batch_report(rows, "report.html", png_dir="plots/")

`rows` are the rows of the batch's results.csv as dicts, one per cylinder (values float,
int, str or None; a missing key, None, "" or NaN means not available; numbers may come as
strings straight from the CSV). Contents: a headline (how many cylinders, identified,
failed) with the failed rows and their errors; the cylinders' data; the friction-velocity
maps of every identified cylinder on one plot (seed 004 Fig. 7) with the low-speed
(Stribeck) region apart; the static friction parameters per direction (seed 004 Table 3)
and, for simulated cylinders with a known truth, the relative errors; the efficiency
factor m = friction / (p A) (seed 004 Eq. 1) against the catalogues' rules of thumb; the
fit quality. Inputs are SI; the report shows mm/s, um, kPa and bar.

Curves come from the models' one definition (`FRICTION_MODELS[family].static_force`), the
nominal model's is Fc + Fv v + kp |p1 - p2| (opposing motion). The HTML helpers and the
figure helpers are the single-cylinder report's (`diagnose_report`).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from sim.cylinder import PARAMETERS
from sim.friction_models import DIRECTIONS, FRICTION_MODELS

from ..friction import FIT_SPECS
from ..report.figures import new_figure, png_bytes, wrap_lines
from ..report.html import CSS, escape, img_tag, write_html_and_plots
from ..report.text import format_value, sig

__all__ = ["write_batch_report", "render_batch_report", "friction_curve", "efficiency", "REF_SPEED",
           "RULE_OF_THUMB", "CATALOGUE_FACTORS"]

REF_SPEED = 0.2  # m/s: the speed at which the efficiency factor is compared
RULE_OF_THUMB = (0.05, 0.20)  # the catalogues' range of m (seed 004 section 2)
# seed 004 section 2: what the catalogues and books quote for m
CATALOGUE_FACTORS = (("Festo (1996)", 0.10, 0.10), ("Parker (1998)", 0.20, 0.20),
                     ("Bollmann (1997)", 0.05, 0.10), ("Pinches and Callear (1997)", 0.02, 0.06))
REL_TOL = 0.05  # relative error against the truth beyond which a parameter is highlighted
_DEFAULT_MAX_SPEED = 0.5  # m/s: velocity range of a curve whose fastest speed is unknown
_DEFAULT_ATMOSPHERE = 1.013e5  # Pa, as in configs/
_TINY_SPEED = 1e-9  # m/s: "at rest, about to slide" for the breakaway force
_DIRS = tuple((d, sfx, sign) for d, (sfx, sign) in DIRECTIONS.items())  # (direction, suffix, sign of v)
# seed 004 Table 3: quantity, heading, unit shown, factor SI -> shown
_TABLE3 = (("Fs", "F<sub>s</sub> static", "N", 1.0), ("Fc", "F<sub>c</sub> Coulomb", "N", 1.0),
           ("B", "B viscous", "N s/m", 1.0), ("vs", "v<sub>s</sub> Stribeck", "mm/s", 1e3))
_NOMINAL_AS = {"Fc": "Fc", "B": "Fv"}  # Table 3 quantity -> nominal parameter (one value, both directions)
_ALIASES = {"B": ("Fv",)}  # Table 3 quantity -> its other names in the family
_C_EXT, _C_RET = "#1f77b4", "#e8590c"
_RULE_TEXT = f"{RULE_OF_THUMB[0]:.2f}–{RULE_OF_THUMB[1]:.2f}"
_TOL_TEXT = f"{100 * REL_TOL:g} %"


# ------------------------------------------------------------------ reading rows

def _num(row: Mapping[str, Any], key: str) -> float | None:
    """A finite number or None (missing, None, "", NaN, text that is no number)."""
    v = row.get(key)
    if v is None or isinstance(v, bool):
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def _text(row: Mapping[str, Any], key: str) -> str:
    v = row.get(key)
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return ""
    return str(v).strip()


@dataclass(eq=False)  # hashed by identity: keys the efficiencies of a report
class _Cyl:
    """One row, read: its model's full parameter vector and what the row gave of it."""

    row: Mapping[str, Any]
    name: str
    status: str
    model: str
    family: str | None  # "nominal", a FRICTION_MODELS key, or None (model unknown)
    names: tuple[str, ...] = ()  # the model's parameters, in its order
    units: dict[str, str] = field(default_factory=dict)
    values: dict[str, float] = field(default_factory=dict)  # complete: row, else fixed by the spec, else default
    given: set[str] = field(default_factory=set)  # parameters the row gives
    fixed: set[str] = field(default_factory=set)  # held fixed by the fit spec (not in the row)

    def num(self, key: str) -> float | None:
        return _num(self.row, key)

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def drawable(self) -> bool:
        return self.family is not None and bool(self.given)

    @property
    def defaulted(self) -> list[str]:
        return [n for n in self.names if n not in self.given and n not in self.fixed]

    def std(self, p: str) -> float | None:
        s = self.num(f"{p}_std")
        return s if s is not None and s > 0 else None

    @property
    def max_speed(self) -> float:
        v = self.num("max_speed")
        return v if v is not None and v > 0 else _DEFAULT_MAX_SPEED

    @property
    def needs(self) -> tuple[str, ...]:
        """The operating conditions its static curve takes."""
        if self.family == "nominal":
            return ("dp",)
        return FRICTION_MODELS[self.family].CONDITIONS if self.family else ()

    def conditions(self) -> dict[str, float]:
        """Operating conditions of the static curve: dp, pc from the runs' means (0 when
        not available), load = the model's Fn."""
        cond = {}
        needs = self.needs
        for key, col in (("dp", "mean_dp"), ("pc", "mean_pc")):
            if key in needs:
                cond[key] = self.num(col) or 0.0
        if "load" in needs:
            cond["load"] = self.values.get("Fn", 0.0)
        return cond

    def missing_conditions(self) -> list[str]:
        if self.family == "nominal" and not self.values.get("kp"):
            return []
        return [col for key, col in (("dp", "mean_dp"), ("pc", "mean_pc"))
                if key in self.needs and self.num(col) is None]

    def supply_gauge(self) -> float | None:
        """supply_pressure - atmosphere (Pa; the default atmosphere when the row has none)."""
        ps, pa = self.num("supply_pressure"), self.num("atmosphere")
        return ps - (pa if pa is not None else _DEFAULT_ATMOSPHERE) if ps is not None else None


def _read(row: Mapping[str, Any], i: int) -> _Cyl:
    name = _text(row, "name") or f"row {i + 1}"
    model = _text(row, "model")
    c = _Cyl(row, name, _text(row, "status").lower(), model, None)
    if model == "nominal":
        c.family, c.names = "nominal", ("Fc", "Fv", "kp")
        c.units = {n: PARAMETERS[n].unit for n in c.names}
        defaults = {n: 0.0 for n in c.names}
    elif model in FIT_SPECS:
        spec = FIT_SPECS[model]
        cls = FRICTION_MODELS[spec.family]
        c.family, c.names = spec.family, tuple(cls.PARAMS)
        c.units = {n: info.unit for n, info in cls.PARAMS.items()}
        defaults = cls.defaults()
        for base, val in spec.fixed.items():
            for n in (base, f"{base}_pos", f"{base}_neg"):
                if n in cls.PARAMS:
                    defaults[n] = float(val)
                    c.fixed.add(n)
    else:
        return c
    c.values = {n: defaults[n] for n in c.names}
    for n in c.names:
        v = c.num(n)
        if v is not None:
            c.values[n] = v
            c.given.add(n)
    c.fixed -= c.given
    return c


# ------------------------------------------------------------------ the curves, the factor

def _curve(c: _Cyl, v) -> np.ndarray:
    v = np.asarray(v, float)
    cond = c.conditions()
    if c.family == "nominal":
        q = c.values
        return np.sign(v) * (q["Fc"] + q["kp"] * cond["dp"]) + q["Fv"] * v
    cls = FRICTION_MODELS[c.family]
    return np.asarray(cls.static_force(v, [c.values[n] for n in cls.PARAMS], **cond), float)


def friction_curve(row: Mapping[str, Any], v) -> np.ndarray:
    """The static friction F(v) (N, opposing motion: the sign of v) of one results row, at
    the row's mean pressure conditions (mean_dp, mean_pc; 0 when not given); parameters the
    row lacks at the model's defaults. ValueError when the row's model is unknown or the
    row gives none of its parameters."""
    c = _read(row, 0)
    if c.family is None:
        raise ValueError(f"{c.name}: unknown friction model '{c.model}'")
    if not c.given:
        raise ValueError(f"{c.name}: the results give none of the parameters of model {c.model}")
    return _curve(c, v)


@dataclass
class _Efficiency:
    pA: float | None  # N: the piston force p A
    m_break: dict[str, float | None]  # direction -> m at breakaway
    m_ref: dict[str, float | None]  # direction -> m at the reference speed
    extrapolated: bool  # the reference speed lies beyond the fastest speed of the runs
    atmosphere_assumed: bool


def _breakaway(c: _Cyl, sign: float) -> float:
    """|friction| at rest, about to slide: Fs (Fc where the model has no Fs; the pressure and
    load terms at the row's conditions)."""
    if c.family == "threlfall":  # its curve rises from 0: the plateau Fc is its breakaway
        return c.values[f"Fc_{'pos' if sign > 0 else 'neg'}"]
    return abs(float(_curve(c, sign * _TINY_SPEED)))


def _efficiency(c: _Cyl, ref_speed: float) -> _Efficiency:
    bore, p = c.num("bore"), c.supply_gauge()
    pA = p * math.pi * bore ** 2 / 4 if bore is not None and bore > 0 and p is not None and p > 0 else None
    ok = pA is not None and c.drawable
    mb = {d: _breakaway(c, sign) / pA if ok else None for d, _sfx, sign in _DIRS}
    mr = {d: abs(float(_curve(c, sign * ref_speed))) / pA if ok else None for d, _sfx, sign in _DIRS}
    ms = c.num("max_speed")
    return _Efficiency(pA, mb, mr, ms is not None and ms < ref_speed, c.num("atmosphere") is None and pA is not None)


def _efficiencies(cs: Sequence[_Cyl], ref_speed: float) -> dict[_Cyl, _Efficiency]:
    """The efficiency of every identified cylinder that has a curve, in batch order: computed
    once per report (the plots, the headline and the table read it)."""
    return {c: _efficiency(c, ref_speed) for c in cs if c.ok and c.drawable}


def efficiency(row: Mapping[str, Any], ref_speed: float = REF_SPEED) -> dict[str, float | None]:
    """The efficiency factor m = friction / (p A) of seed 004 Eq. 1 for one results row:
    p the working pressure (supply gauge: supply_pressure - atmosphere), A the bore area.
    Keys `breakaway_extension`, `breakaway_retraction` (Fs, or Fc where the model has no
    Fs) and `extension`, `retraction` at `ref_speed`; None where not available."""
    c = _read(row, 0)
    e = _efficiency(c, ref_speed)
    return {**{f"breakaway_{d}": e.m_break[d] for d, _s, _g in _DIRS}, **{d: e.m_ref[d] for d, _s, _g in _DIRS}}


# ------------------------------------------------------------------ numbers for people

_NA = '<span class="no">n/a</span>'
_DASH = '<span class="no">—</span>'


def _num_cell(v: float | None, k: float = 1.0, digits: int = 3) -> str:
    return f'<td class="num">{sig(v * k, digits) if v is not None else _NA}</td>'


def _mpl(s: str, width: int = 0) -> str:
    """Text for matplotlib: no mathtext from '$', no label hidden by a leading '_'."""
    if width and len(s) > width:
        s = s[:width - 1] + "…"
    s = s.replace("$", r"\$")
    return " " + s if s.startswith("_") else s


def _label(c: _Cyl, width: int = 0) -> str:
    """`name (model)` for a legend, the name shortened to `width` characters."""
    return _mpl(c.name, width) + f" ({_mpl(c.model)})"


def _wrapped(s: str, width: int = 30, lines: int = 2) -> str:
    """A name on at most `lines` lines of about `width` characters (shortened beyond)."""
    parts = wrap_lines(s, width)
    if len(parts) > lines:
        parts = parts[:lines]
        parts[-1] = parts[-1][:width - 1] + "…"
    return "\n".join(_mpl(p) for p in parts)


def _table3_param(c: _Cyl, q: str, sfx: str) -> str | None:
    """The model's parameter for Table 3 quantity q in direction sfx, or None (no such)."""
    if c.family == "nominal":
        return _NOMINAL_AS.get(q)
    for name in (q, *_ALIASES.get(q, ())):  # cv_dp writes the viscous coefficient as Fv, as the nominal law
        n = f"{name}_{sfx}"
        if n in c.names:
            return n
    return None


def _param_text(c: _Cyl, p: str, k: float = 1.0) -> str:
    """A Table 3 cell: value ± std (in the table's unit, via factor k), or n/a."""
    if p in c.fixed:
        return f"{format_value(c.values[p] * k, None, '')} (fixed)"
    if p not in c.given:
        return _NA
    s = c.std(p)
    return escape(format_value(c.values[p] * k, s * k if s is not None else None, ""))


# ------------------------------------------------------------------ plots

def _speeds(vmax: float, n: int = 240) -> np.ndarray:
    """0 < v <= vmax, dense at low speed (Stribeck) and evenly spread above."""
    return np.unique(np.concatenate([np.geomspace(1e-6, vmax, n), np.linspace(0.0, vmax, n + 1)[1:]]))


def _style(i: int) -> dict:
    from matplotlib import colormaps

    cols = colormaps["tab10"].colors
    return {"color": cols[i % 10], "ls": ("-", "--", "-.", ":")[(i // 10) % 4]}


def _low_speed_limit(cs: Sequence[_Cyl]) -> float:
    """The upper end of the low-speed panels: 5 x the largest velocity scale of the models
    (Stribeck velocity, stick band, Threlfall's ve), between 20 and 100 mm/s."""
    scales = [c.values[n] for c in cs if c.family in FRICTION_MODELS
              for s in FRICTION_MODELS[c.family].SCALES for n in (f"{s}_pos", f"{s}_neg") if n in c.values]
    top = 5 * max(scales) if scales else 0.05
    return float(min(max(top, 0.02), 0.1))


def _plot_maps(cs: Sequence[_Cyl]):
    """seed 004 Fig. 7: every curve over -max_speed..max_speed (retraction at negative v and
    F); below, the low-speed region per direction on a logarithmic speed axis."""
    v_low = _low_speed_limit(cs)
    fig = new_figure(11, 7.6 + 0.21 * math.ceil(len(cs) / 2))
    top, bottom = fig.subfigures(2, 1, height_ratios=[1.25, 1])
    ax = top.subplots()
    axe, axr = bottom.subplots(1, 2, sharey=True)
    low_max = 0.0
    for i, c in enumerate(cs):
        st = _style(i)
        vmax = c.max_speed
        for _d, _sfx, sign in _DIRS:
            v = sign * _speeds(vmax)
            ax.plot(v * 1e3, _curve(c, v), lw=1.4, label=_label(c, 56) if sign > 0 else None, **st)
            vl = sign * _speeds(min(v_low, vmax), 300)
            F = np.abs(_curve(c, vl))
            # the axis spans the breakaway region; curves that climb beyond leave it (the map above shows them)
            low_max = max(low_max, float(np.max(F[np.abs(vl) <= v_low / 5])))
            (axe if sign > 0 else axr).plot(np.abs(vl) * 1e3, F, lw=1.4, **st)
    ax.axhline(0, color="#555555", lw=0.6)
    ax.axvline(0, color="#555555", lw=0.6)
    ax.grid(alpha=0.3)
    ax.set_xlabel("velocity v (mm/s): extension > 0, retraction < 0")
    ax.set_ylabel("friction force F (N)")
    ax.set_title("Static friction-velocity maps (as seed 004 Fig. 7)", fontsize=10)
    ax.text(0.99, 0.03, "extension →", transform=ax.transAxes, ha="right", va="bottom", fontsize=9, color="#555555")
    ax.text(0.01, 0.97, "← retraction", transform=ax.transAxes, ha="left", va="top", fontsize=9, color="#555555")
    for a, word in ((axe, "extension"), (axr, "retraction")):
        a.set_xscale("log")
        a.set_xlim(0.1, v_low * 1e3)
        a.set_ylim(0, 1.3 * low_max if low_max > 0 else 1)
        a.grid(alpha=0.3, which="both")
        a.set_xlabel(f"speed |v| (mm/s, log scale), {word}")
        a.set_title(f"Low speed, {word}: the Stribeck region", fontsize=10)
    axe.set_ylabel("friction |F| (N)")
    ncol = 2 if len(cs) > 3 else 1
    fig.legend(loc="outside lower center", ncols=ncol, fontsize=8, frameon=False)
    return fig


def _plot_efficiency(cs: Sequence[_Cyl], effs: Sequence[_Efficiency], ref_speed: float):
    n = len(cs)
    fig = new_figure(11, 2.3 + 0.45 * n)
    axes = fig.subplots(1, 2, sharey=True)
    y = np.arange(n)[::-1]
    top = max([RULE_OF_THUMB[1] * 1.25] + [v * 1.1 for e in effs for m in (e.m_break, e.m_ref)
                                             for v in m.values() if v is not None])
    for ax, which, title in ((axes[0], "m_break", "at breakaway (Fs; Fc where the model has none)"),
                             (axes[1], "m_ref", f"at {sig(ref_speed * 1e3)} mm/s")):
        first = ax is axes[0]
        ax.axvspan(*RULE_OF_THUMB, color="#d3f9d8", zorder=0,
                   label=f"catalogue rule of thumb {_RULE_TEXT}" if first else None)
        ax.axvspan(0.02, 0.06, facecolor="none", edgecolor="#adb5bd", hatch="///", lw=0, zorder=0,
                   label="Pinches and Callear 0.02–0.06" if first else None)
        ax.axvline(0.10, color="#2b8a3e", ls="--", lw=1, label="Festo 0.10" if first else None)
        ax.axvline(0.20, color="#2b8a3e", ls=":", lw=1.2, label="Parker ≈ 0.20" if first else None)
        for (d, _s, _g), dy, col in zip(_DIRS, (0.2, -0.2), (_C_EXT, _C_RET)):
            vals = [getattr(e, which)[d] for e in effs]
            h = [v if v is not None else 0.0 for v in vals]
            hatch = ["xx" if which == "m_ref" and e.extrapolated else None for e in effs]
            bars = ax.barh(y + dy, h, height=0.38, color=col, label=d if first else None)
            for b, ht, v in zip(bars, hatch, vals):
                if ht:
                    b.set_hatch(ht)
                    b.set_edgecolor("white")
                if v is None:
                    ax.text(0.002, b.get_y() + b.get_height() / 2, "n/a", va="center", fontsize=7, color="#868e96")
        ax.set_xlim(0, top)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("efficiency factor m")
        ax.grid(axis="x", alpha=0.3)
    axes[0].set_yticks(y, [_wrapped(c.name) for c in cs], fontsize=8)
    axes[0].set_ylim(-0.6, n - 0.4)
    fig.suptitle("Efficiency factor m = friction / (p·A): friction as a share of the piston force", fontsize=10)
    handles, labels = axes[0].get_legend_handles_labels()
    if any(e.extrapolated for e in effs):
        from matplotlib.patches import Patch

        handles.append(Patch(facecolor="#868e96", hatch="xx", edgecolor="white"))
        labels.append("extrapolated: beyond the fastest speed of the runs")
    fig.legend(handles, labels, loc="outside lower center", ncols=4, fontsize=8, frameon=False)
    return fig


_PLOTS = (("a_friction_maps", "Friction-velocity maps of the identified cylinders"),
          ("b_efficiency", "Efficiency factor of the identified cylinders"))


def _make_plots(effs: Mapping[_Cyl, _Efficiency], ref_speed: float) -> dict[str, bytes]:
    if not effs:
        return {}
    drawn, effs = list(effs), list(effs.values())
    out = {"a_friction_maps": png_bytes(_plot_maps(drawn))}
    if any(v is not None for e in effs for m in (e.m_break, e.m_ref) for v in m.values()):
        out["b_efficiency"] = png_bytes(_plot_efficiency(drawn, effs, ref_speed))
    return out


# ------------------------------------------------------------------ HTML sections

_MORE_CSS = """
.scroll{overflow-x:auto;max-width:100%}h3{font-size:1em;margin:1em 0 .2em}
td.low{background:#e7f5ff}td.high{background:#fff4e6}
th.sub{font-weight:normal;font-size:.85em}td.name{max-width:22em}
.headline.fail{border-left-color:#c92a2a}.headline.clean{border-left-color:#2b8a3e}
"""


def _headline(cs: Sequence[_Cyl], effs_of: Mapping[_Cyl, _Efficiency], ref_speed: float) -> tuple[list[str], str]:
    n = len(cs)
    ok = [c for c in cs if c.ok]
    failed = [c for c in cs if c.status == "failed"]
    skipped = [c for c in cs if c.status == "skipped"]
    other = [c for c in cs if c.status not in ("ok", "failed", "skipped")]
    if n == 0:
        return ["The batch holds no cylinders."], "fail"
    parts = [f"{len(ok)} identified", f"{len(failed)} failed"]
    if skipped:
        parts.append(f"{len(skipped)} skipped")
    if other:
        parts.append(f"{len(other)} without a known status")
    out = [escape(f"{n} cylinder{'s' if n != 1 else ''} in the batch: {', '.join(parts)}.")]
    cls = "fail" if failed or other else "clean"
    if not ok:
        out.append("No cylinder was identified, so there is nothing to compare"
                   + (": see why below." if failed or skipped or other else "."))
        return out, "fail"
    effs = [(c.name, e) for c, e in effs_of.items()]  # names may repeat
    ref = f"{sig(ref_speed * 1e3)} mm/s"
    at_ref = [(max(v for v in e.m_ref.values() if v is not None), name) for name, e in effs
              if any(v is not None for v in e.m_ref.values())]
    brk = [(v, name, d) for name, e in effs for d, v in e.m_break.items() if v is not None]
    if brk:
        lo, hi = min(brk), max(brk)
        out.append(escape(f"At breakaway, friction takes m = {sig(lo[0], 2)} ({lo[1]}, {lo[2]}) to {sig(hi[0], 2)} "
                      f"({hi[1]}, {hi[2]}) of the piston force p·A."))
    if len(at_ref) > 1:
        lo, hi = min(at_ref), max(at_ref)
        inside = sum(1 for _n, e in effs if all(v is not None and RULE_OF_THUMB[0] <= v <= RULE_OF_THUMB[1]
                                                     for v in e.m_ref.values()))
        out.append(escape(f"At {ref}, {lo[1]} has the least friction (m = {sig(lo[0], 2)}, the larger of its two "
                      f"directions) and {hi[1]} the most (m = {sig(hi[0], 2)}); {inside} of {len(at_ref)} stay "
                      f"within the catalogues' rule of thumb {_RULE_TEXT} in both directions."))
    rm = [(c.num("rmse_x"), c.name) for c in ok if c.num("rmse_x") is not None]
    if rm:
        lo, hi = min(rm), max(rm)
        out.append(escape(f"Position error of the fits (RMSE) from {sig(lo[0] * 1e6)} µm to {sig(hi[0] * 1e6)} µm "
                      f"({hi[1]})."))
    truth = [_truth_errors(c) for c in ok]
    checked = [t for t in truth if t]
    if checked:
        bad = [f"{c.name}: {p}" for c, t in zip(ok, truth) for p, (rel, _z) in t.items()
               if rel is not None and abs(rel) > REL_TOL]
        total = sum(len(t) for t in checked)
        if bad:
            out.append(escape(f"Against the truth of the simulated cylinders, {len(bad)} of {total} parameters "
                          f"{'is' if len(bad) == 1 else 'are'} off by more than {_TOL_TEXT}: "
                          + "; ".join(bad[:6]) + ("; …" if len(bad) > 6 else "")
                          + "."))
        else:
            out.append(escape(f"All {total} parameters of the simulated cylinders with a known truth are within "
                          f"{_TOL_TEXT} of it."))
    return out, cls


def _not_identified_html(cs: Sequence[_Cyl]) -> str:
    bad = [c for c in cs if not c.ok]
    if not bad:
        return ""
    rows = "".join(
        f'<tr><td class="name">{escape(c.name)}</td><td>{escape(c.status or "unknown")}</td><td>{escape(c.model) or _DASH}</td>'
        f'<td class="small">{escape(_text(c.row, "config")) or _DASH}</td>'
        f'<td class="err">{escape(_text(c.row, "error")) or "<i>no reason given</i>"}</td></tr>' for c in bad)
    return f"""<h2>Not identified</h2>
<table><tr><th>cylinder</th><th>status</th><th>model</th><th>config</th><th>why</th></tr>{rows}</table>"""


def _cylinders_html(cs: Sequence[_Cyl]) -> str:
    rows = []
    for c in cs:
        if not c.ok:
            continue
        runs = c.num("n_runs")
        about = [t for t in (_text(c.row, "cylinder"), _text(c.row, "config")) if t and t != c.name]
        rows.append(
            f'<tr><td class="name">{escape(c.name)}<br><span class="small">{"<br>".join(escape(t) for t in about)}</span></td>'
            f'<td>{escape(_text(c.row, "source")) or _NA}</td><td class="num">{int(runs) if runs is not None else _NA}</td>'
            + _num_cell(c.num("duration_s"), 1.0) + _num_cell(c.num("bore"), 1e3) + _num_cell(c.num("rod"), 1e3) + _num_cell(c.num("stroke"), 1e3)
            + _num_cell(c.supply_gauge(), 1e-5) + _num_cell(c.num("mean_dp"), 1e-5) + _num_cell(c.num("mean_pc"), 1e-5)
            + _num_cell(c.num("max_speed"), 1e3) + "</tr>")
    if not rows:
        return ""
    return f"""<h2>The cylinders</h2>
<table><tr><th>cylinder</th><th>runs</th><th>number of runs</th><th>duration of the runs (s)</th><th>bore (mm)</th><th>rod (mm)</th><th>stroke (mm)</th>
<th>supply (bar gauge)</th><th>mean |p1 − p2| (bar)</th><th>mean counter pressure (bar gauge)</th>
<th>fastest speed (mm/s)</th></tr>{''.join(rows)}</table>"""


def _maps_html(ok: Sequence[_Cyl], img: Mapping[str, str]) -> str:
    drawn = [c for c in ok if c.drawable]
    if not drawn:
        return ('<h2>Friction against velocity</h2><p>None of the identified cylinders has friction parameters '
                'that can be drawn.</p>') if ok else ""
    notes = []
    undrawn = [c for c in ok if not c.drawable]
    if undrawn:
        notes.append("Not drawn: " + "; ".join(
            f"{c.name} ({_undrawn_reason(c)})"
            for c in undrawn) + ".")
    press = [c for c in drawn if c.family == "nominal" or (c.family and FRICTION_MODELS[c.family].CONDITIONS)]
    if press:
        notes.append("Pressure- and load-dependent models are drawn at the mean conditions of their runs: "
                     + "; ".join(f"{c.name}: {_conditions_text(c)}" for c in press) + ".")
    dflt = [c for c in drawn if c.defaulted]
    if dflt:
        notes.append("Parameters missing from the results are drawn at the model's defaults: " + "; ".join(
            f"{c.name}: {', '.join(c.defaulted)}" for c in dflt) + ".")
    nospeed = [c.name for c in drawn if c.num("max_speed") is None]
    if nospeed:
        notes.append(f"Fastest speed not in the results, curve drawn up to {sig(_DEFAULT_MAX_SPEED * 1e3)} mm/s: "
                     + ", ".join(nospeed) + ".")
    return f"""<h2>Friction against velocity</h2>
<p class="explain">The static friction of each identified cylinder, as its model computes it (seed 004 Eq. 3 for the
Stribeck models; Fc + Fv·v + kp·|p1 − p2| for the nominal model), in both directions: retraction at negative velocity
and force, as in seed 004 Fig. 7. Each curve runs up to the fastest speed of its cylinder's runs. Below, the low-speed
region of each direction on a logarithmic speed axis, where static friction (breakaway) and the Stribeck dip show.</p>
{img.get("a_friction_maps", "")}
{''.join(f'<p class="small">{escape(n)}</p>' for n in notes)}"""


def _undrawn_reason(c: _Cyl) -> str:
    if c.family is not None:
        return "no parameters in the results"
    return f"unknown model {c.model!r}" if c.model else "no model in the results"


def _conditions_text(c: _Cyl) -> str:
    cond = c.conditions()
    parts = [f"|p1 − p2| = {sig(cond['dp'] / 1e5)} bar"] if "dp" in cond else []
    if "pc" in cond:
        parts.append(f"counter pressure {sig(cond['pc'] / 1e5)} bar gauge")
    if "load" in cond:
        parts.append(f"normal load Fn = {sig(cond['load'])} N")
    miss = c.missing_conditions()
    return ", ".join(parts) + (f" ({', '.join(miss)} not in the results: taken as 0)" if miss else "")


def _other_params(c: _Cyl) -> str:
    table = {p for q, *_ in _TABLE3 for _d, sfx, _g in _DIRS if (p := _table3_param(c, q, sfx))}
    parts = []
    for p in c.names:
        if p in table:
            continue
        unit = c.units.get(p, "")
        base, pair = p[:-4], p[:-4] + "_neg"
        if p.endswith("_pos") and {p, pair} <= c.fixed and c.values[p] == c.values[pair]:
            parts.append(f"{base} = {format_value(c.values[p], None, unit)} (fixed, both directions)")
        elif p.endswith("_neg") and {p, base + "_pos"} <= c.fixed and c.values[p] == c.values[base + "_pos"]:
            continue
        elif p in c.fixed:
            parts.append(f"{p} = {format_value(c.values[p], None, unit)} (fixed)")
        elif p in c.given:
            parts.append(f"{p} = {format_value(c.values[p], c.std(p), unit)}")
        else:
            parts.append(f"{p} n/a")
    return "<br>".join(escape(s) for s in parts) or _DASH


def _table3_html(ok: Sequence[_Cyl]) -> str:
    """Seed 004's Table 3 as two tables, one per direction (both in one table overflowed the
    page at 1400 px), then the other parameters."""
    if not ok:
        return ""
    head = "".join(f"<th>{h} ({escape(u)})</th>" for _q, h, u, _k in _TABLE3)
    tables = []
    for word, sfx, _g in _DIRS:
        rows = []
        for c in ok:
            cells = []
            for q, _h, _u, k in _TABLE3:
                p = _table3_param(c, q, sfx)
                cells.append(f'<td class="num">{_param_text(c, p, k) if p else _DASH}</td>')
            model = escape(c.model) if c.model else _NA
            if c.family is None and c.model:
                model += ' <span class="small">(unknown)</span>'
            rows.append(f'<tr><td class="name">{escape(c.name)}</td><td>{model}</td>{"".join(cells)}</tr>')
        tables.append(f"<h3>{escape(word)}</h3>\n<table><tr><th>cylinder</th><th>model</th>{head}</tr>"
                      f"{''.join(rows)}</table>")
    others = [(c, _other_params(c)) for c in ok]
    others_html = "".join(f'<tr><td class="name">{escape(c.name)}</td><td class="small">{o}</td></tr>'
                          for c, o in others if o != _DASH)
    if others_html:
        tables.append(f"<h3>other parameters</h3>\n<table><tr><th>cylinder</th><th>parameters</th></tr>"
                      f"{others_html}</table>")
    return f"""<h2>Friction parameters (as seed 004 Table 3)</h2>
{chr(10).join(tables)}
<p class="explain">Per direction: extension (v &gt; 0) and retraction (v &lt; 0). All values are magnitudes: seed 004
prints the retraction forces and Stribeck velocities negative. ± one standard deviation where the identification gives
it. — : the model has no such parameter (the nominal model has one Coulomb friction Fc and one viscous coefficient
B = Fv for both directions and a pressure term kp); n/a: the model has it, the results do not.</p>
{_truth_html(ok)}"""


def _truth_errors(c: _Cyl) -> dict[str, tuple[float | None, float | None]]:
    """parameter -> (relative error against the truth, error in standard deviations)."""
    out = {}
    for p in c.names:
        t = c.num(f"truth_{p}")
        if t is None or p not in c.given:
            continue
        err = c.values[p] - t
        s = c.std(p)
        out[p] = (err / abs(t) if t != 0 else None, err / s if s is not None else None)
    return out


def _truth_html(ok: Sequence[_Cyl]) -> str:
    rows = []
    for c in ok:
        errs = _truth_errors(c)
        if not errs:
            continue
        cells, nbad = [], 0
        for p, (rel, z) in errs.items():
            v, t = c.values[p], c.num(f"truth_{p}")
            bad = rel is not None and abs(rel) > REL_TOL
            nbad += bad
            rel_txt = f"{100 * rel:+.1f} %" if rel is not None else f"{sig(v - t)} (truth 0)"
            z_txt = f"{z:+.1f} σ" if z is not None else "n/a"
            tip = f"identified {sig(v, 4)}, truth {sig(t, 4)} ({c.units.get(p, '')})"
            cells.append(f'<tr><td>{escape(p)}</td><td class="num{" bad" if bad else ""}" title="{escape(tip)}">{rel_txt}'
                         f'</td><td class="num">{z_txt}</td></tr>')
        summary = (f'<b>{nbad} of {len(errs)}</b> beyond {_TOL_TEXT}' if nbad
                   else f'all {len(errs)} within {_TOL_TEXT}')
        rows.append(f'<tr><td class="name">{escape(c.name)}<br><span class="small">{summary}</span></td>'
                    f'<td>{escape(c.model)}</td>'
                    f'<td><table style="margin:0"><tr><th>parameter</th><th>error</th><th>in std</th></tr>'
                    f'{"".join(cells)}</table></td></tr>')
    if not rows:
        return ""
    return f"""<h3>Against the truth (simulated cylinders)</h3>
<table><tr><th>cylinder</th><th>model</th><th>identified − truth, relative (red: beyond {_TOL_TEXT})</th></tr>
{''.join(rows)}</table>
<p class="explain"><b>in std</b>: the error in units of the parameter's standard deviation; beyond ±2 σ the standard
deviation understates the real uncertainty. Hover over an error for both values.</p>"""


def _m_cell(v: float | None, star: bool = False) -> str:
    if v is None:
        return f'<td class="num">{_NA}</td>'
    cls = " low" if v < RULE_OF_THUMB[0] else (" high" if v > RULE_OF_THUMB[1] else "")
    return f'<td class="num{cls}">{v:.3f}{"*" if star else ""}</td>'


def _efficiency_html(effs: Mapping[_Cyl, _Efficiency], img: Mapping[str, str], ref_speed: float) -> str:
    if not effs:
        return ""
    rows, any_star, assumed = [], False, []
    for c, e in effs.items():
        bore = c.num("bore")
        area = math.pi * bore ** 2 / 4 if bore else None
        p = c.supply_gauge() if e.pA is not None else None
        any_star |= e.extrapolated
        if e.atmosphere_assumed:
            assumed.append(c.name)
        rows.append(f'<tr><td class="name">{escape(c.name)}</td><td>{escape(c.model)}</td>' + _num_cell(p, 1e-5)
                    + _num_cell(area, 1e4) + _num_cell(e.pA)
                    + "".join(_m_cell(e.m_break[d]) for d, _s, _g in _DIRS)
                    + "".join(_m_cell(e.m_ref[d], e.extrapolated) for d, _s, _g in _DIRS) + "</tr>")
    ref = f"{sig(ref_speed * 1e3)} mm/s"
    quotes = ", ".join(f"{who} {lo:.2f}" + (f"–{hi:.2f}" if hi != lo else "") for who, lo, hi in CATALOGUE_FACTORS)
    notes = []
    if any_star:
        notes.append(f"* {ref} is beyond the fastest speed of this cylinder's runs: the curve is extrapolated.")
    if assumed:
        notes.append(f"Atmosphere not in the results, {sig(_DEFAULT_ATMOSPHERE / 1e5, 4)} bar assumed: "
                     + ", ".join(assumed) + ".")
    return f"""<h2>Efficiency factor (seed 004 Eq. 1)</h2>
<p class="explain">Catalogues state friction as a share m of the piston force: F = m·p·A, with p the working pressure
(here the supply pressure, gauge) and A the bore area πD²/4, in both directions as Eq. 1 has one area (on retraction
the rod leaves a smaller annulus, so m understates the share of the force that direction really has). Seed 004 quotes
{escape(quotes)}: the shaded band {_RULE_TEXT} spans the manufacturers' values and Bollmann's, Pinches and Callear's lower
range is hatched in the chart. m at breakaway uses the static friction Fs (Fc where the model has none; the
pressure term at the runs' mean |p1 − p2|), m at {ref} the friction curve at that speed. Blue cells: less friction than
the rules of thumb assume, orange: more.</p>
<table><tr><th rowspan="2">cylinder</th><th rowspan="2">model</th><th rowspan="2">p (bar gauge)</th>
<th rowspan="2">A (cm²)</th><th rowspan="2">p·A (N)</th><th colspan="2">m at breakaway</th>
<th colspan="2">m at {ref}</th></tr>
<tr><th class="sub">extension</th><th class="sub">retraction</th><th class="sub">extension</th>
<th class="sub">retraction</th></tr>{''.join(rows)}</table>
{''.join(f'<p class="small">{escape(n)}</p>' for n in notes)}
{img.get("b_efficiency", "")}"""


def _r2(r2: float | None) -> str:
    """R² to as many decimals as show 1 − R² to 2 significant digits (fits of x are close to 1)."""
    if r2 is None:
        return _NA
    gap = 1.0 - r2
    if gap <= 0:
        return f"{r2:g}"
    return f"{r2:.{min(9, max(3, 1 - math.floor(math.log10(gap))))}f}"


def _fit_html(ok: Sequence[_Cyl]) -> str:
    if not ok:
        return ""
    diagnosed = any(_text(c.row, "verdict") for c in ok)
    rows = []
    for c in ok:
        it = c.num("iterations")
        r2 = c.num("r2_x")
        row = (f'<tr><td class="name">{escape(c.name)}</td><td>{escape(c.model) or _NA}</td>'
               + _num_cell(c.num("rmse_x"), 1e6)
               + f'<td class="num">{_r2(r2)}</td>'
               + _num_cell(c.num("rmse_p1"), 1e-3) + _num_cell(c.num("rmse_p2"), 1e-3)
               + f'<td>{escape(_text(c.row, "solver_status")) or _NA}</td>'
               + f'<td class="num">{int(it) if it is not None else _NA}</td>'
               + _num_cell(c.num("wall_s"), 1.0, 2))
        if diagnosed:
            shrink = c.num("verdict_shrink")
            row += (f'<td>{escape(_text(c.row, "verdict")) or _DASH}</td>'
                    f'<td class="num">{f"{100 * shrink:.0f} %" if shrink is not None else _DASH}</td>')
        rows.append(row + "</tr>")
    diag_head = "<th>diagnosis verdict</th><th>its shrink of the error</th>" if diagnosed else ""
    diag_note = (" <b>Diagnosis verdict</b>: the effect that best explains what the model still misses, and the "
                 "share of the validation position error it removes.") if diagnosed else ""
    return f"""<h2>Fit quality</h2>
<table><tr><th>cylinder</th><th>model</th><th>RMSE x (µm)</th><th>R² of x</th><th>RMSE p1 (kPa)</th>
<th>RMSE p2 (kPa)</th><th>solver</th><th>iterations</th><th>wall time (s)</th>{diag_head}</tr>{''.join(rows)}</table>
<p class="explain">How well the identified model reproduces the runs: root-mean-square error of the position (µm) and
of the chamber pressures (kPa); R² of the position (1 = perfect).{diag_note}</p>"""


# ------------------------------------------------------------------ the report

def render_batch_report(rows: Sequence[Mapping[str, Any]], *, title: str = "Batch identification",
                        ref_speed: float = REF_SPEED, plots: Mapping[str, bytes] | None = None) -> str:
    """The report as one HTML string (plots drawn unless given)."""
    cs = [_read(r, i) for i, r in enumerate(rows)]
    effs = _efficiencies(cs, ref_speed)
    return _render(cs, effs, title, ref_speed, _make_plots(effs, ref_speed) if plots is None else plots)


def scroll_wide_tables(page: str) -> str:
    """Every table that is not inside another in a box that scrolls sideways: a table wider
    than the page (long names, many parameters) scrolls instead of running off it."""
    out, depth, pos = [], 0, 0
    for m in re.finditer(r"<table\b[^>]*>|</table>", page):
        out.append(page[pos:m.start()])
        tag = m.group(0)
        if tag.startswith("<table"):
            out.append(('<div class="scroll">' if depth == 0 else "") + tag)
            depth += 1
        else:
            depth -= 1
            out.append(tag + ("</div>" if depth == 0 else ""))
        pos = m.end()
    out.append(page[pos:])
    return "".join(out)


def _render(cs: Sequence[_Cyl], effs: Mapping[_Cyl, _Efficiency], title: str, ref_speed: float,
            plots: Mapping[str, bytes]) -> str:
    img = {k: img_tag(v, alt) for k, alt in _PLOTS if (v := plots.get(k)) is not None}
    ok = [c for c in cs if c.ok]
    lines, cls = _headline(cs, effs, ref_speed)
    return scroll_wide_tables(f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{escape(title)}</title>
<meta name="viewport" content="width=device-width, initial-scale=1"><style>{CSS}{_MORE_CSS}</style></head><body>
<h1>{escape(title)}</h1>
<div class="headline {cls}">{''.join(f'<p>{s}</p>' for s in lines)}</div>
{_not_identified_html(cs)}
{_cylinders_html(cs)}
{_maps_html(ok, img)}
{_table3_html(ok)}
{_efficiency_html(effs, img, ref_speed)}
{_fit_html(ok)}
<p class="small">combined_reality batch report, {len(cs)} cylinder{'s' if len(cs) != 1 else ''}.</p>
</body></html>
""")


def write_batch_report(rows: Sequence[Mapping[str, Any]], path: str | Path, png_dir: str | Path | None = None,
                       title: str = "Batch identification", *, ref_speed: float = REF_SPEED) -> None:
    """Write the report of the batch's `rows` to `path` as one self-contained HTML file
    (atomically); with `png_dir`, also every plot as a PNG there."""
    cs = [_read(r, i) for i, r in enumerate(rows)]
    effs = _efficiencies(cs, ref_speed)
    plots = _make_plots(effs, ref_speed)
    write_html_and_plots(path, _render(cs, effs, title, ref_speed, plots), plots, png_dir)
