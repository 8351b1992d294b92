"""Identification: parameters of the one plant from recorded runs.

- offline: multiple-shooting least squares over whole runs (`identify`)
- online: the same problem over a moving horizon of a live stream (`MovingHorizonEstimator`)
- validation: scoring a model on a run it was not fitted to (`validate`)
- regimes: the operating regimes of a run, the share of a validation's error in each (`regions`),
  and those where it gathers that the fitting runs held too little of (`untaught_regions`)
- newton: friction from Newton's law with the measured pressures (the identifier's start), and
  the column-scaled least squares of such equation-error fits (`scaled_lstsq`)
- preflight: whether runs can belong to the cylinder file and determine the chosen parameters at all
- determined: whether a fit's estimate is one (`too_uncertain`: its standard deviation below a
  share of its value or of its effect's yardstick)
- drives: which drive may estimate which parameter
- shooting, smoothing: the shared machinery (intervals, Gauss-Newton, covariance; derivatives)
- gauss_newton: one Gauss-Newton iteration (damped step, line search) for offline and online
  alike, and `Exit`: every way a fit stops, named, with the status it reports
"""
from .determined import not_determined, too_uncertain
from .drives import DriveError, check_drive
from .newton import equation_error_friction, friction_from_newton, scaled_lstsq
from .offline import MISMATCH, Estimate, IdentifyOptions, IdentifyResult, identify, lower_cost
from .online import MovingHorizonEstimator, OnlineEstimate, OnlineOptions
from .regimes import (FAILS_CONCENTRATION, MIN_REGION_FRACTION, TRUSTED_VALID, misses_valid, operating_regions,
                      regions, untaught_regions)
from .preflight import Preflight, check_determinable, motion_summary, preflight
from .shooting import UNITS, IdentificationError, PriorRow, at_bounds, sensor_noise
from .smoothing import derivative_kernels, savgol_kernels, velocity_estimate
from .validation import Validation, validate, validation_gain, validation_segments

__all__ = ["equation_error_friction", "friction_from_newton", "MISMATCH", "Estimate", "IdentifyOptions",
           "IdentifyResult", "identify", "lower_cost", "not_determined", "DriveError", "check_drive", "check_determinable",
           "motion_summary", "Preflight",
           "preflight", "MovingHorizonEstimator", "OnlineEstimate", "OnlineOptions", "UNITS", "IdentificationError",
           "PriorRow",
           "at_bounds", "sensor_noise", "derivative_kernels", "savgol_kernels", "velocity_estimate", "Validation",
           "validate", "validation_gain", "validation_segments", "scaled_lstsq", "too_uncertain", "FAILS_CONCENTRATION",
           "MIN_REGION_FRACTION", "TRUSTED_VALID", "misses_valid", "operating_regions", "regions", "untaught_regions"]
