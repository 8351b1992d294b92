"""The model beside the rig: experiment programs, running them on any rig, the live
session (recording, lock-step simulation, online estimation, sinks), its console and its
Rerun view."""
from .console import Console
from .experiment import run_program, simulate_run
from .programs import PROGRAMS, PositionProgram, ProgramOptions, guarded, make_program
from .session import (ConsoleSink, InlineEstimator, LockstepSimulator, PacedRig, ProcessEstimator, ReplayRig,
                      SessionResult, run_session)

__all__ = ["Console", "run_program", "simulate_run", "PROGRAMS", "PositionProgram", "ProgramOptions", "guarded",
           "make_program", "ConsoleSink", "InlineEstimator", "LockstepSimulator", "PacedRig", "ProcessEstimator",
           "ReplayRig", "SessionResult", "run_session"]
