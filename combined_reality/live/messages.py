"""What a session's helper process (the estimator, the Rerun view) has said: (kind, value)
messages on a multiprocessing queue, taken without waiting."""
from __future__ import annotations

import queue
from typing import Any, Iterator

__all__ = ["pending"]


def pending(outbox) -> Iterator[tuple[str, Any]]:
    """The messages waiting in `outbox`, oldest first, each taken when it is asked for (what the
    caller stops before stays queued); ends when the queue is empty."""
    while True:
        try:
            message = outbox.get_nowait()
        except queue.Empty:
            return
        yield message
