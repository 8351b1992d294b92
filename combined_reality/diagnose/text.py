"""A diagnosis in words: the verdict as sentences, parameters with their meaning and
standard deviations, the z of a candidate, a subsystem's error against its floor. Shared
by the HTML report, the console and the Rerun view."""
from __future__ import annotations

import math
from typing import Callable

from sim.cylinder import PARAMETERS
from sim.effects import EFFECTS

from ..calibrate import CalibrateOptions
from ..identify import at_bounds, misses_valid
from ..report.text import finite, format_value, pct, sig, um

__all__ = ["WITHIN_NOISE", "param_info", "at_its_bound", "params_text", "friction_text", "effect_description",
           "fit_caveat", "headline", "prediction_caveat", "subsystem_value", "z_text"]


def param_info(effect: str, name: str):
    """ParamInfo of `name` (a parameter of `effect`, or `effect.param` for a pair) or None."""
    if "." in name:
        effect, name = name.split(".", 1)
    cls = EFFECTS.get(effect)
    return cls.PARAMS.get(name) if cls is not None else None


def at_its_bound(v: float, info) -> bool:
    if info is None or not finite(v):
        return False
    return bool(at_bounds(v, info.lower, info.upper))


def params_text(c, sep: str = ", ", bounds: bool = False) -> str:
    """`tau = 1.416 ms ± 0.0003 ms, share = ...`; with `bounds`, a parameter the fit left at
    a bound of its range is marked (its std then means little)."""
    parts = []
    for n, v in (c.params or {}).items():
        info = param_info(c.effect, n)
        std = (c.std or {}).get(n)
        if info is not None and finite(std) and std > info.upper - info.lower:
            # a std wider than the whole range says the data do not determine the parameter
            txt = f"{n} = {format_value(v, None, info.unit)} (not determined by the data)"
        else:
            txt = f"{n} = {format_value(v, std, info.unit if info else '')}"
        if bounds and at_its_bound(v, info):
            txt += " (at its bound)"
        parts.append(txt)
    return sep.join(parts)


def friction_text(fr: dict, std: dict | None = None) -> str:
    return ", ".join(f"{n} = {format_value(fr[n], (std or {}).get(n), PARAMETERS[n].unit)}"
                     + (" (at its bound 0)" if fr[n] == 0 else "") for n in ("Fc", "Fv", "kp") if n in fr)


def effect_description(name: str) -> str:
    if "+" in name:
        return " and ".join(effect_description(n) for n in name.split("+"))
    cls = EFFECTS.get(name)
    return cls.description if cls is not None else ""


def headline(d, strong: Callable[[str], str] = lambda s: s, esc: Callable[[str], str] = lambda s: s) -> list[str]:
    """The verdict in plain sentences (the first one is the headline). `strong` marks the
    effect word (HTML <b>, markdown **), `esc` escapes the rest."""
    out = _verdict_sentences(d, strong, esc)
    cal = getattr(d, "calibration", None)
    if cal is not None:  # right after the headline: the baseline it speaks of is the calibrated model
        mis = cal.get("mis_set") or []
        model = cal.get("model", "none")
        text = ("The cylinder file's valve, dead volumes, mass and sensor offsets were calibrated on TRAIN together "
                "with each candidate (the nominal model is the calibration without an effect); "
                + (f"as calibrated with {model}, " if model != "none" else ""))
        if mis:
            text += "mis-set in the file: " + "; ".join(
                f"{m['quantity']} {format_value(m['file'], None, m['unit'])} → "
                f"{format_value(m['calibrated'], m['std'], m['unit'])} ({pct(m['change'])})" for m in mis) + "."
        else:
            text += "none of them is off."
        out.insert(1, esc(text))
    return out


def _verdict_sentences(d, strong, esc) -> list[str]:
    b = d.baseline
    noise_x = b["noise"]["x"]
    before = b.get("rmse_x_validation", math.nan)
    nrms = b.get("normalized_rms", math.nan)
    if d.best is not None:
        return _explained(d, before, nrms, strong, esc)
    if d.verdict == "unexplained":
        return _unexplained(d, before, nrms, strong, esc)
    return _no_effect(d, noise_x, before, nrms, strong, esc)


def _explained(d, before: float, nrms: float, strong, esc) -> list[str]:
    """The verdict's effect: what it shrinks, its parameters, what remains, the other helpers, the pair."""
    best = d.best
    after = best.rmse_x_validation
    params = params_text(best)
    out = [esc("The gap is best explained by ") + strong(best.effect)
           + esc(f" ({effect_description(best.effect)}): with it, the validation position error shrinks by "
                 f"{pct(best.shrink)} ({um(before)} → {um(after)})" + (f"; {params}." if params else "."))]
    meaning = [f"{n} is the {info.description}" for n in best.params if (info := param_info(best.effect, n))]
    if meaning:  # a_coulomb or share mean nothing to a reader without it
        out.append(esc("Its parameters: " + "; ".join(meaning) + "."))
    rest = best.validation.normalized_rms()  # the verdict is significant, hence validated
    if rest < WITHIN_NOISE:
        out.append(esc(f"What remains is at the sensor noise ({sig(rest)} × the noise over all outputs; "
                       f"it was {sig(nrms)} ×)."))
    else:
        out.append(esc(f"Part of the gap remains: {sig(rest)} × the sensor noise over all outputs "
                       f"(it was {sig(nrms)} ×; 1 would be a perfect model)."))
    caveat = fit_caveat(best)
    if caveat:
        out.append(esc(caveat))
    told = d.prediction()
    if told and told["caveat"]:
        out.append(esc(told["caveat"]))
    if d.verdict_note:
        out.append(esc("Why the pair: " + d.verdict_note + "."))
    others = [c.effect for c in d.ranking if c.significant and c.effect != best.effect]
    if others:
        out.append(esc("Other candidates that also help significantly (usually by imitating part of the same "
                       "error): " + ", ".join(others) + "."))
    p = d.pair
    if p is not None and p is not best:
        out.append(_pair_sentence(p, strong, esc))
    return out


# how a fit on TRAIN that did not converge stopped, in words
_STOPPED = {"max_iterations": "it ran out of iterations", "line_search_failed": "its line search failed",
            "above_reference": "it was given up", "time_limit": "its time ran out"}


def fit_caveat(c) -> str:
    """A sentence where the verdict's values are no measurement of the rig: its fit on TRAIN
    stopped before converging (where the calibration's residual says nothing, or stays above
    CalibrateOptions.misfit x the noise), or ends that far above the noise all the same. The
    effect is still the one that predicts VALID best; "" where the fit can be trusted."""
    res = (c.calibration or {}).get("residual_sigma")
    high = finite(res) and res > CalibrateOptions.misfit
    level = f" at {sig(res)} × the sensor noise on TRAIN" if finite(res) else ""
    if c.status != "converged" and (high or not finite(res)):
        how = _STOPPED.get(c.status, c.status.replace("_", " "))
        return (f"Its fit on TRAIN stopped before converging ({how} after {c.iterations} iterations){level}: "
                "its values are where the fit stopped, not the rig's; the effect is named because it predicts "
                "VALID best.")
    if high:
        return (f"Even with it, the calibrated model stays{level}: the effect's form or another effect leaves "
                "part of the gap, so take its values as indicative, not as the rig's.")
    return ""


def prediction_caveat(d, nrms: float, where: list[dict]) -> str:
    """identify.misses_valid for the model the verdict shows (the one without an effect for `none`)."""
    model = "calibrated model" if getattr(d, "calibration", None) is not None else "model"
    who = f"the {model} without an effect" if d.best is None else f"the {model} with {d.best.effect}"
    return misses_valid(who, nrms, where, d.options.trusted_valid)


def _pair_sentence(p, strong, esc) -> str:
    """The verdict's effect with the runner-up: likely both present, not fitted, not scored, or no better."""
    if p.significant:
        return (esc("Together with the runner-up, ") + strong(p.effect)
                + esc(f" shrinks the position error by {pct(p.shrink)} (to {um(p.rmse_x_validation)}), "
                      "significantly better than the verdict alone: both effects are likely present."))
    if p.status == "failed":
        return esc("The pair ") + strong(p.effect) + esc(" could not be fitted.")
    if not finite(p.shrink):  # screened out on TRAIN, or its simulation of VALID diverged
        return esc("The pair ") + strong(p.effect) + esc(f" was not scored on VALID: {p.error or p.status}.")
    return esc("The pair ") + strong(p.effect) + esc(
        " is not significantly better than the verdict alone "
        f"(position error {um(p.rmse_x_validation)}).")


def _unexplained(d, before: float, nrms: float, strong, esc) -> list[str]:
    """No candidate removes a significant part of the gap, or the best one only part of it."""
    tried = [c.effect for c in d.ranking]
    runner = d.runner
    if runner is None:
        return [esc("The gap is ") + strong("unexplained") + esc(
            f": the nominal model misses VALID by {um(before)} in position ({sig(nrms)} × the sensor noise over all "
            f"outputs), and none of the {len(tried)} candidates tried removes a significant part of it. The cause "
            "is likely outside the vocabulary (a sensor error, another physical effect). See where the error lies "
            "below."),
            esc("Candidates tried: " + ", ".join(tried) + ".")]
    left = sig(runner.validation.normalized_rms())
    out = [esc("The gap is ") + strong("unexplained") + esc(
        f": the nominal model misses VALID by {um(before)} in position ({sig(nrms)} × the sensor noise over all "
        f"outputs), and the best candidate, {runner.effect}, removes only part of it (position error "
        f"{pct(runner.shrink)} smaller, {um(runner.rmse_x_validation)}; all outputs {left} × the noise). "
        "A weak winner is no diagnosis: the cause is likely outside the vocabulary (a sensor "
        "error, another physical effect) or several effects combine. See where the error lies below.")]
    if d.verdict_note:
        out.append(esc("Why: " + d.verdict_note + "."))
    out.append(esc("Candidates tried: " + ", ".join(tried) + "."))
    return out


def _no_effect(d, noise_x: float, before: float, nrms: float, strong, esc) -> list[str]:
    """Verdict none: within the noise already, or a gap none of the candidates tried explains; which
    candidates the screens kept from validation."""
    tried = [c.effect for c in d.ranking]
    out = []
    if finite(nrms) and nrms < WITHIN_NOISE:
        out.append(esc(f"The nominal model already fits VALID to within the sensor noise (position error {um(before)}"
                       f" with {um(noise_x)} sensor noise; all outputs {sig(nrms)} × the noise): ") + strong("none")
                   + esc(" of the candidate effects improves it significantly."))
    else:
        out.append(esc(f"No candidate effect explains the gap: the nominal model misses VALID by {um(before)} in "
                       f"position ({sig(nrms)} × the sensor noise over all outputs), and none of the "
                       f"{len(tried)} candidates tried removes a significant part of it (verdict ") + strong("none")
                   + esc("). See where the error lies below, and consider effects that were not tried."))
    told = d.prediction()
    if told and told["caveat"]:
        out.append(esc(told["caveat"]))
    if tried:
        out.append(esc("Candidates tried: " + ", ".join(tried) + "."))
    screened = [c.effect for c in d.ranking if c.status == "no_gain_on_train"]
    if screened and screened == tried:
        out.append(esc("None of them fits TRAIN better than the nominal model, so none was validated (the fast "
                       "screen)."))
    elif screened:
        out.append(esc("Not validated, as they fit TRAIN no better than the nominal model (the fast screen): "
                       + ", ".join(screened) + "."))
    slight = [c.effect for c in d.ranking if c.status == "screened_out"]
    if slight:
        out.append(esc(f"Not validated either, as they gain under {d.options.screen_share:.0%} of the best "
                       "candidate's gain on TRAIN (the screen): " + ", ".join(slight) + "."))
    return out


def subsystem_value(r: dict) -> tuple[str, str]:
    unit = r.get("unit", "")
    if unit == "m":
        return um(r.get("rmse")), um(r.get("floor"))
    if unit == "Pa":
        f = lambda v: f"{sig(float(v) / 1e3)} kPa" if finite(v) else "n/a"  # noqa: E731
        return f(r.get("rmse")), f(r.get("floor"))
    return f"{sig(r.get('rmse'))} {unit}", f"{sig(r.get('floor'))} {unit}"


def z_text(z) -> str:
    """The z statistic of a candidate's validation gain; n/a when it was not validated."""
    return f"{float(z):.1f}" if finite(z) else "n/a"


WITHIN_NOISE = 1.2  # all-output RMS in noise units below which the nominal model "fits"
