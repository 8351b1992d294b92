"""A rig on a serial port (USB CDC, UART, or the virtual rig's pseudo-terminal), docs/protocol.md.

    rig = SerialRig("/dev/serial/by-id/usb-rig", on_event=print)
    rig.start()
    while ...:
        s = rig.read(timeout=0.1)   # Sample or None
        rig.send(controller(s))
    rig.stop()

When the port errors or vanishes the link is closed and the same path reopened every
100 ms; START is re-sent when it is back. Give the rig a stable path (a udev
/dev/serial/by-id link, or `combined-reality virtual-rig --link PATH`) so that it is found
again when it comes back as another device.
"""
from __future__ import annotations

from typing import Callable

import serial

from .protocol import FrameDecoder, HostFrame, LinkDown, LinkRig, encode
from .rig import RigError


class SerialRig(LinkRig):
    link = "serial"

    def __init__(self, port: str, *, baudrate: int = 2_000_000, on_event: Callable[[str], None] | None = None,
                 reconnect: bool = True, give_up_after: float | None = None, queue_size: int = 100_000):
        self.port = port
        self.baudrate = baudrate
        self._decoder = FrameDecoder()
        self._ser: serial.Serial | None = None
        super().__init__(port, on_event=on_event, reconnect=reconnect, give_up_after=give_up_after,
                         queue_size=queue_size)

    def _open(self) -> None:
        try:
            # a short read timeout keeps the reader thread responsive to stop(); a write
            # timeout keeps a stuck port from blocking the host's control loop
            ser = serial.Serial(self.port, self.baudrate, timeout=0.05, write_timeout=0.2)
            ser.reset_input_buffer()  # whatever piled up while nobody listened is stale
        except (serial.SerialException, OSError, ValueError) as e:
            raise RigError(f"cannot open serial port {self.port}: {e}") from None
        self._decoder.resync()
        self._ser = ser

    def _close(self) -> None:
        ser, self._ser = self._ser, None
        if ser is not None:
            ser.close()

    def _receive(self, timeout: float) -> None:
        # only the reader thread calls this, and only while the port is open
        ser = self._ser
        try:
            data = ser.read(max(1, ser.in_waiting))
        except (serial.SerialException, OSError) as e:
            raise LinkDown(f"{self.port}: {e}") from None
        for frame in self._decoder.feed(data):
            self._deliver(frame)

    def _transmit(self, frame: HostFrame) -> None:
        ser = self._ser
        if ser is None:
            raise LinkDown(f"{self.port}: not open")
        try:
            ser.write(encode(frame))
        except serial.SerialTimeoutException:
            pass  # the rig does not read: this frame is lost, its watchdog takes over
        except (serial.SerialException, OSError) as e:
            raise LinkDown(f"{self.port}: {e}") from None

    def _frame_counts(self) -> tuple[int, int]:
        return self._decoder.frames_corrupt, self._decoder.bytes_discarded
