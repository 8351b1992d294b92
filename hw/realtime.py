"""Real-time scheduling for the threads that keep a rig's timing: the virtual rig's loop, a
host's acquisition (its link reader and the loop that answers each sample).

SCHED_FIFO where the OS grants it (root, CAP_SYS_NICE, or an rtprio limit such as
`@realtime - rtprio 20` in /etc/security/limits.conf); the kernel still keeps 5 % of every
second for the rest. Where it is not granted nothing changes, and the caller says so: on a
busy machine such a host answers late more often.
"""
from __future__ import annotations

import os
import threading

from .rig import Rig

__all__ = ["make_realtime", "make_normal", "realtime_available", "take_host_priority", "HOST_PRIORITY"]

# SCHED_FIFO priority of a host loop that answers a rig's samples (a live session's
# acquisition, a friction procedure): below the virtual rig's loop (10) and its reader (9),
# which may run on the same machine
HOST_PRIORITY = 5


def _tid(thread: threading.Thread | None) -> int | None:
    return 0 if thread is None else thread.native_id  # 0: the calling thread


def make_realtime(priority: int, thread: threading.Thread | None = None) -> str | None:
    """Run `thread` (default: the calling one) under SCHED_FIFO at `priority`: None when
    granted, else why not (one phrase)."""
    tid = _tid(thread)
    if tid is None:
        return "the thread has not started"
    try:
        os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
    except AttributeError:
        return "this OS has no SCHED_FIFO"
    except OSError as e:
        return e.strerror or str(e)
    return None


def make_normal(thread: threading.Thread | None = None) -> None:
    """Back to ordinary time sharing (best effort)."""
    tid = _tid(thread)
    if tid is None:
        return
    try:
        os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
    except (AttributeError, OSError):
        pass


def take_host_priority(rig: Rig, priority: int) -> tuple[bool, str | None]:
    """SCHED_FIFO at `priority` for a host loop (the calling thread) and for the rig's own
    threads (its link reader, through `Rig.realtime(priority)`): (whether the
    calling thread got it, so make_normal() gives it back; why not, one phrase, or None)."""
    why = make_realtime(priority)
    taken = why is None
    why = why or rig.realtime(priority)
    return taken, why


def realtime_available() -> bool:
    """Whether this process may use SCHED_FIFO (tried on the calling thread and undone)."""
    try:
        before = os.sched_getscheduler(0), os.sched_getparam(0)
    except (AttributeError, OSError):
        return False
    if make_realtime(1) is not None:
        return False
    try:
        os.sched_setscheduler(0, before[0], before[1])
    except OSError:
        make_normal()
    return True
