"""The model beside the rig: experiment programs, running them on any rig, the live
session (recording, lock-step simulation, online estimation, sinks), its console and its
Rerun view. Names are imported from their modules on first use (lazy_loader), so that the
command line's help can read the program catalogue without loading the numerics."""
import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach(__name__, submod_attrs={
    "assembly": ["SessionParts", "assemble_session"],
    "catalogue": ["DESCRIPTIONS", "PROGRAMS", "program_revision"],
    "console": ["Console"],
    "ending": ["RUN_SIGMA_S", "SessionEnd", "conclude_session", "final_run_sigma", "session_verdict"],
    "experiment": ["run_program"],
    "monitor": ["WHAT_TO_DO", "MonitorOptions", "RunSigma", "SessionMonitor", "change_message", "drift_message"],
    "programs": ["PositionProgram", "ProgramOptions", "guarded", "make_program"],
    "session": ["ESTIMATOR_NICE_AHEAD", "ESTIMATOR_NICE_BEHIND", "ConsoleSink", "Estimator", "InlineEstimator",
                "LockstepSimulator", "PacedRig", "PipelinedEstimator", "ProcessEstimator", "ReplayRig",
                "SessionResult", "Sink", "run_session", "set_estimator_priority"],
})
