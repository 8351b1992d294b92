"""The rig side of a transport: host frames in, rig frames out through fault injection and
a transmit buffer. A pseudo-terminal that a host opens like a serial port (the serial
protocol here, SLCAN in hw.slcan_server) or a python-can bus (tests). What faults to
inject (`FaultSpec`) and what the server counts (`ServerStats`) live here too, since a
link does the injecting and counting."""
from __future__ import annotations

import math
import os
import select
import threading
import tty
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from .can_mapping import CanCodec
from .protocol import Command, ErrorFrame, Frame, FrameDecoder, Heartbeat, HostFrame, Start, Stop, encode

__all__ = ["FaultSpec", "ServerStats", "Link", "PtyLink", "SerialPtyLink", "CanBusLink"]


@dataclass(frozen=True)
class FaultSpec:
    """Faults the virtual rig injects on demand (times in s since the server started)."""

    drop: float = 0.0  # probability that a rig->host frame is dropped (on CAN: each of a sample's 3 frames)
    corrupt: float = 0.0  # probability that a serial frame gets 1 to 3 of its bytes overwritten
    # stall: the link stops sending at stall_at for stall_for seconds. The rig keeps sampling;
    # its frames wait in the transmit buffer and go out in one burst when the stall ends
    # (delayed, not lost, as when a USB link or a host driver hiccups)
    stall_at: float | None = None
    stall_for: float | None = None
    # vanish: the pty is closed at vanish_at (an unplugged cable). With vanish_for the rig runs
    # on meanwhile (its watchdog trips) and comes back on a new pty (same link path) after
    # vanish_for seconds; without, it is gone for good and RigServer.run() returns
    vanish_at: float | None = None
    vanish_for: float | None = None
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("drop", "corrupt"):
            p = getattr(self, name)
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"{name} is a probability between 0 and 1, not {p:g}")
        if (self.stall_at is None) != (self.stall_for is None):
            raise ValueError("stall_at and stall_for go together")
        if self.vanish_for is not None and self.vanish_at is None:
            raise ValueError("vanish_for needs vanish_at")
        for name in ("stall_at", "stall_for", "vanish_at", "vanish_for"):
            v = getattr(self, name)
            if v is not None and not (v >= 0 and math.isfinite(v)):
                raise ValueError(f"{name} must be a non-negative number of seconds, not {v:g}")


@dataclass
class ServerStats:
    ticks: int = 0
    samples_sent: int = 0
    frames_dropped: int = 0  # by fault injection
    frames_corrupted: int = 0  # by fault injection
    tx_overflow: int = 0  # frames dropped because the host did not read
    overruns: int = 0  # ticks missed entirely
    # (rig time, lateness) of the missed deadlines, s: which ticks the rig did not keep
    overrun_at: deque = field(default_factory=lambda: deque(maxlen=1000), repr=False)
    watchdog_trips: int = 0
    # the last 10^5 ticks: actual - target wake-up time, and t_k - t_k-1 of streamed samples
    late_us: deque = field(default_factory=lambda: deque(maxlen=100_000), repr=False)
    period_us: deque = field(default_factory=lambda: deque(maxlen=100_000), repr=False)
    busy_us: deque = field(default_factory=lambda: deque(maxlen=100_000), repr=False)  # work per streamed tick
    cpu_s: float = 0.0
    wall_s: float = 0.0

    def summary(self) -> str:
        per = np.asarray(self.period_us)
        late = np.asarray(self.late_us)
        jitter = f"period {per.mean() / 1000:.3f} ms +- {per.std():.1f} us (min {per.min():.0f}, " \
                 f"max {per.max():.0f} us)" if len(per) > 1 else "no samples streamed"
        late_s = f", wake-up late by {np.percentile(late, 99):.0f} us (99 %)" if len(late) else ""
        if len(self.busy_us):
            busy = np.asarray(self.busy_us)
            late_s += f", tick work {np.median(busy):.0f} us (median), {busy.max():.0f} us (max)"
        cpu = f", CPU {100 * self.cpu_s / self.wall_s:.0f} %" if self.wall_s > 0 else ""
        faults = f"; faults injected: {self.frames_dropped} frames dropped, {self.frames_corrupted} corrupted" \
            if self.frames_dropped or self.frames_corrupted else ""
        missed = ""
        if self.overrun_at:
            shown = list(self.overrun_at)[:10]
            missed = " (deadlines missed at " + ", ".join(f"{t:.3f} s by {late * 1e3:.1f} ms" for t, late in shown) \
                + (f" and {self.overruns - len(shown)} more" if self.overruns > len(shown) else "") + ")"
        return (f"{self.ticks} ticks, {self.samples_sent} samples sent; {jitter}{late_s}; {self.overruns} overruns"
                f"{missed}, {self.watchdog_trips} watchdog trips, {self.tx_overflow} frames dropped for a slow host"
                f"{faults}{cpu}")


class Link:
    """Rig side of a transport: host frames in, rig frames out through fault injection and a
    transmit buffer. Subclasses turn frames into wire units and move bytes/messages."""

    def __init__(self, faults: FaultSpec, rng: np.random.Generator, stats: ServerStats, tx_limit: int):
        self.faults = faults
        self.rng = rng
        self.stats = stats
        self.tx_limit = tx_limit
        self.stalled = False
        self.overflowed = 0  # frames dropped for lack of buffer since the last report
        self.path: str | None = None
        self._pending: deque = deque()
        self._pending_size = 0

    @property
    def rx_corrupt(self) -> int:
        """Damaged frames from the host rejected so far."""
        return 0

    def poll(self) -> list[HostFrame]:
        raise NotImplementedError

    def _units(self, frame: Frame) -> list:
        raise NotImplementedError

    def _write(self, unit) -> int | None:
        """Write as much of `unit` as the OS takes now: bytes written (None = all)."""
        raise NotImplementedError

    def _corrupt(self, unit):
        return unit

    def _size(self, unit) -> int:
        return len(unit)

    def close(self) -> None:
        pass

    def send(self, frame: Frame) -> None:
        # error frames (a few per second at most: ErrorGate) never wait for room, or a full
        # buffer would swallow its own TX_OVERFLOW report
        limited = not isinstance(frame, ErrorFrame)
        for unit in self._units(frame):
            if self.faults.drop and self.rng.random() < self.faults.drop:
                self.stats.frames_dropped += 1
                continue
            if self.faults.corrupt and self.rng.random() < self.faults.corrupt:
                unit = self._corrupt(unit)
                self.stats.frames_corrupted += 1
            if limited and not self.stalled and self._pending_size > self.tx_limit:
                self.stats.tx_overflow += 1
                self.overflowed += 1
                continue
            self._pending.append(unit)
            self._pending_size += self._size(unit)

    def flush(self) -> None:
        while self._pending and not self.stalled:
            unit = self._pending[0]
            n = self._write(unit)
            if n is None:
                self._pending.popleft()
                self._pending_size -= self._size(unit)
            else:  # partly written: keep the rest for the next tick
                self._pending[0] = unit[n:]
                self._pending_size -= n
                return


class PtyLink(Link):
    """A pseudo-terminal in raw mode; the host opens `path` like any serial port.

    Input is read by a helper thread: a read on a pty master may wait for the kernel's
    tty worker (normal priority, so starved on a busy machine) for milliseconds, which
    must not hold up the sampling loop."""

    def __init__(self, *args, **kw):
        super().__init__(*args, **kw)
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # bytes pass unchanged: no echo, no line editing, no CR/LF mapping
        tty.setraw(self.master)
        os.set_blocking(self.master, False)
        # the slave stays open here too, so the pty survives the host closing and reopening it
        self.path = os.ttyname(self.slave)
        self._inbox: deque[bytes] = deque()
        self._closing = False
        self._wake_r, self._wake_w = os.pipe()
        self.reader = threading.Thread(target=self._read_loop, name=f"pty reader {self.path}", daemon=True)
        self.reader.start()

    def _read_loop(self) -> None:
        while not self._closing:
            try:
                ready, _, _ = select.select([self.master, self._wake_r], [], [], 0.5)
            except (OSError, ValueError):
                return
            if self._closing:
                return
            if self.master in ready:
                try:
                    data = os.read(self.master, 65536)
                except (BlockingIOError, InterruptedError):
                    continue
                except OSError:
                    return
                self._inbox.append(data)

    def _read(self) -> bytes:
        chunks = []
        while self._inbox:
            chunks.append(self._inbox.popleft())
        return b"".join(chunks)

    def _write(self, unit: bytes) -> int | None:
        try:
            n = os.write(self.master, unit)
        except BlockingIOError:
            return 0
        return None if n == len(unit) else n

    def flush(self) -> None:
        # one write per tick: a write to a pty costs ~20 us whatever its size
        if len(self._pending) > 1 and not self.stalled:
            data = b"".join(self._pending)
            self._pending.clear()
            self._pending.append(data)
        super().flush()

    def close(self) -> None:
        # stop the reader before closing: its fd numbers could be reused by the next pty
        self._closing = True
        os.write(self._wake_w, b"x")
        self.reader.join(timeout=2.0)
        for fd in (self.master, self.slave, self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass


class SerialPtyLink(PtyLink):
    """docs/protocol.md serial framing (COBS + CRC-16) on a pty."""

    def __init__(self, *args, **kw):
        super().__init__(*args, **kw)
        self.decoder = FrameDecoder()

    @property
    def rx_corrupt(self) -> int:
        return self.decoder.frames_corrupt

    def poll(self) -> list[HostFrame]:
        data = self._read()
        if not data:
            return []
        return [f for f in self.decoder.feed(data) if isinstance(f, (Start, Stop, Command, Heartbeat))]

    def _units(self, frame: Frame) -> list[bytes]:
        return [encode(frame)]

    def _corrupt(self, unit: bytes) -> bytes:
        b = bytearray(unit)
        for _ in range(int(self.rng.integers(1, 4))):
            b[int(self.rng.integers(len(b)))] = int(self.rng.integers(256))
        return bytes(b)


class CanBusLink(Link):
    """The rig as a node on a python-can bus (virtual in tests; socketcan vcan/can works too)."""

    def __init__(self, bus, *args, **kw):
        super().__init__(*args, **kw)
        self.bus = bus
        self.codec = CanCodec()
        self.path = str(bus.channel_info)

    def poll(self) -> list[HostFrame]:
        out = []
        while (msg := self.bus.recv(0)) is not None:
            f = self.codec.host_frame(msg)
            if f is not None:
                out.append(f)
        return out

    def _units(self, frame: Frame) -> list:
        return self.codec.rig_messages(frame)

    def _size(self, unit) -> int:
        return 16

    def _write(self, unit) -> int | None:
        self.bus.send(unit)
        return None
