"""Experiment programs: every one keeps the command bound and the soft stroke limits."""
import numpy as np
import pytest

from combined_reality.live import ProgramOptions, make_program


@pytest.mark.parametrize("name", ["mixed", "steps", "ramps", "sines", "pulses", "file"])
def test_programs_stay_bounded_and_push_back_past_the_soft_limits(cyl_a, tmp_path, name):
    L = cyl_a.geometry.stroke
    if name == "file":
        (tmp_path / "cmd.csv").write_text("# a wild command file\nt,u\n0,0.3\n0.5,-7\n1.0,nan\n1.5,0.9\n")
        name = f"file:{tmp_path / 'cmd.csv'}"
    prog = make_program(name, cyl_a, 10.0, seed=3) if not name.startswith("file") else None
    if prog is None:
        with pytest.raises(ValueError, match="finite"):
            make_program(name, cyl_a, 10.0)
        (tmp_path / "cmd.csv").write_text("t,u\n0,0.3\n0.5,-7\n1.5,0.9\n")
        with pytest.raises(ValueError, match=r"u = -7 at t = 0.5 s is outside \[-1, 1\]"):
            make_program(name, cyl_a, 10.0)  # refused, not bounded silently
        (tmp_path / "cmd.csv").write_text("t,u\n0,0.3\n0.5,-1\n1.5,0.9\n")
        prog = make_program(name, cyl_a, 10.0)
        assert prog.command(0.7, 0.5 * L) == -ProgramOptions().u_max  # held, then clipped to the bound
        assert prog.command(0.2, 0.5 * L) == 0.3
    t = np.arange(0, 10, 0.001)
    mid = np.array([prog.command(tk, 0.5 * L) for tk in t])
    assert np.all(np.abs(mid) <= ProgramOptions().u_max)
    assert np.ptp(mid) > 0.1  # it does excite
    low = np.array([prog.command(tk, 0.01 * L) for tk in t[::50]])
    high = np.array([prog.command(tk, 0.99 * L) for tk in t[::50]])
    assert np.all(low > 0) and np.all(high < 0)  # past a soft limit only back into the stroke


def test_pulses_alternate_with_rests(cyl_a):
    prog = make_program("pulses", cyl_a, 5.0, seed=1)
    u = np.array([prog.command(t, 0.05) for t in np.arange(0, 5, 0.001)])
    pulses = u[np.abs(u) > 0]
    signs = np.sign(pulses)[np.flatnonzero(np.diff(np.r_[0, np.sign(pulses)]))]
    assert len(signs) >= 6 and np.all(signs[1:] != signs[:-1])
    assert np.mean(u == 0) > 0.4
