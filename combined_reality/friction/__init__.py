"""Friction beyond the nominal law: static friction-velocity maps from points tables or runs
(map), the seed papers' breakaway and constant-speed test procedures on a rig
(procedures), and the friction-model family identified dynamically on runs and compared
on a validation run (dynamic)."""
from .dynamic import (DYNAMIC_SPECS, ModelComparison, check_model, compare_friction_models, identify_friction_model,
                      identify_model, model_parameters)
from .map import (FIT_SPECS, FitSpec, FrictionMap, FrictionMapError, MapPoint, PointsFormatError, SegmentOptions,
                  TooFewPointsError, build_map, fit_model, is_points_table, plot_map, points_from_run, read_points)
from .procedures import (BreakawayOptions, ProcedureError, SafetyOptions, SweepOptions, breakaway_test, speed_sweep,
                         steady_speed, target_speeds, write_points)

__all__ = ["DYNAMIC_SPECS", "ModelComparison", "check_model", "compare_friction_models", "identify_friction_model",
           "identify_model", "model_parameters", "FIT_SPECS", "FitSpec", "FrictionMap", "FrictionMapError", "MapPoint",
           "PointsFormatError", "SegmentOptions", "TooFewPointsError", "build_map", "fit_model", "is_points_table",
           "plot_map", "points_from_run", "read_points", "BreakawayOptions", "ProcedureError", "SafetyOptions",
           "SweepOptions", "breakaway_test", "speed_sweep", "steady_speed", "target_speeds", "write_points"]
