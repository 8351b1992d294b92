"""The built-in experiment programs by name: which closed-loop references each uses (None:
its own class), what each does in a few words, and the revision of its commands. Plain
data, so that the command line can list them without importing the session."""
from __future__ import annotations

__all__ = ["PROGRAMS", "DESCRIPTIONS", "REVISIONS", "program_revision"]

PROGRAMS = {"mixed": ("step", "ramp", "sine"), "steps": ("step",), "ramps": ("ramp",), "sines": ("sine",),
            "pulses": None, "calibration": None}
# what each program does, in a few words (the command line's help lists them all)
DESCRIPTIONS = {
    "mixed": "closed-loop position control along steps, ramps and sines (the default)",
    "steps": "closed-loop position steps", "ramps": "closed-loop constant-speed ramps",
    "sines": "closed-loop sines", "pulses": "open-loop pulses of random height and length",
    "calibration": "what calibrate and diagnose need: creeps through the valve's overlap, slow moves across the "
                   "stroke both ways into the end stops, holds there with the valve open and closed, a closed hold "
                   "at mid-stroke, pulses of growing command, position control",
}
# bumped when a built-in program's commands change: stored runs are keyed by it (benchmarks)
REVISIONS = {"calibration": 2}


def program_revision(name: str) -> int:
    """The revision of a built-in program's commands (1 for those never changed)."""
    return REVISIONS.get(name, 1)
