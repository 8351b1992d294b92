"""The moving-horizon estimator: recovery, honesty of its std, agreement with the offline fit."""
import numpy as np
import pytest

from combined_reality.identify import IdentifyOptions, identify
from combined_reality.identify import MovingHorizonEstimator, OnlineOptions


def _stream(mhe, run, chunk=100):
    estimates = []
    for k in range(0, run.n, chunk):
        s = slice(k, k + chunk)
        mhe.add(run.t[s], run.u[s], run.x[s], run.p1[s], run.p2[s])
        while mhe.ready():
            estimates.append(mhe.update())
    return estimates


@pytest.fixture(scope="module")
def online_a(cyl_a, run_a):
    start = cyl_a.with_values({"Fc": cyl_a.friction.Fc * 1.5, "Fv": cyl_a.friction.Fv * 0.6,
                               "kp": cyl_a.friction.kp * 2})
    mhe = MovingHorizonEstimator(start, run_a.sample_period, OnlineOptions())
    return mhe, _stream(mhe, run_a)


def test_recovers_friction_from_a_poor_start_and_reports_honest_std(cyl_a, online_a):
    mhe, est = online_a
    assert len(est) > 80  # one update per 0.2 s of data after the first 2 s window
    early = next(e for e in est if e.t >= 5.0)
    for e in (early, est[-1]):
        for n in ("Fc", "Fv"):
            truth = cyl_a.value(n)
            assert abs(e.values[n] - truth) < 0.01 * truth
    final = est[-1]
    for n in ("Fc", "Fv", "kp"):
        assert abs(final.values[n] - cyl_a.value(n)) < 4 * final.std[n], n
    assert 0.9 < final.sigma < 1.1  # fits to the sensor noise
    # the arrival cost accumulates information: the std shrinks as data come in
    assert final.std["Fc"] < 0.8 * early.std["Fc"]


def test_online_agrees_with_the_offline_fit_of_the_same_data(cyl_a, run_a, online_a):
    _, est = online_a
    off = identify(cyl_a, [run_a], IdentifyOptions())
    final = est[-1]
    for n in ("Fc", "Fv", "kp"):
        assert abs(final.values[n] - off.params[n].value) < 3 * final.std[n], n


def test_catching_up_never_skips_data(cyl_a, run_a):
    """Fed everything at once, the windows slide by at most a window: every sample enters."""
    mhe = MovingHorizonEstimator(cyl_a, run_a.sample_period, OnlineOptions())
    run = run_a.slice(0, 7000)
    mhe.add(run.t, run.u, run.x, run.p1, run.p2)
    est = []
    while mhe.ready():
        est.append(mhe.update())
    windows = [e.window for e in est]
    for (a0, a1), (b0, b1) in zip(windows, windows[1:]):
        assert b0 <= a1 + 1.5e-3  # the next window starts no later than right after the previous one
    assert est[-1].samples_seen == 7000 - 7000 % mhe.M
    assert len(est) == 4  # 2 s, then slides of 2 s, 2 s and 1 s


def test_rejects_unknown_parameters(cyl_a):
    from combined_reality.identify import IdentificationError

    with pytest.raises(IdentificationError, match="cannot be estimated"):
        MovingHorizonEstimator(cyl_a, 1e-3, OnlineOptions(estimate=("Fc", "bogus")))


def test_no_window_bridges_lost_samples(cyl_a, run_a):
    """A lost sample hides the command held over its period; windows stop before a gap and
    start again after it, keeping what they learnt, so the fit stays at the noise."""
    from combined_reality.files import Run

    keep = np.ones(run_a.n, bool)
    keep[[4321, 9876]] = False  # two lost samples
    keep[12000:13000] = False  # and a 1 s outage
    idx = np.flatnonzero(keep)
    run = Run(t=run_a.t[idx], u=run_a.u[idx], x=run_a.x[idx], p1=run_a.p1[idx], p2=run_a.p2[idx])
    mhe = MovingHorizonEstimator(cyl_a, run_a.sample_period, OnlineOptions())
    est = _stream(mhe, run)
    gaps = [(run_a.t[i - 1], run_a.t[i + 1]) for i in (4321, 9876)] + [(run_a.t[11999], run_a.t[13000])]
    for e in est:
        assert e.sigma < 1.15
        for a, b in gaps:
            assert not (e.window[0] <= a and e.window[1] >= b), (e.window, a, b)
    for n in ("Fc", "Fv"):
        assert abs(est[-1].values[n] - cyl_a.value(n)) < 4 * est[-1].std[n]
