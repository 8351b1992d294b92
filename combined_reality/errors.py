"""The tool's own errors: what went wrong is either the request (a bad file, option or path:
exit status 2) or the tool and its surroundings (a full disk, a failed write: exit status 1).
Each message is one sentence that names what failed and why.

Older errors (RunFormatError, MappingError, ...) keep their own classes; new ones derive from
these two so that the command line maps them to their exit status in one place."""
from __future__ import annotations

from sim.inputs import QUOTE_LIMIT, shorten

__all__ = ["CombinedRealityError", "InputError", "ToolFailure", "QUOTE_LIMIT", "shorten"]


class CombinedRealityError(Exception):
    """An error the tool reports in one sentence; `exit_status` says whose fault it is."""

    exit_status = 1


class InputError(CombinedRealityError, ValueError):
    """A bad request: a file, an option or a path the tool cannot use (exit status 2)."""

    exit_status = 2


class ToolFailure(CombinedRealityError):
    """A failure of the tool or its surroundings on a valid request (exit status 1)."""

    exit_status = 1

