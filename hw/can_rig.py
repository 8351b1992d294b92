"""A rig on a CAN bus through python-can (socketcan, slcan, virtual, ...), docs/protocol.md.

    rig = CanRig("can0")                                     # socketcan
    rig = CanRig("/dev/ttyACM0", interface="slcan")          # a USB SLCAN adapter
    rig = CanRig("test", interface="virtual")                # unit tests

Identifiers and scaling come from hw/rig_can.dbc (hw.can_mapping). Extra keyword
arguments go to `can.Bus` (e.g. `sleep_after_open=0` for an SLCAN adapter that needs no
reset time).
"""
from __future__ import annotations

from typing import Any, Callable

import can
import serial
from can.exceptions import error_check
from can.interfaces.slcan import slcanBus

from .can_mapping import CanCodec, SampleAssembler
from .protocol import HostFrame, LinkDown, LinkRig
from .rig import RigError


class CanRig(LinkRig):
    link = "CAN"
    seq_bits = 8  # RigSample*.Seq
    t_bits = 32  # RigSampleTime.TimeUs
    cmd_seq_mask = 0xFFFF  # RigCommand.CmdSeq
    DRAIN = 64  # messages handled per pass of the reader thread at most

    def __init__(self, channel: str, *, interface: str = "socketcan", bitrate: int = 1_000_000,
                 on_event: Callable[[str], None] | None = None, reconnect: bool = True,
                 give_up_after: float | None = None, queue_size: int = 100_000, **bus_kwargs: Any):
        self.channel = channel
        self.interface = interface
        self.bitrate = bitrate
        self.bus_kwargs = bus_kwargs
        self.codec = CanCodec()
        self._assembler = SampleAssembler(self.codec)
        self._bad_lines = 0  # frames the interface could not parse (garbled SLCAN text)
        self._bus: can.BusABC | None = None
        super().__init__(f"{interface}:{channel}", on_event=on_event, reconnect=reconnect,
                         give_up_after=give_up_after, queue_size=queue_size)

    def _open(self) -> None:
        try:
            if self.interface == "slcan":
                bus = ChunkedSlcanBus(channel=self.channel, bitrate=self.bitrate, **self.bus_kwargs)
            else:
                bus = can.Bus(channel=self.channel, interface=self.interface, bitrate=self.bitrate, **self.bus_kwargs)
        except (can.CanError, OSError, ValueError, ImportError) as e:
            raise RigError(f"cannot open CAN {self.interface} channel {self.channel}: {e}") from None
        self._assembler.reset()
        self._bus = bus

    def _close(self) -> None:
        bus, self._bus = self._bus, None
        if bus is not None:
            bus.shutdown()

    def _receive(self, timeout: float) -> None:
        # only the reader thread calls this, and only while the bus is open
        bus = self._bus
        msg, n = self._recv(bus, timeout), 0
        while msg is not None:
            for frame in self._assembler.feed(msg):
                self._deliver(frame)
            n += 1  # then what is waiting already (a sample is three messages), a bounded number
            msg = self._recv(bus, 0) if n < self.DRAIN else None

    def _recv(self, bus: can.BusABC, timeout: float) -> can.Message | None:
        try:
            return bus.recv(timeout)
        except (ValueError, IndexError):  # a garbled SLCAN line: python-can cannot parse it
            self._bad_lines += 1
            return None
        except (can.CanError, OSError) as e:
            raise LinkDown(f"{self.where}: {e}") from None

    def _transmit(self, frame: HostFrame) -> None:
        bus = self._bus
        if bus is None:
            raise LinkDown(f"{self.where}: not open")
        try:
            for msg in self.codec.host_messages(frame):
                bus.send(msg, timeout=0.2)
        except (can.CanError, OSError):
            # buffer full or the adapter is gone: this frame is lost and the rig's watchdog
            # takes over; a dead link is noticed (and reopened) by the reader thread
            pass

    def _frame_counts(self) -> tuple[int, int]:
        return self._bad_lines + self._assembler.malformed, 0


class ChunkedSlcanBus(slcanBus):
    """python-can's SLCAN bus reading whatever the port holds in one call.

    python-can 4.6.1 reads SLCAN text one byte per system call (python-can#2027): a rig
    streaming at 1 kHz sends three 26-character frames per sample, so the host's reader
    thread made ~80 000 calls a second, took a whole core, answered every command after
    the rig's next tick and starved the estimator (online update p50 140 ms, 57 ms with this
    read, on a 2-core machine).
    This is the read of python-can#2028 (merged after 4.6.1); drop the class once a release
    with it is the lowest python-can allowed."""

    def _read(self, timeout: float | None) -> str | None:
        deadline = serial.Timeout(timeout)
        port, buf = self.serialPortOrig, self._buffer
        with error_check("Could not read from serial device"):
            while True:
                end = _line_end(buf)
                if end < 0:
                    buf.extend(port.read(port.in_waiting or 1))  # blocks up to the port's timeout
                    end = _line_end(buf)
                if end >= 0:
                    line = buf[: end + 1].decode(errors="replace")
                    del buf[: end + 1]
                    return line
                if deadline.expired():
                    return None


def _line_end(buf: bytearray) -> int:
    """Index of the first SLCAN terminator (CR, or BEL for an error) in `buf`, -1 if none."""
    cr = buf.find(b"\r")
    bel = buf.find(b"\a", 0, cr if cr >= 0 else len(buf))  # only before the CR: one line's scan
    return bel if bel >= 0 else cr
