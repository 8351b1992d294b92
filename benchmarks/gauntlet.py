"""Calibration and diagnosis together: the cylinder file is off AND an effect the model lacks is at work.

Every case is a rig whose truth departs from its cylinder file as in benchmarks/calibration.py
(valve conductance x0.5-1.5 per direction, critical ratio 0.15-0.5, a non-linear flow
characteristic per direction with an overlap up to 0.08, dead volumes x0.3-3, mass x0.7-1.5,
pressure sensor offsets up to +-5 kPa) and, but for the effect-free cases, has one effect of the
vocabulary at a random realistic strength (drawn as benchmarks/diagnosis.py draws them). Two
plants make the runs:

- `project`: the project's virtual rig. Its truth is a cylinder file with the departed values
  (each characteristic on the tool's own grid) plus one effect of sim/effects.py: one case per
  word and cylinder.
- `reference`: the independent plant of benchmarks/reference_plant.py (written from the
  physics, not from sim/) with the same departures (`Case(calibration=...)`, the characteristics
  in shapes that are not the tool's) and the effect in each of its forms, the standard and the
  alternative ones: one case per word, form and cylinder.

Both also have effect-free cases (departures only). Two cylinder sizes. TRAIN is a 20 s run of
the calibration program, VALID a 20 s run of the mixed program (another seed) that no fit sees.
Each case runs `diagnose --calibrate` through the library (the call the command line makes) on
the nominal cylinder file, and one `calibrate` of the same TRAIN run in the same process: the
time ratio travels between machines better than seconds.

Prints per plant: the confusion matrix (rows: true effect, columns: verdict), the quantities of
the file that depart from the truth beyond the diagnosis's mis-set thresholds and which of them
it listed as mis-set, the friction's errors, VALID's normalized RMS (1 = the sensor noise) of the
calibrated model with the effect the verdict names, the time per case and its ratio to one
calibrate; then the summary against the targets of issue 40. On the project plant each case also
scores the rig's own cylinder file on VALID with and without its effect: the first is what the
best model can do (under stick-slip the 1 s open-loop segments drift beyond the noise even for
the truth, so a named model is also judged against that floor), the second how much the effect
shows at all (an effect whose absence costs the truth less than 10 % is counted apart as
barely visible). The reference plant's truth is not in the tool's model family, so there VALID's
segments are replayed on the plant itself without the effect, each from the true state before
it; the truth with the effect leaves just the noise, and the same 10 % sets an effect apart.

A rigid mass and a valve dead zone are the file's own quantities (moving mass, overlap): a
calibration that absorbs them and lists them as mis-set has found them too (`absorbed`), which
the summary counts apart.

    python benchmarks/gauntlet.py --quick                 # 4 cases on cylinder A, on both plants
    python benchmarks/gauntlet.py --out DIR               # every case; resumable (a JSON per case in DIR)
    python benchmarks/gauntlet.py --plant reference --cases leakage,none --jobs 2

--jobs N runs N cases at once, each diagnosis on cores / N workers: their times are not this
machine's per-case times (the summary says so); the time targets are measured with --jobs 1.

Targets (issue 40): the effect named (or the pair containing it) in >= 90 % of the cases with
an effect, `none` on every effect-free case, the mis-set quantities that depart beyond the
thresholds listed, where the effect is named VALID within 2 x the noise, and a diagnosis of a
20 s TRAIN and VALID in at most 120 s median and 300 s worst case.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
import zlib
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from combined_reality.calibrate import calibrate, validation_figures  # noqa: E402
from combined_reality.diagnose import DiagnoseOptions, diagnose  # noqa: E402
from combined_reality.files import Run, cylinder_tag  # noqa: E402
from combined_reality.identify import sensor_noise, validation_segments  # noqa: E402
from combined_reality.live import make_program, run_program  # noqa: E402
from hw.virtual_rig import VirtualRig  # noqa: E402
from sim.compiled import cached_model_code  # noqa: E402
from sim.cylinder import OPENING_GRID, VALVE_DIRECTIONS, Cylinder, cylinder_to_toml, load_cylinder  # noqa: E402
from sim.effects import EFFECTS  # noqa: E402

import calibration as calbench  # noqa: E402  (benchmarks/ is on sys.path)
import reference_plant as ref  # noqa: E402

CYLINDERS = ("cyl_a_32x100", "ind3_norgren_40x250")
DURATION = 20.0  # s of TRAIN and of VALID
RATE = 1000.0  # Hz
QUICK = ("leakage", "friction_asymmetry", "friction_dynamics", "none")
SHORT = {"stiction": "stict", "friction_asymmetry": "f_asym", "friction_position": "f_pos",
         "friction_dynamics": "f_dyn", "valve_deadzone": "v_dz", "valve_delay": "v_del", "leakage": "leak",
         "heat_transfer": "heat", "supply_droop": "droop", "unexplained": "unexpl"}
# the diagnosis's mis-set thresholds (combined_reality/diagnose): 2 % of the file's value,
# offsets 1 kPa, a constant force 1 N
MIS_SET_RELATIVE = 0.02
MIS_SET_ABSOLUTE = {"offset_p1": 1000.0, "offset_p2": 1000.0, "external_force": 1.0}
QUANTITIES = ("mass", "critical_ratio", "dead_volume_cap", "dead_volume_rod", "offset_p1", "offset_p2",
              "external_force", "valve characteristic")
# effects that are a calibrated quantity of the file under another name
ABSORBED = {"mass": "mass", "valve_deadzone": "valve characteristic"}
# effects that leave the nominal friction law (Fc, Fv, kp) as the file has it
RESHAPES_FRICTION = ("stiction", "friction_asymmetry", "friction_position", "friction_dynamics")
TARGETS = {"found": 0.9, "valid": 2.0, "median_s": 120.0, "max_s": 300.0}
FAINT = 1.1  # an effect whose absence costs the truth less than 10 % on VALID is barely visible there


# ------------------------------------------------------------------ cases


def case_list(plant: str, cylinders, words, clean: int, standard_form_only: bool = False) -> list[dict]:
    """One case per effect word (project plant) or per word and form (reference plant) and
    cylinder, and `clean` effect-free cases per cylinder; `none` in `words` asks for them."""
    cases = []
    for cfg in cylinders:
        for w in words:
            if w == "none":
                continue
            if plant == "project":
                cases.append({"plant": plant, "cylinder": cfg, "effect": w, "draw": 0})
            else:
                forms = ref.forms_of(w)[:1] if standard_form_only else ref.forms_of(w)
                cases += [{"plant": plant, "cylinder": cfg, "effect": w, "form": f.FORM, "draw": 0} for f in forms]
        if "none" in words:
            cases += [{"plant": plant, "cylinder": cfg, "effect": "none", "draw": d} for d in range(clean)]
    return cases


def case_id(c: dict) -> str:
    parts = [c["plant"], c["cylinder"], c["effect"]] + ([c["form"]] if c.get("form") else [])
    return "__".join(parts + [str(c["draw"])])


def case_seed(c: dict) -> int:
    return zlib.crc32(f"gauntlet__{case_id(c)}".encode()) % 100_000


def selected(c: dict, selectors: list[str]) -> bool:
    """`--cases`: an effect word, `word:form` or a case id."""
    label = c["effect"] + (f":{c['form']}" if c.get("form") else "")
    return any(s in (c["effect"], label, case_id(c)) for s in selectors)


def draw(c: dict, cyl: Cylinder):
    """The case's departures from the file (a reference_plant.Calibration) and its effect (None,
    an effect of sim/effects.py or of reference_plant.py), from its seed alone."""
    rng = np.random.default_rng(case_seed(c))
    departure = calbench.departure(rng, cyl)
    if c["effect"] == "none":
        return departure, None
    if c["plant"] == "project":
        return departure, EFFECTS[c["effect"]].random(rng, cyl)
    return departure, ref.random_effect(rng, cyl, c["effect"], c.get("form"))


def project_truth(cyl: Cylinder, departure: ref.Calibration) -> Cylinder:
    """The cylinder file of the rig: the departed values, each direction's characteristic
    (conductance scale times shape) at the tool's grid of openings beyond its overlap."""
    t = departure.resolved(cyl)
    grid = np.asarray(OPENING_GRID)
    values = {"mass": t["moving_mass"], "critical_ratio": t["critical_ratio"],
              "dead_volume_cap": t["dead_volume_cap"], "dead_volume_rod": t["dead_volume_rod"],
              "offset_p1": t["offset_p1"], "offset_p2": t["offset_p2"], "external_force": t["external_force"]}
    flows = {}
    for d, side in zip(VALVE_DIRECTIONS, ("pos", "neg")):
        shape = getattr(departure, f"characteristic_{side}") or ref.Linear()
        values[f"overlap_{d}"] = shape.overlap
        flows[f"flow_{d}"] = tuple(float(v) for v in getattr(departure, f"conductance_{side}") * shape.g(grid))
    truth = cyl.with_values(values)
    return replace(truth, valve=replace(truth.valve, **flows))


def reference_cases(c: dict, cyl: Cylinder, duration: float) -> tuple[ref.Case, ref.Case]:
    departure, effect = draw(c, cyl)
    seed = case_seed(c)
    return tuple(ref.Case(cyl=cyl, duration=duration, seed=s, calibration=departure,
                          effects=(effect,) if effect is not None else (), program=p)
                 for s, p in ((seed, "calibration"), (seed + 1, "mixed")))


def project_runs(c: dict, cyl: Cylinder, duration: float) -> tuple[Run, Run]:
    """TRAIN (calibration program) and VALID (mixed program) of the project's virtual rig; the
    programs are designed from the file, as a user's would be."""
    departure, effect = draw(c, cyl)
    truth, seed = project_truth(cyl, departure), case_seed(c)
    runs = []
    for s, program in ((seed, "calibration"), (seed + 1, "mixed")):
        rig = VirtualRig(truth, (effect,) if effect is not None else (), rate=RATE, seed=s)
        run = run_program(rig, make_program(program, cyl, duration, seed=s), int(round(duration * RATE)))
        runs.append(replace(run, comments=(cylinder_tag(cyl),)))
    return runs[0], runs[1]


def truth_of(c: dict, cyl: Cylinder) -> dict:
    """What the rig is: the calibrated quantities (the departures, with what a rigid mass effect
    adds), the file's friction, the effect and its values."""
    departure, effect = draw(c, cyl)
    t = calbench.truth_values(ref.Case(cyl=cyl, calibration=departure))
    values = {n: t[n] for n in QUANTITIES[:-1]}
    if effect is not None and c["effect"] == "mass":  # what the piston carries (a payload: at low frequency)
        e = effect.values() if c["plant"] == "reference" else {"dm": effect.delta * values["mass"]}
        values["mass"] += e.get("dm", e.get("m_p", 0.0))
    f = cyl.friction
    out = {"calibrated": values, "friction": {"Fc": f.Fc, "Fv": f.Fv, "kp": f.kp},
           "valve": {"conductance_extend": departure.conductance_pos, "conductance_retract": departure.conductance_neg,
                     "characteristic_extend": ref.Linear().to_dict() if departure.characteristic_pos is None
                     else departure.characteristic_pos.to_dict(),
                     "characteristic_retract": ref.Linear().to_dict() if departure.characteristic_neg is None
                     else departure.characteristic_neg.to_dict()}}
    if effect is not None:
        params = effect.values() if c["plant"] == "reference" else {k: getattr(effect, k) for k in effect.PARAMS}
        out["effect"] = {"word": c["effect"], "form": c.get("form", "project"), **params}
    if c["plant"] == "project":  # the rig again: `live --virtual --config` this file, `--effect` this spec
        out["cylinder_toml"] = cylinder_to_toml(project_truth(cyl, departure))
        if effect is not None:
            out["effect_spec"] = f"{c['effect']}:" + ",".join(f"{k}={v:.9g}" for k, v in params.items())
    return out


def departed_quantities(cyl: Cylinder, departure: ref.Calibration, calibrated: dict[str, float]) -> list[str]:
    """The file's quantities that depart from the truth (`calibrated`: truth_of's values, and the
    departure's valve) beyond the mis-set thresholds."""
    out = []
    for n, v in calibrated.items():
        f = cyl.value(n)
        if abs(v - f) > MIS_SET_ABSOLUTE.get(n, MIS_SET_RELATIVE * abs(f)):
            out.append(n)
    file_valve, grid = cyl.valve, np.asarray(OPENING_GRID)
    for d, side in zip(VALVE_DIRECTIONS, ("pos", "neg")):
        shape = getattr(departure, f"characteristic_{side}") or ref.Linear()
        true_flow = getattr(departure, f"conductance_{side}") * shape.g(grid)
        file_flow = np.asarray(getattr(file_valve, f"flow_{d}"))
        if np.any(np.abs(true_flow - file_flow) > MIS_SET_RELATIVE * np.abs(file_flow)) or \
                abs(shape.overlap - getattr(file_valve, f"overlap_{d}")) > 1e-3:
            out.append("valve characteristic")
            break
    return out


# ------------------------------------------------------------------ one case


def case_runs(c: dict, cyl: Cylinder, duration: float, cache: Path | None) -> tuple[Run, Run]:
    if c["plant"] == "project":
        return project_runs(c, cyl, duration)
    train, valid = ref.cached_runs(reference_cases(c, cyl, duration), cache)
    return train, valid


def run_case(c: dict, duration: float, workers: int, cache: Path | None) -> dict:
    cyl = load_cylinder(ROOT / "configs" / f"{c['cylinder']}.toml")
    train, valid = case_runs(c, cyl, duration, cache)
    truth = truth_of(c, cyl)
    floor = truth_floor(c, cyl, valid) if c["plant"] == "project" else reference_floor(c, cyl, valid, duration, cache)
    t0 = time.perf_counter()
    cal = calibrate(cyl, [train])
    t_cal = time.perf_counter() - t0
    cal_valid = validation_figures(cal.cylinder, valid, train=[train])
    built = len(cached_model_code())  # what the diagnosis builds first counts in its time, not calibrate's
    t0 = time.perf_counter()
    dg = diagnose(cyl, train, valid, DiagnoseOptions(calibrate=True, workers=workers))
    t_diag = time.perf_counter() - t0
    doc = dg.to_json()
    named = dg.best  # the verdict's candidate (None for none and unexplained)
    nominal_nrms = dg.base_validation.normalized_rms()
    named_nrms = (named.validation.normalized_rms() if named is not None and named.validation is not None
                  else nominal_nrms if doc["verdict"] == "none" else math.nan)
    friction = dict(named.friction) if named is not None and named.friction else dict(doc["baseline"]["friction"])
    found = [m["quantity"] for m in (doc.get("calibration") or {}).get("mis_set", [])]
    departed = departed_quantities(cyl, draw(c, cyl)[0], truth["calibrated"])
    return {**c, "id": case_id(c), "seed": case_seed(c), "truth": truth, "floor": floor,
            "verdict": doc["verdict"], "verdict_note": doc.get("verdict_note", ""),
            "pair": doc["pair"]["effect"] if doc.get("pair") else None,
            "found": effect_found(c["effect"], doc["verdict"], found),
            "mis_set": {"departed": departed, "listed": found},
            "friction": {"estimated": friction,
                         "errors": {k: friction[k] / truth["friction"][k] - 1 for k in ("Fc", "Fv", "kp")
                                    if k in friction}},
            "valid": {"nominal_nrms": nominal_nrms, "named_nrms": named_nrms,
                      "nominal_rmse_x": doc["baseline"]["rmse_x_validation"]},
            "calibrate": {"status": cal.result.solver["status"], "residual": cal.result.solver["residual_sigma"],
                          "valid_nrms": cal_valid["normalized_rms"], "valid_rmse_x": cal_valid["rmse_x"]},
            "calibration_in_diagnosis": {k: v for k, v in (doc.get("calibration") or {}).items() if k != "mis_set"},
            "t_diagnose": t_diag, "t_calibrate": t_cal, "compiled": len(cached_model_code()) - built,
            "workers": workers, "cores": os.cpu_count() or 1,
            "diagnosis": doc}  # the whole document: each candidate's status, iterations and time


def truth_floor(c: dict, cyl: Cylinder, valid: Run) -> dict:
    """Project plant: what the best model can do on VALID (the rig's own cylinder file scored
    as the diagnosis scores; stick-slip makes open-loop segments sensitive beyond the noise)
    and what the best model without the effect can do: the effect's visibility."""
    departure, effect = draw(c, cyl)
    truth = project_truth(cyl, departure)
    floor = validation_figures(truth, valid, effects=(effect,) if effect is not None else ())["normalized_rms"]
    without = validation_figures(truth, valid)["normalized_rms"] if effect is not None else floor
    return {"truth_nrms": floor, "without_effect_nrms": without}


def reference_floor(c: dict, cyl: Cylinder, valid: Run, duration: float, cache: Path | None) -> dict:
    """Reference plant: how much its effect shows on VALID. Its truth is not in the tool's model
    family, so it is replayed instead: each of VALID's scoring segments simulated again on the
    reference plant without the effect (the departed file alone), open loop with VALID's
    commands, from the true state before the segment (the first from rest). The truth with the
    effect leaves just the sensor noise there (`noise_nrms`). A start fitted per segment, as the
    diagnosis scores, could hide more of the effect: this measure calls fewer effects faint."""
    _, case = reference_cases(c, cyl, duration)
    states = ref.cached_states([case], cache)[0] if cache is not None else ref.simulate_detailed([case])[0].states
    segments = validation_segments(valid, 1.0)
    parts = [replace(case, effects=(), noise=False, duration=(b - a) / RATE, commands=valid.u[a:b],
                     start={n: float(states[n][a - 1]) for n in ("p1", "p2", "x", "v")} if a else None,
                     command_before=float(valid.u[a - 1]) if a else 0.0)
             for a, b in segments]
    outputs = ("x", "p1", "p2")
    sigma = sensor_noise(cyl, outputs)
    noise = ref.sensor_noise(case)
    cost = noise_cost = n = 0.0
    for (a, b), replay in zip(segments, ref.simulate(parts)):
        for i, o in enumerate(outputs):
            cost += float(np.sum(((getattr(valid, o)[a:b] - getattr(replay, o)) / sigma[i]) ** 2))
            noise_cost += float(np.sum((noise[a:b, i] / sigma[i]) ** 2))
        n += len(outputs) * (b - a)
    return {"noise_nrms": math.sqrt(noise_cost / n), "without_effect_nrms": math.sqrt(cost / n),
            "replayed": "from the true state per segment"}


def truth_score(r: dict) -> float:
    """The truth's own score on VALID (the reference plant's: the noise's), NaN where not measured."""
    f = r.get("floor") or {}
    return f.get("truth_nrms", f.get("noise_nrms", math.nan))


def is_faint(r: dict) -> bool:
    """The effect barely shows on VALID: the truth without it scores within FAINT x of the truth."""
    f = r.get("floor") or {}
    return r["effect"] != "none" and "without_effect_nrms" in f and f["without_effect_nrms"] <= FAINT * truth_score(r)


def within_target(r: dict) -> bool:
    """VALID within TARGETS["valid"] x the noise, or within that factor of the truth's own score
    where the truth itself cannot reach it (stick-slip)."""
    named = r["valid"]["named_nrms"]
    floor = r.get("floor", {}).get("truth_nrms", 1.0)
    return named <= TARGETS["valid"] * max(1.0, floor)


def effect_found(truth: str, verdict: str, listed: list[str]) -> str:
    """`named` (the verdict or its pair holds the effect), `absorbed` (a rigid mass or a dead
    zone calibrated as the file's mass or valve characteristic, verdict none), `none` (right on
    an effect-free case), `missed`."""
    if truth == "none":
        return "none" if verdict == "none" else "missed"
    if truth in verdict.split("+"):
        return "named"
    if verdict == "none" and ABSORBED.get(truth) in listed:
        return "absorbed"
    return "missed"


# ------------------------------------------------------------------ report


def report(rows: list[dict], title: str) -> None:
    print(f"\n===== {title} =====")
    words = [w for w in ref.WORDS if any(r["effect"] == w for r in rows)] + ["none"]
    verdicts = words + sorted({r["verdict"] for r in rows} - set(words))
    width = max(len(w) for w in words) + 1
    print("\nconfusion matrix (rows: true effect, columns: verdict)")
    print(" " * width + " ".join(f"{SHORT.get(v, v[:6]):>6s}" for v in verdicts))
    for w in words:
        mine = [r for r in rows if r["effect"] == w]
        if mine:
            counts = [sum(r["verdict"] == v for r in mine) for v in verdicts]
            print(f"{w:{width}s}" + " ".join(f"{n:6d}" if n else f"{'.':>6s}" for n in counts))

    print("\nmis-set quantities (departed from the truth beyond the thresholds: listed by the diagnosis / departed; "
          "listed without departing)")
    for q in QUANTITIES:
        dep = [r for r in rows if q in r["mis_set"]["departed"]]
        hit = sum(q in r["mis_set"]["listed"] for r in dep)
        false = sum(q in r["mis_set"]["listed"] and q not in r["mis_set"]["departed"] for r in rows)
        if dep or false:
            print(f"  {q:22s} {hit:3d} / {len(dep):3d}" + (f"   {false} listed without departing" if false else ""))

    print(f"\n{'case':42s} {'verdict':22s} {'VALID':>6s} {'named':>6s} {'truth':>6s} {'w/o':>6s} {'cal':>6s} {'cal res':>7s} "
          f"{'Fc %':>6s} {'Fv %':>6s} {'kp %':>6s} {'mis-set':>7s} {'diag s':>7s} {'/cal':>5s}")
    for r in rows:
        e = r["friction"]["errors"]
        label = f"{r['cylinder'][:18]} {r['effect']}" + (f":{r['form']}" if r.get("form") else "") + \
            (f" #{r['draw']}" if r["effect"] == "none" else "")
        dep = set(r["mis_set"]["departed"])
        print(f"{label[:42]:42s} {r['verdict'][:22]:22s} {r['valid']['nominal_nrms']:6.2f} "
              f"{r['valid']['named_nrms']:6.2f} {truth_score(r):6.2f} "
              f"{r.get('floor', {}).get('without_effect_nrms', math.nan):6.2f} "
              f"{r['calibrate']['valid_nrms']:6.2f} {r['calibrate']['residual']:7.2f} "
              + " ".join(f"{100 * e[k]:+6.1f}" if k in e else f"{'-':>6s}" for k in ("Fc", "Fv", "kp"))
              + f" {len(dep & set(r['mis_set']['listed'])):3d}/{len(dep):<3d} {r['t_diagnose']:7.1f} "
              f"{r['t_diagnose'] / r['t_calibrate']:5.1f}")
    print("  (VALID: the calibrated nominal model's normalized RMS; named: the calibrated model with the named "
          "effect; truth / w/o: the rig's own file with / without its effect (reference plant: replayed from "
          "the true states, the truth's score the noise's); cal / cal res: "
          "calibrate alone on VALID / its TRAIN residual, x the noise)")
    summary(rows)


def summary(rows: list[dict]) -> None:
    eff = [r for r in rows if r["effect"] != "none"]
    clean = [r for r in rows if r["effect"] == "none"]
    named = [r for r in eff if r["found"] == "named"]
    absorbed = [r for r in eff if r["found"] == "absorbed"]
    print()
    if eff:
        print(f"effect named (or in the pair): {len(named)}/{len(eff)} = {len(named) / len(eff):.0%}   "
              f"(target >= {TARGETS['found']:.0%}); with the absorbed ones (a mass or dead zone calibrated as the "
              f"file's): {len(named) + len(absorbed)}/{len(eff)}")
        faint = [r for r in eff if is_faint(r)]
        if faint:
            seen = [r for r in eff if not is_faint(r)]
            ok = sum(r["found"] in ("named", "absorbed") for r in seen)
            print(f"  barely visible (without its effect the rig's own file scores within {FAINT:g} x of the truth "
                  f"on VALID): {', '.join(r['id'] + ' -> ' + r['verdict'] for r in faint)}; named or absorbed "
                  f"among the others: {ok}/{len(seen)}")
        verdicts: dict[str, int] = {}
        for r in eff:
            verdicts[r["verdict"]] = verdicts.get(r["verdict"], 0) + 1
        print("  verdicts on the cases with an effect: "
              + ", ".join(f"{v} {n}" for v, n in sorted(verdicts.items(), key=lambda x: -x[1])))
    if clean:
        print(f"effect-free cases: {sum(r['verdict'] == 'none' for r in clean)}/{len(clean)} verdict none   "
              f"({', '.join(r['verdict'] for r in clean)})")
    dep = sum(len(r["mis_set"]["departed"]) for r in rows)
    hit = sum(len(set(r["mis_set"]["departed"]) & set(r["mis_set"]["listed"])) for r in rows)
    false = sum(len(set(r["mis_set"]["listed"]) - set(r["mis_set"]["departed"])) for r in rows)
    print(f"mis-set quantities listed: {hit}/{dep} of those that depart beyond the thresholds; "
          f"{false} listed that do not")
    scored = [r for r in named + [r for r in clean if r["verdict"] == "none"]]
    if scored:
        ok = sum(r["valid"]["named_nrms"] <= TARGETS["valid"] for r in scored)
        print(f"VALID within {TARGETS['valid']:g} x the noise where the verdict is right: {ok}/{len(scored)} "
              f"(worst {max(r['valid']['named_nrms'] for r in scored):.2f}); within {TARGETS['valid']:g} x the "
              f"truth's own score where that is above the noise: {sum(within_target(r) for r in scored)}/{len(scored)}")
        beyond = [r for r in scored if r["valid"]["named_nrms"] > TARGETS["valid"]]
        told = [r for r in beyond if (r["diagnosis"].get("prediction") or {}).get("caveat")]
        untaught = [r for r in told if any(not g["taught"] for g in r["diagnosis"]["prediction"]["regions"])]
        if beyond:
            print(f"  beyond it, the diagnosis says its predictions are no match in {len(told)}/{len(beyond)}"
                  + (f" (older results carry no such field: {len(beyond) - len(told)})" if len(told) < len(beyond)
                     else "") + f"; naming a regime TRAIN showed too little of in {len(untaught)}: "
                  + ", ".join(r["id"] for r in untaught))

    plain = [r for r in rows if r["effect"] not in RESHAPES_FRICTION]
    if plain:
        for k in ("Fc", "Fv", "kp"):
            errs = np.array([abs(r["friction"]["errors"][k]) for r in plain if k in r["friction"]["errors"]])
            if errs.size:
                print(f"  |{k} error| where the effect leaves the friction law: median {100 * np.median(errs):.1f} %, "
                      f"max {100 * errs.max():.1f} %")
    t = np.array([r["t_diagnose"] for r in rows])
    ratio = np.array([r["t_diagnose"] / r["t_calibrate"] for r in rows])
    tc = np.array([r["t_calibrate"] for r in rows])
    print(f"time of diagnose --calibrate: median {np.median(t):.0f} s, max {t.max():.0f} s (target median <= "
          f"{TARGETS['median_s']:.0f} s, max <= {TARGETS['max_s']:.0f} s); {np.median(ratio):.1f} x (median) one "
          f"calibrate of the same TRAIN run in the same process (calibrate: median {np.median(tc):.0f} s, "
          f"max {tc.max():.0f} s)")
    shared = [r for r in rows if r.get("workers", math.inf) < r.get("cores", 1)]
    if shared:
        print(f"  {len(shared)} of these ran beside other cases (--jobs > 1, each diagnosis on fewer workers than "
              f"the machine's cores): their times are not this machine's, which need --jobs 1")
    cold = [r for r in rows if r.get("compiled")]
    if cold:
        print(f"  {len(cold)} of these built model functions first, and their time includes that "
              f"({', '.join(r['id'] for r in cold)})")


# ------------------------------------------------------------------ main


def _run_and_store(job) -> dict:
    c, duration, workers, cache, out = job
    r = run_case(c, duration, workers, cache)
    if out is not None:
        path = out / f"{case_id(c)}.json"
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(r, indent=1, default=float))
        os.replace(tmp, path)
    return r


def _progress_line(i: int, n: int, r: dict) -> str:
    label = r["effect"] + (f":{r['form']}" if r.get("form") else "")
    mark = {"named": "ok", "none": "ok", "absorbed": "abs"}.get(r["found"], "MISS")
    return (f"[{i:3d}/{n}] {mark:4s} {r['plant'][:3]} {r['cylinder']:20s} {label:30s} -> {r['verdict']:22s} "
            f"VALID {r['valid']['named_nrms']:6.2f}  {r['t_diagnose']:5.0f} s ({r['t_diagnose'] / r['t_calibrate']:.1f} "
            f"x calibrate)" + (f"  (built {r['compiled']} model functions)" if r.get("compiled") else ""))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true",
                    help=f"{', '.join(QUICK)} on the first cylinder (the reference plant: each word's standard form)")
    ap.add_argument("--plant", choices=("project", "reference", "both"), default="both")
    ap.add_argument("--cases", help="comma-separated: effect words, word:form (reference plant), `none` or case ids")
    ap.add_argument("--cylinders", default=",".join(CYLINDERS))
    ap.add_argument("--clean", type=int, default=2, help="effect-free cases per cylinder (default 2; --quick 1)")
    ap.add_argument("--duration", type=float, default=DURATION, help="s of TRAIN and of VALID (default 20)")
    ap.add_argument("--jobs", type=int, default=1,
                    help="cases at once, each diagnosis then on cores / jobs processes (timings need 1)")
    ap.add_argument("--out", type=Path, help="folder of the per-case results (JSON with the whole diagnosis); "
                                             "re-running skips the cases already there")
    ap.add_argument("--runs", type=Path, default=Path(os.environ.get("TMPDIR", "/tmp")) / "cr_gauntlet_runs",
                    help="cache of the reference plant's runs (simulated once; keyed by content)")
    args = ap.parse_args(argv)
    cylinders = args.cylinders.split(",")
    words, clean = (*ref.WORDS, "none"), args.clean
    if args.quick:
        cylinders, words, clean = cylinders[:1], QUICK, 1
    plants = ["project", "reference"] if args.plant == "both" else [args.plant]
    cases = [c for p in plants for c in case_list(p, cylinders, words, clean, standard_form_only=args.quick)]
    if args.cases:
        cases = [c for c in cases if selected(c, [s.strip() for s in args.cases.split(",") if s.strip()])]
    if not cases:
        print("no case matches --cases", file=sys.stderr)
        return 2
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
    done = {case_id(c): json.loads((args.out / f"{case_id(c)}.json").read_text()) for c in cases
            if args.out and (args.out / f"{case_id(c)}.json").exists()}
    todo = [c for c in cases if case_id(c) not in done]
    # the reference plant's runs at once (one vectorised simulation), before any case
    pairs = [reference_cases(c, load_cylinder(ROOT / "configs" / f"{c['cylinder']}.toml"), args.duration)
             for c in todo if c["plant"] == "reference"]
    if pairs:  # and VALID's true states, which the visibility replays start from (older caches lack them)
        ref.cached_runs([rc for pair in pairs for rc in pair], args.runs)
        ref.cached_states([valid for _, valid in pairs], args.runs)
    t_all = time.perf_counter()
    workers = max(1, (os.cpu_count() or 1) // max(1, args.jobs))
    jobs = [(c, args.duration, workers, args.runs, args.out) for c in todo]
    n = len(cases)
    for i, c in enumerate(cases):
        if case_id(c) in done:
            print(_progress_line(i + 1, n, done[case_id(c)]) + "  (stored)", flush=True)
    if args.jobs > 1 and len(jobs) > 1:
        with ProcessPoolExecutor(args.jobs) as pool:
            futures = [pool.submit(_run_and_store, j) for j in jobs]
            for k, f in enumerate(as_completed(futures)):
                r = f.result()
                done[r["id"]] = r
                print(_progress_line(len(done), n, r), flush=True)
    else:
        for j in jobs:
            r = _run_and_store(j)
            done[r["id"]] = r
            print(_progress_line(len(done), n, r), flush=True)
    print(f"\n{len(todo)} cases run in {time.perf_counter() - t_all:.0f} s ({len(cases) - len(todo)} stored)")
    rows = [done[case_id(c)] for c in cases]
    for p in plants:
        note = " (benchmarks/reference_plant.py: other forms of the effects and the valve)" if p == "reference" else ""
        mine = [r for r in rows if r["plant"] == p]
        if mine:
            report(mine, f"{p} plant{note}")
    if len(plants) > 1:
        print("\n===== both plants =====")
        summary(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
