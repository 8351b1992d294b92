"""The static friction map: points from runs and tables, per-direction fits, flags, command.

Every model's fit agrees with scipy's curve_fit on the same static curve from the same
start; noisy points give back the parameters they were made with; parameters the points
cannot show are flagged; points and breakaways of a constructed run are exact; the map of
a virtual-rig run lies on the true friction curve; bad tables are refused in one sentence.
"""
import argparse
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import curve_fit

from combined_reality.cli import friction_map as cli_friction
from combined_reality.errors import InputError
from combined_reality.friction.fits import fit_model, linear_fit
from combined_reality.friction.map import build_map
from combined_reality.friction.points import MapPoint, points_from_run
from combined_reality.friction.specs import (FIT_SPECS, PARSIMONY, FrictionMapError, PointsFormatError, SegmentOptions,
                                            TooFewPointsError)
from combined_reality.friction.tables import read_points
from combined_reality.files import Run, write_run
from sim.friction_models import (CV, CVS, DIRECTIONS, Belforte, CVLoad, CVPressure, CVSLoad, Efficiency, Karnopp,
                                 LuGre, Threlfall, without_nominal_friction)

# seed 004 Table 3, actuator 2 (Norgren 32 x 100), SI, magnitudes
TABLE3_N2 = dict(Fc_pos=16.87, Fc_neg=13.47, Fs_pos=22.0, Fs_neg=20.0, vs_pos=0.00342, vs_neg=0.00616,
                 B_pos=178.85, B_neg=165.59)

# the truth each fit is tried on (fit name -> model)
TRUTH = {
    "cv": CV(Fc_pos=16.9, Fc_neg=13.5, B_pos=179.0, B_neg=166.0),
    "karnopp": Karnopp(Fc_pos=16.9, Fc_neg=13.5, Fs_pos=22.0, Fs_neg=20.0, B_pos=179.0, B_neg=166.0,
                       dv_pos=0.005, dv_neg=0.008),
    "threlfall": Threlfall(Fc_pos=16.9, Fc_neg=13.5, ve_pos=0.006, ve_neg=0.01, B_pos=179.0, B_neg=166.0),
    "cvs": CVS(**TABLE3_N2),
    "cvs_delta": CVS(**TABLE3_N2, delta_pos=1.5, delta_neg=2.5),
    "lugre": LuGre(**TABLE3_N2),
    "cv_load": CVLoad(Fc_pos=10.0, Fc_neg=8.0, mu_pos=0.2, mu_neg=0.3, B_pos=150.0, B_neg=120.0,
                      mu_v_pos=0.5, mu_v_neg=0.8),
    "cvs_load": CVSLoad(Fc_pos=10.0, Fc_neg=8.0, mu_pos=0.2, mu_neg=0.3, Fs_pos=14.0, Fs_neg=12.0, mu_s_pos=0.3,
                        mu_s_neg=0.35, vs_pos=0.004, vs_neg=0.006, B_pos=150.0, B_neg=120.0, mu_v_pos=0.5,
                        mu_v_neg=0.8),
    "belforte": Belforte(FA_pos=8.0, FA_neg=6.0, K1_pos=3.0, K1_neg=2.0, alpha_pos=0.8, alpha_neg=1.2,
                         K2_pos=2e-5, K2_neg=1.5e-5, K3_pos=1e-5, K3_neg=2e-5),
    "belforte_dp": Belforte(FA_pos=8.0, FA_neg=6.0, K1_pos=3.0, K1_neg=2.0, alpha_pos=0.8, alpha_neg=1.2,
                            K2_pos=2e-5, K2_neg=1.5e-5, K3_pos=0.0, K3_neg=0.0),
    "cv_dp": CVPressure(Fc_pos=16.9, Fc_neg=13.5, kp_pos=2e-5, kp_neg=3e-5, Fv_pos=179.0, Fv_neg=166.0),
    "efficiency": Efficiency(kp_pos=2e-5, kp_neg=3e-5),
}


def _points(model, speeds, noise=0.2, seed=3, **fixed_cond):
    """Points of a model's static curve at +-speeds with white force noise; conditions random
    (as many distinct loads and pressures as points, so load and pressure terms are visible)."""
    rng = np.random.default_rng(seed)
    v = np.concatenate([speeds, -np.asarray(speeds)])
    cond = {"dp": rng.uniform(0.5e5, 5e5, v.size), "pc": rng.uniform(0.0, 3e5, v.size),
            "load": rng.uniform(0.0, 100.0, v.size)}
    cond.update({k: np.full(v.size, x) for k, x in fixed_cond.items()})
    F = model.static_curve(v, **cond) + rng.normal(0.0, noise, v.size)
    return [MapPoint(v=float(a), F=float(f), dp=float(d), pc=float(c), load=float(l))
            for a, f, d, c, l in zip(v, F, cond["dp"], cond["pc"], cond["load"])]


def _direction(points, direction):
    return [p for p in points if p.direction == direction]


def _table(tmp_path, points, name="points.csv", columns=("v", "F")):
    lines = ["# friction map points, SI", ",".join(columns)]
    lines += [",".join(repr(getattr(p, c)) for c in columns) for p in points]
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def _cli(argv):
    """The subcommand through its own parser (independent of the wiring in cli.py)."""
    parser = argparse.ArgumentParser(prog="combined-reality")
    sub = parser.add_subparsers(dest="command", required=True)
    cli_friction.add_parser(sub)
    args = parser.parse_args(["friction-map", *map(str, argv)])
    return args.func(args)


# ------------------------------------------------------------------ fits against scipy's curve_fit

@pytest.mark.parametrize("name", list(FIT_SPECS))
def test_fit_agrees_with_curve_fit(name):
    """Same static curve, same points, same start: the same parameters (1e-6 relative) and the
    same standard deviations as curve_fit (Levenberg-Marquardt, finite differences); R^2, RMSE
    and MAE as defined (seed 000 Eq. 10; seed 003's mean error = mean |residual|)."""
    model = TRUTH[name]
    cls = type(model)
    spec = FIT_SPECS[name]
    speeds = np.geomspace(0.01 if name == "karnopp" else 1e-3, 0.3, 30)
    for direction, (suffix, _) in DIRECTIONS.items():
        pts = _direction(_points(model, speeds), direction)
        fixed = {"dv": getattr(model, f"dv_{suffix}"), "Fs": 20.0} if name == "karnopp" else {}
        fit = fit_model(pts, spec, fixed)
        assert fit.status == "converged" and fit.direction == direction
        v = np.array([p.v for p in pts])
        F = np.array([p.F for p in pts])
        cond = {k: np.array([getattr(p, k) for p in pts]) for k in cls.CONDITIONS}
        names = list(cls.PARAMS)
        base = np.array([cls.defaults()[k] for k in names])
        for b, val in {**spec.fixed, **fixed}.items():
            base[names.index(f"{b}_{suffix}")] = val
        idx = [names.index(f"{b}_{suffix}") for b in fit.free]

        def curve(i, *theta):
            p = base.copy()
            p[idx] = theta
            i = i.astype(int)
            return cls.static_force(v[i], p, **{k: c[i] for k, c in cond.items()})

        popt, pcov = curve_fit(curve, np.arange(len(v), dtype=float), F, p0=[fit.start[b] for b in fit.free],
                               ftol=1e-14, xtol=1e-14, gtol=1e-14, maxfev=100_000)
        ours = np.array([fit.params[b] for b in fit.free])
        np.testing.assert_allclose(ours, popt, rtol=1e-6)
        np.testing.assert_allclose([fit.std[b] for b in fit.free], np.sqrt(np.diag(pcov)), rtol=1e-4)
        res = F - curve(np.arange(len(v), dtype=float), *popt)
        assert fit.r2 == pytest.approx(1 - np.sum(res**2) / np.sum((F - F.mean()) ** 2), rel=1e-9)
        assert fit.rmse == pytest.approx(np.sqrt(np.mean(res**2)), rel=1e-6)
        assert fit.mae == pytest.approx(np.mean(np.abs(res)), rel=1e-6)
        assert 0.99 < fit.r2 <= 1.0 and fit.dof == len(v) - len(fit.free)
        for b in fit.free:  # 95 % intervals with Student's t
            lo, hi = fit.ci95[b]
            assert lo < fit.params[b] < hi


def test_parameters_recovered_from_noisy_points():
    """Seed 004 Table 3 (actuator 2) with 0.2 N noise on 20 speeds per direction, 1-300 mm/s."""
    truth = CVS(**TABLE3_N2)
    fmap = build_map(_points(truth, np.geomspace(1e-3, 0.3, 20), seed=7), ["cvs", "cv", "cvs_delta"], strict=True)
    for direction, (suffix, _) in DIRECTIONS.items():
        d = fmap.directions[direction]
        fit = d.fits["cvs"]
        t = {b: getattr(truth, f"{b}_{suffix}") for b in ("Fc", "Fs", "vs", "B")}
        assert fit.params["Fc"] == pytest.approx(t["Fc"], abs=0.3)
        assert fit.params["Fs"] == pytest.approx(t["Fs"], abs=0.6)
        assert fit.params["vs"] == pytest.approx(t["vs"], rel=0.15)
        assert fit.params["B"] == pytest.approx(t["B"], rel=0.02)
        for b, x in t.items():  # the truth inside the 95 % interval
            lo, hi = fit.ci95[b]
            assert lo <= x <= hi, (direction, b, x, fit.ci95[b])
        assert not fit.flags
        assert d.fits["cvs_delta"].params["delta"] == pytest.approx(2.0, abs=0.4)
        # the Stribeck curve explains the points better than the straight line, for its parameters too
        assert d.fits["cvs"].aicc < d.fits["cv"].aicc and d.fits["cvs"].r2 > d.fits["cv"].r2
    ext = fmap.to_json()["models"]["cvs"]
    assert ext["params"]["Fc_neg"] == pytest.approx(13.47, abs=0.3) and ext["spec"].startswith("cvs:Fc_pos=")


def test_load_and_pressure_terms_recovered():
    truth = TRUTH["cv_load"]
    fit = fit_model(_direction(_points(truth, np.geomspace(2e-3, 0.3, 25), noise=0.1), "retraction"), "cv_load")
    assert fit.params["mu"] == pytest.approx(truth.mu_neg, abs=0.01)
    assert fit.params["mu_v"] == pytest.approx(truth.mu_v_neg, abs=0.1)
    truth = TRUTH["belforte"]
    fit = fit_model(_direction(_points(truth, np.geomspace(2e-3, 0.3, 25), noise=0.05), "extension"), "belforte")
    assert fit.params["K2"] == pytest.approx(truth.K2_pos, rel=0.1)
    assert fit.params["K3"] == pytest.approx(truth.K3_pos, rel=0.1)


# ------------------------------------------------------------------ identifiability

def test_stribeck_velocity_below_the_slowest_speed_is_flagged():
    """Only the tail of the Stribeck drop reaches the slowest points: the fitted vs lies below
    them and is flagged; with no trace of the drop at all, vs is flagged as undetermined."""
    truth = CVS(**{**TABLE3_N2, "vs_pos": 3e-3, "vs_neg": 3e-3})
    fmap = build_map(_points(truth, np.geomspace(4e-3, 0.3, 15), noise=0.05), ["cvs"], strict=True)
    for d in fmap.directions.values():
        fit = d.fits["cvs"]
        flagged = {f["param"]: f["reason"] for f in fit.flags}
        assert fit.params["vs"] < 4e-3
        assert "vs" in flagged and "below the slowest tested speed 0.004 m/s" in flagged["vs"]
    truth = CVS(**{**TABLE3_N2, "vs_pos": 5e-4, "vs_neg": 5e-4})
    fmap = build_map(_points(truth, np.geomspace(5e-3, 0.3, 15)), ["cvs"], strict=True)
    for d in fmap.directions.values():
        assert "vs" in {f["param"] for f in d.fits["cvs"].flags}
    # resolved: points slower than vs, nothing flagged
    fmap = build_map(_points(CVS(**TABLE3_N2), np.geomspace(1e-3, 0.3, 15)), ["cvs"], strict=True)
    assert all(not d.fits["cvs"].flags for d in fmap.directions.values())


def test_undetermined_parameters_are_flagged():
    pts = _points(TRUTH["cvs"], np.geomspace(1e-3, 0.3, 15), load=30.0)  # one load for every point
    fmap = build_map(pts, ["lugre", "cv_load", "karnopp"], strict=True)
    for d in fmap.directions.values():
        lugre = {f["param"] for f in d.fits["lugre"].flags}
        assert {"sigma0", "sigma1"} <= lugre and d.fits["lugre"].params["sigma0"] is None
        cv_load = d.fits["cv_load"]  # Fc and mu Fn cannot be told apart at one load
        assert math.isinf(cv_load.std["mu"]) and "mu" in {f["param"] for f in cv_load.flags}
        karnopp = d.fits["karnopp"]  # no breakaway in a table of steady speeds
        assert karnopp.params["Fs"] is None and "Fs" in {f["param"] for f in karnopp.flags}
        assert karnopp.params["dv"] == pytest.approx(1e-3)  # the slowest steady speed


def test_linear_fit_is_seed_000_least_squares():
    pts = _points(TRUTH["cv"], np.geomspace(5e-3, 0.3, 12))
    for direction in DIRECTIONS:
        p = _direction(pts, direction)
        lin = linear_fit(p)
        v, F = np.array([q.v for q in p]), np.array([q.F for q in p])
        slope, intercept = np.polyfit(v, F, 1)
        assert lin.B == pytest.approx(slope, rel=1e-10)
        assert lin.Fc == pytest.approx(abs(intercept), rel=1e-10)  # F = -Fc + B v retracting
        cv = fit_model(p, "cv")
        assert cv.params["Fc"] == pytest.approx(lin.Fc, rel=1e-8) and cv.r2 == pytest.approx(lin.r2, rel=1e-10)


def test_breakaway_rows_are_not_fitted_as_sliding_points():
    """Rows marked breakaway (procedure breakaway) feed the stick band, karnopp's Fs and the Fs of
    cvs/lugre; every fit is of the sliding points alone, so cv and the linear fit are those of the
    sliding points and vs below the slowest sliding speed is flagged."""
    truth = CVS(**{**TABLE3_N2, "vs_pos": 4e-3, "vs_neg": 4e-3})
    sliding = _points(truth, np.geomspace(0.006, 0.3, 8), noise=0.05)  # the tail of the Stribeck drop, no more
    trials = {1: np.array([21.9, 22.1, 22.0, 22.2]), -1: np.array([19.8, 20.1, 20.0])}
    rows = [MapPoint(v=s * 1e-4, F=s * float(f.mean()), F_std=float(f.std(ddof=1)), count=len(f), breakaway=True)
            for s, f in trials.items()]
    with_rows = build_map(sliding + rows, ["cv", "karnopp", "cvs"], strict=True)
    without = build_map(sliding, ["cv", "karnopp", "cvs"], strict=True)
    for direction, (suffix, s) in DIRECTIONS.items():
        d, ref = with_rows.directions[direction], without.directions[direction]
        assert d.fits["cv"].params == ref.fits["cv"].params and d.linear.Fc == ref.linear.Fc
        assert d.stick_band.dv == ref.stick_band.dv == pytest.approx(0.006)  # the slowest sliding point
        band = d.stick_band
        assert band.breakaway_count == len(trials[s])
        assert band.breakaway_mean == pytest.approx(trials[s].mean(), rel=1e-12)
        assert band.breakaway_std == pytest.approx(trials[s].std(ddof=1), rel=1e-12)
        for name in ("karnopp", "cvs"):
            fit = d.fits[name]
            assert fit.params["Fs"] == pytest.approx(trials[s].mean(), rel=1e-12) and "Fs" in fit.fixed
            assert fit.std["Fs"] == pytest.approx(trials[s].std(ddof=1) / math.sqrt(len(trials[s])), rel=1e-12)
            assert fit.n_points == 8
        cvs = d.fits["cvs"]
        assert cvs.params["vs"] == pytest.approx(getattr(truth, f"vs_{suffix}"), rel=0.3)
        assert "below the slowest tested speed 0.006 m/s" in {f["param"]: f["reason"] for f in cvs.flags}["vs"]
        assert "Fs" in {f["param"] for f in ref.fits["karnopp"].flags}  # without rows: no breakaway
        assert [p.breakaway for p in d.points] == [True] + [False] * 8
    # pooled: rows and single breakaways of runs together, as one sample of all trials
    from combined_reality.friction.map import StickBand
    band = StickBand("extension", 0.01, False, (21.5, 22.4), None, None, breakaway_rows=((22.05, 0.129, 4),))
    everything = np.concatenate([[21.5, 22.4], trials[1]])
    assert band.breakaway_count == 6 and band.breakaway_mean == pytest.approx(everything.mean(), rel=1e-12)
    assert band.breakaway_std == pytest.approx(everything.std(ddof=1), rel=1e-3)  # 0.129 is rounded


def test_too_few_points_for_a_model():
    pts = _direction(_points(TRUTH["cvs"], np.geomspace(1e-3, 0.3, 4)), "extension")
    with pytest.raises(TooFewPointsError, match="extension direction has 4 points, too few to fit cvs with 4 "
                                                "parameters \\(at least 5 points\\)"):
        fit_model(pts, "cvs")
    fmap = build_map(pts, ["cv", "cvs"])  # not strict: skipped with the reason
    assert "cv" in fmap.directions["extension"].fits and "at least 5" in fmap.directions["extension"].skipped["cvs"]
    assert "no points" in fmap.directions["retraction"].skipped["cv"]


# ------------------------------------------------------------------ points tables

def test_points_table_is_read(tmp_path):
    path = tmp_path / "p.csv"
    path.write_text("# seed 004 style\nv,F,F_std,comment\n0.05,25.1,0.3,first\n\n# between\n-0.04,-20.2,0.4,x\n")
    pts = read_points(path)
    assert [(p.v, p.F, p.F_std) for p in pts] == [(0.05, 25.1, 0.3), (-0.04, -20.2, 0.4)]
    assert [p.direction for p in pts] == ["extension", "retraction"]
    assert not any(p.breakaway for p in pts)
    path.write_text("v,F,count,breakaway\n0.05,25.1,1,0\n0.002,30.0,15,1\n")
    assert [(p.breakaway, p.count) for p in read_points(path)] == [(False, 1), (True, 15)]


@pytest.mark.parametrize("text, fragments", [
    ("v,G\n0.1,3\n", ["line 1", "no column 'F'"]),
    ("v,F\n0.1,3\n0.2,abc\n", ["line 3", "column 'F'", "'abc' is not a number"]),
    ("v,F\n0.1,nan\n", ["line 2", "not a finite number"]),
    ("v,F\n0,3\n", ["line 2", "v = 0 has no direction"]),
    ("v,F\n50,3\n", ["line 2", "not mm/s"]),
    ("v,F\n0.1,3,4\n", ["line 2 has 3 cells but the header has 2"]),
    ("# only a comment\n", ["empty"]),
    ("v,F\n", ["no points"]),
    ("v,F,v\n0.1,2,3\n", ["'v' appears twice"]),
    ("v,F,breakaway\n0.1,2,2\n", ["line 2", "column 'breakaway'", "neither 1"]),
])
def test_bad_points_tables_are_refused(tmp_path, text, fragments):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(PointsFormatError) as e:
        read_points(path)
    msg = str(e.value)
    assert "bad.csv" in msg and msg.count(". ") == 0 and msg.endswith(".")  # one sentence
    for f in fragments:
        assert f in msg


# ------------------------------------------------------------------ the command

def test_command_on_a_points_table(tmp_path, capsys):
    truth = CVS(**TABLE3_N2)
    table = _table(tmp_path, _points(truth, np.geomspace(1e-3, 0.3, 15)))
    out, png = tmp_path / "map.json", tmp_path / "map.png"
    assert _cli([table, "--model", "cv,cvs", "--model", "cvs_delta", "--json", out, "--plot", png, "-q"]) == 0
    printed = capsys.readouterr().out
    assert "extension: 15 sliding points" in printed and "cvs_delta" in printed and "R2" in printed and "MAE" in printed
    data = json.loads(out.read_text())
    for direction in ("extension", "retraction"):
        d = data["directions"][direction]
        assert set(d["models"]) == {"cv", "cvs", "cvs_delta"}
        cvs = d["models"]["cvs"]
        assert {"params", "std", "ci95", "r2", "rmse", "mae", "flags"} <= set(cvs)
        assert cvs["params"]["delta"] == 2.0 and cvs["std"]["delta"] is None  # held fixed
        assert len(d["points"]) == 15 and d["stick_band"]["dv"] == pytest.approx(1e-3)
        assert d["linear"]["r2"] > 0.9
    assert data["directions"]["retraction"]["models"]["cvs"]["params"]["Fc"] == pytest.approx(13.47, abs=0.3)
    assert data["models"]["cvs"]["params"]["vs_pos"] == pytest.approx(0.00342, rel=0.2)
    pytest.importorskip("matplotlib")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_plot_that_cannot_be_written_says_the_json_is(tmp_path, capsys, monkeypatch):
    """The plot is written after the JSON: when it fails (here its folder is gone after the
    outputs were checked), the one line says so, and that the JSON is there."""
    pytest.importorskip("matplotlib")
    from combined_reality import cli

    table = _table(tmp_path, _points(CVS(**TABLE3_N2), np.geomspace(1e-3, 0.3, 12)))
    out, png = tmp_path / "map.json", tmp_path / "gone" / "map.png"
    monkeypatch.setattr(cli_friction, "check_paths", lambda *a, **kw: None)
    code = cli.main(["friction-map", str(table), "--model", "cv", "--json", str(out), "--plot", str(png), "-q"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and json.loads(out.read_text())["models"], err
    assert err.startswith(f"combined-reality friction-map: --plot {png}: cannot write it: the folder does not exist")
    assert err.endswith(f"; the JSON {out} is written.")


def test_command_default_models_skip_what_the_points_cannot_feed(tmp_path, capsys):
    table = _table(tmp_path, _points(CVS(**TABLE3_N2), np.geomspace(1e-3, 0.3, 12)))
    out = tmp_path / "map.json"
    assert _cli([table, "--json", out, "-q"]) == 0
    ext = json.loads(out.read_text())["directions"]["extension"]
    assert {"cv", "karnopp", "threlfall", "cvs", "cvs_delta", "lugre"} <= set(ext["models"])
    assert "load" in ext["skipped"]["cv_load"] and "dp" in ext["skipped"]["belforte"]
    # with the conditions in the table, they are fitted
    table = _table(tmp_path, _points(TRUTH["belforte"], np.geomspace(1e-3, 0.3, 12)), "b.csv",
                   ("v", "F", "dp", "pc", "load"))
    assert _cli([table, "--json", out, "-q", "--model", "belforte,cv_load"]) == 0
    assert set(json.loads(out.read_text())["directions"]["retraction"]["models"]) == {"belforte", "cv_load"}


@pytest.mark.parametrize("option, value, says", [
    ("--min-speed", "-1", "--min-speed must be a positive number, not -1."),
    ("--spread", "nan", "--spread must be a positive number, not nan."),
    ("--min-duration", "0", "--min-duration must be a positive number of seconds, not 0."),
    ("--load", "-5", "--load must be a non-negative force in N, not -5."),
])
def test_segment_and_load_options_are_refused_as_parsed(tmp_path, capsys, option, value, says):
    """The options' rules (combined_reality.options), said as the option is parsed, in the
    sentence every subcommand with the option says (friction-compare's --load alike)."""
    from combined_reality import cli

    out = tmp_path / "o.json"
    assert cli.main(["friction-map", "t.csv", "--json", str(out), option, value]) == 2
    assert capsys.readouterr().err.strip() == f"combined-reality friction-map: {says}"
    if option == "--load":
        assert cli.main(["friction-compare", "t.csv", "--validate", "v.csv", "--config", "c.toml", option,
                         value]) == 2
        assert capsys.readouterr().err.strip() == f"combined-reality friction-compare: {says}"
    assert not out.exists()


@pytest.mark.parametrize("argv, fragments", [
    (["{table}", "--model", "cvs,stribeck"], ["unknown model stribeck"]),
    (["{small}", "--model", "cvs"], ["small.csv", "3 points, too few to fit cvs with 4 parameters"]),
    (["{bad}"], ["bad.csv", "line 3", "column 'F'"]),
    (["{tmp}/nope.csv"], ["nope.csv", "not found"]),
    (["{breakaways}"], ["breakaways.csv: only breakaway rows, no sliding points"]),
])
def test_command_refuses_bad_input_in_one_sentence(tmp_path, argv, fragments):
    pts = _points(CVS(**TABLE3_N2), np.geomspace(1e-3, 0.3, 8))
    paths = {"table": _table(tmp_path, pts), "small": _table(tmp_path, pts[:3] + pts[8:11], "small.csv"),
             "tmp": tmp_path}
    (tmp_path / "bad.csv").write_text("v,F\n0.1,3\n0.2,x\n")
    paths["bad"] = tmp_path / "bad.csv"
    (tmp_path / "breakaways.csv").write_text("v,F,breakaway\n0.002,30,1\n-0.002,-31,1\n")
    paths["breakaways"] = tmp_path / "breakaways.csv"
    out = tmp_path / "o.json"
    with pytest.raises(InputError) as e:  # bad input: main() says it in one line, exit 2
        _cli([a.format(**paths) for a in argv] + ["--json", out])
    msg = str(e.value)
    assert "\n" not in msg and msg.endswith(".")
    for f in fragments:
        assert f in msg
    assert not out.exists()


def test_a_run_without_constant_velocity_stretches_gives_no_map_in_the_library_as_in_the_command(tmp_path, run_a,
                                                                                                 cyl_a, capsys):
    """The rules of what a map cannot be made from live in the library (friction.inputs): a
    script gets the sentence the command prints."""
    from combined_reality.friction import gather_map_inputs, map_of_inputs
    from combined_reality.friction.specs import SegmentOptions

    from combined_reality import cli

    path = tmp_path / "run.csv"
    write_run(path, run_a)
    strict = SegmentOptions(min_duration=5.0)  # no stretch of the virtual-rig run is that long
    got = gather_map_inputs([path], str(cyl_a.source), strict)
    assert got.cyl is not None and len(got.runs) == 1 and not got.points
    with pytest.raises(FrictionMapError, match=r"no constant-velocity stretch found \(at least 5 s above") as e:
        map_of_inputs(got)
    out = tmp_path / "o.json"
    assert cli.main(["friction-map", str(path), "--config", str(cyl_a.source), "--min-duration", "5", "--json",
                     str(out), "-q"]) == 2
    assert capsys.readouterr().err.strip() == f"combined-reality friction-map: {e.value}"
    assert not out.exists()


def test_command_through_the_main_entry_point(tmp_path):
    from combined_reality import cli

    table = _table(tmp_path, _points(CVS(**TABLE3_N2), np.geomspace(1e-3, 0.3, 10)))
    assert cli.main(["friction-map", str(table), "--json", str(tmp_path / "m.json"), "-q"]) == 0
    assert cli.main(["friction-map", str(tmp_path / "nope.csv"), "--json", str(tmp_path / "n.json")]) == 2


# ------------------------------------------------------------------ points from runs

# (direction sign, steady speed [m/s], seconds at that speed)
MOVES = ((1, 0.02, 0.5), (1, 0.05, 0.4), (1, 0.1, 0.3), (-1, 0.03, 0.5), (-1, 0.06, 0.4), (-1, 0.1, 0.3))
FRICTION = {1: (28.0, 20.0, 100.0), -1: (24.0, 15.0, 90.0)}  # direction: Fs, Fc, B


def _constructed_run(cyl):
    """A run whose friction is known exactly: before each move the piston sticks while the
    applied force ramps up to Fs; it then breaks away, reaches a constant speed smoothly
    (friction Fc + B|v|), holds it and stops smoothly. Pressures from Newton's law (p2 fixed),
    no noise."""
    dt, ramp, rest = 1e-3, 0.05, 0.6  # s per sample, to reach speed, of sticking before a move
    g = cyl.geometry
    A1, A2, pa, M = g.area_cap, g.area_rod, cyl.supply.atmosphere, cyl.mechanics.moving_mass
    total = sum(rest + 2 * ramp + hold for _, _, hold in MOVES) + rest
    t = np.arange(0.0, total, dt)
    v, acc, F = np.zeros_like(t), np.zeros_like(t), np.zeros_like(t)
    t0 = 0.0
    for s, speed, hold in MOVES:
        Fs, Fc, B = FRICTION[s]
        stuck = (t >= t0 + 0.1) & (t < t0 + rest)
        F[stuck] = s * Fs * (t[stuck] - t0 - 0.1) / (rest - 0.1)  # the applied force ramps to Fs
        a, e = t0 + rest, t0 + rest + 2 * ramp + hold
        up, down, steady = (t >= a) & (t < a + ramp), (t >= e - ramp) & (t < e), (t >= a + ramp) & (t < e - ramp)
        ph_up, ph_down = (t[up] - a) / ramp, (t[down] - e + ramp) / ramp
        v[up] = s * speed * (1 - np.cos(np.pi * ph_up)) / 2
        acc[up] = s * speed * np.pi / (2 * ramp) * np.sin(np.pi * ph_up)
        v[steady] = s * speed
        v[down] = s * speed * (1 + np.cos(np.pi * ph_down)) / 2
        acc[down] = -s * speed * np.pi / (2 * ramp) * np.sin(np.pi * ph_down)
        moving = up | steady | down
        F[moving] = s * Fc + B * v[moving]
        t0 = e
    x = 0.02 + np.concatenate([[0.0], np.cumsum((v[1:] + v[:-1]) / 2 * dt)])
    p2 = np.full_like(t, 3.0e5)
    p1 = (M * acc + F + p2 * A2 + pa * (A1 - A2)) / A1
    return Run(t=t, u=np.zeros_like(t), x=x, p1=p1, p2=p2)


def test_points_and_breakaways_of_a_constructed_run(cyl_a):
    cyl = without_nominal_friction(cyl_a)
    g, pa = cyl.geometry, cyl.supply.atmosphere
    rp = points_from_run(cyl, _constructed_run(cyl))
    for s, speed, hold in MOVES:
        Fs, Fc, B = FRICTION[s]
        pts = [p for p in rp.points if abs(p.v - s * speed) < 0.01 * speed]
        assert pts and sum(p.count for p in pts) * 1e-3 > hold - 0.1  # most of the stretch at speed
        level = s * (Fc + B * speed)
        for p in pts:
            assert p.F == pytest.approx(level, abs=0.02)
            p1 = (level + 3.0e5 * g.area_rod + pa * (g.area_cap - g.area_rod)) / g.area_cap
            assert p.pc == pytest.approx((3.0e5 if s > 0 else p1) - pa, rel=1e-6)  # the counter chamber
            assert p.dp == pytest.approx(abs(p1 - 3.0e5), rel=1e-6)
    for direction, s in (("extension", 1), ("retraction", -1)):
        forces = [b.force for b in rp.breakaways if b.direction == direction]
        assert len(forces) == 3
        np.testing.assert_allclose(forces, FRICTION[s][0], atol=0.5)
    assert rp.stuck_time == pytest.approx(6 * 0.6 + 0.6, abs=0.3)  # the rests


def test_constructed_run_makes_the_map_with_its_band(cyl_a):
    cyl = without_nominal_friction(cyl_a)
    rp = points_from_run(cyl, _constructed_run(cyl))
    fmap = build_map(rp.points, ["cv", "karnopp"], rp.breakaways, stuck_speed=rp.stuck_speed,
                     stuck_time=rp.stuck_time, strict=True)
    for direction, s in (("extension", 1), ("retraction", -1)):
        Fs, Fc, B = FRICTION[s]
        d = fmap.directions[direction]
        assert d.stick_band.dv == pytest.approx(min(m[1] for m in MOVES if m[0] == s), rel=1e-3)
        assert d.stick_band.breakaway_mean == pytest.approx(Fs, abs=0.5)
        karnopp = d.fits["karnopp"]
        assert karnopp.params["Fc"] == pytest.approx(Fc, abs=0.05) and karnopp.params["B"] == pytest.approx(B, rel=1e-3)
        assert karnopp.params["Fs"] == pytest.approx(Fs, abs=0.5)
        assert karnopp.params["dv"] == pytest.approx(d.stick_band.dv, rel=1e-12)  # just below the slowest point
        assert not karnopp.flags


# ------------------------------------------------------------------ a virtual-rig run

@pytest.fixture(scope="module")
def cvs_rig_run(tmp_path_factory):
    """20 s of the default closed-loop excitation on the virtual rig, whose friction is seed
    004's Table 3 curve of actuator 2 (cylinder file ind2, nominal friction off)."""
    from combined_reality.simulation import simulate_run
    from sim.cylinder import load_cylinder
    from conftest import CONFIGS

    cfg = CONFIGS / "ind2_norgren_32x100.toml"
    cyl = without_nominal_friction(load_cylinder(cfg))
    run = simulate_run(cyl, 20.0, seed=1, effects=[CVS(**TABLE3_N2)])
    path = tmp_path_factory.mktemp("rig") / "cvs_run.csv"
    write_run(path, run)
    return cyl, cfg, path, run


def test_map_of_a_virtual_rig_run_lies_on_the_true_curve(cvs_rig_run):
    """Closed-loop position control gives few constant-velocity stretches (sine crests, ramps),
    all well above the Stribeck velocities: the points lie on the true curve, cv recovers the
    sliding branch."""
    cyl, _, _, run = cvs_rig_run
    truth = CVS(**TABLE3_N2)
    rp = points_from_run(cyl, run)
    for direction, (suffix, _) in DIRECTIONS.items():
        pts = [p for p in rp.points if p.direction == direction]
        assert len(pts) >= 4
        for p in pts:
            assert p.F == pytest.approx(float(truth.static_curve(p.v)), abs=max(0.6, 0.01 * abs(p.F)))
        cv = fit_model(pts, "cv")
        assert cv.params["B"] == pytest.approx(getattr(truth, f"B_{suffix}"), rel=0.05)
        assert cv.params["Fc"] == pytest.approx(getattr(truth, f"Fc_{suffix}"), abs=1.5)


def test_command_on_a_virtual_rig_run(cvs_rig_run, tmp_path, capsys):
    _, cfg, path, _ = cvs_rig_run
    out = tmp_path / "rig.json"
    assert _cli([path, "--config", cfg, "--model", "cv,cvs,karnopp", "--json", out]) == 0
    data = json.loads(out.read_text())
    assert data["runs"][0]["points"] >= 8 and data["config"].endswith("ind2_norgren_32x100.toml")
    for d in data["directions"].values():
        assert d["models"]["cv"]["r2"] > 0.99
        band = d["stick_band"]
        assert band["dv"] > SegmentOptions().min_speed and band["stuck_speed"] > 0
        # the slowest points are far above the true Stribeck velocities: cvs cannot be trusted there
        assert d["models"]["karnopp"]["params"]["dv"] == pytest.approx(band["dv"], rel=1e-12)
    assert "constant-velocity points" in capsys.readouterr().err


# ------------------------------------------------------------------ measured seals (issue 17)

def _seal_points(seed=4, noise=0.1):
    """Measured-style points of a seal whose friction grows with pressure (one chamber held at 1, 3, 5, 7 bar,
    friction from about 4 N to 8 N), the speeds rising with the pressure as on a rig driven by that chamber."""
    rng = np.random.default_rng(seed)
    pts, truth = [], {1: (3.33, 6.67e-6, 5.0), -1: (3.0, 7.0e-6, 6.0)}  # Fc, kp, Fv per direction
    for s, (Fc, kp, Fv) in truth.items():
        for bar, base in zip((1, 3, 5, 7), (10e-3, 25e-3, 45e-3, 70e-3)):
            for f in (0.75, 0.875, 1.0, 1.125, 1.25):
                v, dp = base * f, bar * 1e5 * (1 + rng.normal(0, 0.01))
                pts.append(MapPoint(v=s * v, F=s * (Fc + kp * dp + Fv * v + rng.normal(0, noise)), dp=dp))
    return pts, truth


def test_friction_growing_with_pressure_selects_the_law_with_the_pressure_term(tmp_path, capsys):
    pts, truth = _seal_points()
    table = _table(tmp_path, pts, columns=("v", "F", "dp"))
    assert _cli([table, "--json", tmp_path / "map.json", "--plot", tmp_path / "map.png"]) == 0
    out = capsys.readouterr().out
    doc = json.loads((tmp_path / "map.json").read_text())
    for direction, (suffix, s) in DIRECTIONS.items():
        d = doc["directions"][direction]
        assert d["best"] == "cv_dp", d["best"]
        law = d["models"]["cv_dp"]
        assert law["r2"] >= 0.95 and law["preferable"]
        assert law["params"]["kp"] == pytest.approx(truth[s][1], rel=0.15)
        assert law["params"]["Fc"] == pytest.approx(truth[s][0], abs=0.3)
        # the confounding is said, with its correlation
        assert [c["quantities"] for c in d["confounded"]] == [["speed", "dp"]] and d["confounded"][0]["r"] > 0.9
        # models without dp fit far worse: the pressure term is what the points need
        assert d["models"]["cv"]["r2"] < 0.9
    assert out.count("speed and |p1 - p2| changed together") == 2
    assert out.count(" *  ") == 2 and all("cv_dp" in line for line in out.splitlines() if " *  " in line)


def test_parameters_the_points_do_not_pin_down_are_not_printed_and_not_ranked(tmp_path, capsys):
    pts, _ = _seal_points()
    fmap = build_map(pts)
    seen = 0
    for d in fmap.directions.values():
        for name, fit in d.fits.items():
            if fit.not_determined:
                seen += 1
                assert not fit.preferable and name != d.best
        assert d.best is not None and d.fits[d.best].preferable
        # the best is among the preferable fits only, within PARSIMONY of their lowest AICc
        assert d.fits[d.best].aicc <= min(f.aicc for f in d.fits.values() if f.preferable) + PARSIMONY
    assert seen >= 2  # cvs_delta, belforte_dp: several Stribeck and speed parameters on these points
    table = _cli_table(tmp_path, pts, capsys)
    rows = [line for line in table.splitlines() if line.strip().startswith(("cvs_delta", "belforte_dp"))]
    assert rows and all("not determined" in r for r in rows)
    assert "e-32" not in table and "e+04" not in table  # no absurd value printed as an estimate


def _cli_table(tmp_path, pts, capsys) -> str:
    table = _table(tmp_path, pts, name="p.csv", columns=("v", "F", "dp"))
    assert _cli([table, "--json", tmp_path / "m.json"]) == 0
    return capsys.readouterr().out


def test_a_static_level_below_the_coulomb_level_is_flagged_and_not_preferred():
    """Friction lower at low speed (Fs < Fc): cvs fits best by AICc but is not preferred."""
    rng = np.random.default_rng(2)
    speeds = np.geomspace(2e-3, 0.2, 16)
    pts = []
    for s in (1, -1):
        F = 10.0 + 60.0 * speeds - 3.0 * np.exp(-(speeds / 0.01) ** 2) + rng.normal(0, 0.05, speeds.size)
        pts += [MapPoint(v=s * v, F=s * f) for v, f in zip(speeds, F)]
    fmap = build_map(pts, ["cv", "cvs"])
    for d in fmap.directions.values():
        cvs = d.fits["cvs"]
        assert cvs.aicc < d.fits["cv"].aicc  # the better fit by the numbers ...
        assert any("below the Coulomb level" in p for p in cvs.problems) and not cvs.preferable
        assert d.best == "cv"  # ... is not the one preferred


def test_points_from_a_run_with_channels_not_measured(cyl_a, run_a):
    """Empty cells (NaN) cut Newton's-law friction into stretches: no point spans a sample
    not measured, and the rest of the run still gives its points."""
    from dataclasses import replace

    from combined_reality.friction.points import points_from_run

    full = points_from_run(cyl_a, run_a)
    x = run_a.x.copy()
    x[::2000] = np.nan  # one position in two seconds not measured
    holey = points_from_run(cyl_a, replace(run_a, x=x))
    t_nan = run_a.t[::2000]
    assert len(holey.points) >= 0.5 * len(full.points) > 0
    for pt in holey.points:
        assert not np.any((t_nan >= pt.t_start - 0.016) & (t_nan <= pt.t_end + 0.016)), pt


def test_clean_nominal_points_rank_the_nominal_law_first_and_no_needless_parameter(tmp_path, capsys):
    """A sweep and a breakaway test of the nominal virtual rig (tests/data, made by `procedure
    sweep|breakaway --virtual`, cylinder A): extending, the product's own law cv_dp (its Fc, kp,
    Fv near the truth) over Threlfall, whose scale only bends the curve through the slowest
    point (its AICc was 0.8 lower); retracting, where |p1 - p2| follows the speed and cv_dp's Fc
    and kp cannot be told apart, Coulomb-viscous, what the law reduces to there, not Threlfall
    (2.7 lower). The console table fits 100 columns."""
    data = Path(__file__).parent / "data"
    sweep, brk = data / "nominal_cyl_a_sweep.csv", data / "nominal_cyl_a_breakaway.csv"
    fmap = build_map(read_points(sweep) + read_points(brk))
    ext, ret = fmap.directions["extension"], fmap.directions["retraction"]
    assert ext.best == "cv_dp" and ret.best == "cv"
    assert ext.fits["threlfall"].aicc < ext.fits["cv_dp"].aicc < ext.fits["threlfall"].aicc + PARSIMONY
    assert ret.fits["threlfall"].aicc < ret.fits["cv"].aicc < ret.fits["threlfall"].aicc + PARSIMONY
    law = ext.fits["cv_dp"].params
    assert law["Fc"] == pytest.approx(24.8, abs=0.2) and law["kp"] == pytest.approx(2.89e-5, rel=0.15)
    assert law["Fv"] == pytest.approx(13.45, rel=0.02)
    assert _cli([sweep, brk, "--json", tmp_path / "m.json"]) == 0
    table = capsys.readouterr().out.splitlines()
    assert max(map(len, table)) <= 100
    assert sum(" *  best" in line for line in table) == 2
