"""The tool's error tree, at the bottom so that every layer (sim, hw, the application) derives
its errors from it. What went wrong is either the request (a bad file, option or path:
InputError, exit status 2) or the tool and its surroundings (a rig that fails, a fit that
cannot be carried out, a full disk: ToolFailure, exit status 1). Each message is one
sentence that names what failed and why; the command line prints it and exits with
`exit_status`, in one place (combined_reality.cli.main)."""
from __future__ import annotations

__all__ = ["CombinedRealityError", "InputError", "ToolFailure"]


class CombinedRealityError(Exception):
    """An error the tool reports in one sentence; `exit_status` says whose fault it is."""

    exit_status = 1


class InputError(CombinedRealityError, ValueError):
    """A bad request: a file, an option or a path the tool cannot use (exit status 2)."""

    exit_status = 2


class ToolFailure(CombinedRealityError):
    """A failure of the tool or its surroundings on a valid request (exit status 1)."""

    exit_status = 1
