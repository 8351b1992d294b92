"""Compiled model functions are cached on disk and shared by structure."""
import os
import subprocess
import sys

from sim.compiled import shooting_functions
from sim.effects import Stiction
from sim.plant import build_plant


def test_second_process_and_second_cylinder_reuse_compiled_code(tmp_path, cyl_a, cyl_50):
    env = dict(os.environ, COMBINED_REALITY_CACHE=str(tmp_path))
    os.environ["COMBINED_REALITY_CACHE"] = str(tmp_path)
    try:
        plant = build_plant("command", [Stiction()])
        first = shooting_functions(plant, 50, (12, 13))
        assert not first.stats.cache_hit
        assert list(tmp_path.glob("cr_*.so")) or list(tmp_path.glob("cr_*.casadi"))
        # same structure, other values (another cylinder, another stiction level): a cache hit
        again = shooting_functions(build_plant("command", [Stiction(Fs_excess=3.0)]), 50, (12, 13))
        assert again.stats.cache_hit
        code = ("from sim.compiled import shooting_functions; from sim.plant import build_plant;"
                "from sim.effects import Stiction;"
                "sf = shooting_functions(build_plant('command', [Stiction()]), 50, (12, 13));"
                "print(sf.stats.cache_hit)")
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
        assert out.stdout.strip() == "True"
        # another structure (other free parameters) is another entry
        other = shooting_functions(plant, 50, (12,))
        assert not other.stats.cache_hit
    finally:
        os.environ.pop("COMBINED_REALITY_CACHE", None)


def test_without_a_compiler_the_serialised_functions_give_the_same_numbers(tmp_path, cyl_a, monkeypatch):
    import numpy as np

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
