"""The one rig interface: anything that accepts a valve command and yields timestamped samples.

Serial, CAN, the virtual rig and file replay all satisfy it, so the pipeline never
knows which one it has (as python-can's Bus does for CAN interfaces).

Timing contract (MODEL.md): `read()` returns the sample taken at t_k; the command sent
after it is held over [t_k, t_k+1) and is recorded with sample k.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable


@dataclass(frozen=True)
class Sample:
    t: float  # s, rig clock
    x: float  # m
    p1: float  # Pa absolute
    p2: float  # Pa absolute
    ps: float | None = None  # Pa absolute, if measured
    u_applied: float = 0.0  # the command the rig actually applied over the previous period
    status: int = 0  # rig status bits (0 = healthy)


@runtime_checkable
class Rig(Protocol):
    def start(self) -> None: ...

    def read(self, timeout: float | None = None) -> Sample | None: ...

    def send(self, u: float) -> None: ...

    def stop(self) -> None:
        """Centre the valve and release the rig."""
        ...


def bounded(u: float, limit: float = 1.0) -> float:
    """A command the valve can take: finite and within +-limit (NaN centres the valve)."""
    if u != u:  # NaN
        return 0.0
    return max(-limit, min(limit, float(u)))
