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
