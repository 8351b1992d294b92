"""The simulated plant beside the host build of the rig firmware (hw/firmware, `make host`).

The compiled firmware is the rig's controller: it owns the pseudo-terminal the host opens,
speaks the wire protocol, runs the watchdog, the command bounds and the soft stroke limits,
and its timer drives the 1 kHz clock. This module is its physical world: at every tick the
firmware sends the instant and the valve output it held since the previous tick; the plant
(`hw.virtual_rig.VirtualRig`, the one plant) is integrated over that period with that
output, and the sensor readings at the instant go back as ADC counts, converted with the
scaling the firmware reported when it started (so the firmware's own conversion from
counts to SI is what the host sees).

    rig = FirmwareRig("hw/firmware/build/rig-host", cyl)
    print(rig.path)          # the pty, for `combined-reality live --serial PATH`
    rig.run(duration=60)     # blocks; stop() from a signal handler or another thread

The exchange runs over a SOCK_SEQPACKET socket pair with fixed little-endian records (the
layouts below and in hw/firmware/host/rig_host.c). Each side gives up on the other: the
firmware centres the valve and exits when the plant is gone or silent for 2 s, and
`run()` ends with `failure` set when the firmware exits or stops ticking for 2 s.
"""
from __future__ import annotations

import gc
import math
import os
import socket
import struct
import subprocess
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from sim.cylinder import Cylinder
from sim.effects import Effect

from .rig import RigError, Status
from .virtual_rig import VirtualRig

__all__ = ["Channel", "FirmwareConfig", "FirmwareRig", "FirmwareStats", "TICK_FIELDS", "EXCHANGE_VERSION"]

Log = Callable[[str], None]

EXCHANGE_VERSION = 1
TIMEOUT_S = 2.0  # silence after which either side gives up on the other (as rig_host.c does)
HELLO_TIMEOUT_S = 10.0
ADC_MAX = 0xFFFF

# hello: magic, version, period_us, watchdog_us, stroke, end_zone, t0_ns (CLOCK_MONOTONIC),
# has_supply, supply_min, valve centre, span, max; then four channels (x, p1, p2, ps) of
# (offset, scale, valid_min, valid_max); then the pty path
_HELLO = struct.Struct("<4sHIIffQBfHHH" + "ffHH" * 4)
# request, at tick k: t_us of tick k; the outcome of tick k-1: seq, valve output held since,
# status bits, u_applied, cmd_seq
_REQUEST = struct.Struct("<QIHHfI")
# reply: ADC counts of x, p1, p2, ps at tick k; ok (0: the plant failed)
_REPLY = struct.Struct("<HHHHB")

# one row per tick of FirmwareRig.ticks(): the instant, what the sensors read (SI, before
# the ADC), and what the firmware decided at that tick
TICK_FIELDS = ("t_us", "x", "p1", "p2", "ps", "seq", "valve_out", "status", "u_applied", "cmd_seq")


@dataclass(frozen=True)
class Channel:
    """One sensor channel of the firmware: SI = offset + scale * counts."""

    offset: float
    scale: float
    valid_min: int
    valid_max: int

    def counts(self, value: float) -> int:
        """The ADC reading for an SI value (rounded, saturated at the converter's range)."""
        c = (value - self.offset) / self.scale
        return 0 if not c > 0 else ADC_MAX if c >= ADC_MAX else int(c + 0.5)

    def value(self, counts: int) -> float:
        return self.offset + self.scale * counts


@dataclass(frozen=True)
class FirmwareConfig:
    """What the firmware reported when it started (its rig_config.h, with the overrides)."""

    period_us: int
    watchdog_us: int
    stroke: float
    end_zone: float
    t0_ns: int  # CLOCK_MONOTONIC (time.monotonic_ns) at the rig clock's 0
    supply_min: float | None
    valve_centre: int
    valve_span: int
    valve_max: int
    x: Channel
    p1: Channel
    p2: Channel
    ps: Channel | None
    pty: str

    @classmethod
    def from_hello(cls, data: bytes) -> FirmwareConfig:
        n = _HELLO.size
        if len(data) <= n:
            raise RigError(f"the firmware's hello has {len(data)} bytes; expected more than {n}")
        (magic, version, period_us, watchdog_us, stroke, end_zone, t0_ns, has_supply, supply_min, centre, span,
         vmax, *channels) = _HELLO.unpack_from(data)
        if magic != b"RIGF" or version != EXCHANGE_VERSION:
            raise RigError(f"not a host-built rig firmware of exchange version {EXCHANGE_VERSION} "
                           f"(magic {magic!r}, version {version})")
        x, p1, p2, ps = (Channel(*channels[i:i + 4]) for i in range(0, 16, 4))
        return cls(period_us=period_us, watchdog_us=watchdog_us, stroke=stroke, end_zone=end_zone, t0_ns=t0_ns,
                   supply_min=supply_min if has_supply else None, valve_centre=centre, valve_span=span,
                   valve_max=vmax, x=x, p1=p1, p2=p2, ps=ps if has_supply else None, pty=data[n:].decode())

    def u_of(self, valve_out: int) -> float:
        """The command the valve holds at an output (what the valve driver makes of it)."""
        return (valve_out - self.valve_centre) / self.valve_span


@dataclass
class FirmwareStats:
    ticks: int = 0  # sensor readings the plant served
    streaming: int = 0  # ticks at which the firmware streamed (RUNNING; a sample, unless the host lagged)
    overruns: int = 0  # ticks the firmware flagged OVERRUN (its loop was late: the machine is busy)
    watchdog_trips: int = 0
    soft_limits: int = 0  # entries into an end zone with a command that drove further in
    wall_s: float = 0.0

    def summary(self) -> str:
        return (f"{self.ticks} ticks, {self.streaming} of them streaming, {self.overruns} overruns, "
                f"{self.watchdog_trips} watchdog trips, {self.soft_limits} soft-limit stops")


class FirmwareRig:
    """The plant of `VirtualRig` wired to the host-built firmware `firmware` (a path).

    Starting it compiles the plant (cached), starts the firmware and waits for its hello;
    `path` is then the pty the host opens. `run()` serves the firmware's ticks until
    `stop()`, `duration` seconds of rig time, or a failure (`failure` says which).
    With `history_s`, the last that many seconds of ticks are kept for `ticks()`."""

    def __init__(self, firmware: str | os.PathLike[str], cyl: Cylinder, effects: Sequence[Effect] = (), *,
                 rate: float = 1000.0, watchdog_ms: float = 50.0, seed: int = 0, noise: bool = True,
                 log: Log | None = None, progress: Log | None = None, history_s: float = 0.0,
                 realtime: bool = True):
        if not 10 <= rate <= 100_000:
            raise ValueError(f"rate must lie between 10 and 100000 Hz, not {rate:g}")
        if not (watchdog_ms >= 1 and math.isfinite(watchdog_ms)):
            raise ValueError(f"watchdog_ms must be at least 1, not {watchdog_ms:g}")
        binary = Path(firmware)
        if not binary.is_file() or not os.access(binary, os.X_OK):
            raise RigError(f"{binary} is not an executable file (build it with `make -C hw/firmware host`)")
        self._log = log or (lambda msg: None)
        self.realtime = realtime
        self.stats = FirmwareStats()
        self.failure: str | None = None  # why run() ended by itself
        self._stop = False
        self._history: deque = deque(maxlen=max(int(history_s * rate), 1))
        self._keep_history = history_s > 0
        self.plant = VirtualRig(cyl, effects, rate=rate, seed=seed, noise=noise, progress=progress)
        self.plant.start()
        self._ps_rng = np.random.default_rng([seed, 1])  # the supply transducer's noise
        self._sock, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        argv = [str(binary), "--plant-fd", str(theirs.fileno()), "--stroke", repr(cyl.geometry.stroke),
                "--watchdog-ms", repr(float(watchdog_ms)), "--rate", repr(float(rate))]
        try:
            # its stderr is ours: what it says when this process is gone still reaches the terminal
            self.proc = subprocess.Popen(argv, pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL,
                                         stdout=subprocess.DEVNULL)
        except OSError as e:
            self._sock.close()
            raise RigError(f"cannot start the firmware {binary}: {e.strerror}") from None
        finally:
            theirs.close()
        self._sock.settimeout(HELLO_TIMEOUT_S)
        try:
            hello = self._sock.recv(1024)
        except (socket.timeout, OSError):
            hello = b""
        if not hello:
            self.close()
            raise RigError(f"the firmware {binary} did not start (exit status {self.proc.returncode}; "
                           "its own message is above)")
        try:
            self.config = FirmwareConfig.from_hello(hello)
        except RigError:
            self.close()
            raise
        self._sock.settimeout(TIMEOUT_S)

    # ---------------------------------------------------------------- public

    @property
    def path(self) -> str:
        """The pty the host opens."""
        return self.config.pty

    def stop(self) -> None:
        """Ask run() to return (safe from a signal handler or another thread)."""
        self._stop = True

    def run(self, duration: float | None = None) -> FirmwareStats:
        """Serve the firmware's ticks; returns the statistics when it ends (then the firmware is stopped)."""
        t_wall = time.perf_counter()
        if self.realtime:
            self._realtime()
        try:
            self._serve(duration)
        finally:
            if self.realtime:
                gc.unfreeze()
            self.stats.wall_s = time.perf_counter() - t_wall
            self.close()
        return self.stats

    def ticks(self) -> dict[str, np.ndarray]:
        """The kept ticks as columns (TICK_FIELDS): at each instant, what the sensors read and
        what the firmware latched then (the valve output held until the next tick)."""
        rows = list(self._history)
        if len(rows) < 2:
            return {f: np.array([]) for f in TICK_FIELDS}
        a = np.array(rows, dtype=float)
        # a request carries tick k's instant and readings with tick k-1's outcome
        cols = [a[:-1, 0], a[:-1, 1], a[:-1, 2], a[:-1, 3], a[:-1, 4], *(a[1:, i] for i in range(5, 10))]
        return dict(zip(TICK_FIELDS, cols))

    def rig_time(self, monotonic_s: float) -> float:
        """A time.monotonic() instant on the rig's clock, s (both are CLOCK_MONOTONIC)."""
        return monotonic_s - self.config.t0_ns * 1e-9

    def close(self) -> None:
        """Stop the firmware (SIGTERM: it centres the valve) and release the channel."""
        proc = self.proc
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        self._sock.close()

    # ---------------------------------------------------------------- internals

    def _realtime(self) -> None:
        try:  # this thread only; below the firmware's own priority
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(9))
        except (AttributeError, OSError) as e:
            self._log(f"firmware plant: runs without real-time priority "
                      f"({e.strerror if isinstance(e, OSError) else e}); expect more overruns")
        gc.collect()
        gc.freeze()  # the plant's objects stay out of full collections, which took ms off a tick

    def _serve(self, duration: float | None) -> None:
        cfg, plant, stats = self.config, self.plant, self.stats
        sock, keep = self._sock, self._keep_history
        x_ch, p1_ch, p2_ch, ps_ch = cfg.x, cfg.p1, cfg.p2, cfg.ps
        ps_true = plant.cyl.supply.pressure
        ps_noise = plant.cyl.sensors.pressure_noise if plant.noise else 0.0
        rng = self._ps_rng
        prev_t: int | None = None
        prev_status = 0
        plant_failed = False
        end_us = None if duration is None else duration * 1e6
        while not self._stop:
            try:
                data = sock.recv(64)
            except socket.timeout:
                self._fail(f"the firmware stopped ticking (silent for {TIMEOUT_S:g} s)")
                return
            except OSError as e:
                self._fail(self._gone(f"the channel to the firmware failed: {e.strerror}"))
                return
            if len(data) != _REQUEST.size:
                self._fail(self._gone("the firmware closed the channel") if not data else
                           f"the firmware sent a {len(data)}-byte request")
                return
            t_us, seq, valve_out, status, u_applied, cmd_seq = _REQUEST.unpack(data)
            if plant_failed:  # the firmware has had its tick to report the fault
                return
            # the valve held the output of the previous tick over [t_k-1, t_k)
            plant.latch(cfg.u_of(valve_out))
            dt = plant.dt if prev_t is None else (t_us - prev_t) * 1e-6
            prev_t = t_us
            try:
                _, x, p1, p2 = plant.integrate(dt)
            except RuntimeError as e:  # the plant diverged: the firmware hears it cannot read its sensors
                self.failure = str(e)
                self._log(f"firmware plant: {e}")
                plant_failed = True
                sock.send(_REPLY.pack(0, 0, 0, 0, 0))
                continue
            ps = ps_true + ps_noise * rng.standard_normal() if ps_ch is not None else math.nan
            reply = _REPLY.pack(x_ch.counts(x), p1_ch.counts(p1), p2_ch.counts(p2),
                                ps_ch.counts(ps) if ps_ch is not None else 0, 1)
            try:
                sock.send(reply)
            except OSError as e:
                self._fail(self._gone(f"the channel to the firmware failed: {e.strerror}"))
                return
            stats.ticks += 1
            if seq:
                stats.streaming += bool(status & Status.RUNNING)
                stats.overruns += bool(status & Status.OVERRUN)
                stats.watchdog_trips += bool(status & ~prev_status & Status.WATCHDOG)
                stats.soft_limits += bool(status & ~prev_status & Status.SOFT_LIMIT)
            prev_status = status
            if keep:
                self._history.append((t_us, x, p1, p2, ps, seq, valve_out, status, u_applied, cmd_seq))
            if end_us is not None and t_us >= end_us:
                return

    def _gone(self, otherwise: str) -> str:
        """Why the channel broke: the firmware's exit status when it has ended."""
        try:
            return f"the firmware exited (status {self.proc.wait(timeout=TIMEOUT_S)})"
        except subprocess.TimeoutExpired:
            return otherwise

    def _fail(self, why: str) -> None:
        if not self._stop:
            self.failure = self.failure or why
            self._log(f"firmware plant: {why}")
