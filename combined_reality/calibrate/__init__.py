"""Calibration: estimate what the cylinder file only guesses (the valve's flow characteristic,
the critical ratio, dead volumes, moving mass, pressure sensor offsets, a constant external
force) together with the friction, staged the way the physics separates them."""
from .identifiability import Identifiability, assess, flow_coverage, separability
from .prefit import breakaway_forces, chamber_prefit, force_balance_prefit, settled_offsets, stiction_prefit
from .stages import (CALIBRATED, DATA_STARTS, MECHANICAL, OTHER_STARTS_ABOVE, PNEUMATIC, START_S, START_STRETCH_S,
                     CalibrateOptions, Calibration, applies, breakaway_fit, calibrate, effect_names, finish,
                     first_stages, force_balance, force_balance_in_model, from_data, joint_start, misfit_note,
                     model_start, run_stage, smooth_valve_prior, stage_summaries, start_share, validation_figures,
                     valve_and_chambers, whole_model, with_model_error)

__all__ = ["Identifiability", "assess", "flow_coverage", "separability", "breakaway_forces", "chamber_prefit",
           "force_balance_prefit", "settled_offsets", "stiction_prefit", "CALIBRATED", "DATA_STARTS", "MECHANICAL",
           "OTHER_STARTS_ABOVE", "PNEUMATIC", "START_S", "START_STRETCH_S", "CalibrateOptions", "Calibration",
           "applies", "breakaway_fit", "calibrate", "effect_names", "finish", "first_stages", "force_balance",
           "force_balance_in_model", "from_data", "joint_start", "misfit_note", "model_start", "run_stage",
           "smooth_valve_prior", "stage_summaries", "start_share", "validation_figures", "valve_and_chambers",
           "whole_model", "with_model_error"]
