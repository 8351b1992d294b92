"""The tool's own errors: what went wrong is either the request (a bad file, option or path:
exit status 2) or the tool and its surroundings (a full disk, a failed write: exit status 1).
Each message is one sentence that names what failed and why.

The base classes live in sim.errors (the lowest layer, so that sim's and hw's errors derive
from them too) and are the same classes under these names here; every error class of the tool
derives from InputError or ToolFailure, and the command line maps them to their exit status in
one place."""
from __future__ import annotations

from sim.errors import CombinedRealityError, InputError, ToolFailure
from sim.inputs import QUOTE_LIMIT, shorten

__all__ = ["CombinedRealityError", "InputError", "ToolFailure", "QUOTE_LIMIT", "shorten"]
