"""The online identifier judges what it sees: steps and drifts of the rig's friction are
found and followed, a model that does not explain the rig is said to be so, and a session
that cannot determine the parameters ends with no estimate."""
import json
import math

import numpy as np
import pytest

from combined_reality.cli import main
from combined_reality.files import write_run
from combined_reality.identify import IdentifyOptions, OnlineEstimate, OnlineOptions, identify
from combined_reality.identify.tracking import Blocks, Change, Regime, analyse
from combined_reality.live import InlineEstimator, SessionMonitor, final_run_sigma, session_verdict
from combined_reality.simulation import simulate_run
from sim.effects import EFFECTS, make_friction_change


@pytest.fixture(scope="module")
def rig(cyl_a):
    """The issue's rig: cylinder A's geometry with Fc = 22 N, Fv = 55 N s/m."""
    return cyl_a.with_values({"Fc": 22.0, "Fv": 55.0})


def replayed(cyl, run, catch_up=True, **options):
    """The estimates of a replay as fast as possible (a window at a time, as replay --speed max),
    or without `catch_up` on a live session's schedule (an update per update_s of data)."""
    est = InlineEstimator(cyl, run.sample_period, OnlineOptions(**options), catch_up=catch_up)
    rows = np.vstack([run.t, run.u, run.x, run.p1, run.p2, np.zeros(run.n)])
    out = []
    for k in range(0, run.n, 20):
        est.add(rows[:, k:k + 20])
        out += est.poll()
    return out + est.finish()


def truth(cyl, change, t):
    c, f = change.relative(np.asarray(t, float))
    return {"Fc": cyl.value("Fc") * (1 + c), "Fv": cyl.value("Fv") * (1 + f)}


# ---------------------------------------------------------------- the tests on synthetic blocks


def _blocks(theta, t0, rng, n=3, info=None):
    """Blocks of 0.2 s whose quadratics put their own best at theta(t) plus noise of unit
    information `info` (no model error)."""
    info = np.diag([1e4, 1e3, 1e2]) if info is None else info
    L = np.linalg.cholesky(np.linalg.inv(info))
    best = np.array([theta(t) for t in t0]) + (L @ rng.standard_normal((n, len(t0)))).T
    lin = np.zeros_like(best)  # linearised at 0: gradient -A best
    A = np.repeat(info[None], len(t0), axis=0)
    return Blocks(n, t0, t0 + 0.199, np.arange(len(t0)) * 2, lin, -(A @ best[:, :, None])[..., 0], A)


def test_a_step_in_the_blocks_is_found_and_located_and_noise_alone_is_not():
    rng = np.random.default_rng(1)
    t0 = np.arange(0.0, 20.0, 0.2)
    z_null = [analyse(_blocks(lambda t: np.array([1.0, 2.0, 3.0]), t0, rng), np.zeros(3), 20.0,
                      min_after_s=1.0).z_step for _ in range(20)]
    assert max(z_null) < 4.5  # chi-square(3) over some 90 boundaries: the largest near 3.5
    jump = np.array([0.1, 0.0, 0.0])  # 10 standard deviations of one block in the first parameter
    an = analyse(_blocks(lambda t: np.array([1.0, 2.0, 3.0]) + jump * (t >= 16.0), t0, rng), np.zeros(3), 20.0,
                 min_after_s=1.0)
    assert an.z_step > 15
    assert abs(an.t_change - 16.0) < 0.25 and an.t_change_std < 0.2
    assert an.after.value[0] - an.before.value[0] == pytest.approx(0.1, abs=3 * math.sqrt(an.after.cov[0, 0]))


def test_a_regime_covariance_asks_for_more_evidence_and_a_drift_is_told_from_a_step():
    rng = np.random.default_rng(2)
    t0 = np.arange(0.0, 20.0, 0.2)
    jump = np.array([0.1, 0.0, 0.0])
    blocks = _blocks(lambda t: np.array([1.0, 2.0, 3.0]) + jump * (t >= 16.0), t0, rng)
    quiet = analyse(blocks, np.zeros(3), 20.0, min_after_s=1.0)
    # a rig whose regimes move the first parameter by 0.05: the same step is a fifth as clear
    regime = Regime(np.array([0.5, 1.0, 2.0, 4.0]), np.repeat(np.diag([0.05 ** 2, 0.0, 0.0])[None], 4, axis=0))
    moving = analyse(blocks, np.zeros(3), 20.0, regime, min_after_s=1.0)
    assert moving.z_step < quiet.z_step / 3
    ramp = analyse(_blocks(lambda t: np.array([1.0 + 0.01 * t, 2.0, 3.0]), t0, rng), np.zeros(3), 20.0,
                   min_after_s=1.0)
    assert ramp.z_drift > 10
    assert ramp.dispersion["drift_chi2"] < ramp.dispersion["step_chi2"]  # a trend explains it better
    assert ramp.trend.rate[0] == pytest.approx(0.01, abs=3 * math.sqrt(ramp.trend.rate_cov[0, 0]))


# ---------------------------------------------------------------- the estimator on a rig that changes


@pytest.fixture(scope="module")
def step_run(rig):
    change = make_friction_change({"t_step": 8.0, "step_Fc": 0.3, "step_Fv": 0.3})
    return change, simulate_run(rig, 16.0, seed=3, effects=[change])


def test_a_step_of_the_friction_is_announced_located_and_followed(rig, step_run):
    change, run = step_run
    es = replayed(rig, run)
    found = [e.change for e in es if e.change is not None]
    assert len(found) == 1, found
    c = found[0]
    assert c.t_detected - 8.0 <= 2.0 + 1e-9  # the first window with data after the step
    assert abs(c.t - 8.0) <= max(3 * c.t_std, 0.2)
    assert c.before["Fc"] == pytest.approx(22.0, rel=0.01) and c.after["Fc"] == pytest.approx(28.6, rel=0.01)
    assert c.after["Fv"] == pytest.approx(71.5, rel=0.01)
    for e in es:
        tr = truth(rig, change, e.t)
        if e.t < 8.0 or e.t >= 10.0:  # outside the window that holds the step
            for n in ("Fc", "Fv"):
                assert abs(e.values[n] - tr[n]) <= max(3 * e.std[n], 0.01 * tr[n]), (e.t, n, e.values[n], tr[n])
    assert all(e.values[n] == pytest.approx(truth(rig, change, e.t)[n], rel=0.01) for e in es if e.t >= 10.0
               for n in ("Fc", "Fv"))


def test_a_drifting_friction_is_followed_with_an_honest_std(rig):
    ramp = make_friction_change({"t_ramp": 0.0, "ramp_Fc": 0.4 / 60, "ramp_Fv": 0.4 / 60})
    run = simulate_run(rig, 20.0, seed=3, effects=[ramp])
    es = replayed(rig, run)
    assert not any(e.change for e in es)
    followed = [e for e in es if e.drift is not None]
    assert followed and followed[0].t <= 10.0
    late = [e for e in es if e.t >= 10.0]
    inside = []
    for e in late:
        tr = truth(rig, ramp, e.t)
        for n in ("Fc", "Fv"):
            assert e.values[n] == pytest.approx(tr[n], rel=0.01)
            inside.append(abs(e.values[n] - tr[n]) <= 3 * e.std[n])
    assert np.mean(inside) >= 0.9
    assert followed[-1].drift.rate["Fc"] == pytest.approx(22.0 * 0.4 / 60, rel=0.1)


def test_a_steady_rig_with_an_effect_the_model_lacks_gives_no_change(rig):
    """Barely visible stiction moves the locally best friction with the operating regime
    (residual 1.05 x the noise): no change, no drift, and the estimate as without tracking."""
    run = simulate_run(rig, 20.0, seed=5, effects=[EFFECTS["stiction"].typical(rig, 0.0)])
    es = replayed(rig, run)
    assert not any(e.change or e.drift for e in es)
    plain = replayed(rig, run, track=False)
    assert [e.values for e in es] == [e.values for e in plain]


# ---------------------------------------------------------------- the session's judgement


def _estimate(t, sigma, change=None):
    return OnlineEstimate(t=t, values={"Fc": 22.0}, std={"Fc": 0.1}, units={"Fc": "N"}, window=(t - 2.0, t),
                          samples_seen=int(t * 1000), sigma=sigma, rmse={}, iterations=1, wall_s=0.01, change=change)


def test_the_monitor_says_when_the_model_stops_and_starts_explaining_the_rig():
    m = SessionMonitor(t0=0.0)
    said = []
    for t, s in [(2.0, 1.0), (2.2, 40.0), (2.4, 45.0), (2.6, 1.0), (2.8, 50.0), (3.0, 50.0), (3.4, 60.0)]:
        said += m.take(_estimate(t, s))
    assert not said and m.trusted  # windows above the limit for less than 1 s of data
    said += m.take(_estimate(3.8, 55.0))
    assert len(said) == 1 and "does not explain" in said[0] and "calibrate" in said[0] and "diagnose" in said[0]
    assert not m.trusted and m.mismatch[0].t_start == pytest.approx(0.8) and m.mismatch[0].t_said == 3.8
    for t in (4.0, 4.6):
        said += m.take(_estimate(t, 1.0))
    assert not m.trusted and len(said) == 1
    said += m.take(_estimate(5.0, 1.0))
    assert m.trusted and "explains the rig again from t = 2.0 s" in said[-1]
    c = Change(t=4.0, t_std=0.05, z=30.0, t_detected=4.6, before={"Fc": 22.0}, after={"Fc": 28.6},
               std_before={"Fc": 0.1}, std_after={"Fc": 0.2}, std={"Fc": 0.22})
    said += m.take(_estimate(5.2, 1.0, c))
    assert said[-1].startswith("friction changed at t = 4.00") and "Fc 22 -> 28.6 N" in said[-1]
    doc = json.loads(json.dumps(m.to_json()))
    assert doc["explained"] is True and doc["mismatch"][0]["t_end"] is not None
    assert doc["changes"][0]["params"]["Fc"] == {"before": 22.0, "after": 28.6, "std": 0.22, "std_before": 0.1,
                                                 "std_after": 0.2}
    assert doc["sigma_session"] > 1.0


def test_a_run_without_motion_ends_with_no_estimate(rig):
    from combined_reality.files import Run

    t = np.arange(3000) * 1e-3
    run = Run(t=t, u=np.zeros_like(t), x=np.full_like(t, 0.05), p1=np.full_like(t, 4e5), p2=np.full_like(t, 4e5))
    e = OnlineEstimate(t=3.0, values={"Fc": 702.0, "Fv": 1.0, "kp": 1e-6}, std={"Fc": 20.0, "Fv": 0.1, "kp": 1e-8},
                       units={}, window=(1.0, 3.0), samples_seen=3000, sigma=1.03, rmse={}, iterations=1, wall_s=0.0)
    assert "does not move" in session_verdict(run, e, ("Fc", "Fv", "kp"), rig)
    assert session_verdict(run, None, ("Fc",), rig).startswith("fewer samples")


def test_an_estimate_without_a_standard_deviation_is_no_estimate(rig):
    """identify's rule (identify.not_determined): a parameter with no finite std, or one as large
    as the value, is not determined, whatever the window's fit."""
    run = simulate_run(rig, 4.0, seed=3)
    e = OnlineEstimate(t=4.0, values={"Fc": 22.0, "Fv": 55.0, "kp": 1e-6}, std={"Fc": 0.2, "kp": 1e-8},
                       units={}, window=(2.0, 4.0), samples_seen=4000, sigma=1.0, rmse={}, iterations=1, wall_s=0.0)
    assert session_verdict(run, e, ("Fc", "Fv", "kp"), rig).startswith("Fv not determined")
    e.std["Fv"], e.std["kp"] = 0.5, 2e-6
    assert session_verdict(run, e, ("Fc", "Fv", "kp"), rig).startswith("kp not determined")
    e.std["kp"] = 1e-8
    assert session_verdict(run, e, ("Fc", "Fv", "kp"), rig) is None


def test_replay_of_a_cylinder_whose_file_is_off_says_the_estimate_is_untrusted(rig, tmp_path, capsys):
    from sim.cylinder import cylinder_to_toml

    off = rig.with_values({"conductance": 1.3 * rig.value("conductance"), "mass": 1.2 * rig.value("mass"),
                           "dead_volume_cap": 2 * rig.value("dead_volume_cap"),
                           "dead_volume_rod": 2 * rig.value("dead_volume_rod")})
    cfg, path, js = tmp_path / "off.toml", tmp_path / "run.csv", tmp_path / "o.json"
    cfg.write_text(cylinder_to_toml(off))
    write_run(path, simulate_run(rig, 6.0, seed=3))
    code = main(["replay", str(path), "--config", str(cfg), "--speed", "max", "--json", str(js), "-q"])
    out = capsys.readouterr()
    assert code == 1  # as identify ends on it
    assert "not to be trusted" in out.out and "calibrate" in out.out
    doc = json.loads(js.read_text())
    mon = doc["monitor"]
    assert mon["explained"] is False and doc["solver"]["explains_run"] is False
    assert mon["mismatch"][0]["t_said"] - doc["history"][0]["t"] <= 3.0
    assert mon["sigma_recent"] > 10 and mon["changes"] == []
    # identify's own figure for the session's last estimate, comparable with identify's on the run
    res = identify(off, [simulate_run(rig, 6.0, seed=3)], IdentifyOptions())
    assert mon["sigma_run_span"] == [pytest.approx(0.0, abs=2e-3), pytest.approx(6.0, abs=2e-3)]
    # identify fits the friction to the whole run, the session holds the estimate of its last
    # window: never below identify's, and close to it (1.23 x on these 6 s, 1.09-1.12 x on 20 s)
    assert res.solver["residual_sigma"] <= mon["sigma_run"] <= 1.3 * res.solver["residual_sigma"]
    assert f"the last estimate leaves {mon['sigma_run']:.3g} × the sensor noise" in out.out


def test_the_run_residual_is_taken_over_the_data_since_the_last_change(rig):
    run = simulate_run(rig, 4.0, seed=5)
    m = SessionMonitor(t0=float(run.t[0]))
    m.changes.append(Change(t=float(run.t[0]) + 2.5, t_std=0.05, z=30.0, t_detected=3.0, before={}, after={},
                            std_before={}, std_after={}, std={}))
    e = OnlineEstimate(t=float(run.t[-1]), values={n: rig.value(n) for n in ("Fc", "Fv", "kp")}, std={}, units={},
                       window=(2.0, 4.0), samples_seen=run.n, sigma=1.0, rmse={}, iterations=1, wall_s=0.0)
    r = final_run_sigma(run, e, rig, m)
    assert r.t_start == pytest.approx(2.5, abs=2e-3) and r.t_end == pytest.approx(float(run.t[-1] - run.t[0]))
    assert 0.8 < r.sigma < 1.3  # the true friction on the project's own plant: at the noise


def test_data_that_do_not_determine_the_friction_are_not_taken_for_a_step():
    """Blocks after a boundary that say nothing of the first parameter (a hold at an end stop:
    the piston does not move) cannot show a step in it, however far the estimate before lies."""
    rng = np.random.default_rng(3)
    t0 = np.arange(0.0, 20.0, 0.2)
    blocks = _blocks(lambda t: np.array([1.0, 2.0, 3.0]), t0, rng)
    held = t0 >= 18.0
    blocks.A[held, 0, :] = blocks.A[held, :, 0] = 0.0
    blocks.s[held, 0] = 0.0
    # the boundaries looked at: those of the hold (min_after_s 0: each judged at once)
    an = analyse(blocks, np.zeros(3), 20.0, recent_s=2.0)
    assert an.z_step < 6


def test_the_calibration_program_on_a_steady_rig_gives_no_change_and_no_drift(cyl_a):
    """Its holds at the end stops and with the valve closed determine no friction: neither a
    live schedule nor a replay may announce a change there (they once announced z = 1e70)."""
    from combined_reality.live import make_program, run_program
    from hw.virtual_rig import VirtualRig

    prog = make_program("calibration", cyl_a, 20.0, seed=4)
    run = run_program(VirtualRig(cyl_a, (), rate=1000, seed=4), prog, 20_000)
    for catch_up in (True, False):
        out = replayed(cyl_a, run, catch_up)
        assert not [e.change for e in out if e.change is not None], catch_up
        assert not [e.drift for e in out if e.drift is not None], catch_up
        assert out[-1].values["Fc"] == pytest.approx(cyl_a.value("Fc"), rel=0.01)
