"""One error tree (issue 44): every public error class of sim, hw and the application derives
from CombinedRealityError, as bad input (InputError, exit 2) or a failure of the tool
(ToolFailure, exit 1), and the command line says each in one line with that status."""
import importlib
import inspect
import pkgutil
from pathlib import Path

import pytest

from combined_reality.cli import main
from combined_reality.errors import CombinedRealityError, InputError, ToolFailure

ROOT = Path(__file__).resolve().parents[1]

# every public error class -> its exit status (what the command line gave it before the tree)
STATUS = {
    "sim.cylinder.ConfigError": 2,
    "sim.inputs.InputFileError": 2,
    "hw.protocol.FrameError": 1,
    "hw.protocol.LinkDown": 1,
    "hw.rig.RigError": 1,
    "hw.rig.LinkLost": 1,
    "combined_reality.options.OptionError": 2,
    "combined_reality.identify.drives.DriveError": 2,
    "combined_reality.files.outputs.OutputError": 2,
    "combined_reality.files.outputs.WriteError": 1,
    "combined_reality.files.runs.RunFormatError": 2,
    "combined_reality.cli.common.UsageError": 2,
    "combined_reality.friction.specs.FrictionMapError": 2,
    "combined_reality.friction.specs.PointsFormatError": 2,
    "combined_reality.friction.specs.TooFewPointsError": 2,
    "combined_reality.friction.procedures.ProcedureError": 1,
    "combined_reality.importing.units.UnitProblem": 2,
    "combined_reality.importing.mapping.MappingError": 2,
    "combined_reality.batch.manifest.ManifestError": 2,
    "combined_reality.identify.shooting.IdentificationError": 1,
}
# the bases code catches them by (except ValueError / RuntimeError), kept beside the tree
ALSO = {"FrameError": ValueError, "RigError": RuntimeError, "LinkLost": RuntimeError,
        "ProcedureError": RuntimeError, "IdentificationError": RuntimeError}
BASES = {"sim.errors.CombinedRealityError", "sim.errors.InputError", "sim.errors.ToolFailure"}
CONTROL_FLOW = {"combined_reality.live.session.EndOfRun"}  # a replayed run's end, never reported


def _public_exceptions() -> dict[str, type]:
    found = {}
    for pkg in ("sim", "hw", "combined_reality"):
        for info in pkgutil.walk_packages(importlib.import_module(pkg).__path__, pkg + "."):
            if info.name.endswith("__main__"):
                continue
            mod = importlib.import_module(info.name)
            for name, obj in vars(mod).items():
                if (inspect.isclass(obj) and issubclass(obj, BaseException) and obj.__module__ == mod.__name__
                        and not name.startswith("_")):
                    found[f"{mod.__name__}.{name}"] = obj
    return found


ERRORS = _public_exceptions()


def test_every_public_error_class_derives_from_the_tree_with_its_exit_status():
    assert set(ERRORS) - BASES - CONTROL_FLOW == set(STATUS)
    for path, status in STATUS.items():
        cls = ERRORS[path]
        assert issubclass(cls, InputError if status == 2 else ToolFailure), path
        assert cls.exit_status == status, path
        assert issubclass(cls, ALSO.get(cls.__name__, CombinedRealityError)), path
    # the application's names are sim's classes: one tree, whichever layer raises
    assert ERRORS["sim.errors.InputError"] is InputError and issubclass(InputError, ValueError)


@pytest.mark.parametrize("path", sorted(STATUS))
def test_main_says_each_error_in_one_line_with_its_status(path, monkeypatch, capsys):
    from combined_reality.cli import demo

    def fail(args):
        raise ERRORS[path]("what went wrong, in one sentence.")

    monkeypatch.setattr(demo, "run", fail)
    code = main(["demo", "-q"])
    captured = capsys.readouterr()
    assert (code, captured.out, captured.err) == (STATUS[path], "",
                                                  "combined-reality demo: what went wrong, in one sentence.\n")


def test_an_identification_that_cannot_be_carried_out_is_said_by_main(tmp_path, monkeypatch, capsys):
    """identify leaves its IdentificationError to main(): the same line, exit 1."""
    import combined_reality.identify as identify_lib
    from combined_reality.cli import identify as identify_cli
    from combined_reality.identify import IdentificationError

    def fail(*args, **kw):
        raise IdentificationError("the runs have no gap-free stretch of 3 samples or more.")

    monkeypatch.setattr(identify_lib, "identify", fail)
    monkeypatch.setattr(identify_cli, "preflight_runs", lambda *a, **kw: None)
    run = tmp_path / "run.csv"
    run.write_text("t,u,x,p1,p2\n" + "".join(f"{k / 1000:.3f},0.1,{0.05 + k * 1e-4:.4f},4.0e5,3.0e5\n"
                                              for k in range(5)))
    code = main(["identify", "--config", str(ROOT / "configs" / "cyl_a_32x100.toml"), str(run), "-q"])
    captured = capsys.readouterr()
    assert code == 1 and captured.out == ""
    assert captured.err == "combined-reality identify: the runs have no gap-free stretch of 3 samples or more.\n"
