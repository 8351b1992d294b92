"""The protocol's frames on CAN (hw/rig_can.dbc, docs/protocol.md), encoded and decoded by cantools.

A sample does not fit one classic 8-byte CAN frame, so the rig sends three
(RigSampleTime, RigSamplePosition, RigSamplePressure) tied by an 8-bit sequence byte;
`SampleAssembler` puts them back together. Resolution is far below the sensor noise:
x 10 nm/bit (noise ~5 um), pressures 20 Pa/bit (noise ~300 Pa), command 1e-4/bit.
"""
from __future__ import annotations

from importlib import resources
from pathlib import Path

import can
import cantools
from cantools.database.can import Database

from .protocol import Command, ErrorFrame, Frame, Heartbeat, HostFrame, SampleFrame, Start, StatusFrame, Stop

DBC_NAME = "rig_can.dbc"

ID_ERROR = 0x080
ID_COMMAND = 0x100
ID_CONTROL = 0x101
ID_SAMPLE_TIME = 0x180
ID_SAMPLE_POSITION = 0x181
ID_SAMPLE_PRESSURE = 0x182
ID_STATUS = 0x1F0
SAMPLE_IDS = (ID_SAMPLE_TIME, ID_SAMPLE_POSITION, ID_SAMPLE_PRESSURE)
HOST_IDS = (ID_COMMAND, ID_CONTROL)
RIG_IDS = (ID_ERROR, *SAMPLE_IDS, ID_STATUS)

REQUEST_START, REQUEST_STOP, REQUEST_HEARTBEAT = 1, 2, 3


def dbc_path() -> Path:
    return Path(str(resources.files("hw") / DBC_NAME))


def load_dbc() -> Database:
    return cantools.database.load_file(dbc_path())


class CanCodec:
    """Protocol frames <-> python-can Messages, through the DBC (values clamped to the signal ranges)."""

    def __init__(self, db: Database | None = None):
        self.db = db if db is not None else load_dbc()
        self._msg = {m.frame_id: m for m in self.db.messages}
        for fid in (*HOST_IDS, *RIG_IDS):
            if fid not in self._msg:
                raise ValueError(f"{dbc_path()} lacks message 0x{fid:03x}")

    # ---------------------------------------------------------------- encoding

    def _message(self, fid: int, values: dict[str, float]) -> can.Message:
        m = self._msg[fid]
        clamped = {}
        for sig in m.signals:  # saturate instead of wrapping around: an overrange reads as full scale
            v = values[sig.name]
            clamped[sig.name] = min(max(v, sig.minimum), sig.maximum)
        # clamped already: cantools' own range checks (strict) cost 17 of the 41 us that encoding
        # a sample's three messages took in the virtual rig's 1 kHz tick; the bytes are the same
        return can.Message(arbitration_id=fid, is_extended_id=False, data=m.encode(clamped, strict=False))

    def quantise_u(self, u: float) -> float:
        """The command as it arrives after the trip through RigCommand.U."""
        return self._decode(self._message(ID_COMMAND, {"CmdSeq": 0, "U": u}))["U"]

    def host_messages(self, frame: HostFrame) -> list[can.Message]:
        match frame:
            case Command(seq, u):
                return [self._message(ID_COMMAND, {"CmdSeq": seq & 0xFFFF, "U": u})]
            case Start():
                return [self._message(ID_CONTROL, {"Request": REQUEST_START, "Counter": 0})]
            case Stop():
                return [self._message(ID_CONTROL, {"Request": REQUEST_STOP, "Counter": 0})]
            case Heartbeat(seq):
                return [self._message(ID_CONTROL, {"Request": REQUEST_HEARTBEAT, "Counter": seq & 0xFF})]
        raise TypeError(f"not a host frame: {frame!r}")

    def rig_messages(self, frame: Frame) -> list[can.Message]:
        match frame:
            case SampleFrame():
                f, seq = frame, frame.seq & 0xFF
                return [
                    self._message(ID_SAMPLE_TIME, {"Seq": seq, "Status": f.status & 0xFF, "UApplied": f.u_applied,
                                                   "TimeUs": f.t_us & 0xFFFFFFFF}),
                    self._message(ID_SAMPLE_POSITION, {"Seq": seq, "X": f.x, "Ps": 0.0 if f.ps is None else f.ps}),
                    self._message(ID_SAMPLE_PRESSURE, {"Seq": seq, "P1": f.p1, "P2": f.p2,
                                                       "CmdSeq": f.cmd_seq & 0xFFFF}),
                ]
            case ErrorFrame(code, _t, value):
                return [self._message(ID_ERROR, {"Code": code, "Value": value})]
            case StatusFrame(seq, t_us, status):
                return [self._message(ID_STATUS, {"Seq": seq & 0xFF, "Status": status & 0xFF,
                                                  "TimeUs": t_us & 0xFFFFFFFF})]
        raise TypeError(f"not a rig frame: {frame!r}")

    # ---------------------------------------------------------------- decoding

    def _decode(self, msg: can.Message) -> dict:
        return self._msg[msg.arbitration_id].decode(bytes(msg.data), decode_choices=False)

    def host_frame(self, msg: can.Message) -> HostFrame | None:
        """What the rig makes of a frame from the host; None for other traffic or a malformed frame."""
        if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame or msg.arbitration_id not in HOST_IDS:
            return None
        try:
            d = self._decode(msg)
        except Exception:  # wrong length: cantools raises DecodeError
            return None
        if msg.arbitration_id == ID_COMMAND:
            return Command(int(d["CmdSeq"]), float(d["U"]))
        request = int(d["Request"])
        if request == REQUEST_START:
            return Start()
        if request == REQUEST_STOP:
            return Stop()
        if request == REQUEST_HEARTBEAT:
            return Heartbeat(int(d["Counter"]))
        return None


class SampleAssembler:
    """Rig frames in, protocol records out: SampleFrame (seq 8 bit, t_us 32 bit), ErrorFrame, StatusFrame.

    A sample is complete when its three parts with the same Seq are in; a part with another
    Seq while one is pending means the pending sample lost a part (it is dropped and
    counted in `incomplete`; the host also sees it as a sequence gap)."""

    def __init__(self, codec: CanCodec):
        self.codec = codec
        self.incomplete = 0
        self.malformed = 0  # rig identifiers with the wrong length
        self._seq: int | None = None
        self._parts: dict[int, dict] = {}

    def reset(self) -> None:
        """Forget a partly received sample (the bus was reopened)."""
        self._seq = None
        self._parts = {}

    def feed(self, msg: can.Message) -> list[Frame]:
        fid = msg.arbitration_id
        if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame or fid not in RIG_IDS:
            return []  # other traffic on the bus
        try:
            d = self.codec._decode(msg)
        except Exception:
            self.malformed += 1
            return []
        if fid == ID_ERROR:
            return [ErrorFrame(int(d["Code"]), 0, int(d["Value"]))]
        if fid == ID_STATUS:
            return [StatusFrame(int(d["Seq"]), int(d["TimeUs"]), int(d["Status"]))]
        seq = int(d["Seq"])
        if self._seq is not None and seq != self._seq:
            self.incomplete += 1
            self._parts.clear()
        self._seq = seq
        self._parts[fid] = d
        if len(self._parts) < len(SAMPLE_IDS):
            return []
        t, pos, prs = (self._parts[i] for i in SAMPLE_IDS)
        self._seq = None
        self._parts = {}
        ps = float(pos["Ps"])
        return [SampleFrame(seq=seq, t_us=int(t["TimeUs"]), x=float(pos["X"]), p1=float(prs["P1"]),
                            p2=float(prs["P2"]), ps=ps if ps > 0 else None, u_applied=float(t["UApplied"]),
                            status=int(t["Status"]), cmd_seq=int(prs["CmdSeq"]))]
