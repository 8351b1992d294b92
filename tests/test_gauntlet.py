"""The gauntlet benchmark's cases (benchmarks/gauntlet.py): drawn from the case's seed alone,
the project plant's truth holds the departures on the tool's own grid, what departs beyond the
mis-set thresholds is told from the truth, and a stored run of a changed program is not reused."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import gauntlet  # noqa: E402
import reference_plant as ref  # noqa: E402
from combined_reality.live import catalogue  # noqa: E402
from sim.cylinder import OPENING_GRID  # noqa: E402


def test_the_cases_cover_every_word_and_form_on_both_plants():
    words = (*ref.WORDS, "none")
    project = gauntlet.case_list("project", gauntlet.CYLINDERS, words, 2)
    reference = gauntlet.case_list("reference", gauntlet.CYLINDERS, words, 2)
    assert len(project) == 2 * (len(ref.WORDS) + 2)
    assert len(reference) == 2 * (len(ref.EFFECT_FORMS) + 2)
    assert len({gauntlet.case_id(c) for c in project + reference}) == len(project) + len(reference)
    quick = gauntlet.case_list("reference", gauntlet.CYLINDERS[:1], gauntlet.QUICK, 1, standard_form_only=True)
    assert [c["effect"] for c in quick] == list(gauntlet.QUICK)


@pytest.mark.parametrize("plant", ["project", "reference"])
def test_a_case_is_drawn_from_its_seed_alone(cyl_a, plant):
    case = {"plant": plant, "cylinder": "cyl_a_32x100", "effect": "friction_asymmetry", "draw": 0}
    if plant == "reference":
        case["form"] = ref.forms_of("friction_asymmetry")[1].FORM
    (dep, eff), (dep2, eff2) = gauntlet.draw(case, cyl_a), gauntlet.draw(dict(case), cyl_a)
    assert dep.to_json() == dep2.to_json() and eff == eff2 and eff is not None
    other, _ = gauntlet.draw({**case, "effect": "leakage", "form": "piston"}, cyl_a)
    assert other.to_json() != dep.to_json()
    # departures like the calibration benchmark's, an effect at a realistic strength
    assert 0.5 <= dep.conductance_pos <= 1.5 and 0.15 <= dep.critical_ratio <= 0.5
    assert abs(dep.offset_p1) <= 5e3
    if plant == "reference":
        assert not eff.is_neutral()
    else:
        assert eff.a_coulomb != 0
    if plant == "reference":
        train, valid = gauntlet.reference_cases(case, cyl_a, 20.0)
        assert (train.program, valid.program) == ("calibration", "mixed") and train.seed != valid.seed
        assert train.key() == gauntlet.reference_cases(case, cyl_a, 20.0)[0].key()


def test_the_project_truth_holds_the_departures_on_the_tools_grid(cyl_a):
    case = {"plant": "project", "cylinder": "cyl_a_32x100", "effect": "none", "draw": 0}
    dep, effect = gauntlet.draw(case, cyl_a)
    truth = gauntlet.project_truth(cyl_a, dep)
    assert effect is None
    assert truth.value("mass") == dep.moving_mass and truth.value("offset_p2") == dep.offset_p2
    assert truth.valve.overlap_extend == dep.characteristic_pos.overlap
    np.testing.assert_allclose(truth.valve.flow_retract,
                               dep.conductance_neg * dep.characteristic_neg.g(np.asarray(OPENING_GRID)))
    calibrated = gauntlet.truth_of(case, cyl_a)["calibrated"]
    assert gauntlet.departed_quantities(cyl_a, ref.Calibration(), {n: cyl_a.value(n) for n in calibrated}) == []
    heavier = {**{n: cyl_a.value(n) for n in calibrated}, "mass": 1.03 * cyl_a.value("mass")}
    assert gauntlet.departed_quantities(cyl_a, ref.Calibration(), heavier) == ["mass"]
    assert "valve characteristic" in gauntlet.departed_quantities(cyl_a, dep, calibrated)


def test_what_counts_as_found():
    assert gauntlet.effect_found("leakage", "leakage", []) == "named"
    assert gauntlet.effect_found("leakage", "heat_transfer+leakage", []) == "named"
    assert gauntlet.effect_found("leakage", "unexplained", []) == "missed"
    assert gauntlet.effect_found("mass", "none", ["mass"]) == "absorbed"
    assert gauntlet.effect_found("leakage", "none", ["mass"]) == "missed"
    assert gauntlet.effect_found("none", "none", ["mass"]) == "none"
    assert gauntlet.effect_found("none", "stiction", []) == "missed"


def test_a_stored_run_of_a_changed_program_is_not_taken_for_a_new_one(cyl_a, monkeypatch):
    cal, mixed = (ref.Case(cyl_a, 0.05, 4, program=p) for p in ("calibration", "mixed"))
    before = cal.key(), mixed.key()
    monkeypatch.setitem(catalogue.REVISIONS, "calibration", catalogue.REVISIONS["calibration"] + 1)
    assert cal.key() != before[0] and mixed.key() == before[1]


def test_times_of_cases_run_beside_others_are_said_not_to_be_this_machines(capsys):
    """A case that ran with fewer workers than the machine's cores (--jobs > 1) shares the cores:
    the summary says its time is not the target's measure; a case on every core is not named."""
    def row(workers):
        return {"effect": "none", "id": f"w{workers}", "verdict": "none", "found": "none",
                "mis_set": {"departed": [], "listed": []}, "valid": {"named_nrms": 1.0},
                "friction": {"errors": {}}, "floor": {}, "t_diagnose": 60.0, "t_calibrate": 10.0,
                "workers": workers, "cores": 2}

    gauntlet.summary([row(2), row(2)])
    assert "ran beside other cases" not in capsys.readouterr().out
    gauntlet.summary([row(2), row(1)])
    assert "1 of these ran beside other cases" in capsys.readouterr().out


@pytest.mark.slow
def test_a_reference_effect_shows_by_how_much_its_replay_without_it_misses_valid(cyl_a, monkeypatch, tmp_path):
    """The reference plant's visibility: VALID's segments replayed on the plant without the effect,
    from the true states, with the departed file. Effect-free, the replay leaves just the noise (the
    departures are replayed too); a strong leak is far from it; a leak of a thousandth of that is
    barely visible, and counted apart."""
    c = {"plant": "reference", "cylinder": "cyl_a_32x100", "effect": "leakage", "form": "piston", "draw": 0}
    departure = ref.Calibration(conductance_pos=0.8, offset_p1=3000.0, moving_mass=1.3 * cyl_a.value("mass"))
    floors = {}
    for name, effect in (("none", None), ("strong", ref.LeakPiston(q_ref=3e-5)), ("faint", ref.LeakPiston(q_ref=3e-8))):
        monkeypatch.setattr(gauntlet, "draw", lambda *_a, e=effect: (departure, e))
        _, case = gauntlet.reference_cases(c, cyl_a, 3.0)
        valid = ref.cached_runs([case], tmp_path)[0]
        floors[name] = f = gauntlet.reference_floor(c, cyl_a, valid, 3.0, tmp_path)
        assert f["noise_nrms"] == pytest.approx(1.0, abs=0.05)
    assert floors["none"]["without_effect_nrms"] == pytest.approx(floors["none"]["noise_nrms"], rel=1e-3)
    assert floors["strong"]["without_effect_nrms"] > 3 * floors["strong"]["noise_nrms"]
    faint = {**c, "floor": floors["faint"]}
    assert gauntlet.is_faint(faint) and not gauntlet.is_faint({**c, "floor": floors["strong"]})
    assert not gauntlet.is_faint({**faint, "effect": "none"})


@pytest.mark.slow
def test_the_true_states_of_valid_are_simulated_with_the_runs_before_any_case(tmp_path, monkeypatch):
    """A run cache from before the true states were kept (CSV only) gets VALID's states in the one
    batch before the cases, not a simulation of its own inside each case."""
    args = ["--plant", "reference", "--cases", "leakage:piston", "--cylinders", "cyl_a_32x100", "--duration", "0.2",
            "--runs", str(tmp_path)]

    class FirstCase(Exception):
        pass

    def first_case(*_a, **_k):
        raise FirstCase

    monkeypatch.setattr(gauntlet, "run_case", first_case)
    with pytest.raises(FirstCase):
        gauntlet.main(args)
    for npz in tmp_path.glob("*.states.npz"):
        npz.unlink()  # the cache as an older gauntlet left it
    batches = []
    simulate = ref.simulate_detailed
    monkeypatch.setattr(ref, "simulate_detailed", lambda cases, *a, **k: batches.append(
        [c.program for c in cases]) or simulate(cases, *a, **k))
    with pytest.raises(FirstCase):
        gauntlet.main(args)
    assert batches == [["mixed"]]  # VALID alone, once, before the first case
    assert len(list(tmp_path.glob("*.states.npz"))) == 1


@pytest.mark.slow
def test_a_hard_dead_zone_the_calibration_took_into_the_overlap_is_named(tmp_path):
    """A gauntlet case: the reference plant's valve stays shut up to 0.02 and then opens to the full
    command, on a Norgren cylinder whose file is off. The calibration takes the dead zone into its
    overlaps (the valve and chambers fit to the noise with the motion measured, so the gate's screen
    gains nothing) and leaves the whole model at 1.44 x the noise; the gate calibrated with that
    overlap handed over is named, with the truth's overlap."""
    from combined_reality.diagnose import DiagnoseOptions, diagnose

    c = {"plant": "reference", "cylinder": "ind3_norgren_40x250", "effect": "valve_deadzone", "form": "hard",
         "draw": 0}
    cyl = gauntlet.load_cylinder(gauntlet.ROOT / "configs" / "ind3_norgren_40x250.toml")
    truth = gauntlet.draw(c, cyl)[1]
    train, valid = gauntlet.case_runs(c, cyl, 20.0, tmp_path)
    d = diagnose(cyl, train, valid, DiagnoseOptions(calibrate=True, workers=1, candidates=(
        "valve_deadzone", "valve_delay", "leakage", "mass"))).to_json()
    assert d["verdict"] == "valve_deadzone", d["verdict_note"]
    row = next(r for r in d["ranking"] if r["effect"] == "valve_deadzone")
    assert row["calibration"]["start"] == "handed-over"
    assert row["params"]["overlap"] == pytest.approx(truth.d, rel=0.05) and row["params"]["gate"] > 0.9
    assert row["normalized_rms_validation"] < 0.7 * d["baseline"]["normalized_rms"]
