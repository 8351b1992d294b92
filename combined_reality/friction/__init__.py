"""Friction beyond the nominal law: static friction-velocity maps from points tables or runs
(map; what it offers as plain data: specs), the seed papers' breakaway and constant-speed
test procedures on a rig (procedures), and the friction-model family identified dynamically
on runs and compared on a validation run (dynamic). Names are imported from their modules on
first use (lazy_loader), so that the command line's help can read the specs alone."""
import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach(__name__, submod_attrs={
    "dynamic": ["ModelComparison", "check_model", "compare_friction_models", "identify_friction_model",
                "identify_model", "model_parameters"],
    "specs": ["DYNAMIC_SPECS", "FIT_SPECS", "FitSpec", "FrictionMapError", "PointsFormatError", "SegmentOptions", "TooFewPointsError"],
    "map": ["FrictionMap", "MapPoint", "build_map", "fit_model", "is_points_table", "plot_map", "points_from_run",
            "read_points"],
    "procedures": ["BreakawayOptions", "ProcedureError", "SafetyOptions", "SweepOptions", "breakaway_test",
                   "speed_sweep", "steady_speed", "target_speeds", "write_points"],
})
