"""The streaming session: replay, lock-step simulation, recording that survives a kill, Rerun."""
import json
import math
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from combined_reality.cli import main
from combined_reality.live import simulate_run
from combined_reality.identify import OnlineOptions
from combined_reality.files import read_run, write_run
from conftest import assert_refused
from combined_reality.live import InlineEstimator, LockstepSimulator, ReplayRig, run_session


@pytest.fixture(scope="module")
def clean_run(cyl_a):
    return simulate_run(cyl_a, 4.0, seed=5, noise=False)


def test_lockstep_simulation_follows_a_noise_free_rig_with_the_true_parameters(cyl_a, clean_run):
    """Same plant, same applied command, same timing: the lock-step model tracks the rig to
    well below the sensor noise. A command applied one sample late would show up here as
    tens of micrometres."""
    sim = LockstepSimulator(cyl_a, resync_s=100.0)
    rows = np.vstack([clean_run.t, clean_run.u, clean_run.x, clean_run.p1, clean_run.p2])
    out = np.hstack([sim.advance(rows[:, k:k + 20]) for k in range(0, clean_run.n, 20)])
    assert np.max(np.abs(out[0] - clean_run.x)) < 1e-6
    assert np.max(np.abs(out[1] - clean_run.p1)) < 50.0
    late = np.concatenate([[0.0], clean_run.u[:-1]])
    sim_late = LockstepSimulator(cyl_a, resync_s=100.0)
    rows[1] = late
    out_late = np.hstack([sim_late.advance(rows[:, k:k + 20]) for k in range(0, clean_run.n, 20)])
    assert np.max(np.abs(out_late[0] - clean_run.x)) > 1e-5


def test_replay_as_fast_as_possible_records_every_sample_and_estimates(cyl_a, run_a, tmp_path):
    est = InlineEstimator(cyl_a, run_a.sample_period, OnlineOptions())
    res = run_session(cyl_a, ReplayRig(run_a, math.inf), estimator=est, record_to=tmp_path / "copy.csv",
                      simulator=LockstepSimulator(cyl_a))
    assert res.stop_reason == "end of the recorded run"
    back = read_run(tmp_path / "copy.csv")
    for col in ("t", "u", "x", "p1", "p2"):
        np.testing.assert_array_equal(getattr(back, col), getattr(run_a, col))
        np.testing.assert_array_equal(getattr(res.run, col), getattr(run_a, col))
    assert res.final.samples_seen >= run_a.n - 100
    assert abs(res.final.values["Fc"] - cyl_a.friction.Fc) < 0.01 * cyl_a.friction.Fc


def _cli(*args, **kw):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    # as from a terminal: a suite started in the background (`cmd &`) ignores SIGINT, and a
    # child inheriting that would never see the Ctrl-C this test sends
    return subprocess.Popen([sys.executable, "-m", "combined_reality", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL), **kw)


@pytest.mark.slow
@pytest.mark.parametrize("how", ["SIGKILL", "SIGINT", "SIGTERM"])
def test_recording_stays_valid_when_the_host_is_killed_or_interrupted(tmp_path, how):
    rec = tmp_path / "run.csv"
    out = tmp_path / "o.json"
    p = _cli("live", "--virtual", "--duration", "60", "--record", str(rec), "--json", str(out))
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:  # wait until a few seconds have been recorded
        time.sleep(0.5)
        if rec.exists() and rec.stat().st_size > 200_000:
            break
    os.kill(p.pid, getattr(signal, how))
    _, err = p.communicate(timeout=60)
    run = read_run(rec)  # whole lines only, whatever the moment of the kill
    assert run.n > 2000
    assert np.all(np.diff(run.t) > 0)
    if how != "SIGKILL":  # Ctrl-C and SIGTERM end the session cleanly
        assert p.returncode == 0, err
        assert "interrupted" in err
        assert json.loads(out.read_text())["solver"]["n_samples"] == run.n
    else:
        assert p.returncode == -signal.SIGKILL


def test_replay_cli_writes_identify_format_and_a_rerun_recording(cyl_a, run_a, tmp_path, capsys):
    from rerun.chunk import RrdReader

    path = tmp_path / "run.csv"
    write_run(path, run_a.slice(0, 6000))
    rrd, js = tmp_path / "s.rrd", tmp_path / "o.json"
    code = main(["replay", str(path), "--config", str(cyl_a.source), "--speed", "max", "--json", str(js),
                 "--rerun", "save", str(rrd), "-q"])
    assert code == 0
    out = json.loads(js.read_text())
    assert set(out["params"]) == {"Fc", "Fv", "kp"}
    for n in ("Fc", "Fv", "kp"):
        assert set(out["params"][n]) == {"value", "std", "unit"}
    assert {"rmse_x", "rmse_p1", "rmse_p2"} <= set(out["fit"])
    assert out["solver"]["n_samples"] == 6000
    series: dict[str, list] = {}
    for chunk in RrdReader(rrd).stream():
        rb = chunk.to_record_batch()
        for name in rb.schema.names:
            if name.endswith(":scalars"):
                series.setdefault(chunk.entity_path, []).extend(v[0] for v in rb.column(name).to_pylist())
            elif name.endswith(":positions") or name.endswith(":strips"):
                series.setdefault(chunk.entity_path, []).append(rb.column(name).to_pylist())
    for path_ in ("/position/measured", "/position/simulated", "/pressure/p1/measured", "/pressure/p2/simulated",
                  "/command/u", "/residual/x", "/params/Fc/value", "/params/Fc/upper", "/params/Fc/lower",
                  "/fit/sigma", "/friction/measured", "/friction/model"):
        assert path_ in series, path_
    np.testing.assert_allclose(sorted(series["/position/measured"]), sorted(run_a.x[:6000]))
    assert series["/params/Fc/value"][-1] == pytest.approx(out["params"]["Fc"]["value"])
    assert series["/params/Fc/lower"][-1] < series["/params/Fc/value"][-1] < series["/params/Fc/upper"][-1]
    # residuals are measured minus simulated and stay near the noise
    assert np.sqrt(np.mean(np.square(series["/residual/x"]))) < 5e-5


@pytest.mark.parametrize("args, message", [
    (["replay", "missing.csv"], "missing.csv"),
    (["replay", "RUN", "--speed", "fast"], "--speed fast"),
    (["replay", "RUN", "--rerun", "tv"], "--rerun tv"),
    (["replay", "RUN", "--window", "0"], "--window"),
    (["live", "--virtual", "--duration", "5", "--record", "r.csv", "--program", "zigzag"], "zigzag"),
    (["live", "--serial", "/dev/null", "--duration", "5", "--record", "r.csv", "--effect", "leakage"], "--virtual"),
    (["live", "--virtual", "--duration", "5", "--record", "RUN"], "never overwritten"),
    (["live", "--serial", "/dev/does-not-exist", "--duration", "5", "--record", "r.csv"], "cannot open serial port"),
])
def test_bad_input_is_refused_with_one_sentence(run_a, tmp_path, capsys, monkeypatch, args, message):
    monkeypatch.chdir(tmp_path)
    write_run(tmp_path / "run.csv", run_a.slice(0, 3000))
    args = [str(tmp_path / "run.csv") if a == "RUN" else a for a in args]
    code = main(args)
    assert_refused(code, capsys.readouterr().err, message)


def test_a_measured_supply_pressure_is_recorded_too(cyl_a, run_a, tmp_path):
    from dataclasses import replace

    run = replace(run_a.slice(0, 500), ps=np.full(500, 7.0e5))
    est = InlineEstimator(cyl_a, run.sample_period, OnlineOptions())
    run_session(cyl_a, ReplayRig(run, math.inf), estimator=est, record_to=tmp_path / "r.csv")
    back = read_run(tmp_path / "r.csv")
    np.testing.assert_array_equal(back.ps, run.ps)
    np.testing.assert_array_equal(back.x, run.x)


def test_a_rig_sampling_at_another_rate_than_expected_is_reported(cyl_a, run_a):
    est = InlineEstimator(cyl_a, run_a.sample_period, OnlineOptions())
    res = run_session(cyl_a, ReplayRig(run_a.slice(0, 300), math.inf), estimator=est, expected_period=0.5e-3)
    assert any("samples every 1 ms, not every 0.5 ms" in e for e in res.events)
    res = run_session(cyl_a, ReplayRig(run_a.slice(0, 300), math.inf), estimator=est, expected_period=1e-3)
    assert not res.events
