"""Compiled model functions are cached on disk and shared by structure."""
import subprocess
import sys

import numpy as np

from sim.compiled import cached_model_code, shooting_functions
from sim.effects import Stiction
from sim.integrator import StepBuilder
from sim.plant import build_plant


def test_second_process_and_second_cylinder_reuse_compiled_code(tmp_path, cyl_a, cyl_50, monkeypatch):
    monkeypatch.setenv("COMBINED_REALITY_CACHE", str(tmp_path))
    plant = build_plant("command", [Stiction()])
    first = shooting_functions(plant, 50, (12, 13))
    assert not first.stats.cache_hit
    # one file for the structure (compiled, or serialised without a compiler), not its lock
    built = cached_model_code()
    assert len(built) == 1 and built[0].parent == tmp_path and built[0].suffix in (".so", ".casadi")
    # same structure, other values (another cylinder, another stiction level): a cache hit
    other_plant = build_plant("command", [Stiction(Fs_excess=3.0)])
    again = shooting_functions(other_plant, 50, (12, 13))
    assert again.stats.cache_hit and cached_model_code() == built
    # ... whose code computes the second cylinder's trajectory (parameters are inputs, not baked in)
    s, W, H = [4.0e5, 3.0e5, 0.05, 0.0], np.full((1, 51), 0.3), np.full((1, 50), 1e-3)
    p50 = other_plant.parameter_vector(cyl_50)
    x50 = np.asarray(again.interval(s, W, p50, H))[:, -1]
    step = StepBuilder(other_plant).step()  # not compiled, not cached
    x = s
    for _ in range(50):
        x = step(x, 0.3, 0.3, p50, 1e-3)
    np.testing.assert_allclose(x50, np.asarray(x).ravel(), rtol=1e-9, atol=1e-12)
    xa = np.asarray(first.interval(s, W, plant.parameter_vector(cyl_a), H))[:, -1]
    assert abs(xa[2] - x50[2]) > 1e-4  # and the first cylinder's is another one
    code = ("from sim.compiled import shooting_functions; from sim.plant import build_plant;"
            "from sim.effects import Stiction;"
            "sf = shooting_functions(build_plant('command', [Stiction()]), 50, (12, 13));"
            "print(sf.stats.cache_hit)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)  # same env
    assert out.stdout.strip() == "True"
    # another structure (other free parameters) is another entry
    other = shooting_functions(plant, 50, (12,))
    assert not other.stats.cache_hit


def test_without_a_compiler_the_serialised_functions_give_the_same_numbers(tmp_path, cyl_a, monkeypatch):
    plant = build_plant("command")
    p = plant.parameter_vector(cyl_a)
    s = [4.0e5, 3.0e5, 0.05, 0.1]
    monkeypatch.setenv("COMBINED_REALITY_CACHE", str(tmp_path / "compiled"))
    compiled = shooting_functions(plant, 20, (12, 13, 14))
    monkeypatch.setenv("COMBINED_REALITY_CACHE", str(tmp_path / "vm"))
    monkeypatch.setenv("CC", "none")
    built = shooting_functions(plant, 20, (12, 13, 14))
    assert not built.stats.cache_hit and built.stats.path.endswith(".casadi")
    loaded = shooting_functions(plant, 20, (12, 13, 14))  # a later process: from the serialised file
    assert loaded.stats.cache_hit
    W, H = np.full((1, 21), 0.3), np.full((1, 20), 1e-3)
    for sf in (built, loaded):
        X, S = sf.sens(s, W, p, H)
        X0, S0 = compiled.sens(s, W, p, H)
        np.testing.assert_allclose(np.asarray(X), np.asarray(X0), rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(np.asarray(S), np.asarray(S0), rtol=1e-9, atol=1e-12)


def test_a_failing_compiler_is_tried_once(tmp_path, monkeypatch):
    """When compiling fails the serialised form is stored, and later calls load it instead of
    building and failing again."""
    monkeypatch.setenv("COMBINED_REALITY_CACHE", str(tmp_path))
    monkeypatch.setenv("CC", "false")  # a "compiler" that always fails
    plant = build_plant("command")
    said = []
    built = shooting_functions(plant, 5, (), progress=said.append)
    assert not built.stats.cache_hit and built.stats.path.endswith(".casadi")
    assert any("compiling failed" in s for s in said)
    said.clear()
    again = shooting_functions(plant, 5, (), progress=said.append)
    assert again.stats.cache_hit and again.stats.path.endswith(".casadi") and not said


def test_a_compiler_installed_later_compiles_what_was_stored_without_one(tmp_path, cyl_a, monkeypatch):
    from sim.compiled import shooting_functions
    from sim.plant import build_plant

    monkeypatch.setenv("COMBINED_REALITY_CACHE", str(tmp_path))
    monkeypatch.setenv("CC", "none")
    assert shooting_functions(build_plant("command"), 7, ()).stats.path.endswith(".casadi")
    monkeypatch.delenv("CC")
    assert shooting_functions(build_plant("command"), 7, ()).stats.path.endswith(".so")


def test_numpy_call_gives_the_dm_call_numbers_and_refuses_wrong_shapes():
    import casadi as ca
    import pytest

    from sim.compiled import NumpyCall

    x, p = ca.SX.sym("x", 3, 2), ca.SX.sym("p", 2)
    f = ca.Function("f", [x, p], [ca.sin(x) * p[0] + p[1], ca.sum1(x)]).map(4)
    X = np.random.default_rng(0).normal(size=(3, 8))
    P = np.array([1.5, -0.25])
    call = NumpyCall(f)
    out = call(X, P)  # a column fills every mapped column, as a DM call does
    ref = [np.asarray(r) for r in f(X, P)]
    for a, b in zip(out, ref):
        assert a.shape == b.shape and a.flags.c_contiguous
        np.testing.assert_array_equal(a, b)
    again = call(2 * X, P)
    np.testing.assert_array_equal(out[0], ref[0])  # an earlier result is not overwritten
    assert not np.array_equal(again[0], out[0])
    with pytest.raises(ValueError, match=r"input 0 has shape \(3, 7\), expected \(3, 8\)"):
        call(X[:, :7], P)
    with pytest.raises(TypeError, match="takes 2 inputs, got 1"):
        call(X)


def test_vector_call_gives_the_dm_call_numbers_and_refuses_what_it_cannot_hold():
    import casadi as ca
    import pytest

    from sim.compiled import VectorCall

    x, u, p = ca.SX.sym("x", 3), ca.SX.sym("u"), ca.SX.sym("p", 2)
    f = ca.Function("f", [x, u, p], [ca.sin(x) * p[0] + u * p[1]])
    call = VectorCall(f)
    xs, P = np.array([0.1, -2.0, 3.0]), np.array([1.5, -0.25])
    out = call(xs, 0.7, P)
    np.testing.assert_array_equal(out, np.asarray(f(xs, 0.7, P)).ravel())
    again = call(2 * xs, 0.7, P)
    assert not np.array_equal(again, out)  # a fresh array each time: an earlier result stays
    np.testing.assert_array_equal(out, np.asarray(f(xs, 0.7, P)).ravel())
    with pytest.raises(TypeError, match="takes 3 inputs, got 2"):
        call(xs, 0.7)
    with pytest.raises(ValueError, match="one dense output"):
        VectorCall(ca.Function("g", [x], [x, 2 * x]))
    diag = ca.SX.sym("s", ca.Sparsity.diag(2))
    with pytest.raises(ValueError, match="dense inputs"):
        VectorCall(ca.Function("h", [diag], [ca.sum1(ca.sum2(diag))]))


def test_plant_columns_give_the_symbolic_map_numbers_over_any_number_of_columns(cyl_a):
    import pytest

    from sim.compiled import COLUMN_CHUNK, plant_columns
    from sim.plant import build_plant

    plant = build_plant("pressure")
    p = np.array(plant.parameter_vector(cyl_a))
    rng = np.random.default_rng(1)
    for n in (1, COLUMN_CHUNK, 2 * COLUMN_CHUNK + 7):  # one, a whole chunk, a padded last chunk
        X = np.vstack([rng.uniform(0, 0.1, n), rng.normal(0, 0.2, n)])
        U = rng.uniform(1e5, 6e5, (2, n))
        # to rounding: the compiled code may reorder sums (sim.compiled.FAST_MATH_FLAGS)
        np.testing.assert_allclose(plant_columns(plant)(X, U, p), np.asarray(plant.rhs.map(n)(X, U, p)),
                                   rtol=1e-12, atol=0)
    with pytest.raises(ValueError, match=r"columns of unequal length: \[3, 2\]"):
        plant_columns(plant)(np.zeros((2, 3)), np.zeros((2, 2)), p)


def test_the_valve_law_over_columns_gives_the_symbolic_numbers(cyl_a):
    """calibrate's unit flows (two column inputs, two shared ones) through the compiled map,
    against the law of sim.flow evaluated symbolically, in both directions and past choking."""
    import casadi as ca

    from combined_reality.calibrate.prefit import unit_flows
    from sim.flow import mass_flow

    rng = np.random.default_rng(2)
    n = 3000
    p_from, p_to = rng.uniform(1e5, 7e5, n), rng.uniform(1e5, 7e5, n)
    got = unit_flows(cyl_a, p_from, p_to, 0.3)
    a, b = ca.SX.sym("a"), ca.SX.sym("b")
    law = ca.Function("law", [a, b], [mass_flow(1.0, a, b, 0.3, cyl_a.supply.temperature)]).map(n)
    np.testing.assert_allclose(got, np.asarray(law(p_from[None], p_to[None])).ravel(), rtol=1e-12, atol=0)
    assert (got > 0).any() and (got < 0).any()


def test_processes_that_start_cold_together_build_once(tmp_path, monkeypatch):
    """The workers of a batch start at once on an empty cache: one builds and compiles, the
    others wait for it and load its library (each compiling it too cost the suite minutes)."""
    import threading
    import time

    import casadi as ca

    from sim.compiled import load_or_build

    monkeypatch.setenv("COMBINED_REALITY_CACHE", str(tmp_path))
    monkeypatch.setenv("CC", "none")  # the serialised form: the test is about who builds, not about gcc
    builds, said, got = [], [], []

    def build():
        builds.append(threading.get_ident())
        time.sleep(0.5)  # long enough for the other one to arrive while this one builds
        x = ca.SX.sym("x")
        return [ca.Function("twice", [x], [2 * x])]

    def worker():
        fns, stats = load_or_build(("lock test",), build, ["twice"], progress=said.append)
        got.append((float(fns["twice"](3.0)), stats.cache_hit))

    threads = [threading.Thread(target=worker) for _ in range(2)]
    for th in threads:
        th.start()
        time.sleep(0.1)
    for th in threads:
        th.join(timeout=30)
    assert len(builds) == 1
    assert sorted(got) == [(6.0, False), (6.0, True)]
    assert any("another process is building" in s for s in said)


def test_a_compiler_that_refuses_the_host_flags_builds_the_portable_library(tmp_path, monkeypatch):
    """-march=native is asked for where the compiler has it; one that refuses it (another
    compiler, another architecture) still compiles, without it, and the code is not marked
    as failed."""
    import casadi as ca

    import sim.compiled as compiled

    monkeypatch.setenv("COMBINED_REALITY_CACHE", str(tmp_path))
    monkeypatch.setattr(compiled, "HOST_FLAGS", ("-mno-such-target-flag",))
    x = ca.SX.sym("x")
    fns, stats = compiled.load_or_build(("host-flags-test",), lambda: [ca.Function("twice_plus", [x], [2 * x + 1])],
                                        ["twice_plus"])
    assert stats.path.endswith(".so") and not list(tmp_path.glob("*.compile_failed"))
    assert float(fns["twice_plus"](3.0)) == 7.0
    # the host's identity is part of the key: a library built for one CPU is not another's
    monkeypatch.setattr(compiled, "host_cpu", lambda: "another cpu")
    _, other = compiled.load_or_build(("host-flags-test",), lambda: [ca.Function("twice_plus", [x], [2 * x + 1])],
                                      ["twice_plus"])
    assert not other.cache_hit and other.path != stats.path
