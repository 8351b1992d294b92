"""The integrator is accurate for this stiff plant at 1 kHz: refining it does not matter."""
import numpy as np

from sim.compiled import shooting_functions
from sim.integrator import IntegratorOptions
from sim.plant import build_plant


def _open_loop(plant, opts, run, p, M=100):
    sf = shooting_functions(plant, M, (), opts)
    N = run.n
    K = -(-N // M)
    u = np.concatenate([run.u, np.full(K * M + 1 - N, run.u[-1])])
    H = np.concatenate([np.diff(run.t), np.zeros(K * M - N + 1)])
    s = np.array([run.p1[0], run.p2[0], run.x[0], 0.0])
    out = [s[:, None]]
    for k in range(K):
        X = np.asarray(sf.interval(s, u[None, k * M:k * M + M + 1], p, H[None, k * M:(k + 1) * M]))
        out.append(X)
        s = X[:, -1]
    return np.hstack(out)[:, :N]


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
