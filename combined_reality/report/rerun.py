"""Where Rerun data go: a spawned viewer, a viewer at an address, or a .rrd file. Live
sessions and the diagnosis log through the same recording stream."""
from __future__ import annotations

import rerun as rr

__all__ = ["APP_ID", "open_recording"]

APP_ID = "combined_reality"


def open_recording(mode: str, target: str | None = None) -> rr.RecordingStream | None:
    """`spawn` a viewer, `connect` to one at ADDR (rerun+http://host:port/proxy), `save` to a
    .rrd file, or `off`."""
    if mode == "off":
        return None
    rec = rr.RecordingStream(APP_ID)
    if mode == "spawn":
        rec.spawn()
    elif mode == "connect":
        rec.connect_grpc(target) if target else rec.connect_grpc()
    elif mode == "save":
        if not target:
            raise ValueError("--rerun save needs a file name")
        rec.save(target)
    else:
        raise ValueError(f"unknown Rerun mode '{mode}' (spawn, connect ADDR, save FILE, off)")
    return rec
