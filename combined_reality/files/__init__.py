"""What the tool reads and writes: run files (the run CSV), what a run alone shows to be in
the wrong unit (plausibility), their checks against a cylinder file, and atomic writing of
every output.

Cylinder files themselves are parsed where their parameters live (sim.cylinder)."""
from .atomic import atomic_write, clean_json, write_json_atomic, write_text_atomic
from .checks import check_run_against_cylinder, check_train_and_valid, run_name
from .plausibility import first_implausible, time_unit_problem
from .runs import (MEASURED_CHANNELS, REQUIRED_COLUMNS, Run, RunFormatError, RunRecorder, cylinder_identity,
                   cylinder_tag, read_run, recorded_cylinder, recorded_elsewhere, recorded_file, recorded_geometry,
                   split_at_gaps, write_run)

__all__ = ["atomic_write", "clean_json", "write_json_atomic", "write_text_atomic", "check_run_against_cylinder",
           "check_train_and_valid", "run_name", "first_implausible", "time_unit_problem", "MEASURED_CHANNELS",
           "REQUIRED_COLUMNS", "Run", "RunFormatError", "RunRecorder", "cylinder_identity", "cylinder_tag", "read_run",
           "recorded_cylinder", "recorded_elsewhere", "recorded_file", "recorded_geometry", "split_at_gaps",
           "write_run"]
