"""The one rig interface: anything that accepts a valve command and yields timestamped samples.

Serial, CAN, the virtual rig and file replay all derive from `Rig`, so the pipeline never
knows which one it has (as python-can's BusABC does for CAN interfaces).

Timing contract (docs/model.md): at each tick t_k the rig samples its sensors and latches the
latest command it has received; the valve holds that command over [t_k, t_k+1) and the
sample reports it as `u_applied`. A recording writes `u = u_applied` on the sample's row,
so the row is complete the moment it arrives. A command sent in reply to sample k is
latched at tick k+1 at the earliest.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from enum import IntFlag

from sim.errors import ToolFailure


class Status(IntFlag):
    """Rig status bits (docs/protocol.md). `Sample.status` carries them without RUNNING
    (every sample is taken while running), so 0 = healthy."""

    RUNNING = 0x01  # streaming samples (wire only)
    WATCHDOG = 0x02  # host silent too long: valve centred until the next command
    CMD_CLIPPED = 0x04  # the latched command was out of range or NaN and was bounded
    SOFT_LIMIT = 0x08  # the latched command drove into an end zone and was set to 0
    SUPPLY_FAULT = 0x10  # supply pressure missing or low
    OVERRUN = 0x20  # the rig missed its sampling deadline before this sample
    TX_OVERFLOW = 0x40  # the rig dropped frames before this one: the link was too slow


@dataclass(frozen=True)
class Sample:
    t: float  # s, rig clock
    x: float  # m
    p1: float  # Pa absolute
    p2: float  # Pa absolute
    ps: float | None = None  # Pa absolute, if measured
    u_applied: float = 0.0  # the command latched at this tick, held over [t, t + period)
    status: int = 0  # rig status bits (Status; 0 = healthy)
    seq: int | None = None  # rig sample counter (wire rigs); a gap = lost samples


@dataclass(frozen=True)
class LinkStats:
    """Health of a wire link since it was opened (SerialRig.stats, CanRig.stats)."""

    samples: int = 0  # samples delivered by read() or waiting in the queue
    samples_lost: int = 0  # from sequence gaps (sent by the rig, never received intact)
    frames_corrupt: int = 0  # frames rejected (bad framing, CRC, length, type)
    bytes_discarded: int = 0  # bytes thrown away while resynchronising
    reconnects: int = 0  # times the link came back after being lost
    rig_errors: int = 0  # error frames received from the rig
    commands_sent: int = 0
    commands_late: int = 0  # replies that missed the rig's next sampling instant
    host_overflow: int = 0  # samples dropped because read() was not called for too long


class RigError(ToolFailure, RuntimeError):
    """The rig cannot be used (port missing, bad answer); the message is one sentence (exit
    status 1)."""


class LinkLost(RigError):
    """The link to the rig is gone and did not come back."""


class Rig(ABC):
    """The base every rig derives from (as python-can's BusABC is for CAN interfaces): a
    backend implements the four abstract methods; the optional parts have defaults that
    fit a rig without a link (nothing queued, no link counters, no threads of its own)."""

    @abstractmethod
    def start(self) -> None:
        """Start sampling: read() then yields samples."""

    @abstractmethod
    def read(self, timeout: float | None = None) -> Sample | None:
        """The next sample, or None when none came within `timeout` seconds."""

    @abstractmethod
    def send(self, u: float) -> None:
        """Command the valve; the rig latches it at its next tick."""

    @abstractmethod
    def stop(self) -> None:
        """Centre the valve and release the rig."""

    def drain(self) -> list[Sample]:
        """The samples received but not read yet, in order, leaving none behind (after stop():
        all the rig took in before it closed). A rig that queues nothing has none."""
        return []

    @property
    def stats(self) -> LinkStats | None:
        """The link's health since it was opened; None for a rig without a link."""
        return None

    def realtime(self, priority: int) -> str | None:
        """Run the rig's own threads (a link's reader) under SCHED_FIFO at `priority` (hw.realtime):
        None when granted or the rig has no threads, else why not (one phrase)."""
        return None


def bounded(u: float) -> float:
    """A command the valve can take: finite and within +-1 (NaN centres the valve)."""
    if u != u:  # NaN
        return 0.0
    return max(-1.0, min(1.0, float(u)))
