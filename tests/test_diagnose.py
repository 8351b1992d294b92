"""Diagnosis (first version): a withheld effect is named, a clean rig gets `none`."""
import json

import pytest

from combined_reality.cli import main, simulate_run
from combined_reality.runs import write_run
from sim.effects import parse_effect_spec

pytestmark = pytest.mark.slow
CANDIDATES = "stiction,valve_delay,leakage"


@pytest.mark.parametrize("spec, verdict", [("leakage:conductance=2e-10", "leakage"), (None, "none")])
def test_diagnose_names_the_withheld_effect_or_none(cyl_a, tmp_path, capsys, spec, verdict):
    effects = [parse_effect_spec(spec)] if spec else []
    for seed, name in ((1, "train.csv"), (2, "valid.csv")):
        write_run(tmp_path / name, simulate_run(cyl_a, 20.0, seed=seed, effects=effects))
    out = tmp_path / "d.json"
    assert main(["diagnose", str(tmp_path / "train.csv"), "--validate", str(tmp_path / "valid.csv"),
                 "--config", str(cyl_a.source), "--candidates", CANDIDATES, "--json", str(out), "-q"]) == 0
    d = json.loads(out.read_text())
    assert d["verdict"] == verdict
    assert not [c for c in d["ranking"] if "error" in c]  # every candidate was fitted and scored
    assert {"rmse_x_validation"} <= set(d["baseline"])
    if spec:
        assert d["ranking"][0]["effect"] == verdict
        top = d["ranking"][0]
        assert top["shrink"] > 0.6
        assert top["params"]["conductance"] == pytest.approx(2e-10, rel=0.05)
    else:
        assert max(c["shrink"] for c in d["ranking"]) < 0.1  # nothing explains a gap that is not there
    assert abs(sum(r["share_of_error"] for r in d["regions"] if r["where"].startswith("time:")) - 1) < 1e-9


def test_validation_run_of_another_rate_is_refused(cyl_a, tmp_path, capsys):
    write_run(tmp_path / "a.csv", simulate_run(cyl_a, 2.0, seed=1))
    write_run(tmp_path / "b.csv", simulate_run(cyl_a, 2.0, seed=2, rate=500.0))
    assert main(["diagnose", str(tmp_path / "a.csv"), "--validate", str(tmp_path / "b.csv"),
                 "--config", str(cyl_a.source)]) == 2
    assert "same rig and rate" in capsys.readouterr().err
