"""The model beside the rig: experiment programs, running them on any rig, the live
session (recording, lock-step simulation, online estimation, sinks), its console and its
Rerun view."""
from .console import Console
from .experiment import run_program, simulate_run
from .monitor import WHAT_TO_DO, MonitorOptions, SessionMonitor, change_message, drift_message, session_verdict
from .programs import (DESCRIPTIONS, PROGRAMS, PositionProgram, ProgramOptions, guarded, make_program,
                       program_revision)
from .session import (ESTIMATOR_NICE_AHEAD, ESTIMATOR_NICE_BEHIND, ConsoleSink, InlineEstimator, LockstepSimulator,
                      PacedRig, PipelinedEstimator, ProcessEstimator, ReplayRig, SessionResult, run_session, set_estimator_priority)

__all__ = ["Console", "run_program", "simulate_run", "PROGRAMS", "DESCRIPTIONS", "PositionProgram", "ProgramOptions",
           "guarded", "make_program", "program_revision", "ConsoleSink", "InlineEstimator", "LockstepSimulator",
           "PacedRig", "PipelinedEstimator", "ProcessEstimator", "ReplayRig", "SessionResult", "run_session",
           "ESTIMATOR_NICE_AHEAD", "ESTIMATOR_NICE_BEHIND", "set_estimator_priority", "WHAT_TO_DO", "MonitorOptions",
           "SessionMonitor", "change_message", "drift_message", "session_verdict"]
