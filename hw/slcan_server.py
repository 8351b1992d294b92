"""An SLCAN (Lawicel ASCII) CAN adapter on a pseudo-terminal, with the virtual rig on its bus.

Speaks what python-can's `slcan` interface sends and expects (can/interfaces/slcan.py):
commands end with CR; "\\r" answers OK and BEL ("\\a") an error; "C" closes and "O"/"L"
opens the channel, "S0".."S9"/"sXXYY" set the bit rate (only while closed), "V"/"N"/"F"
return version, serial number and status flags, "Z0/Z1" turn timestamps off/on, "M", "m",
"X", "Q", "W" are accepted and ignored (docs/protocol.md lists them); host frames arrive as
"tIIILDD..." (11-bit) or "TIIIIIIIILDD..." (29-bit) and are acknowledged with "z"/"Z" + CR;
bus frames go to the host as "tIIILDD...\\r" while the channel is open.
"""
from __future__ import annotations

import time
from typing import Callable

import can

from .can_mapping import CanCodec
from .protocol import Frame, HostFrame
from .links import PtyLink

OK = b"\r"
BELL = b"\a"
_BITRATES = {"S0": 10_000, "S1": 20_000, "S2": 50_000, "S3": 100_000, "S4": 125_000, "S5": 250_000,
             "S6": 500_000, "S7": 750_000, "S8": 1_000_000, "S9": 83_300}
# bits on the bus per frame: 47 of overhead + 8 per data byte, plus ~20 % bit stuffing
_BITS_SAMPLE = 3 * 1.2 * (47 + 64)
_BITS_COMMAND = 1.2 * (47 + 32)


class SlcanPtyLink(PtyLink):
    """The adapter's side of the pty; fault injection drops frames but never corrupts them (RigServer
    refuses `corrupt`): CAN frames carry a hardware CRC, so damaged ones never reach the host."""

    def __init__(self, *args, rate: float, log: Callable[[str], None], **kw):
        super().__init__(*args, **kw)
        self.codec = CanCodec()
        self.rate = rate
        self.log = log
        self.channel_open = False
        self.listen_only = False
        self.timestamps = False
        self._rx = bytearray()
        self._t0 = time.monotonic()

    # ---------------------------------------------------------------- host -> adapter

    def poll(self) -> list[HostFrame]:
        data = self._read()
        if not data:
            return []
        self._rx += data
        frames: list[HostFrame] = []
        replies = bytearray()
        while (i := self._rx.find(b"\r")) >= 0:
            line = bytes(self._rx[:i]).decode("ascii", "replace").strip("\n")
            del self._rx[:i + 1]
            reply, frame = self._command(line)
            replies += reply
            if frame is not None:
                frames.append(frame)
        if len(self._rx) > 64:  # no CR in sight: not a command
            self._rx.clear()
        if replies:  # answers of the adapter itself: not subject to bus faults
            self._pending.append(bytes(replies))
            self._pending_size += len(replies)
            self.flush()
        return frames

    def _command(self, line: str) -> tuple[bytes, HostFrame | None]:
        if not line:
            return OK, None  # python-can sends an empty command after "S8" (no data bit rate)
        c = line[0]
        if c in "tTrR":
            return self._host_frame(line)
        if c == "S" or c == "s":
            if self.channel_open or (c == "S" and line not in _BITRATES):
                return BELL, None
            if c == "S":
                self._check_bitrate(_BITRATES[line])
            return OK, None
        if c in "OL":
            if self.channel_open:
                return BELL, None
            self.channel_open, self.listen_only = True, c == "L"
            return OK, None
        if c == "C":
            self.channel_open = False
            return OK, None
        if c == "V":
            return b"V1013\r", None
        if c == "N":
            return b"NVRIG\r", None
        if c == "F":
            return b"F00\r", None
        if c == "Z":
            self.timestamps = line[1:2] == "1"
            return OK, None
        if c in "MmXQW":
            return OK, None
        return BELL, None

    def _host_frame(self, line: str) -> tuple[bytes, HostFrame | None]:
        extended = line[0] in "TR"
        n = 8 if extended else 3
        ack = b"Z\r" if extended else b"z\r"
        try:
            fid = int(line[1:1 + n], 16)
            dlc = int(line[1 + n])
            data = bytes.fromhex(line[2 + n:2 + n + 2 * dlc]) if line[0] in "tT" else b""
            if dlc > 8 or (line[0] in "tT" and len(data) != dlc):
                return BELL, None
        except (ValueError, IndexError):
            return BELL, None
        if not self.channel_open or self.listen_only:
            return BELL, None
        if line[0] in "rR":
            return ack, None
        msg = can.Message(arbitration_id=fid, is_extended_id=extended, data=data)
        return ack, self.codec.host_frame(msg)

    def _check_bitrate(self, bitrate: int) -> None:
        load = self.rate * (_BITS_SAMPLE + _BITS_COMMAND) / bitrate
        if load > 0.8:
            self.log(f"CAN at {bitrate / 1000:g} kbit/s cannot carry {self.rate:g} samples/s "
                     f"(it would need {100 * load:.0f} % of the bus); the emulation passes them anyway")

    # ---------------------------------------------------------------- adapter -> host

    def _units(self, frame: Frame) -> list[bytes]:
        if not self.channel_open:
            return []  # a closed adapter forwards nothing from the bus
        out = []
        for msg in self.codec.rig_messages(frame):
            line = f"t{msg.arbitration_id:03X}{msg.dlc}{bytes(msg.data).hex().upper()}"
            if self.timestamps:
                line += f"{int((time.monotonic() - self._t0) * 1000) % 60000:04X}"
            out.append((line + "\r").encode("ascii"))
        return out
