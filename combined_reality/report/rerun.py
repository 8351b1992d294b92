"""Where Rerun data go: a spawned viewer, a viewer at an address, or a .rrd file. Live
sessions and the diagnosis log through the same recording stream.

A viewer needs a display: on a machine without one (no DISPLAY or WAYLAND_DISPLAY on Linux),
or when the viewer does not start, `spawn` saves to the fallback .rrd file instead and says
so in one line; open it later with `rerun FILE.rrd`.
"""
from __future__ import annotations

import os
import socket
import sys
import threading
from pathlib import Path
from typing import Callable

import rerun as rr

__all__ = ["APP_ID", "VIEWER_PORT", "open_recording", "display_available", "viewer_listening", "close_recording",
           "fallback_path"]

APP_ID = "combined_reality"
VIEWER_PORT = 9876  # where a spawned viewer listens (rerun's default)
SPAWN_WAIT_S = 15.0  # a viewer that has not started by then is taken as failed


def display_available() -> bool:
    """Whether a viewer window can open: on Linux and the BSDs it needs an X11 or Wayland
    display; elsewhere there is always one."""
    if sys.platform.startswith(("linux", "freebsd", "openbsd", "netbsd")):
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True


def viewer_listening(port: int = VIEWER_PORT, timeout: float = 0.5) -> bool:
    """Whether a viewer accepts connections on localhost:port."""
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=timeout):
            return True
    except OSError:
        return False


def fallback_path(near: str | os.PathLike) -> Path:
    """A .rrd file next to `near` (a recording, a report) that does not exist yet."""
    base = Path(near).with_suffix(".rrd")
    path, k = base, 1
    while path.exists():
        path = base.with_name(f"{base.stem}-{k}.rrd")
        k += 1
    return path


def open_recording(mode: str, target: str | None = None, *, fallback: str | os.PathLike | None = None,
                   say: Callable[[str], None] | None = None) -> rr.RecordingStream | None:
    """`spawn` a viewer, `connect` to one at ADDR (rerun+http://host:port/proxy), `save` to a
    .rrd file, or `off`. A `spawn` that cannot show a viewer saves to `fallback` (and `say`s
    so in one line) or, without a fallback, raises RuntimeError."""
    if mode == "off":
        return None
    rec = rr.RecordingStream(APP_ID)
    if mode == "spawn":
        why = _spawn(rec)
        if why is not None:
            if fallback is None:
                raise RuntimeError(f"cannot spawn a Rerun viewer: {why}")
            rec.save(str(fallback))
            if say:
                say(f"no Rerun viewer ({why}): saving to {fallback} instead (open it with: rerun {fallback})")
    elif mode == "connect":
        rec.connect_grpc(target) if target else rec.connect_grpc()
    elif mode == "save":
        if not target:
            raise ValueError("--rerun save needs a file name")
        rec.save(target)
    else:
        raise ValueError(f"unknown Rerun mode '{mode}' (spawn, connect ADDR, save FILE, off)")
    return rec


def _spawn(rec: rr.RecordingStream) -> str | None:
    """Spawn a viewer (or use the one already listening) and connect; why not, if it fails.
    Waits at most SPAWN_WAIT_S: rerun's own spawn waits in native code for a viewer that
    died, where no signal reaches Python."""
    if not display_available():
        return "no display: neither DISPLAY nor WAYLAND_DISPLAY is set"
    if not viewer_listening():
        failure: list[str] = []

        def spawn() -> None:
            try:
                rr.spawn(port=VIEWER_PORT, connect=False)
            except Exception as e:  # e.g. no viewer executable
                failure.append(str(e).strip().splitlines()[0])

        worker = threading.Thread(target=spawn, name="rerun viewer spawn", daemon=True)
        worker.start()
        worker.join(SPAWN_WAIT_S)
        if failure:
            return failure[0]
        if not viewer_listening():
            return f"the viewer did not start within {SPAWN_WAIT_S:g} s"
    rec.connect_grpc(f"rerun+http://127.0.0.1:{VIEWER_PORT}/proxy")
    return None


def close_recording(rec: rr.RecordingStream, timeout_s: float = 2.0) -> bool:
    """Flush and close; False when the data could not be delivered within `timeout_s` (a
    viewer that went away). A stream that failed stays open: closing it would wait for the
    viewer in native code."""
    try:
        rec.flush(timeout_sec=timeout_s)
    except Exception:
        return False
    rec.disconnect()
    return True
