"""Long recordings: the fit is linearised a chunk of intervals at a time, so that what it holds
grows with the run only by the data, and the result is the one of the whole problem."""
import tracemalloc

import numpy as np
import pytest

from combined_reality.identify import IdentifyOptions, identify
from combined_reality.simulation import simulate_run


def _problem(cyl, runs, chunk_intervals=None):
    """The shooting problem of `runs` as identify lays it out (nominal plant, Fc, Fv, kp free),
    with chunks of `chunk_intervals` intervals (None: the default)."""
    import combined_reality.identify.shooting as sh
    from sim.compiled import shooting_functions
    from sim.plant import plant_for

    plant = plant_for(cyl)
    free = sh.free_parameters(plant, ("Fc", "Fv", "kp"))
    M = 100
    sf = shooting_functions(plant, M, free, with_sens=True)
    layouts, node0 = [], 0
    for r in runs:
        layouts.append(sh.run_layout(r, plant, cyl, M, node0))
        node0 += layouts[-1].K
    layouts, (W, H, Y, mask, S) = sh.concatenated_layouts(layouts)
    has_next = np.ones(node0, bool)
    for lay in layouts:
        has_next[lay.node0 + lay.K - 1] = False
    wts, sscale = sh.residual_scales(plant, cyl, runs[0].sample_period)
    saved = sh.CHUNK_SAMPLES
    if chunk_intervals is not None:
        sh.CHUNK_SAMPLES = chunk_intervals * M
    try:
        prob = sh.ShootingProblem(sf, node0, 2, W, H, Y, mask, wts, sscale, np.flatnonzero(has_next),
                                  plant.possible_states(cyl))
    finally:
        sh.CHUNK_SAMPLES = saved
    p = np.array(plant.parameter_vector(cyl), float)
    return prob, layouts, S, p, free


def test_the_normal_equations_accumulated_chunk_by_chunk_are_those_of_the_whole_problem(cyl_a):
    """Two runs (3.3 s and 2.05 s: 54 intervals) linearised in chunks of 8 intervals (a chunk
    holds the end of one run and the start of the next, clusters straddle chunks) give the
    normal equations, the step, the decrease it predicts and the reported covariance of the
    whole problem linearised at once, to 1e-10; the predicted decrease is the one of the
    linearised residuals themselves."""
    import combined_reality.identify.shooting as sh

    runs = [simulate_run(cyl_a, 3.3, seed=11), simulate_run(cyl_a, 2.05, seed=12)]
    whole, layouts, S, p, free = _problem(cyl_a, runs)
    chunked = _problem(cyl_a, runs, chunk_intervals=8)[0]
    assert len(whole.spans) == 1 and len(chunked.spans) == 7
    pieces = [(lay.node0, lay.K) for lay in layouts]
    S = S.copy()
    S[:, 1::3] *= 1.0 + 1e-3  # open defects: the constant part q of the node increments matters
    one = whole.linearise(S, p, sh.NormalEquations(pieces, whole.nx, whole.nth, 10))
    many = chunked.linearise(S, p, sh.NormalEquations(pieces, whole.nx, whole.nth, 10))
    assert one.kept is not None and many.kept is None

    def close(a, b, tol=1e-10):
        a, b = np.asarray(a, float), np.asarray(b, float)
        return np.max(np.abs(a - b)) <= tol * np.max(np.abs(a))

    for name in ("g", "P", "Q", "q", "D"):
        assert close(getattr(one, name), getattr(many, name)), name
    for name in ("S", "C", "T"):
        assert close(getattr(one.N, name), getattr(many.N, name)), name
    for name in ("states", "params", "piece"):
        assert close(getattr(one.clusters, name), getattr(many.clusters, name)), name
    assert many.cost2 == pytest.approx(one.cost2, rel=1e-12)
    theta = p[free]
    lo, hi = sh.parameter_bounds(whole.plant, ("Fc", "Fv", "kp"))
    n_state = len(pieces) * whole.nx
    step = sh.solve_bounded(sh.step_matrix(one.N), one.g, theta, lo, hi, 0.0)
    assert close(step, sh.solve_bounded(sh.step_matrix(many.N), many.g, theta, lo, hi, 0.0), 1e-8)
    # the decrease predicted from the accumulated sums is that of the residuals linearised whole
    E, D, X, Sens = whole.evaluate(S, p, True)
    G, Hth, _, _ = sh.linearize((E, D, X, Sens), whole.out_idx, whole.wts, whole.mask, whole.M, whole.nx,
                                len(whole.out_idx), whole.nth)
    ds0, dth = step[:n_state].reshape(-1, whole.nx), step[n_state:]
    dS = np.concatenate([one.P[k0:k0 + K] @ ds0[i] + one.Q[k0:k0 + K] @ dth + one.q[k0:k0 + K]
                         for i, (k0, K) in enumerate(pieces)])
    lin = np.einsum("kmoi,ki->kmo", G, dS) + np.einsum("kmoi,i->kmo", Hth, dth)
    for eqs in (one, many):
        gdir, quad = eqs.predicted(step)
        assert gdir == pytest.approx(float(np.sum(E * lin)), rel=1e-9)
        assert quad == pytest.approx(float(np.sum(lin * lin)), rel=1e-9)
    nres = float(np.sum(whole.mask))
    cov1 = sh.reported_covariance(one.N, one.clusters, 0.5 * one.cost2, nres)
    cov2 = sh.reported_covariance(many.N, many.clusters, 0.5 * many.cost2, nres)
    assert close(cov1, cov2)
    # a trial's merit terms are summed a chunk at a time too
    sq1, D1 = whole.merit_terms(S, p)
    sq2, D2 = chunked.merit_terms(S, p)
    assert sq2 == pytest.approx(sq1, rel=1e-12) and np.array_equal(D1, D2)


def test_a_fit_holds_no_more_per_sample_than_the_data(cyl_a, monkeypatch):
    """What a fit allocates at its peak grows with the run by less than 400 bytes per sample
    (its layout of the data: measured 75), not by its sensitivities (a whole run's
    sensitivities, Jacobians and reduced Jacobians took 1.6 kB per sample)."""
    import combined_reality.identify.shooting as sh

    # chunks of 16 intervals, so that these short runs are linearised in several
    monkeypatch.setattr(sh, "CHUNK_SAMPLES", 16 * 100)
    opts = IdentifyOptions(max_iter=2, restart_misfit=False, threads=1)
    peaks = {}
    for duration in (3.0, 12.0):
        run = simulate_run(cyl_a, duration, seed=5)
        identify(cyl_a, [run], opts)  # model functions loaded: not part of what is measured
        tracemalloc.start()
        try:
            identify(cyl_a, [run], opts)
            peaks[duration] = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
    per_sample = (peaks[12.0] - peaks[3.0]) / 9000
    assert per_sample < 400, peaks


def test_a_run_longer_than_a_minute_is_fitted_in_equal_pieces_of_whole_intervals():
    """A run over LONG_PIECE_S is cut into the fewest equal pieces of whole intervals that are
    none longer, every sample in exactly one; a run up to it is left whole."""
    from combined_reality.files import Run
    from combined_reality.identify.offline import LONG_PIECE_S, long_run_pieces

    def run(n):
        t = np.arange(n) * 1e-3
        return Run(t=t, u=np.zeros(n), x=np.zeros(n), p1=np.full(n, 2e5), p2=np.full(n, 2e5))

    short = run(int(LONG_PIECE_S * 1000) + 1)  # exactly LONG_PIECE_S long
    assert long_run_pieces(short, 100) == [short]
    long = run(150_001)  # 150 s
    pieces = long_run_pieces(long, 100)
    assert len(pieces) == 3
    assert all(p.duration <= LONG_PIECE_S for p in pieces)
    assert all(p.n % 100 == 0 for p in pieces[:-1])
    assert np.array_equal(np.concatenate([p.t for p in pieces]), long.t)


def _dense_solve_bounded(N, g, theta, lower, upper, n_state, lam, state_scale=None):
    """The bounded, damped step on the dense matrix (the solver before the start states were
    eliminated piece by piece): the oracle."""
    import combined_reality.identify.shooting as sh

    n = len(g)
    if state_scale is not None:
        N = N.copy()
        N[np.arange(n_state), np.arange(n_state)] += sh.NODE_PROXIMAL / state_scale ** 2
    fixed, d = np.zeros(n, bool), np.zeros(n)
    for _ in range(len(theta) + 1):
        free = ~fixed
        scale = np.sqrt(np.maximum(np.diag(N), 1e-300))
        Ns = N / np.outer(scale, scale)
        Ns = Ns + lam * np.diag(np.diag(Ns))
        rhs = -(g + N[:, fixed] @ d[fixed]) / scale
        d[free] = np.linalg.solve(Ns[np.ix_(free, free)], rhs[free]) / scale[free]
        th_new = theta + d[n_state:]
        viol = (th_new < lower) | (th_new > upper)
        if not viol.any():
            return d
        for i in np.flatnonzero(viol):
            d[n_state + i] = (lower[i] if th_new[i] < lower[i] else upper[i]) - theta[i]
            fixed[n_state + i] = True
    return d


def _arrowhead(rng, R, nx, nth, rows, state_scale=1.0, th_scale=1.0):
    """A random least-squares problem in R pieces' start states and nth parameters: its Jacobian
    J (rows per piece, each piece's rows reaching only its own start state), the residuals r and
    its normal matrix as blocks, each summed from its piece's rows alone."""
    import combined_reality.identify.shooting as sh

    J = np.zeros((R * rows, R * nx + nth))
    blocks = sh.ReducedNormal.zeros(R, nx, nth)
    for i in range(R):
        js = rng.normal(size=(rows, nx)) * state_scale
        jt = rng.normal(size=(rows, nth)) * th_scale
        J[i * rows:(i + 1) * rows, i * nx:(i + 1) * nx], J[i * rows:(i + 1) * rows, R * nx:] = js, jt
        blocks.S[i], blocks.C[i] = js.T @ js, js.T @ jt
        blocks.T[...] += jt.T @ jt
    return J, rng.normal(size=R * rows), blocks


def test_the_start_states_eliminated_piece_by_piece_give_the_dense_step_and_covariance():
    """Six pieces whose start states couple only with three parameters of scales ten decades
    apart, the blocks summed piece by piece: the step (undamped, damped with the node states
    bounded, with a parameter at its bound), the decrease it predicts, the Gauss-Newton and
    cluster-robust covariances, the parameters' information and gradient with the start states
    eliminated, and with a parameter eliminated too, equal numpy's on the dense J'J to 1e-10."""
    import combined_reality.identify.shooting as sh

    rng = np.random.default_rng(5)
    R, nx, nth, rows = 6, 4, 3, 40
    J, r, red = _arrowhead(rng, R, nx, nth, rows, [1e3, 1.0, 1e-3, 1e2], np.array([1.0, 1e-2, 1e8]))
    N, g = J.T @ J, J.T @ r
    n = R * nx

    def close(a, b, tol=1e-10):
        return np.max(np.abs(np.asarray(a) - b)) <= tol * np.max(np.abs(b))

    theta, wide = np.zeros(nth), np.full(nth, 1e9)
    free_step = -np.linalg.solve(N, g)
    assert close(sh.solve_bounded(sh.step_matrix(red), g, theta, -wide, wide, 0.0), free_step)
    scale = rng.uniform(0.5, 2.0, n)
    upper = wide.copy()
    upper[1] = free_step[n + 1] - 0.5 * abs(free_step[n + 1])  # the free step goes beyond it
    for lam, bounds, sscale in ((0.0, (-wide, wide), None), (1e-2, (-wide, wide), scale),
                                (0.0, (-wide, upper), None), (1e-3, (-wide, upper), scale)):
        d = sh.solve_bounded(sh.step_matrix(red, sscale), g, theta, *bounds, lam)
        want = _dense_solve_bounded(N, g, theta, *bounds, n, lam, sscale)
        assert close(d, want), (lam, d - want)
        assert d[n + 1] <= bounds[1][1]
    assert sh.solve_bounded(sh.step_matrix(red), g, theta, -wide, upper, 0.0)[n + 1] == upper[1]
    z = rng.normal(size=len(g))
    assert red.quadratic(z) == pytest.approx(float(z @ N @ z), rel=1e-12)
    cost, nres = 0.5 * float(r @ r), float(len(r))
    inv = np.linalg.inv(N)
    E = red.schur()
    cov = sh.covariance(E, cost, nres)
    assert close(cov, 2 * cost / (nres - len(g)) * inv[n:, n:])
    info = N[n:, n:] - N[n:, :n] @ np.linalg.solve(N[:n, :n], N[:n, n:])
    assert close(E.information(), info)
    assert close(E.reduced(g), g[n:] - N[n:, :n] @ np.linalg.solve(N[:n, :n], g[:n]))
    # clusters of 10 rows within a piece: the sandwich's parameter block
    piece = np.repeat(np.arange(R), rows // 10)
    dense_scores = np.stack([J[k * 10:(k + 1) * 10].T @ r[k * 10:(k + 1) * 10] for k in range(len(piece))])
    states = np.stack([s[p * nx:(p + 1) * nx] for s, p in zip(dense_scores, piece)])
    clusters = sh.Clusters(states, dense_scores[:, n:], piece)
    nb = len(piece)
    sandwich = (inv @ dense_scores.T @ dense_scores @ inv)[n:, n:] * nb / (nb - 1)
    assert close(sh.cluster_covariance(E, clusters), sandwich)
    # the last parameter eliminated with the start states (a nuisance: the online window's gap offsets)
    E2 = red.schur(keep=nth - 1)
    k = n + nth - 1
    assert close(E2.parameter_inverse(), inv[n:k, n:k])
    assert close(E2.information(), np.linalg.inv(inv[n:k, n:k]), 1e-9)
    kept, nuis = np.arange(n, k), np.r_[np.arange(n), k]
    proj = np.linalg.solve(N[np.ix_(nuis, nuis)], N[np.ix_(nuis, kept)])
    assert close(E2.profiled(states, piece, dense_scores[:, n:]), dense_scores[:, kept] - dense_scores[:, nuis] @ proj)


def test_a_start_state_no_residual_sees_takes_no_step_and_leaves_no_covariance():
    """A piece whose start state reaches no residual (a singular block): the step is the
    least-squares one of minimum norm, as the dense solver's fallback gave it, and there is
    no covariance to report."""
    import combined_reality.identify.shooting as sh

    rng = np.random.default_rng(1)
    R, nx, nth, rows = 3, 4, 2, 30
    J, r, red = _arrowhead(rng, R, nx, nth, rows)
    J[:, nx + 3] = 0.0
    red.S[1, 3, :], red.S[1, :, 3], red.C[1, 3] = 0.0, 0.0, 0.0
    d = sh.solve_bounded(sh.step_matrix(red), J.T @ r, np.zeros(nth), np.full(nth, -1e9), np.full(nth, 1e9), 0.0)
    want = np.linalg.lstsq(J, -r, rcond=None)[0]
    assert np.max(np.abs(d - want)) <= 1e-10 * np.max(np.abs(want)) and d[nx + 3] == 0.0
    assert sh.covariance(red.schur(), 1.0, 100.0) is None


def test_the_normal_equations_of_thousands_of_pieces_grow_linearly():
    """20 000 gap-free pieces (an hour's recording losing a sample every 0.18 s): the normal
    equations hold a few blocks per piece (their dense matrix: 51 GB)."""
    import tracemalloc

    import combined_reality.identify.shooting as sh

    R, nx, nth = 20_000, 4, 3
    tracemalloc.start()
    try:
        eqs = sh.NormalEquations([(k, 1) for k in range(R)], nx, nth, 10)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert eqs.N.S.shape == (R, nx, nx) and len(eqs.clusters) == R
    assert peak < 2000 * R  # bytes per piece (measured ~1000)


def test_a_run_losing_a_sample_every_quarter_second_identifies_the_friction(cyl_a, run_a):
    """80 gaps in 20 s (81 pieces, each with its own start state): identified, near the noise,
    the friction within 4 std of the truth."""
    from combined_reality.files import Run

    keep = np.ones(run_a.n, bool)
    keep[125::250] = False
    idx = np.flatnonzero(keep)
    run = Run(t=run_a.t[idx], u=run_a.u[idx], x=run_a.x[idx], p1=run_a.p1[idx], p2=run_a.p2[idx])
    res = identify(cyl_a, [run], IdentifyOptions())
    assert len(res.fit_per_run) == 81
    assert res.solver["status"] == "converged" and res.solver["residual_sigma"] < 1.05
    for n in ("Fc", "Fv", "kp"):
        assert abs(res.params[n].value - cyl_a.value(n)) < 4 * res.params[n].std, n


def test_a_chunk_of_many_free_parameters_is_shorter_and_its_sensitivities_come_in_small_pieces(cyl_a):
    """A chunk's sensitivities stay within CHUNK_SENSITIVITIES numbers whatever the number of free
    parameters (calibrate's whole model: 42), while a 20 s run of that model at 1 kHz and 0.1 s
    intervals is still one chunk and identify's chunks keep CHUNK_SAMPLES; the sensitivities are
    computed by map functions of at most two sizes, an eighth of a chunk at most, however many
    chunks (a map function holds its results between calls), and equal those of one call."""
    import combined_reality.identify.shooting as sh

    for nx, nth in ((4, 42), (5, 60), (2, 37), (4, 3)):
        size = sh.chunk_intervals(100, nx, nth)
        assert size * 100 * nx * (nx + nth) <= sh.CHUNK_SENSITIVITIES and size % sh.TRIAL_CHUNKS == 0
    assert sh.chunk_intervals(100, 4, 42) * 100 >= 20_000
    assert sh.chunk_intervals(100, 4, 3) * 100 == sh.CHUNK_SAMPLES // 800 * 800

    run = simulate_run(cyl_a, 3.3, seed=11)
    prob, layouts, S, p, free = _problem(cyl_a, [run], chunk_intervals=16)
    assert prob.spans == [(0, 16), (16, 32), (32, 33)] and prob.sens_piece == 2
    eqs = prob.linearise(S, p, sh.NormalEquations([(0, prob.K)], prob.nx, prob.nth, 10))
    assert eqs is not None
    sizes = sorted(n for with_sens, n in prob._maps if with_sens)
    assert sizes == [1, 2]
    X, Sens = prob.span_simulation(S, p, 16, 32, True)
    whole = prob._sf.sens.map(16)(S[:, 16:32], prob.W[:, 16 * 101:32 * 101], p, prob.H[:, 1600:3200])
    assert np.array_equal(X, np.asarray(whole[0]).reshape(X.shape))
    assert np.array_equal(Sens, np.asarray(whole[1]).reshape(Sens.shape))


def test_the_chambers_linear_start_holds_no_more_per_sample_than_its_rows(cyl_a, monkeypatch):
    """The valve and chambers' linear start forms its least squares ROWS_AT_ONCE rows at a time
    and keeps the rises of one overlap per direction: what it allocates grows with the run by
    less than 300 bytes a sample (its rows: measured 104; holding the rises of every overlap
    searched and all rows at once, 1.4 kB: 816 MB at 600 s), and its result is that of all rows
    at once to rounding."""
    import combined_reality.calibrate.prefit as pf

    runs = {d: simulate_run(cyl_a, d, seed=7) for d in (2.0, 8.0)}
    whole = pf.chamber_prefit(cyl_a, [runs[8.0]])
    monkeypatch.setattr(pf, "ROWS_AT_ONCE", 256)
    blocked = pf.chamber_prefit(cyl_a, [runs[8.0]])
    assert whole.keys() == blocked.keys()
    for name, value in whole.items():
        assert blocked[name] == pytest.approx(value, rel=1e-9, abs=1e-15), name
    peaks = {}
    for d, run in runs.items():
        tracemalloc.start()
        try:
            pf.chamber_prefit(cyl_a, [run])
            peaks[d] = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
    per_sample = (peaks[8.0] - peaks[2.0]) / 6000
    assert per_sample < 300, peaks
