import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
sys.path.insert(0, str(Path(__file__).resolve().parent))  # the test oracle module


def assert_refused(code, err, *fragments):
    """Bad input: exit status 2 and one sentence naming the culprit, no traceback."""
    assert code == 2
    assert "Traceback" not in err
    lines = [l for l in err.strip().splitlines() if l.strip()]
    assert len(lines) == 1, err
    for f in fragments:
        assert f in lines[0], (f, lines[0])


# Tests that keep real time (live sessions, the virtual rig at 1 kHz on a pseudo-terminal, the
# firmware in the loop) run one after another on one worker: side by side they would load the
# machine beyond the two busy processes they are written to withstand. The rest spreads over
# the other workers (pytest-xdist, `-n` in pyproject.toml's addopts).
REALTIME_MODULES = {"test_live_e2e", "test_rig_server", "test_stream", "test_firmware", "test_procedures",
                    "test_transports"}


# Modules whose module-scoped fixtures are costly (the reference plant's runs of every effect
# form, a calibration's training run and its compiled functions) stay on one worker each:
# spread over two, each worker computed them again (about two minutes of the suite).
SHARED_FIXTURE_MODULES = {"test_reference_plant", "test_calibrate"}


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist reads the groups into the node ids
def pytest_collection_modifyitems(config, items):
    for item in items:
        name = item.module.__name__ if item.module is not None else ""
        if name in REALTIME_MODULES:
            item.add_marker(pytest.mark.xdist_group("realtime"))
        elif name in SHARED_FIXTURE_MODULES:
            item.add_marker(pytest.mark.xdist_group(name))


def pytest_collection_finish(session):
    """On an xdist worker: the real-time group must have reached the node ids, or the
    scheduler spreads those tests over all workers and they overload the machine (pytest 9.2
    with pytest-xdist 3.8 silently stopped grouping, pytest-xdist#1386)."""
    if not getattr(session.config.option, "loadgroup", False):
        return
    lost = [i.nodeid for i in session.items if i.get_closest_marker("xdist_group") and "@" not in i.nodeid]
    if lost:
        raise pytest.UsageError(f"pytest-xdist did not group {len(lost)} real-time tests (e.g. {lost[0]}): "
                                "this pytest and pytest-xdist do not work together; install the versions "
                                "pyproject.toml's test extra names")


@pytest.fixture(scope="session", autouse=True)
def _model_cache(tmp_path_factory):
    """Compiled model functions go to the user cache unless CI asks for a fresh one, which the
    workers of one session share (the cache's writes are atomic: a race only compiles twice)."""
    if os.environ.get("COMBINED_REALITY_FRESH_CACHE"):
        base = tmp_path_factory.getbasetemp()
        shared = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "model_cache"
        shared.mkdir(exist_ok=True)
        os.environ["COMBINED_REALITY_CACHE"] = str(shared)
    yield


@pytest.fixture(scope="session")
def cyl_a():
    from sim.cylinder import load_cylinder

    return load_cylinder(CONFIGS / "cyl_a_32x100.toml")


@pytest.fixture(scope="session")
def cyl_50():
    from sim.cylinder import load_cylinder

    return load_cylinder(CONFIGS / "ind4_norgren_50x400.toml")


@pytest.fixture(scope="session")
def run_a(cyl_a):
    from combined_reality.simulation import simulate_run

    return simulate_run(cyl_a, 20.0, seed=1)


@pytest.fixture(scope="session")
def run_50(cyl_50):
    from combined_reality.simulation import simulate_run

    return simulate_run(cyl_50, 20.0, seed=2)


class BusyProcesses:
    """`n` busy processes (python -c "while True: pass") until stop()."""

    def __init__(self, n: int = 2):
        import subprocess

        self._hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]

    def stop(self) -> None:
        for p in self._hogs:
            p.kill()
            p.wait()
        self._hogs = []


@pytest.fixture(scope="session")
def realtime_models(cyl_a):
    """The model functions of a live session on the default cylinder, built before any busy
    processes start: the lock-step simulator's (which the virtual rig shares) and the online
    estimator's. Compiled under that load into CI's fresh cache, they took the first live test
    to 77-100 s (38 s otherwise), with both busy processes burning the cores all along."""
    from combined_reality.identify import MovingHorizonEstimator, OnlineOptions
    from combined_reality.live import LockstepSimulator

    LockstepSimulator(cyl_a)
    MovingHorizonEstimator(cyl_a, 1e-3, OnlineOptions())


@pytest.fixture
def busy_machine(realtime_models):
    """Two busy processes beside the test, as on a lab PC doing other work: the real-time
    tests must hold what they assert under this load (on a 2-core machine, more than all of it).
    A test whose real-time part ends early stops them (busy_machine.stop()): work after it, such
    as an offline fit of the recording, is no real-time work, and under the load it only slows
    the rest of the suite."""
    hogs = BusyProcesses()
    try:
        yield hogs
    finally:
        hogs.stop()
