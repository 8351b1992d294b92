"""The identifier's discretisation error (identify.discretisation): measured at the solution,
taken out of the estimates, and what it leaves owned by the reported std."""
import numpy as np
import pytest

from combined_reality.identify import IdentifyOptions, identify


@pytest.fixture(scope="module")
def clean_run(cyl_a):
    """6 s of the position program without sensor noise: the fit's only error is its integration
    (the virtual rig integrates 20 x more finely)."""
    from combined_reality.simulation import simulate_run

    return simulate_run(cyl_a, 6.0, seed=5, noise=False)


def test_the_shift_is_the_estimates_discretisation_error_and_is_taken_out(cyl_a, clean_run):
    """Without noise, the estimates of the fit's own integration are off the truth by its
    discretisation error alone (here 1.3e-4 N, 8.7e-4 N s/m, 8.6e-10 N/Pa); the shift measured at the solution is that error to 2 %, and the reported
    estimates, moved by it, lie within a twentieth of it and within their std of the truth.
    Below discretisation_min_s (default 30 s) nothing is measured and the estimates are the fit's."""
    res = identify(cyl_a, [clean_run], IdentifyOptions(discretisation_min_s=0.0))
    term = res.solver["discretisation"]
    assert term["span_s"] == pytest.approx(clean_run.n * 1e-3, abs=0.1)
    plain = identify(cyl_a, [clean_run])
    assert plain.solver["discretisation"] is None
    for n, e in res.params.items():
        truth, shift = cyl_a.value(n), term["shift"][n]
        before = plain.params[n].value - truth
        assert e.value - shift == pytest.approx(plain.params[n].value, rel=1e-12, abs=0.0), n
        assert abs(before) > 1.5 * plain.params[n].std, (n, before, plain.params[n].std)  # the bias is there
        assert shift == pytest.approx(-before, rel=0.02), n
        assert abs(e.value - truth) <= 0.05 * abs(shift), n
        assert abs(e.value - truth) <= e.std, n
        assert term["std"][n] == pytest.approx(0.05 * abs(shift), rel=1e-9)  # the fine integration's own


def test_a_shift_measured_on_stretches_owns_their_spread(cyl_a, clean_run, monkeypatch):
    """Measured on 4 s of the 6 s in two stretches of 2 s, the shift is near the whole run's (within
    40 %) and its std is larger than the fine integration's error alone: the stretches' spread
    is owned."""
    import combined_reality.identify.discretisation as disc

    whole = identify(cyl_a, [clean_run], IdentifyOptions(discretisation_min_s=0.0)).solver["discretisation"]
    monkeypatch.setattr(disc, "SPAN_S", 4.0)
    monkeypatch.setattr(disc, "STRETCH_S", 2.0)
    part = identify(cyl_a, [clean_run], IdentifyOptions(discretisation_min_s=0.0)).solver["discretisation"]
    assert part["span_s"] == pytest.approx(4.0)
    for n in whole["shift"]:
        assert part["shift"][n] == pytest.approx(whole["shift"][n], rel=0.6), n
        assert part["std"][n] > 1.1 * disc.FINE_FACTOR * abs(part["shift"][n]), n


def test_stretches_cover_a_long_run_evenly_and_keep_its_pieces_apart():
    """Beyond SPAN_S of data (padding not counted), SPAN_S / STRETCH_S stretches of STRETCH_S of
    data each, evenly spread; a stretch over pieces of a second (a sample lost every second)
    holds a minute of them, each kept apart, not a single second."""
    from combined_reality.identify.discretisation import SPAN_S, STRETCH_S, pieces_within, stretches
    from combined_reality.identify.shooting import RunLayout

    M, dt = 100, 1e-3

    def layouts(piece_intervals, samples=None):
        out, k0 = [], 0
        for K in piece_intervals:
            H = np.zeros((1, K * M))
            H[0, :K * M if samples is None else samples] = dt
            out.append(RunLayout(None, K, k0, None, H, None, None, None))
            k0 += K
        return out

    short = layouts([600, 600, 300])  # 150 s: measured whole
    assert stretches(short, M) == [(0, 600), (600, 600), (1200, 300)]
    n_pieces = int(3 * SPAN_S / 60)  # three times the span, in pieces of 60 s (600 intervals)
    total = 600 * n_pieces
    parts = stretches(layouts([600] * n_pieces), M)
    each = round(STRETCH_S / (M * dt))
    assert len(parts) == SPAN_S // STRETCH_S and all(K == each for _, K in parts)
    starts = [k0 for k0, _ in parts]
    assert starts == sorted(starts) and starts[0] < total / len(parts) and starts[-1] > total * (1 - 1 / len(parts))
    # an hour and a half losing a sample every second: pieces of 999 samples in 10 intervals
    lossy = layouts([10] * 5400, samples=999)
    assert sum(float(l.H.sum()) for l in lossy) == pytest.approx(5394.6)
    parts = stretches(lossy, M)
    assert len(parts) == SPAN_S // STRETCH_S
    for k0, K in parts:
        pieces = pieces_within(lossy, k0, K)
        assert sum(n for _, n in pieces) == K and len(pieces) >= 60
        assert sum(float(l.H.sum()) for l in lossy[k0 // 10:(k0 + K) // 10]) == pytest.approx(STRETCH_S, rel=0.02)
    assert stretches(layouts([10] * 3000, samples=999), M) == [(10 * i, 10) for i in range(3000)]  # 2997 s: whole


def test_a_shift_measured_on_stretches_of_many_pieces(cyl_a, clean_run, monkeypatch):
    """A run that loses a sample every 0.5 s: measured on 4 s in stretches of 2 s, each stretch
    holds four pieces kept apart and the 4 s measured are 4 s of data (not four pieces' worth of
    padding-free seconds cut to one piece each); the shift is near that of the run measured whole."""
    import combined_reality.identify.discretisation as disc
    from combined_reality.files import Run

    keep = np.ones(clean_run.n, bool)
    keep[250::500] = False
    idx = np.flatnonzero(keep)
    run = Run(t=clean_run.t[idx], u=clean_run.u[idx], x=clean_run.x[idx], p1=clean_run.p1[idx],
              p2=clean_run.p2[idx])
    whole = identify(cyl_a, [run], IdentifyOptions(discretisation_min_s=0.0)).solver["discretisation"]
    monkeypatch.setattr(disc, "SPAN_S", 4.0)
    monkeypatch.setattr(disc, "STRETCH_S", 2.0)
    part = identify(cyl_a, [run], IdentifyOptions(discretisation_min_s=0.0)).solver["discretisation"]
    assert part["span_s"] == pytest.approx(4.0, rel=0.05)
    for n in ("Fc", "Fv"):  # (kp's shift on these 6 s is too small to be measured on 4 s of them)
        assert part["shift"][n] == pytest.approx(whole["shift"][n], rel=0.6), n
