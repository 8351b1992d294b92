"""The moving-horizon estimator: recovery, honesty of its std, agreement with the offline fit."""
import numpy as np
import pytest

from combined_reality.files import Run
from combined_reality.identify import IdentifyOptions, identify
from combined_reality.identify import MovingHorizonEstimator, OnlineOptions
from combined_reality.simulation import simulate_run


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


@pytest.fixture(scope="module")
def lossy_a(cyl_a):
    """20 s of the virtual rig over a link that loses 1 % of the samples: the host neither
    records nor answers them, so the rig holds the command it had (what --drop 0.01 does)."""
    return simulate_run(cyl_a, 20.0, seed=1, drop=0.01)


def test_lost_samples_are_bridged_and_the_commands_held_meanwhile_estimated(cyl_a, run_a, lossy_a):
    """Every gap of the lossy link is bridged (no piece restarts), every sample received enters
    the estimate, the windows fit to the noise and the estimate is as good as without loss."""
    lost = run_a.n - lossy_a.n
    assert 150 < lost < 250
    mhe = MovingHorizonEstimator(cyl_a, 1e-3, OnlineOptions())
    est = _stream(mhe, lossy_a)
    mhe.flush()
    while mhe.ready():
        est.append(mhe.update())
    gaps = int(np.sum(np.diff(lossy_a.t) > 1.5e-3))
    assert mhe.gaps_bridged == gaps and mhe.gaps_cut == 0
    assert est[-1].samples_seen == lossy_a.n
    assert len(est) > 60 and all(e.pieces == 1 for e in est)
    assert np.mean([e.gaps for e in est]) > 10  # the windows hold the gaps, and fit across them
    sigma = np.array([e.sigma for e in est])
    # one Gauss-Newton iteration per update: a window with new gaps may fit a little worse
    # until the next update has taken it up again
    assert np.percentile(sigma, 95) < 1.05 and sigma.max() < 1.25
    for n in ("Fc", "Fv", "kp"):
        assert abs(est[-1].values[n] - cyl_a.value(n)) < 3 * est[-1].std[n], n
    assert abs(est[-1].values["Fv"] - cyl_a.value("Fv")) < 0.01 * cyl_a.value("Fv")


def test_threads_share_the_window_and_change_no_estimate(cyl_a, lossy_a):
    """The compiled map gives each thread a contiguous block of slots: the window's intervals
    are dealt to the blocks in turn, so each thread gets its share of the real ones (a padded
    window had them all in the first block: two threads took as long as one). The estimates,
    gaps bridged and all, are the same to the last bit."""
    from combined_reality.identify.online import _PaddedProblem

    mhe = MovingHorizonEstimator(cyl_a, 1e-3, OnlineOptions(threads=1))
    prob = _PaddedProblem(mhe.sf, 45, 2, mhe.wts, mhe.sscale)
    assert prob.capacity == 46 and sorted(prob.slot) == list(range(46))
    for kw in (10, 20, 23, 24):  # real intervals per block: equal, or one apart
        per_block = np.bincount(prob.slot[:kw] // 23, minlength=2)
        assert per_block.max() - per_block.min() <= 1, (kw, per_block)
    run = lossy_a.slice(0, 6000)
    one = _stream(mhe, run)
    two = _stream(MovingHorizonEstimator(cyl_a, 1e-3, OnlineOptions(threads=2)), run)
    assert len(one) == len(two) > 15 and sum(e.gaps for e in one) > 100
    for a, b in zip(one, two):
        assert a.values == b.values and a.std == b.std and a.sigma == b.sigma


def test_after_an_update_without_a_step_only_the_new_intervals_are_simulated(cyl_a, lossy_a, monkeypatch):
    """An update that took no step leaves its linearisation where the next window starts: the
    intervals both windows share are not simulated again (most updates of a warm stream), nor
    the steps across their gaps, and every estimate is the one that evaluating each whole
    window anew gives."""
    from combined_reality.identify.shooting import ShootingProblem

    run = lossy_a.slice(0, 8000)
    windows = []  # with_sens of every whole-window simulation
    simulate = ShootingProblem.simulate

    def counted(self, S, p, with_sens):
        windows.append(with_sens)
        return simulate(self, S, p, with_sens)

    monkeypatch.setattr(ShootingProblem, "simulate", counted)
    reused = _stream(MovingHorizonEstimator(cyl_a, 1e-3, OnlineOptions()), run)
    reused_sens = sum(windows)
    update = MovingHorizonEstimator.update

    def forgetting(self):  # the same estimator, made to forget its linearisation (and its
        e = update(self)  # gaps' slopes) after every update
        self._prev["Sens"] = None
        self._gap_slopes.clear()
        return e

    monkeypatch.setattr(MovingHorizonEstimator, "update", forgetting)
    windows.clear()
    fresh = _stream(MovingHorizonEstimator(cyl_a, 1e-3, OnlineOptions()), run)
    assert len(reused) == len(fresh) > 25 and sum(e.gaps for e in fresh) > 100
    assert sum(windows) >= len(fresh)  # each update evaluated its whole window at least once
    assert reused_sens < 0.5 * len(reused)
    for a, b in zip(reused, fresh):
        for n in ("Fc", "Fv", "kp"):
            assert a.values[n] == pytest.approx(b.values[n], rel=1e-9, abs=0), (a.t, n)
            assert a.std[n] == pytest.approx(b.std[n], rel=1e-6, abs=0), (a.t, n)


def test_holding_the_last_command_across_a_gap_would_not_fit(cyl_a, lossy_a):
    """Why the command over a gap is estimated: held from the sample before, the windows do
    not fit (the estimator's bridge must beat this)."""
    mhe = MovingHorizonEstimator(cyl_a, 1e-3, OnlineOptions())
    held = lossy_a.slice(0, 4000)
    mhe.add(held.t, held.u, held.x, held.p1, held.p2, lost_before=np.zeros(held.n, bool))
    assert mhe.update().sigma > 3


def _stretched_run(cyl, seed: int, n: int, stretched: int):
    """A closed-loop run of a rig whose firmware overruns now and then: `stretched` ticks come
    5-30 ms late (a busy host), no sample is lost and the sequence numbers run on; the valve
    holds the command latched at the tick before all along."""
    from combined_reality.live import run_program
    from combined_reality.live.programs import PositionProgram
    from hw.virtual_rig import VirtualRig

    rng = np.random.default_rng(seed)
    periods = np.full(n, 1e-3)
    periods[rng.choice(np.arange(100, n), stretched, replace=False)] = rng.uniform(5e-3, 30e-3, stretched)
    rig = VirtualRig(cyl, seed=seed)
    ticks = iter(periods)
    rig.read = lambda timeout=None: rig.advance(next(ticks))
    return run_program(rig, PositionProgram(cyl, n * 1e-3, seed=seed), n)


def test_a_stretched_period_is_the_plants_physics_in_steps_of_a_period(cyl_a):
    """The virtual rig over one 20 ms period (its firmware overran) is where twenty 1 ms periods
    with the same command take it: one step of 20 ms is more than the integrator refines."""
    from hw.virtual_rig import VirtualRig

    rigs = [VirtualRig(cyl_a, noise=False) for _ in range(2)]
    for r in rigs:
        r.start()
        r.latch(0.6)  # the piston accelerates, the chambers fill and empty
        r.advance(1e-3)
    once = rigs[0].advance(20e-3)
    for _ in range(20):
        stepwise = rigs[1].advance(1e-3)
    assert once.t == pytest.approx(stepwise.t, abs=1e-12)
    assert abs(once.x - stepwise.x) < 1e-9 and max(abs(once.p1 - stepwise.p1), abs(once.p2 - stepwise.p2)) < 1e-3


def test_a_rig_whose_ticks_come_late_is_estimated_across_them(cyl_a):
    """150 ticks 5-30 ms late in 20000 and nothing lost (the rig's numbers run on): the
    command was held, known, so the estimator steps across at about a period with nothing
    measured in between. Across one long step each, the windows missed by 20 x the noise and a
    live estimate fell from Fc 24.8 to 0 (a firmware session on an overloaded host)."""
    run = _stretched_run(cyl_a, seed=3, n=20000, stretched=150)
    assert np.sum(np.diff(run.t) > 4e-3) == 150
    mhe = MovingHorizonEstimator(cyl_a, 1e-3, OnlineOptions())
    est = []
    for k in range(0, run.n, 100):
        s = slice(k, k + 100)
        mhe.add(run.t[s], run.u[s], run.x[s], run.p1[s], run.p2[s], lost_before=np.zeros(len(run.t[s]), bool))
        while mhe.ready():
            est.append(mhe.update())
    assert mhe.gaps_bridged == mhe.gaps_cut == 0
    sigma = np.array([e.sigma for e in est])
    print(f"\n{len(est)} updates, sigma p95 {np.percentile(sigma, 95):.3f} max {sigma.max():.3f}; final "
          + ", ".join(f"{n} {est[-1].values[n]:.5g} +- {est[-1].std[n]:.2g}" for n in ("Fc", "Fv", "kp")))
    assert len(est) > 80 and np.percentile(sigma, 95) < 1.05 and sigma.max() < 1.15
    for n in ("Fc", "Fv", "kp"):
        assert abs(est[-1].values[n] - cyl_a.value(n)) < 3 * est[-1].std[n], n
    assert abs(est[-1].values["Fc"] - cyl_a.value("Fc")) < 0.01 * cyl_a.value("Fc")


def test_an_outage_starts_a_new_piece_and_the_estimate_goes_on(cyl_a, run_a):
    keep = np.ones(run_a.n, bool)
    keep[9000:10000] = False  # the link is gone for 1 s
    run = Run(t=run_a.t[keep], u=run_a.u[keep], x=run_a.x[keep], p1=run_a.p1[keep], p2=run_a.p2[keep])
    mhe = MovingHorizonEstimator(cyl_a, 1e-3, OnlineOptions())
    est = _stream(mhe, run)
    assert mhe.gaps_cut == 1 and mhe.gaps_bridged == 0
    spanning = [e for e in est if e.window[0] < 9.0 < 10.0 < e.window[1]]
    assert spanning and all(e.pieces == 2 for e in spanning)
    assert len(est) > 80 and max(e.sigma for e in est) < 1.1
    for n in ("Fc", "Fv"):
        assert abs(est[-1].values[n] - cyl_a.value(n)) < 3 * est[-1].std[n], n


def test_channels_not_measured_have_no_residual(cyl_a, run_a):
    rng = np.random.default_rng(3)
    cols = {n: getattr(run_a, n).copy() for n in ("x", "p1", "p2")}
    for c in cols.values():
        c[rng.random(run_a.n) < 0.01] = np.nan
    mhe = MovingHorizonEstimator(cyl_a, 1e-3, OnlineOptions())
    est = _stream(mhe, Run(t=run_a.t, u=run_a.u, **cols))
    assert len(est) > 80 and max(e.sigma for e in est) < 1.05
    assert all(np.isfinite(v) for e in est for v in e.rmse.values())
    for n in ("Fc", "Fv", "kp"):
        assert abs(est[-1].values[n] - cyl_a.value(n)) < 3 * est[-1].std[n], n


@pytest.mark.slow
def test_the_reported_std_covers_the_truth_over_20_seeds(cyl_a):
    """Honest uncertainty: over 20 lossy runs (1 % of the samples lost) with different seeds,
    the truth lies within 3 reported std of the final estimate in >= 90 % of the runs, for
    every parameter (benchmarks/online_coverage.py measures it on longer runs)."""
    f = cyl_a.friction
    start = cyl_a.with_values({"Fc": 1.3 * f.Fc, "Fv": 0.7 * f.Fv, "kp": 1.3 * f.kp})
    inside = {"Fc": 0, "Fv": 0, "kp": 0}
    for seed in range(300, 320):
        run = simulate_run(cyl_a, 8.0, seed=seed, drop=0.01)
        mhe = MovingHorizonEstimator(start, 1e-3, OnlineOptions())
        est = _stream(mhe, run, chunk=20)
        mhe.flush()
        while mhe.ready():
            est.append(mhe.update())
        for n in inside:
            inside[n] += abs(est[-1].values[n] - cyl_a.value(n)) <= 3 * est[-1].std[n]
    assert all(k >= 18 for k in inside.values()), inside


def test_the_gap_offsets_columns_taken_through_the_node_states_equal_the_dense_ones():
    """The offsets over bridged gaps reach the residuals only through the node states, so the
    window's normal equations, the residual change of a step, the scores and the profiled
    information are taken through nx-by-nx blocks: they equal what the dense columns give."""
    from combined_reality.identify.online import _Piece, _ReducedWindow
    from combined_reality.identify.shooting import normal_equations, reduce_nodes

    rng = np.random.default_rng(3)
    K, M, ny, nx, nth, ngap = 9, 5, 3, 4, 3, 4
    G = rng.normal(size=(K, M, ny, nx))
    Hth = rng.normal(size=(K, M, ny, nth))
    A = 0.3 * rng.normal(size=(K, nx, nx)) + np.eye(nx)
    B = rng.normal(size=(K, nx, nth + ngap))
    B[..., nth:] = 0.0
    before = [1, 2, 6, 7]  # the intervals a gap ends (the first piece holds two, the second two)
    B[before, :, nth + np.arange(ngap)] = rng.normal(size=(ngap, nx))
    E = rng.normal(size=(K, M, ny))
    has_next = np.array([1, 1, 1, 0, 1, 1, 1, 1, 0], bool)  # pieces 0-3 and 4-8
    D = rng.normal(size=(nx, int(has_next.sum())))
    pieces = [_Piece(0, 4), _Piece(4, 5)]
    piece_of = np.repeat([0, 1], [4, 5])
    nu = nth + ngap

    dense_H = np.concatenate([Hth, np.zeros((K, M, ny, ngap))], axis=-1)
    P, Q, q, Js, Jt, r0 = reduce_nodes((G, dense_H, A, B), E, D, has_next, nx, nu)
    N, g, _ = normal_equations(Js, Jt, r0, pieces, nx, nu)
    red = _ReducedWindow((G, Hth, A, B), E, D, has_next, nx, nth)
    N2, g2 = red.normal_equations(pieces)
    for name in ("S", "C", "T"):
        a, b = getattr(N2, name), getattr(N, name)
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10 * np.abs(b).max(), err_msg=name)
    np.testing.assert_allclose(g2, g, rtol=1e-10, atol=1e-10 * np.abs(g).max())
    np.testing.assert_allclose(red.r0, r0, rtol=1e-12)

    ds0, dth = rng.normal(size=(2, nx)), rng.normal(size=nu)
    dense_step = (Js.reshape(K, -1, nx) @ ds0[piece_of][:, :, None]).reshape(r0.shape) + Jt @ dth
    np.testing.assert_allclose(red.apply(ds0[piece_of], dth), dense_step, rtol=1e-10, atol=1e-10)
    rr = r0.reshape(K, -1)
    g_state, g_par = red.scores(r0)
    np.testing.assert_allclose(g_par, np.einsum("kmoi,kmo->ki", Jt, r0), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(g_state, np.einsum("kmoi,kmo->ki", Js, r0), rtol=1e-10, atol=1e-10)

    ks = np.arange(4, 9)  # the second piece leaving the window: its state and gaps profiled out
    nuis = np.concatenate([Js[ks].reshape(5, -1, nx), Jt[ks][..., nth:].reshape(5, -1, ngap)], axis=-1)
    par = Jt[ks][..., :nth].reshape(5, -1, nth)
    fn, fp = nuis.reshape(-1, nx + ngap), par.reshape(-1, nth)
    par = par - nuis @ (np.linalg.pinv(fn.T @ fn) @ (fn.T @ fp))
    s_k, A_k, r_k = red.profiled_scores(ks, r0)
    np.testing.assert_allclose(s_k, (par.transpose(0, 2, 1) @ rr[ks][:, :, None])[..., 0], rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(A_k, par.transpose(0, 2, 1) @ par, rtol=1e-8, atol=1e-8)
    np.testing.assert_array_equal(r_k, rr[ks])
