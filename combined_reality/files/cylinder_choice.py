"""Which cylinder file applies to runs: the one the user gave, else the one the first run's
header names (where it exists), else the built-in cylinder A; with the sentence that says
which, so that every subcommand and script says it alike."""
from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Sequence

from sim.cylinder import Cylinder, load_cylinder

from .checks import header_cylinder_file, run_name
from .runs import recorded_file

__all__ = ["BUILT_IN", "cylinder_for_runs", "default_config_path"]

BUILT_IN = "no --config: the built-in cylinder A (32 mm x 100 mm) is used"


def default_config_path() -> Path:
    """The built-in cylinder A (32 mm x 100 mm) of the combined-reality paper."""
    return Path(str(resources.files("combined_reality") / "data" / "cyl_a_32x100.toml"))


def cylinder_for_runs(path: str | None, runs: Sequence) -> tuple[Cylinder, str | None]:
    """The cylinder file given (`path`, the command line's --config); else the one the first
    run's header names, where it exists; else the built-in one. With the line that says which
    when no file was given (to print once the input is accepted: a refusal stays the only
    line)."""
    if path:
        return load_cylinder(path), None
    for run in runs:
        named = header_cylinder_file(run)
        if named is not None:
            return load_cylinder(named), f"no --config: the cylinder file {named} that {run_name(run)} names is used"
    missing = next((recorded_file(r) for r in runs if recorded_file(r)), None)
    return load_cylinder(default_config_path()), BUILT_IN + (
        f" (the run's header names {missing}, which is not here)" if missing else
        " (the run's header names no cylinder file)")
