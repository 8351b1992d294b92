"""The human report of a diagnosis (one self-contained HTML file) and its Rerun logging, on a
small hand-made Diagnosis (synthetic arrays, no model runs: fast)."""
import base64
import math
import re

import numpy as np
import pytest

from combined_reality.cli.diagnose import format_summary
from combined_reality.diagnose import Candidate, DiagnoseOptions, Diagnosis, regions, whiteness
from combined_reality.diagnose.report import render_report, write_report
from combined_reality.diagnose.text import headline, params_text
from combined_reality.identify import Validation
from combined_reality.report.text import format_value
from combined_reality.files import Run

N, DT = 4000, 1e-3
SEGMENTS = [(0, 1000), (1000, 2100), (2100, 3000), (3000, N)]
NOISE = np.array([5e-6, 300.0, 300.0])


def _validation(valid: Run, resid_x: np.ndarray, resid_p: float, rng) -> Validation:
    meas = np.vstack([valid.x, valid.p1, valid.p2])
    resid = np.vstack([resid_x, rng.normal(0, resid_p, N), rng.normal(0, resid_p, N)])
    cost = np.array([float(np.sum((resid[:, a:b] / NOISE[:, None]) ** 2)) for a, b in SEGMENTS])
    return Validation(("x", "p1", "p2"), meas - resid, resid, list(SEGMENTS), cost, NOISE.copy(), "converged")


def _diagnosis(cyl, verdict: str = "valve_delay", gap: bool = True) -> Diagnosis:
    rng = np.random.default_rng(0)
    t = np.arange(N) * DT
    x = 0.05 + 0.03 * np.sin(2 * np.pi * 0.7 * t)
    p1 = 4e5 + 5e4 * np.sin(2 * np.pi * 0.7 * t + 0.3)
    p2 = 4.5e5 - 3e4 * np.sin(2 * np.pi * 0.7 * t)
    u = 0.3 * np.cos(2 * np.pi * 0.7 * t)
    valid = Run(t=t, u=u, x=x + rng.normal(0, 5e-6, N), p1=p1, p2=p2)
    train = Run(t=t, u=u, x=x, p1=p1, p2=p2)
    v = np.gradient(x, t)
    base_x = (3e-4 * np.sign(v) * np.abs(np.sin(8 * t)) if gap else 0) + rng.normal(0, 5e-6, N)
    base = _validation(valid, base_x, 3000.0 if gap else 300.0, rng)
    good = _validation(valid, rng.normal(0, 5.1e-6, N), 310.0, rng)
    leak = _validation(valid, base_x * 0.98, 2900.0, rng)
    best = Candidate("valve_delay", shrink=1 - good.rmse("x") / base.rmse("x"), rmse_x_validation=good.rmse("x"),
                     params={"tau": 1.4159e-3, "share": 0.9988}, std={"tau": 1.9e-7, "share": 6.5e-4},
                     score=0.97, status="converged", shrink_all=0.98, z=5.4, significant=True,
                     friction={"Fc": 24.8, "Fv": 13.45, "kp": 2.89e-5}, wall_s=4.3, validation=good)
    other = Candidate("leakage", shrink=0.02, rmse_x_validation=leak.rmse("x"), params={"conductance": 0.0},
                      std={"conductance": 7e-12}, score=0.0, status="max_iterations", shrink_all=0.01, z=1.2,
                      significant=False, friction={"Fc": 22.3, "Fv": 0.0, "kp": 0.0}, wall_s=7.7, validation=leak)
    failed = Candidate("stiction", status="failed", wall_s=0.5,
                       error="IdentificationError: the line search failed <at iteration 3>")
    screened = Candidate("mass", params={"delta": 0.01}, std={"delta": 0.002}, status="no_gain_on_train", wall_s=1.1,
                         error="fits TRAIN no better than the nominal model (+0.01% of its cost): not validated")
    pair = Candidate("valve_delay+leakage", shrink=best.shrink, rmse_x_validation=good.rmse("x"),
                     params={"valve_delay.tau": 1.4e-3, "valve_delay.share": 1.0, "leakage.conductance": 1e-13},
                     std={"valve_delay.tau": 2e-7, "valve_delay.share": 1e-3, "leakage.conductance": 1e-14},
                     status="converged", shrink_all=0.98, z=0.4, significant=False, validation=good)
    if verdict == "none":
        best.significant, best.z, pair = False, 1.0, None
    ranking = [best, other, screened, failed]
    nrms = base.normalized_rms()
    baseline = {"rmse_x_validation": base.rmse("x"), "rmse_p1_validation": base.rmse("p1"),
                "rmse_p2_validation": base.rmse("p2"), "normalized_rms": nrms,
                "friction": {"Fc": 22.45, "Fv": 0.0, "kp": 0.0}, "friction_std": {"Fc": 10.3, "Fv": 24.9, "kp": 1.2e-4},
                "rmse_x_train": 2.8e-3, "horizon_s": 1.0, "noise": {"x": 5e-6, "p": 300.0}}
    subsystems = [
        {"subsystem": "piston force balance (friction, mass), driven by the measured pressures", "output": "x",
         "rmse": 1.36e-4, "floor": 1.65e-4, "unit": "m", "excess": 0.0, "within_noise": True, "share_of_error": 0.0},
        {"subsystem": "chamber pressures, valve near centre (chambers, leakage, heat)", "output": "p1, p2",
         "rmse": 7700.0, "floor": 300.0, "unit": "Pa", "excess": 660.0, "within_noise": False, "share_of_error": 0.5},
        {"subsystem": "chamber pressures, valve open (valve characteristic, timing, supply)", "error": "no samples",
         "excess": 0.0, "within_noise": False, "share_of_error": 0.0},
    ]
    correlations = [{"regressor": "command rate (du/dt)", "hints": "valve_delay", "r": 0.6, "n": 700},
                    {"regressor": "pressure difference (p1 - p2)", "hints": "leakage", "r": -0.1, "n": 700}]
    d = Diagnosis(cylinder=cyl, train=train, valid=valid,
                  options=DiagnoseOptions(candidates=("valve_delay", "leakage", "mass", "stiction"), workers=1),
                  baseline=baseline, verdict=verdict, ranking=ranking, pair=pair,
                  regions=regions(cyl, valid, base, good if verdict != "none" else None), subsystems=subsystems,
                  whiteness=whiteness(base.residual[0]), correlations=correlations, base_validation=base, wall_s=12.0)
    return d


@pytest.fixture(scope="module")
def diag(cyl_a):
    return _diagnosis(cyl_a)


def _images(text: str) -> list[bytes]:
    return [base64.b64decode(m) for m in re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', text)]


def test_the_report_is_one_self_contained_file_with_the_verdict_and_every_candidate(diag, tmp_path):
    path, png = tmp_path / "out" / "report.html", tmp_path / "png"
    path.parent.mkdir()  # writers create no folders (the command line checks them first)
    write_report(diag, path, png_dir=png)
    text = path.read_text(encoding="utf-8")
    assert text.startswith("<!DOCTYPE html>") and text.rstrip().endswith("</html>")
    # nothing outside the file: no remote or relative resources, no scripts or stylesheets to fetch
    assert not re.search(r'(?:src|href)\s*=\s*(?!["\']?(?:data:|#))', text, re.I)
    assert not re.search(r"https?://|<link|<script|@import|url\(", text, re.I)
    imgs = _images(text)
    assert len(imgs) == text.count("<img") == 6
    assert all(i.startswith(b"\x89PNG\r\n\x1a\n") for i in imgs)
    # the verdict in one sentence, with the shrink, the errors in um and the parameter in ms
    assert re.search(r"The gap is best explained by <b>valve_delay</b> .*shrinks by \d+ % "
                     r"\([\d.]+ um → [\d.]+ um\); tau = 1\.41590 ms ± 0\.00019 ms", text)
    assert ("Its parameters: tau is the time constant of the valve opening; share is the share of the opening "
            "that lags (1: a pure lag; 2: a dead time 2 tau).") in text  # what tau and share mean
    rows = re.findall(r"<tr[^>]*>.*?</tr>", text, re.S)
    for effect in ("valve_delay", "leakage", "mass", "stiction", "valve_delay+leakage"):
        assert any(f"<b>{effect}</b>" in r for r in rows), effect
    # a failed candidate shows its error (escaped), a parameter left at its bound is marked
    assert "IdentificationError: the line search failed &lt;at iteration 3&gt;" in text
    assert "conductance = 0 m³/(s·Pa) ± 7.0e-12 m³/(s·Pa) (at its bound)" in text
    assert "leakage.conductance = 1.00e-13" in text  # pair parameters with their effect's unit
    for section in ("Inputs", "Where the error lies", "Which subsystem carries it", "regressor screen"):
        assert section in text
    # the PNGs, and no temporary file left behind
    assert sorted(p.name for p in png.iterdir()) == sorted(
        ["a_residual_time.png", "b_residual_velocity.png", "c_residual_position.png", "d_traces.png",
         "e_regions.png", "f_subsystems.png"])
    assert [p.name for p in path.parent.iterdir()] == ["report.html"]


def test_none_verdict_says_so_in_plain_words(cyl_a):
    clean = _diagnosis(cyl_a, verdict="none", gap=False)
    text = render_report(clean, title="clean rig")
    assert "<title>clean rig</title>" in text
    assert "The nominal model already fits VALID to within the sensor noise" in text
    assert "Candidates tried: valve_delay, leakage, mass, stiction." in text
    assert len(_images(text)) == 6
    # a gap that no candidate explains is not "within the noise"
    unexplained = _diagnosis(cyl_a, verdict="none", gap=True)
    first = headline(unexplained)[0]
    assert first.startswith("No candidate effect explains the gap") and "none" in first


def test_write_is_atomic(diag, tmp_path, monkeypatch):
    import combined_reality.diagnose.report as rep

    monkeypatch.setattr(rep, "_make_plots", lambda d: {})  # the plots are not the point here
    path = tmp_path / "r.html"
    path.write_text("old report")
    monkeypatch.setattr(rep, "render_report", lambda *a, **k: (_ for _ in ()).throw(RuntimeError("boom")))
    with pytest.raises(RuntimeError):
        write_report(diag, path)
    assert path.read_text() == "old report"
    monkeypatch.setattr(rep, "render_report", render_report)
    write_report(diag, path, title="new")
    assert "<title>new</title>" in path.read_text(encoding="utf-8")
    assert [p.name for p in tmp_path.iterdir()] == ["r.html"]


def test_candidates_not_validated_are_described_as_such(cyl_a):
    d = _diagnosis(cyl_a, verdict="none", gap=True)
    assert ("Not validated, as they fit TRAIN no better than the nominal model (the fast screen): mass."
            in headline(d))
    text = render_report(d, plots={})
    row = next(r for r in re.findall(r"<tr[^>]*>.*?</tr>", text, re.S) if "<b>mass</b>" in r)
    # rank, then shrink of x, shrink of all outputs, z and x error: none exists without a validation
    assert re.findall(r'<td class="num">([^<]*)</td>', row) == ["3", "n/a", "n/a", "n/a", "n/a"]
    assert "no_<wbr>gain_<wbr>on_<wbr>train" in row  # may wrap, so the table stays on the page
    assert '<td colspan="9" class="small">fits TRAIN no better' in text  # a screen's reason, not an error
    # a pair that ended worse on TRAIN than the nominal model was not scored: not "not better than the verdict"
    d = _diagnosis(cyl_a)
    d.pair = Candidate("valve_delay+leakage", status="worse_than_nominal",
                       error="the fit ended worse on TRAIN than the nominal model it contains: a local minimum")
    last = headline(d)[-1]
    assert "was not scored on VALID: the fit ended worse on TRAIN" in last and "significantly" not in last


@pytest.mark.parametrize("value, std, unit, text", [
    (1.4159e-3, 1.9e-7, "s", "1.41590 ms ± 0.00019 ms"),
    (7.734e-3, 2e-5, "m/s", "7.734 mm/s ± 0.020 mm/s"),
    (2.89e-5, 6.6e-9, "N/Pa", "2.89000 N/bar ± 0.00066 N/bar"),
    (5.1447e-12, 6.3e-16, "m^3/(s Pa)", "5.14470e-12 m³/(s·Pa) ± 6.3e-16 m³/(s·Pa)"),
    (0.5, math.nan, "1", "0.5000"),
    (math.nan, 1.0, "N", "n/a"),
])
def test_values_are_shown_in_units_for_people(value, std, unit, text):
    assert format_value(value, std, unit) == text


def _read_rrd(path):
    from rerun.chunk import RrdReader

    data: dict[str, dict[str, list]] = {}
    for chunk in RrdReader(path).stream():
        rb = chunk.to_record_batch()
        cols = data.setdefault(chunk.entity_path, {})
        for name in rb.schema.names:
            if ":" in name:
                cols.setdefault(name.split(":", 1)[1], []).extend(rb.column(name).to_pylist())
    return data


@pytest.mark.parametrize("verdict", ["valve_delay", "none"])
def test_rerun_recording_holds_the_diagnosis(cyl_a, tmp_path, verdict):
    from combined_reality.diagnose.rerun import log_diagnosis
    from combined_reality.report.rerun import open_recording

    d = _diagnosis(cyl_a, verdict=verdict)
    rrd = tmp_path / "d.rrd"
    rec = open_recording("save", str(rrd))
    log_diagnosis(d, rec)
    rec.flush()
    rec.disconnect()
    data = _read_rrd(rrd)
    paths = ["/diagnosis/position/measured", "/diagnosis/position/nominal", "/diagnosis/pressure/p1/measured",
             "/diagnosis/pressure/p2/nominal", "/diagnosis/residual/x/nominal", "/diagnosis/residual/p1/nominal",
             "/diagnosis/command/u", "/diagnosis/velocity", "/diagnosis/segment", "/diagnosis/summary",
             "/diagnosis/regions/share_of_error", "/diagnosis/regions/fraction_of_samples",
             "/diagnosis/regions/labels"]
    after = ["/diagnosis/position/verdict", "/diagnosis/pressure/p1/verdict", "/diagnosis/residual/x/verdict"]
    for p in paths + (after if verdict != "none" else []):
        assert p in data, p
    if verdict == "none":
        assert not any(p.endswith("/verdict") for p in data)
    x = [v[0] for v in data["/diagnosis/position/measured"]["scalars"]]
    np.testing.assert_allclose(sorted(x), sorted(d.valid.x))
    r = [v[0] for v in data["/diagnosis/residual/x/nominal"]["scalars"]]
    np.testing.assert_allclose(sorted(r), sorted(d.base_validation.residual[0]))
    bars = data["/diagnosis/regions/share_of_error"]["values"][-1][0]  # a tensor
    np.testing.assert_allclose(bars["buffer"], [r_["share_of_error"] for r_ in d.regions])
    summary = data["/diagnosis/summary"]["text"][-1][0]
    for effect in ("valve\\_delay", "leakage", "mass", "stiction"):
        assert effect in summary
    assert "line search failed" in summary and "no\\_gain\\_on\\_train" in summary
    labels = data["/diagnosis/regions/labels"]["text"][-1][0]
    assert all(r_["where"].replace("|", "\\|") in labels for r_ in d.regions)


def test_a_small_parameter_far_inside_its_range_is_not_marked_at_its_bound():
    # a leak conductance of 1.9e-11 in a range of 0 to 1e-7: tiny, yet far from the bound 0
    inside = Candidate(effect="leakage", params={"conductance": 1.9e-11}, std={"conductance": 6e-16})
    assert "(at its bound)" not in params_text(inside, bounds=True)
    at_zero = Candidate(effect="leakage", params={"conductance": 0.0}, std={"conductance": 6e-16})
    assert "(at its bound)" in params_text(at_zero, bounds=True)


def test_an_undetermined_parameter_says_so_instead_of_printing_its_std():
    # a fit the data do not constrain: std 1e26 for a parameter whose range is -0.9 .. 10
    c = Candidate(effect="friction_position", params={"bump": -0.9, "slope": 0.5},
                  std={"bump": 9.87e25, "slope": 0.02})
    text = params_text(c, bounds=True)
    assert "bump = -0.9000 (not determined by the data) (at its bound)" in text
    assert "slope = 0.500 ± 0.020" in text
    assert format_value(-0.9, 9.87e25, "1") == "-0.900 ± 9.9e+25"  # never a 26-digit integer
    assert format_value(16.1794, 4.4e-34, "N s/m") == "16.1794 N s/m ± 4.4e-34 N s/m"  # nor 35 decimals


def test_a_regime_of_a_handful_of_samples_is_not_singled_out():
    from types import SimpleNamespace

    from combined_reality.diagnose.report import _regions_sentence

    d = SimpleNamespace(regions=[
        {"where": "high flow (|u| > 0.5)", "share_of_error": 0.001, "fraction_of_samples": 5e-5, "concentration": 18.4},
        {"where": "retraction (v < -5 mm/s)", "share_of_error": 0.6, "fraction_of_samples": 0.3, "concentration": 2.0}])
    text = _regions_sentence(d)
    assert text.startswith("Most concentrated: retraction") and "high flow" not in text


def test_when_every_candidate_is_screened_out_the_list_is_not_repeated(cyl_a):
    d = _diagnosis(cyl_a, verdict="none", gap=False)
    for c in d.ranking:
        c.status = "no_gain_on_train"
    lines = headline(d)
    assert lines[-1] == "None of them fits TRAIN better than the nominal model, so none was validated (the fast screen)."
    assert sum("valve_delay, leakage, mass, stiction" in line for line in lines) == 1


def test_an_unexplained_gap_and_a_pair_verdict_say_so_in_plain_words(cyl_a):
    d = _diagnosis(cyl_a)
    d.verdict = "unexplained"
    d.verdict_note = "the best candidate, valve_delay, explains only 30% of the gap"
    assert d.best is None and d.runner.effect == "valve_delay"
    lines = headline(d)
    assert lines[0].startswith("The gap is unexplained: the nominal model misses VALID by")
    assert "the best candidate, valve_delay, removes only part of it" in lines[0]
    assert "Why: the best candidate, valve_delay, explains only 30% of the gap." in lines
    text = render_report(d, plots={})
    assert "unexplained" in text and "Why: the best candidate" in text
    # both effects: the pair is the verdict, named and described as such
    d = _diagnosis(cyl_a)
    d.verdict = d.pair.effect
    d.verdict_note = "valve_delay alone explains 40% of the gap, together with leakage 95%"
    assert d.best is d.pair
    lines = headline(d)
    assert lines[0].startswith("The gap is best explained by valve_delay+leakage")
    assert "Why the pair: valve_delay alone explains 40% of the gap, together with leakage 95%." in lines
    assert not any("Together with the runner-up" in line for line in lines)
    assert "valve_delay+leakage" in render_report(d, plots={})


def test_a_gap_no_candidate_touches_is_unexplained_in_words(cyl_a):
    d = _diagnosis(cyl_a, verdict="none", gap=True)
    d.verdict = "unexplained"
    assert d.runner is None
    first = headline(d)[0]
    assert first.startswith("The gap is unexplained: the nominal model misses VALID by")
    assert "none of the 4 candidates tried removes a significant part of it" in first


def test_mis_set_quantities_follow_the_headline(cyl_a):
    d = _diagnosis(cyl_a)
    d.calibration = {"mis_set": [{"quantity": "mass", "file": 1.036, "calibrated": 0.74, "std": 0.004, "unit": "kg",
                                  "change": 0.74 / 1.036 - 1}], "status": "converged", "wall_s": 9.0}
    lines = headline(d)
    assert lines[0].startswith("The gap is best explained by valve_delay")
    assert lines[1].startswith("The cylinder file's valve, dead volumes, mass and sensor offsets were calibrated")
    assert "mis-set in the file: mass 1.036 kg → 0.7400 kg ± 0.0040 kg (-29 %)." in lines[1]


def test_a_verdict_whose_fit_did_not_settle_says_its_values_are_not_the_rigs(cyl_a):
    """The verdict's values are no measurement where its fit on TRAIN stopped before converging
    above the noise (a reference-plant stiction: line search failed after 59 iterations at 15.4 x),
    or converged far above it; a fit that settled near the noise gets no caveat."""
    d = _diagnosis(cyl_a)
    assert not any("TRAIN" in line and "rig's" in line for line in headline(d))  # as filed, converged
    d.best.status, d.best.iterations = "line_search_failed", 59
    d.best.calibration = {"residual_sigma": 15.39, "start": "staged"}
    lines = headline(d)
    assert ("Its fit on TRAIN stopped before converging (its line search failed after 59 iterations) at 15.4 × the "
            "sensor noise on TRAIN: its values are where the fit stopped, not the rig's; the effect is named because "
            "it predicts VALID best.") in lines
    assert "stopped before converging" in render_report(d, plots={})
    assert d.to_json()["verdict_caveat"].startswith("Its fit on TRAIN stopped before converging")
    d.best.status = "converged"
    assert any(line.startswith("Even with it, the calibrated model stays at 15.4 × the sensor noise on TRAIN")
               for line in headline(d))
    d.best.calibration["residual_sigma"] = 1.12  # settled near the noise: nothing to add
    assert not any("TRAIN" in line and "rig's" in line for line in headline(d))
    assert d.to_json()["verdict_caveat"] == ""
    d.best.status = "max_iterations"  # ran out of iterations at the noise: its values are fine
    assert not any("TRAIN" in line and "rig's" in line for line in headline(d))
    d.best.calibration = None  # as filed, no residual to judge by: the stop is said
    assert any(line.startswith("Its fit on TRAIN stopped before converging (it ran out of iterations after 59 "
                               "iterations):") for line in headline(d))


def _high_flow_miss(cyl, train_goes_there: bool) -> Diagnosis:
    """The verdict's model misses VALID by several times the noise where the valve opens past
    0.5 (a quarter of VALID's samples); TRAIN has the same commands, or stays below 0.5."""
    d = _diagnosis(cyl)
    rng = np.random.default_rng(1)
    t = d.valid.t
    small = 0.3 * np.cos(2 * np.pi * 0.7 * t)
    u = np.where(t % 1.0 < 0.25, np.where(small >= 0, 0.8, -0.8), small)
    d.valid = Run(t=t, u=u, x=d.valid.x, p1=d.valid.p1, p2=d.valid.p2)
    d.train = Run(t=t, u=u if train_goes_there else small, x=d.train.x, p1=d.train.p1, p2=d.train.p2)
    miss = np.where(np.abs(u) > 0.5, rng.normal(0, 4e-5, N), rng.normal(0, 5e-6, N))
    d.best.validation = _validation(d.valid, miss, 300.0, rng)
    return d


def test_a_model_that_misses_valid_where_train_did_not_go_says_so(cyl_a):
    """Beyond trusted_valid x the noise on VALID the shown model's predictions carry a caveat
    naming the regime where its error gathers, with the shares of VALID's and TRAIN's samples
    there: too little in TRAIN is the runs' fault, as much as VALID the model's."""
    d = _high_flow_miss(cyl_a, train_goes_there=False)
    doc = d.to_json()["prediction"]
    assert doc["model"] == "valve_delay" and doc["normalized_rms"] > d.options.trusted_valid
    (row,) = [r for r in doc["regions"] if r["where"] == "high flow (|u| > 0.5)"]
    assert row["concentration"] > 2 and row["train_fraction"] == 0.0 and not row["taught"]
    assert 0.2 < row["valid_fraction"] < 0.3
    lines = headline(d)
    (said,) = [line for line in lines if line.startswith("Do not take its predictions for the rig's")]
    assert "the model with valve_delay still misses VALID by" in said
    assert "high flow (|u| > 0.5)" in said and "TRAIN 0.0%" in said and "TRAIN showed the model too little" in said
    assert doc["caveat"] == said
    assert f"prediction: {said}" in format_summary(d.to_json(), 1.0).splitlines()  # the console says it too
    # TRAIN went there as much as VALID: the model lacks something, not the runs
    d = _high_flow_miss(cyl_a, train_goes_there=True)
    (row,) = [r for r in d.prediction()["regions"] if r["where"] == "high flow (|u| > 0.5)"]
    assert row["taught"] and abs(row["train_fraction"] - row["valid_fraction"]) < 0.01
    said = d.prediction()["caveat"]
    assert "which TRAIN showed as much as VALID: the model still lacks something there" in said
    assert "too little" not in said
    # TRAIN of two runs (diagnose --calibrate cal.csv run.csv): their samples pooled
    d.train_runs = (_high_flow_miss(cyl_a, train_goes_there=False).train, d.train)
    (row,) = [r for r in d.prediction()["regions"] if r["where"] == "high flow (|u| > 0.5)"]
    assert row["train_fraction"] == pytest.approx(row["valid_fraction"] / 2)
    # within trusted_valid: nothing to add
    d = _diagnosis(cyl_a)
    assert d.prediction()["caveat"] == "" and d.prediction()["regions"] == []
    assert not any(line.startswith("Do not take") for line in headline(d))
    # verdict none: the nominal model is the one shown, unexplained shows none
    d = _high_flow_miss(cyl_a, train_goes_there=False)
    d.verdict, d.base_validation = "none", d.best.validation
    d.ranking[0].significant = False
    assert d.best is None and d.prediction()["model"] == "none"
    assert any(line.startswith("Do not take its predictions for the rig's: the model without an effect")
               for line in headline(d))
    d.verdict = "unexplained"
    assert d.prediction() is None and d.to_json()["prediction"] is None
