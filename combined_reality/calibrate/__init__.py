"""Calibration: estimate what the cylinder file only guesses (the valve's flow characteristic,
the critical ratio, dead volumes, moving mass, pressure sensor offsets, a constant external
force) together with the friction, staged the way the physics separates them."""
from .prefit import force_balance_prefit
from .stages import CALIBRATED, MECHANICAL, PNEUMATIC, CalibrateOptions, Calibration, calibrate

__all__ = ["force_balance_prefit", "CALIBRATED", "MECHANICAL", "PNEUMATIC", "CalibrateOptions", "Calibration",
           "calibrate"]
