"""What the tool reads and writes: run files (the run CSV), what a run alone shows to be in
the wrong unit (plausibility), their checks against a cylinder file, output paths checked
before the work (outputs) and atomic writing of every output.

Cylinder files themselves are parsed where their parameters live (sim.cylinder)."""
from .atomic import atomic_write, atomic_writer, clean_json, write_json_atomic, write_text_atomic
from .cylinder_choice import BUILT_IN, cylinder_for_runs, default_config_path
from .checks import (check_distinct_runs, check_run_against_cylinder, check_train_and_valid, run_name,
                     same_data)
from .outputs import OutputError, WriteError, check_outputs, os_error, refuse_special
from .plausibility import first_implausible, measured_value, time_unit_problem
from .runs import (MAX_ROWS, MEASURED_CHANNELS, REQUIRED_COLUMNS, Run, RunFormatError, RunRecorder, cylinder_identity,
                   cylinder_tag, read_run, recorded_cylinder, recorded_elsewhere, recorded_file, recorded_geometry,
                   split_at_gaps, write_run)

__all__ = ["BUILT_IN", "cylinder_for_runs", "default_config_path", "atomic_write", "atomic_writer", "clean_json", "write_json_atomic", "write_text_atomic",
           "check_distinct_runs", "check_run_against_cylinder", "check_train_and_valid", "run_name",
           "same_data", "OutputError", "WriteError", "check_outputs", "os_error", "refuse_special", "first_implausible",
           "measured_value", "time_unit_problem", "MAX_ROWS", "MEASURED_CHANNELS", "REQUIRED_COLUMNS", "Run",
           "RunFormatError", "RunRecorder", "cylinder_identity", "cylinder_tag", "read_run", "recorded_cylinder",
           "recorded_elsewhere", "recorded_file", "recorded_geometry", "split_at_gaps", "write_run"]
