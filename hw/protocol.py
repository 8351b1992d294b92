"""The rig wire protocol (docs/protocol.md): frames, serial framing, and the host's bookkeeping.

Frames are small fixed-layout little-endian records, type byte first. On a serial link each
frame travels as ``0x00 | COBS(payload | CRC-16) | 0x00``; `FrameDecoder` turns any byte
stream back into frames, rejecting and counting what is damaged. On CAN the same records
are mapped onto 8-byte frames by `hw.can_mapping`.

`HostSession` is what a host transport does with the decoded records (sequence and clock
unwrapping, lost-sample counting, one-line fault messages); it does no I/O so it is shared
by `hw.serial_rig.SerialRig` and `hw.can_rig.CanRig` and tested without either.
"""
from __future__ import annotations

import binascii
import logging
import math
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass, replace
from enum import IntEnum
from typing import Callable, Union

from cobs import cobs

from sim.errors import ToolFailure

from .realtime import make_realtime
from .rig import LinkLost, LinkStats, Rig, Sample, Status, bounded

__all__ = [
    "FrameType", "ErrorCode", "Status", "Start", "Stop", "Command", "Heartbeat", "SampleFrame", "ErrorFrame",
    "StatusFrame", "Frame", "HostFrame", "FrameError", "pack", "unpack", "encode", "FrameDecoder", "crc16",
    "describe_error", "EventLimiter", "HostSession", "LinkRig", "LinkDown", "MAX_ENCODED",
]


class FrameType(IntEnum):
    # host -> rig
    START = 0x01
    STOP = 0x02
    COMMAND = 0x03
    HEARTBEAT = 0x04
    # rig -> host
    SAMPLE = 0x81
    ERROR = 0x82
    STATUS = 0x83


class ErrorCode(IntEnum):
    WATCHDOG = 1  # value: ms of host silence that tripped it
    BAD_COMMAND = 2  # value: commands bounded (NaN or out of range) since the last report
    SOFT_LIMIT = 3  # value: position in um where the end zone was entered
    SUPPLY = 4  # value: measured supply pressure in Pa
    OVERRUN = 5  # value: us the rig was late
    TX_OVERFLOW = 6  # value: frames the rig dropped because the link was too slow
    RX_CORRUPT = 7  # value: corrupted host frames the rig rejected
    INTERNAL = 8  # value: 0, or 1-4 the sensor out of its range (x, p1, p2, ps); the rig stopped


_SENSORS = ("x", "p1", "p2", "ps")  # INTERNAL's value 1-4 (the firmware's sensor check)
_ERROR_TEXT: dict[int, Callable[[int], str]] = {
    ErrorCode.WATCHDOG: lambda v: f"watchdog: valve centred after {v} ms of host silence",
    ErrorCode.BAD_COMMAND: lambda v: f"{v} invalid command(s) (NaN or beyond +-1) bounded",
    ErrorCode.SOFT_LIMIT: lambda v: f"soft stroke limit: command into the end zone clipped at x = {v / 1000:.1f} mm",
    ErrorCode.SUPPLY: lambda v: f"supply pressure fault: {v / 1e5:.2f} bar absolute",
    ErrorCode.OVERRUN: lambda v: f"sampling deadline missed by {v} us",
    ErrorCode.TX_OVERFLOW: lambda v: f"link too slow: {v} frame(s) dropped by the rig",
    ErrorCode.RX_CORRUPT: lambda v: f"{v} corrupted host frame(s) rejected by the rig",
    ErrorCode.INTERNAL: lambda v: "internal fault: the rig stopped" + (
        f" (sensor {_SENSORS[v - 1]} reads outside its range: a broken wire?)" if 1 <= v <= len(_SENSORS) else ""),
}


def describe_error(code: int, value: int) -> str:
    """One line for an error frame, e.g. 'watchdog: valve centred after 50 ms of host silence'."""
    text = _ERROR_TEXT.get(code)
    return text(value) if text else f"unknown error code {code} (value {value})"


# ------------------------------------------------------------------ frames


@dataclass(frozen=True)
class Start:
    """Host asks the rig to stream samples (also re-sent after a reconnect)."""


@dataclass(frozen=True)
class Stop:
    """Host asks the rig to centre the valve and stop streaming."""


@dataclass(frozen=True)
class Command:
    seq: int  # host command counter (u32 wire, u16 on CAN); echoed as SampleFrame.cmd_seq
    u: float  # valve command, float32 on the wire; the rig bounds it again


@dataclass(frozen=True)
class Heartbeat:
    seq: int  # host counter; keeps the rig's watchdog quiet without changing the command


@dataclass(frozen=True)
class SampleFrame:
    seq: int  # rig tick counter (u32); counts every tick, sent or not
    t_us: int  # rig clock at the tick, us (u64)
    x: float  # m
    p1: float  # Pa absolute
    p2: float  # Pa absolute
    ps: float | None  # Pa absolute; None (NaN on the wire) when not measured
    u_applied: float  # the command latched at this tick, held until the next one
    status: int  # Status bits, RUNNING included
    cmd_seq: int  # seq of the host Command latched at this tick


@dataclass(frozen=True)
class ErrorFrame:
    code: int  # ErrorCode
    t_us: int
    value: int  # code-dependent detail (i32)


@dataclass(frozen=True)
class StatusFrame:
    """Sent by an idle (not streaming) rig every 100 ms: the link is alive."""

    seq: int
    t_us: int
    status: int


HostFrame = Union[Start, Stop, Command, Heartbeat]
Frame = Union[Start, Stop, Command, Heartbeat, SampleFrame, ErrorFrame, StatusFrame]

# layouts after the type byte (little-endian, no padding)
_LAYOUT: dict[FrameType, struct.Struct] = {
    FrameType.START: struct.Struct("<B"),
    FrameType.STOP: struct.Struct("<B"),
    FrameType.COMMAND: struct.Struct("<BIf"),
    FrameType.HEARTBEAT: struct.Struct("<BI"),
    FrameType.SAMPLE: struct.Struct("<BIQfffffHI"),
    FrameType.ERROR: struct.Struct("<BBQi"),
    FrameType.STATUS: struct.Struct("<BIQH"),
}
_BY_LEN = {(int(t), s.size) for t, s in _LAYOUT.items()}
_CRC = struct.Struct("<H")
MAX_PAYLOAD = max(s.size for s in _LAYOUT.values()) + _CRC.size
MAX_ENCODED = cobs.max_encoded_length(MAX_PAYLOAD)


class FrameError(ToolFailure, ValueError):
    """A payload that is not a valid frame (bad CRC, length, type or field): the link's fault, not
    the request's (exit status 1)."""


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE: polynomial 0x1021, initial value 0xFFFF, no reflection."""
    return binascii.crc_hqx(data, 0xFFFF)


def pack(frame: Frame) -> bytes:
    """The frame's payload (type byte first, no CRC)."""
    match frame:
        case Start():
            return _LAYOUT[FrameType.START].pack(FrameType.START)
        case Stop():
            return _LAYOUT[FrameType.STOP].pack(FrameType.STOP)
        case Command(seq, u):
            return _LAYOUT[FrameType.COMMAND].pack(FrameType.COMMAND, seq & 0xFFFFFFFF, u)
        case Heartbeat(seq):
            return _LAYOUT[FrameType.HEARTBEAT].pack(FrameType.HEARTBEAT, seq & 0xFFFFFFFF)
        case SampleFrame():
            f = frame
            ps = math.nan if f.ps is None else f.ps
            return _LAYOUT[FrameType.SAMPLE].pack(FrameType.SAMPLE, f.seq & 0xFFFFFFFF, f.t_us, f.x, f.p1, f.p2, ps,
                                                  f.u_applied, f.status, f.cmd_seq & 0xFFFFFFFF)
        case ErrorFrame(code, t_us, value):
            return _LAYOUT[FrameType.ERROR].pack(FrameType.ERROR, code, t_us, value)
        case StatusFrame(seq, t_us, status):
            return _LAYOUT[FrameType.STATUS].pack(FrameType.STATUS, seq & 0xFFFFFFFF, t_us, status)
    raise TypeError(f"not a protocol frame: {frame!r}")


def unpack(payload: bytes) -> Frame:
    """Inverse of `pack`; raises FrameError for an unknown type or a wrong length."""
    if not payload or (payload[0], len(payload)) not in _BY_LEN:
        kind = f"type 0x{payload[0]:02x}" if payload else "empty payload"
        raise FrameError(f"{kind} with {len(payload)} bytes is not a frame")
    ftype = FrameType(payload[0])
    v = _LAYOUT[ftype].unpack(payload)
    match ftype:
        case FrameType.START:
            return Start()
        case FrameType.STOP:
            return Stop()
        case FrameType.COMMAND:
            return Command(v[1], v[2])
        case FrameType.HEARTBEAT:
            return Heartbeat(v[1])
        case FrameType.SAMPLE:
            ps = None if math.isnan(v[6]) else v[6]
            return SampleFrame(v[1], v[2], v[3], v[4], v[5], ps, v[7], v[8], v[9])
        case FrameType.ERROR:
            return ErrorFrame(v[1], v[2], v[3])
        case FrameType.STATUS:
            return StatusFrame(v[1], v[2], v[3])
    raise FrameError(f"type 0x{payload[0]:02x} is not a frame")  # pragma: no cover


def encode(frame: Frame) -> bytes:
    """Wire bytes of one frame: 0x00, COBS(payload + CRC-16 LE), 0x00.

    The leading delimiter ends whatever garbage came before, so line noise costs at most
    the frame it hits."""
    payload = pack(frame)
    return b"\x00" + cobs.encode(payload + _CRC.pack(crc16(payload))) + b"\x00"


class FrameDecoder:
    """Bytes in, intact frames out. Never raises on bad input: damaged frames are counted.

    Chunks between 0x00 delimiters are COBS-decoded and must carry a matching CRC, a known
    type and that type's exact length. The bytes before the first delimiter are dropped
    unjudged (the stream may have been joined mid-frame)."""

    def __init__(self) -> None:
        self.frames_ok = 0
        self.frames_corrupt = 0
        self.bytes_discarded = 0
        self._buf = bytearray()
        self._synced = False
        self._overlong = False  # inside a chunk already too long to be a frame

    def resync(self) -> None:
        """Forget a partial frame (the link was reopened)."""
        self._buf.clear()
        self._synced = False
        self._overlong = False

    def feed(self, data: bytes) -> list[Frame]:
        out: list[Frame] = []
        buf = self._buf
        buf += data
        start = 0
        while (end := buf.find(0, start)) >= 0:
            self._chunk(bytes(buf[start:end]), out)
            start = end + 1
        del buf[:start]
        if len(buf) > MAX_ENCODED:  # no delimiter in sight: drop, do not buffer without bound
            self.bytes_discarded += len(buf)
            if self._synced and not self._overlong:
                self.frames_corrupt += 1
            self._overlong = True
            buf.clear()
        return out

    def _chunk(self, chunk: bytes, out: list[Frame]) -> None:
        if self._overlong:
            self.bytes_discarded += len(chunk)
            self._overlong = False
            self._synced = True
            return
        if not self._synced:
            self.bytes_discarded += len(chunk)
            self._synced = True
            return
        if not chunk:
            return  # idle fill / the leading delimiter of the next frame
        frame = self._frame(chunk)
        if frame is None:
            self.frames_corrupt += 1
            self.bytes_discarded += len(chunk)
        else:
            self.frames_ok += 1
            out.append(frame)

    @staticmethod
    def _frame(chunk: bytes) -> Frame | None:
        if len(chunk) > MAX_ENCODED:
            return None
        try:
            raw = cobs.decode(chunk)
        except cobs.DecodeError:
            return None
        if len(raw) < 3 or _CRC.unpack_from(raw, len(raw) - 2)[0] != crc16(raw[:-2]):
            return None
        try:
            return unpack(raw[:-2])
        except FrameError:
            return None


# ------------------------------------------------------------------ host side


class EventLimiter:
    """One-line fault messages, at most one per key per `interval` seconds.

    `count(key, n, template)` sums occurrences and reports them once per interval as
    template.format(n=..., s=plural-s); `say(key, msg)` passes a message unless the same key
    spoke within the interval (what it swallows is mentioned with the next one)."""

    def __init__(self, interval: float = 1.0, clock: Callable[[], float] = time.monotonic):
        self.interval = interval
        self.clock = clock
        self._counts: dict[str, list] = {}  # key -> [n, template, window start]
        self._last: dict[str, float] = {}
        self._muted: dict[str, int] = {}
        self.lines: deque[str] = deque(maxlen=1000)

    def count(self, key: str, n: int, template: str) -> None:
        if n <= 0:
            return
        entry = self._counts.get(key)
        if entry is None:
            self._counts[key] = [n, template, self.clock()]
        else:
            entry[0] += n

    def say(self, key: str, msg: str) -> None:
        now = self.clock()
        if now - self._last.get(key, -math.inf) < self.interval:
            self._muted[key] = self._muted.get(key, 0) + 1
            return
        muted = self._muted.pop(key, 0)
        self._last[key] = now
        self.lines.append(msg + (f" ({muted} similar message(s) suppressed)" if muted else ""))

    def flush(self, force: bool = False) -> None:
        """Turn counts whose window has passed into lines."""
        now = self.clock()
        for key in list(self._counts):
            n, template, t0 = self._counts[key]
            if force or now - t0 >= self.interval:
                del self._counts[key]
                self.lines.append(template.format(n=n, s="" if n == 1 else "s"))

    def pop_lines(self) -> list[str]:
        out = list(self.lines)
        self.lines.clear()
        return out


class HostSession:
    """Turns decoded sample records into Samples; counts losses; phrases faults as one line.

    Sequence numbers and rig timestamps may be narrower than Python ints (CAN carries 8-bit
    sequence numbers and 32-bit microseconds): they are unwrapped here, the sequence with
    the help of the timestamps so that a gap of more than 256 samples is still counted
    right. If the rig restarted (its clock jumped back), `t` continues from the last value
    plus the host's wall-clock gap, so it never runs backwards."""

    def __init__(self, link: str, events: EventLimiter, *, seq_bits: int = 32, t_bits: int = 64,
                 clock: Callable[[], float] = time.monotonic):
        self.link = link
        self.events = events
        self.seq_mod = 1 << seq_bits
        self.t_mod = 1 << t_bits
        self.clock = clock
        self.samples = 0
        self.samples_lost = 0
        self.rig_errors = 0
        self.commands_late = 0
        self.period_us: float | None = None  # estimated sampling period
        self._last: tuple[int, int, float] | None = None  # raw seq, raw t, wall clock of the last sample
        self._count_gap = False  # False right after START: the gap to older samples is no loss
        self._seq_full = 0
        self._t_full = 0  # us
        self._pending_reply: tuple[int, int] | None = None  # (sample seq answered, cmd_seq)
        self._outage_since: float | None = None

    def restart(self) -> None:
        """The host sent START: the samples before it are not expected."""
        self._count_gap = False

    def link_lost(self, reason: str, retrying: bool) -> None:
        if self._outage_since is None:
            self._outage_since = self.clock()
        self.events.say("lost", f"{self.link} link lost ({reason})" + ("; retrying" if retrying else ""))

    def link_back(self, streaming: bool) -> None:
        """The port is open again; when streaming, the first sample tells how many were lost."""
        if self._outage_since is not None and not streaming:
            self.events.say("back", f"{self.link} link back after {self.clock() - self._outage_since:.1f} s")
            self._outage_since = None

    @property
    def outage_s(self) -> float | None:
        return None if self._outage_since is None else self.clock() - self._outage_since

    def command_sent(self, cmd_seq: int, reply_to: int | None) -> None:
        """A command answering sample `reply_to` (its seq) left: it is late unless the very next
        sample latched it."""
        if reply_to is None or self._last is None:
            return
        if self._seq_full > reply_to:  # the next sample is already here, so its tick has passed
            self._late()
            self._pending_reply = None
        else:
            self._pending_reply = (reply_to, cmd_seq)

    def sample(self, seq: int, t_us: int, x: float, p1: float, p2: float, ps: float | None, u_applied: float,
               status: int, cmd_seq: int) -> Sample:
        now = self.clock()
        lost, estimated = 0, False
        if self._last is None:
            self._seq_full, self._t_full = seq, t_us
        else:
            seq0, t0, wall0 = self._last
            dt = (t_us - t0) % self.t_mod
            n = (seq - seq0) % self.seq_mod
            p = self.period_us
            if p and self.seq_mod < (1 << 16):  # narrow counter: resolve its wraps with the clock
                n += self.seq_mod * round((dt / p - n) / self.seq_mod)
            # a rig that restarted: its clock jumped back (further than the host waited), or
            # its counter claims more samples than the time between them allows
            if dt > (now - wall0 + 5.0) * 1e6 or (p and n * p > 1.5 * dt + 10 * p):
                dt = max(int((now - wall0) * 1e6), 1)
                n = max(1, round(dt / p)) if p else 1
                estimated = True
            else:
                if n == 1 and dt > 0:
                    self.period_us = dt if p is None else 0.99 * p + 0.01 * dt
                n = max(n, 1)  # a repeated sequence number: keep the sample, count nothing
            self._seq_full += n
            self._t_full += dt
            if self._count_gap:
                lost = n - 1
        self._last = (seq, t_us, now)
        self._count_gap = True
        self.samples += 1
        self.samples_lost += lost
        if self._outage_since is not None:
            self.events.say("back", f"{self.link} link back after {now - self._outage_since:.1f} s; "
                            f"{'about ' if estimated else ''}{lost} samples lost")
            self._outage_since = None
        elif lost:
            self.events.count("gaps", lost, f"{self.link} link: {{n}} sample{{s}} lost (sequence gaps) "
                              "in the last second")
        self._check_reply(cmd_seq)
        return Sample(t=self._t_full * 1e-6, x=x, p1=p1, p2=p2, ps=ps, u_applied=u_applied,
                      status=int(status) & ~int(Status.RUNNING), seq=self._seq_full)

    def error(self, code: int, value: int) -> None:
        self.rig_errors += 1
        self.events.say(f"error{code}", f"rig reports {describe_error(code, value)}")

    def stats(self, **link: int) -> LinkStats:
        return LinkStats(samples=self.samples, samples_lost=self.samples_lost, rig_errors=self.rig_errors,
                         commands_late=self.commands_late, **link)

    def _check_reply(self, cmd_seq: int) -> None:
        if self._pending_reply is not None and self._seq_full > self._pending_reply[0]:
            if cmd_seq != self._pending_reply[1]:
                self._late()
            self._pending_reply = None

    def _late(self) -> None:
        self.commands_late += 1
        self.events.count("late", 1, f"{self.link} link: {{n}} command{{s}} missed the rig's next tick "
                          "in the last second (host too slow)")


class LinkDown(ToolFailure):
    """Raised by a transport hook when the port or bus failed; the message says why."""


class LinkRig(Rig):
    """Base of SerialRig and CanRig: a reader thread drains the link into a queue, read() pops.

    The thread keeps the OS buffer empty while the host computes, and reopens a lost link
    every 100 ms (re-sending START). Fault messages are delivered to `on_event` from
    read() and stop(), in the caller's thread, one line each and rate-limited. Heartbeats
    are never sent automatically: a host whose control loop hangs must let the rig's
    watchdog centre the valve.

    Subclasses set `link`, `seq_bits`, `t_bits`, `cmd_seq_mask` and implement `_open`,
    `_close`, `_receive`, `_transmit` and `_frame_counts`."""

    link = "serial"
    seq_bits = 32
    t_bits = 64
    cmd_seq_mask = 0xFFFFFFFF
    RETRY_S = 0.1  # reopen attempts while the link is down
    START_RETRY_S = 0.5  # re-send START when streaming was asked for but no sample came

    def __init__(self, where: str, *, on_event: Callable[[str], None] | None, reconnect: bool,
                 give_up_after: float | None, queue_size: int):
        self.where = where
        self.on_event = on_event
        self.reconnect = reconnect
        self.give_up_after = give_up_after
        self._events = EventLimiter()
        self._session = HostSession(self.link, self._events, seq_bits=self.seq_bits, t_bits=self.t_bits)
        self._lock = threading.Lock()  # session, queue, events, counters
        self._wlock = threading.Lock()  # one writer at a time (caller and reader thread)
        self._ready = threading.Condition(self._lock)
        self._queue: deque[Sample] = deque()
        self._queue_size = queue_size
        self._host_overflow = 0
        self._stale = 0  # samples thrown away by start(): they came before the START that asked for them
        self._corrupt_reported = 0  # frames_corrupt already counted into the fault messages
        self._reconnects = 0
        self._commands_sent = 0
        self._cmd_seq = 0
        self._hb_seq = 0
        self._last_read_seq: int | None = None  # the sample the next command answers
        self._streaming = False
        self._fatal: LinkLost | None = None
        self._down = False
        self._last_sample = self._last_start = 0.0
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None
        self._launch()

    # ---------------------------------------------------------------- transport hooks

    def _open(self) -> None:
        raise NotImplementedError

    def _close(self) -> None:
        raise NotImplementedError

    def _receive(self, timeout: float) -> None:
        """Wait up to `timeout` for input and hand complete frames to `_deliver`."""
        raise NotImplementedError

    def _transmit(self, frame: HostFrame) -> None:
        raise NotImplementedError

    def _frame_counts(self) -> tuple[int, int]:
        """(frames_corrupt, bytes_discarded) since the rig object was made (never decreasing)."""
        raise NotImplementedError

    # ---------------------------------------------------------------- Rig interface

    def start(self) -> None:
        """Ask the rig to stream samples; a gap to earlier samples is not counted as lost."""
        if self._thread is None:
            self._launch()
        with self._lock:
            self._session.restart()
            self._stale += len(self._queue)  # samples from before START are stale: not counted as received
            self._queue.clear()
            self._streaming = True
            self._last_start = time.monotonic()
        self._send_frame(Start())

    def read(self, timeout: float | None = None) -> Sample | None:
        """The next sample (t in s of the rig clock, seq set), or None after `timeout` seconds.

        Raises LinkLost when the link is gone for good (reconnect=False, or down for longer
        than give_up_after) and every sample received before has been read."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            sample = fatal = None
            with self._ready:
                while not self._queue and self._fatal is None and not self._events.lines:
                    wait = 0.1 if deadline is None else deadline - time.monotonic()
                    if wait <= 0:
                        break
                    self._ready.wait(min(wait, 0.1))  # wakes up for fault messages too
                if self._queue:
                    sample = self._queue.popleft()
                else:
                    fatal = self._fatal
            self._dispatch()
            if sample is not None:
                self._last_read_seq = sample.seq
                return sample
            if fatal is not None:
                raise fatal
            if deadline is not None and time.monotonic() >= deadline:
                return None

    def send(self, u: float) -> None:
        """Send a bounded command (NaN centres the valve); it also tells the rig the host is alive."""
        u = bounded(u)
        with self._lock:
            self._cmd_seq = (self._cmd_seq + 1) & self.cmd_seq_mask or 1
            seq = self._cmd_seq
            self._session.command_sent(seq, self._last_read_seq)
            self._commands_sent += 1
        self._send_frame(Command(seq, u))

    def heartbeat(self) -> None:
        """Keep the rig's watchdog quiet without a new command."""
        with self._lock:
            self._hb_seq = (self._hb_seq + 1) & 0xFFFFFFFF
            seq = self._hb_seq
        self._send_frame(Heartbeat(seq))

    def stop(self) -> None:
        """Centre the valve, stop streaming, close the link (start() opens it again)."""
        if self._thread is None:
            return
        self.send(0.0)
        self._send_frame(Stop())
        with self._lock:
            self._streaming = False
        self._closing.set()
        self._thread.join(timeout=2.0)
        self._thread = None
        self._close_quietly()
        with self._lock:
            self._events.flush(force=True)
        self._dispatch()

    def realtime(self, priority: int) -> str | None:
        """Run the reader thread under SCHED_FIFO at `priority` (hw.realtime): None when granted."""
        return make_realtime(priority, self._thread) if self._thread is not None else "the link is closed"

    def drain(self) -> list[Sample]:
        """The samples received but not read yet, in order (after stop(): all the link took in
        before it closed), leaving none behind."""
        with self._lock:
            out = list(self._queue)
            self._queue.clear()
        self._dispatch()
        if out:
            self._last_read_seq = out[-1].seq
        return out

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def stats(self) -> LinkStats:
        corrupt, discarded = self._frame_counts()
        with self._lock:
            st = self._session.stats(frames_corrupt=corrupt, bytes_discarded=discarded,
                                     reconnects=self._reconnects, commands_sent=self._commands_sent,
                                     host_overflow=self._host_overflow)
            return replace(st, samples=st.samples - self._stale)

    @property
    def sample_period(self) -> float | None:
        """The rig's sampling period as measured from its timestamps, s (None before two samples)."""
        p = self._session.period_us
        return None if p is None else p * 1e-6

    # ---------------------------------------------------------------- internals

    def _launch(self) -> None:
        self._open()  # raises RigError: fail early when the port is wrong
        self._down = False
        self._fatal = None
        self._closing.clear()
        self._thread = threading.Thread(target=self._run, name=f"{self.link} rig reader {self.where}", daemon=True)
        self._thread.start()

    def _send_frame(self, frame: HostFrame) -> bool:
        if self._down or self._thread is None:
            return False  # the reader thread re-sends START when the link is back
        with self._wlock:
            try:
                self._transmit(frame)
                return True
            except LinkDown:
                return False  # the reader thread notices too and handles it

    def _deliver(self, frame: Frame) -> None:
        """Called by the transport in the reader thread for every intact frame."""
        match frame:
            case SampleFrame():
                self._last_sample = time.monotonic()
                f = frame
                with self._ready:
                    s = self._session.sample(f.seq, f.t_us, f.x, f.p1, f.p2, f.ps, f.u_applied, f.status, f.cmd_seq)
                    if len(self._queue) >= self._queue_size:
                        self._queue.popleft()
                        self._host_overflow += 1
                        self._events.count("overflow", 1, f"{self.link} link: {{n}} sample{{s}} dropped, "
                                                          "read() not called for too long")
                    self._queue.append(s)
                    self._ready.notify()
            case ErrorFrame(code, _t, value):
                with self._lock:
                    self._session.error(code, value)
            case _:
                pass  # StatusFrame: the rig is alive; host frames echoed back are ignored

    def _dispatch(self) -> None:
        with self._lock:
            lines = self._events.pop_lines()
        for line in lines:
            if self.on_event is not None:
                self.on_event(line)
            else:
                logging.getLogger(__name__).warning(line)

    def _close_quietly(self) -> None:
        with self._wlock:  # not while the caller's thread writes to it
            try:
                self._close()
            except Exception:  # closing a vanished port may fail; it is gone either way
                pass

    def _run(self) -> None:
        while not self._closing.is_set():
            if self._down:
                self._reopen()
                continue
            try:
                self._receive(0.05)
            except LinkDown as e:
                self._lost(str(e))
                continue
            corrupt = self._frame_counts()[0]
            now = time.monotonic()
            with self._lock:
                if corrupt > self._corrupt_reported:
                    self._events.count("corrupt", corrupt - self._corrupt_reported,
                                       f"{self.link} link: {{n}} corrupted frame{{s}} rejected in the last second")
                    self._corrupt_reported = corrupt
                self._events.flush()
                # an idle rig (lost START, or restarted) keeps sending STATUS frames but no samples
                resend = self._streaming and now - max(self._last_sample, self._last_start) > self.START_RETRY_S
                if resend:
                    self._last_start = now
            if resend:
                self._send_frame(Start())

    def _lost(self, reason: str) -> None:
        self._down = True
        self._close_quietly()
        with self._ready:
            self._session.link_lost(reason, retrying=self.reconnect)
            if not self.reconnect:
                self._fatal = LinkLost(f"{self.link} link lost ({reason})")
                self._closing.set()
            self._ready.notify_all()

    def _reopen(self) -> None:
        outage = self._session.outage_s or 0.0
        if self.give_up_after is not None and outage > self.give_up_after:
            with self._ready:
                self._fatal = LinkLost(f"{self.link} link to {self.where} lost for {outage:.1f} s; gave up")
                self._events.say("gave_up", str(self._fatal))
                self._ready.notify_all()
            self._closing.set()
            return
        if self._closing.wait(self.RETRY_S):
            return
        try:
            self._open()
        except Exception:
            return
        self._down = False
        with self._lock:
            self._reconnects += 1
            self._session.link_back(self._streaming)
            streaming = self._streaming
            self._last_start = time.monotonic()
        if streaming:
            self._send_frame(Start())
