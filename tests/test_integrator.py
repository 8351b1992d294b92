"""The integrator is accurate for this stiff plant at 1 kHz: refining it does not matter; its
sensitivities are the derivative of the step."""
import numpy as np
import pytest

from sim.compiled import shooting_functions
from sim.integrator import IntegratorOptions
from sim.plant import build_plant


def _open_loop(plant, opts, run, p):
    sf = shooting_functions(plant, 100, (), opts)
    s = np.array([run.p1[0], run.p2[0], run.x[0], 0.0])
    return sf.simulate(s, run.u, p, np.diff(run.t))  # (nx, run.n)


def test_refining_the_step_changes_a_20s_trajectory_less_than_the_noise(cyl_a, run_a):
    """Replays the recorded valve command of a 20 s closed-loop run open-loop (as identification
    does) with the default tolerances and with 10x tighter ones."""
    plant = build_plant("command")
    p = np.array(plant.parameter_vector(cyl_a))
    default = _open_loop(plant, IntegratorOptions(), run_a, p)
    fine = _open_loop(plant, IntegratorOptions().scaled(0.1), run_a, p)
    dx = np.abs(default[2] - fine[2]).max()
    dp = np.abs(default[:2] - fine[:2]).max()
    assert np.ptp(fine[2]) > 0.03  # the run really moves
    print(f"refinement changes x by {dx * 1e6:.2f} um and p by {dp:.1f} Pa at most")
    assert dx < 0.5 * cyl_a.sensors.position_noise, dx
    assert dp < 0.5 * cyl_a.sensors.pressure_noise, dp


def test_fixed_single_step_would_not_be_accurate(cyl_a, run_a):
    """Why refinement exists: one RA34PW2 step per sample misses sub-sample events."""
    plant = build_plant("command")
    p = np.array(plant.parameter_vector(cyl_a))
    coarse = _open_loop(plant, IntegratorOptions(max_depth=0), run_a, p)
    fine = _open_loop(plant, IntegratorOptions(), run_a, p)
    assert np.abs(coarse[2] - fine[2]).max() > cyl_a.sensors.position_noise


def test_zero_length_steps_are_identity(cyl_a):
    plant = build_plant("command")
    sf = shooting_functions(plant, 1)
    s = np.array([4e5, 3e5, 0.05, 0.1])
    out = np.asarray(sf.step(s, 0.7, 0.7, plant.parameter_vector(cyl_a), 0.0)).ravel()
    np.testing.assert_array_equal(out, s)


def test_simulate_runs_any_length_through_one_interval(cyl_a, run_a):
    """simulate pads the last interval with zero-length steps: the same states as stepping
    sample by sample, for a length that is not a multiple of the interval."""
    plant = build_plant("command")
    p = np.array(plant.parameter_vector(cyl_a))
    n = 234
    s = np.array([run_a.p1[0], run_a.p2[0], run_a.x[0], 0.0])
    X = shooting_functions(plant, 100).simulate(s, run_a.u[:n + 1], p, 1e-3)
    assert X.shape == (4, n + 1)
    step = shooting_functions(plant, 1).step
    ref = [s]
    for k in range(n):
        ref.append(np.asarray(step(ref[-1], run_a.u[k], run_a.u[k + 1], p, 1e-3)).ravel())
    np.testing.assert_allclose(X, np.array(ref).T, rtol=1e-12, atol=0)
    assert np.ptp(X[2]) > 1e-3  # it moved


@pytest.mark.parametrize("drive", ["command", "pressure"])
def test_sensitivities_agree_with_central_differences_of_the_interval(cyl_a, drive):
    """The interval's sensitivities are the derivative of the discrete step (CasADi's AD through
    it, its matrix and factors included): against central differences of the simulated interval,
    per state and per free parameter, over the intervals of a 2 s closed-loop run.
    An approximation that leaves the derivative of the step's matrix out (the W-method applied
    to the variational equation: 30 % faster to evaluate, 40 % to compile) was off by a median
    of 0.03-0.1 % and up to 17 % where the piston sticks, and fits went wrong with it: a
    stiction level 7.9 std off, a position bump at its bound on a run without one, initial
    state fits stopped 1 % above their cost. Measured here: medians below 1e-6, the worst
    interval 0.6 % (most likely one where the refinement switches between the two perturbed
    runs: the differences then see a jump the derivative does not)."""
    from combined_reality.identify.shooting import free_parameters, run_layout
    from combined_reality.simulation import simulate_run

    run = simulate_run(cyl_a, 2.0, seed=3)
    plant = build_plant(drive)
    free = free_parameters(plant, ("Fc", "Fv", "kp"))
    sf = shooting_functions(plant, 100, free, with_sens=True)
    lay = run_layout(run, plant, cyl_a, 100, 0)
    p = np.array(plant.parameter_vector(cyl_a), float)
    nz = plant.nx + len(free)
    worst = []  # per interval and column: the worst output row's error relative to its largest value
    for k in range(lay.K):
        s, W, H = lay.S0[:, k], lay.W[:, k * 101:(k + 1) * 101], lay.H[:, k * 100:(k + 1) * 100]
        X, S = (np.asarray(a) for a in sf.sens(s, W, p, H))
        S = S.reshape(plant.nx, 100, nz)
        row = []
        for j in range(nz):
            sp, sm, pp, pm = s.copy(), s.copy(), p.copy(), p.copy()
            if j < plant.nx:
                d = 1e-6 * max(abs(s[j]), 1e-3)
                sp[j] += d
                sm[j] -= d
            else:
                d = 1e-6 * abs(p[free[j - plant.nx]])
                pp[free[j - plant.nx]] += d
                pm[free[j - plant.nx]] -= d
            fd = (np.asarray(sf.interval(sp, W, pp, H)) - np.asarray(sf.interval(sm, W, pm, H))) / (2 * d)
            err = np.abs(fd - S[:, :, j]).max(axis=1) / np.maximum(np.abs(fd).max(axis=1), 1e-300)
            row.append(err[[plant.state_names.index(n) for n in plant.output_names]].max())
        worst.append(row)
    worst = np.array(worst)
    fmt = {"float_kind": lambda v: f"{v:.1e}"}
    print(drive, "median error per column", np.array2string(np.median(worst, axis=0), formatter=fmt),
          "worst", np.array2string(worst.max(axis=0), formatter=fmt))
    assert np.all(np.median(worst, axis=0) < 1e-5), np.median(worst, axis=0)
    assert np.all(worst.max(axis=0) < 0.05), worst.max(axis=0)
