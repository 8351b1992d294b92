"""Friction beyond the nominal law: static friction-velocity maps (their points from runs:
points; points tables: tables; the models fitted to the points: fits; the map: map; the map of runs and tables as friction-map makes it: inputs; its plot:
plot; what the map offers as plain data: specs), the seed papers' breakaway and constant-speed
test procedures on a rig (procedures), and the friction-model family identified dynamically
on runs and compared on a validation run (dynamic). Names are imported from their modules on
first use (lazy_loader), so that the command line's help can read the specs alone."""
import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach(__name__, submod_attrs={
    "dynamic": ["ModelComparison", "check_model", "compare_friction_models", "identify_friction_model",
                "identify_model", "model_parameters"],
    "specs": ["DYNAMIC_SPECS", "FIT_SPECS", "FitSpec", "FrictionMapError", "PointsFormatError", "SegmentOptions", "TooFewPointsError"],
    "points": ["MapPoint", "points_from_run"],
    "tables": ["is_points_table", "read_points"],
    "fits": ["fit_model"],
    "map": ["FrictionMap", "build_map"],
    "inputs": ["MapInputs", "gather_map_inputs", "map_of_inputs"],
    "plot": ["plot_map"],
    "procedures": ["BreakawayOptions", "ProcedureError", "SafetyOptions", "SweepOptions", "breakaway_test",
                   "speed_sweep", "steady_speed", "target_speeds", "write_points"],
})
