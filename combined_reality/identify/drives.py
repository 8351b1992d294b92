"""Which drive may estimate which parameter: a drive that takes a signal as measured cannot
estimate what makes that signal (sim.plant.DRIVES)."""
from __future__ import annotations

from typing import Iterable

from sim.cylinder import FLOW_CHARACTERISTIC
from sim.errors import InputError

__all__ = ["DriveError", "MAKE_PRESSURES", "MAKE_MOTION", "NOT_ESTIMABLE", "check_drive"]

# what makes the pressures (the valve and the chambers) and what makes the motion (not the
# calibration's stages, calibrate.PNEUMATIC / MECHANICAL, which also hold the sensors' offsets)
MAKE_PRESSURES = frozenset({"conductance", "critical_ratio", "dead_volume_cap", "dead_volume_rod", *FLOW_CHARACTERISTIC})
MAKE_MOTION = frozenset({"Fc", "Fv", "kp", "mass", "angle", "external_force"})

# per drive: the measured signals it is driven by, and the parameters it therefore cannot estimate
NOT_ESTIMABLE = {"pressure": ("the measured pressures", MAKE_PRESSURES),
                 "chambers": ("the measured motion", MAKE_MOTION)}


class DriveError(InputError):
    """A parameter asked of a drive that takes the signal it makes as measured."""


def check_drive(drive: str, estimate: Iterable[str]) -> None:
    """Refuse (DriveError) the parameters of `estimate` that `drive` cannot estimate."""
    if drive not in NOT_ESTIMABLE:
        return
    given, excluded = NOT_ESTIMABLE[drive]
    bad = [n for n in estimate if n in excluded]
    if bad:
        raise DriveError(f"--drive {drive} uses {given}, so it cannot estimate {', '.join(bad)}.")
