"""Calibration: estimate what the cylinder file only guesses (the valve's flow characteristic,
the critical ratio, dead volumes, moving mass, pressure sensor offsets, a constant external
force) together with the friction, staged the way the physics separates them."""
from .identifiability import Identifiability, assess, flow_coverage
from .prefit import chamber_prefit, force_balance_prefit, settled_offsets
from .stages import (CALIBRATED, MECHANICAL, PNEUMATIC, CalibrateOptions, Calibration, calibrate, smooth_valve_prior,
                     validation_figures, with_model_error)

__all__ = ["Identifiability", "assess", "flow_coverage", "chamber_prefit", "force_balance_prefit", "settled_offsets",
           "CALIBRATED", "MECHANICAL", "PNEUMATIC", "CalibrateOptions", "Calibration", "calibrate",
           "smooth_valve_prior", "validation_figures", "with_model_error"]
