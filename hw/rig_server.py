"""The virtual rig speaking the wire protocol over a pseudo-terminal (or a python-can bus).

`RigServer` owns an in-process `hw.virtual_rig.VirtualRig` (the same plant as everything
else) and behaves like rig firmware: a real-time loop at `rate` with deadline scheduling
and jitter, rig timestamps = actual tick times, the plant integrated over the actual
period, streaming between START and STOP, the latest command latched at each tick, a
watchdog that centres the valve when the host goes silent, soft stroke limits, and faults
on demand (`hw.links.FaultSpec`). The host sees a real serial device (`transport="serial"`), an
SLCAN adapter (`"slcan"`, hw.slcan_server) or, in tests, a python-can bus (`"can-bus"`).

    combined-reality virtual-rig --serial --link /tmp/rig     # prints the pty path first
"""
from __future__ import annotations

import gc
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from sim.cylinder import Cylinder
from sim.effects import Effect

from .links import CanBusLink, FaultSpec, Link, SerialPtyLink, ServerStats
from .protocol import (Command, ErrorCode, ErrorFrame, EventLimiter, Frame, Heartbeat, HostFrame, SampleFrame, Start,
                       StatusFrame, Stop)
from .realtime import make_realtime
from .rig import Status, bounded
from .slcan_server import SlcanPtyLink
from .virtual_rig import VirtualRig

Log = Callable[[str], None]


@dataclass(frozen=True)
class ServerOptions:
    rate: float = 1000.0  # Hz
    jitter_us: float = 20.0  # standard deviation of the tick times around the nominal grid
    watchdog_ms: float = 50.0  # host silence (no COMMAND, HEARTBEAT or starting START) that centres the valve
    end_zone: float = 0.03  # soft stroke limits: this fraction of the stroke at each end
    spin_us: float = 200.0  # sleep until this long before a deadline, then spin
    status_period_s: float = 0.1  # STATUS frames while not streaming
    tx_limit: int = 1 << 16  # bytes the rig buffers when the host reads too slowly
    realtime: bool = True  # ask for SCHED_FIFO (root or CAP_SYS_NICE): a rig's loop is not preempted

    def __post_init__(self) -> None:
        if not 10 <= self.rate <= 100_000:
            raise ValueError(f"rate must lie between 10 and 100000 Hz, not {self.rate:g}")
        if not 0 <= self.jitter_us <= 0.25e6 / self.rate:
            raise ValueError(f"jitter_us must lie between 0 and a quarter period ({0.25e6 / self.rate:g} us), "
                             f"not {self.jitter_us:g}")
        if not self.watchdog_ms > 0:
            raise ValueError(f"watchdog_ms must be positive, not {self.watchdog_ms:g}")


# ------------------------------------------------------------------ rig logic


class ErrorGate:
    """Error frames at the onset of a fault, then at most one per code per second.

    A counting code (BAD_COMMAND, TX_OVERFLOW, RX_CORRUPT) sums what the gate holds back
    into its next report, sent by `flush` once the second is over; for the others the
    held-back occurrences are only visible in the samples' status bits."""

    COUNTED = frozenset({ErrorCode.BAD_COMMAND, ErrorCode.TX_OVERFLOW, ErrorCode.RX_CORRUPT})

    def __init__(self, interval_us: int = 1_000_000):
        self.interval_us = interval_us
        self._sent_us: dict[int, int] = {}  # code -> time of its last report
        self._held: dict[int, int] = {}  # counting code -> occurrences not reported yet

    def report(self, code: ErrorCode, t_us: int, value: int, out: list[Frame]) -> None:
        """A fault of `code` (value: its detail, or the number of occurrences for a counting code)."""
        if code in self.COUNTED:
            value += self._held.pop(code, 0)
        last = self._sent_us.get(code)
        if last is None or t_us - last >= self.interval_us:
            self._sent_us[code] = t_us
            out.append(ErrorFrame(code, t_us, value))
        elif code in self.COUNTED:
            self._held[code] = value

    def flush(self, t_us: int, out: list[Frame]) -> None:
        """Report the counts held back whose second is over."""
        if self._held:
            for code in [c for c in self._held if t_us - self._sent_us[c] >= self.interval_us]:
                self.report(code, t_us, 0, out)


class RigCore:
    """The rig's firmware logic, without I/O or clock: host frames in, samples out."""

    def __init__(self, rig: VirtualRig, options: ServerOptions, log: Log, stats: ServerStats | None = None):
        self.rig = rig
        self.opts = options
        self.log = log
        self.stats = stats if stats is not None else ServerStats()
        self.errors = ErrorGate()  # every error frame of the rig goes through it
        L = rig.cyl.geometry.stroke
        self.zone = (options.end_zone * L, (1.0 - options.end_zone) * L)
        self.running = False
        self.seq = 0
        self.t_us: int | None = None
        self.cmd_u = 0.0
        self.cmd_seq = 0
        self.cmd_clipped = False
        self.last_host_us = 0
        self.watchdog = False
        self.in_zone = False

    def host_frame(self, frame: HostFrame, t_us: int) -> list[Frame]:
        """Take a frame from the host; returns frames to send back (errors)."""
        out: list[Frame] = []
        match frame:
            case Command(seq, u):
                self.last_host_us = t_us
                self.cmd_u = bounded(u)  # never trust the wire
                self.cmd_clipped = self.cmd_u != u  # NaN != anything
                if self.cmd_clipped:
                    self.errors.report(ErrorCode.BAD_COMMAND, t_us, 1, out)
                self.cmd_seq = seq
                self.watchdog = False  # only a new command re-arms a tripped watchdog
            case Heartbeat():
                self.last_host_us = t_us
            case Start():
                # only a START that starts streaming feeds the watchdog: a host re-sends START
                # while it sees no samples, which must not keep a stale command alive
                if not self.running:
                    self.last_host_us = t_us
                    self.running = True
                    self.log("streaming started by the host")
            case Stop():
                if self.running:
                    self.log("streaming stopped by the host")
                self.running = False
                self.cmd_u, self.cmd_clipped = 0.0, False
        return out

    def tick(self, t_us: int, flags: Status = Status(0)) -> tuple[SampleFrame, list[Frame]]:
        """The tick at t_us: advance the plant to it and sample, check the command against the
        sample, latch it. `flags`: status bits only the I/O side knows (OVERRUN, TX_OVERFLOW)."""
        out: list[Frame] = []
        status = flags
        dt = 1.0 / self.opts.rate if self.t_us is None else (t_us - self.t_us) * 1e-6
        _, x, p1, p2 = self.rig.integrate(dt)  # with the command latched at the previous tick
        self.t_us = t_us
        self.seq += 1
        silence_ms = (t_us - self.last_host_us) / 1000.0
        if self.running and not self.watchdog and silence_ms > self.opts.watchdog_ms:
            self.watchdog = True
            self.stats.watchdog_trips += 1
            self.errors.report(ErrorCode.WATCHDOG, t_us, int(round(silence_ms)), out)
            self.log(f"watchdog: no command for {silence_ms:.0f} ms; valve centred")
        u = self.cmd_u if self.running and not self.watchdog else 0.0
        if self.watchdog:
            status |= Status.WATCHDOG
        if self.cmd_clipped and u == self.cmd_u:
            status |= Status.CMD_CLIPPED
        # soft stroke limits on the position just measured: never drive further into an end zone
        lo, hi = self.zone
        into = (x < lo and u < 0) or (x > hi and u > 0)
        if into:
            u = 0.0
            status |= Status.SOFT_LIMIT
            if not self.in_zone:
                self.errors.report(ErrorCode.SOFT_LIMIT, t_us, int(round(x * 1e6)), out)
        self.in_zone = into
        self.rig.latch(u)
        if self.running:
            status |= Status.RUNNING
        self.errors.flush(t_us, out)
        return SampleFrame(seq=self.seq, t_us=t_us, x=x, p1=p1, p2=p2, ps=None, u_applied=u,
                           status=int(status), cmd_seq=self.cmd_seq), out


# ------------------------------------------------------------------ the server


class RigServer:
    """A real-time virtual rig behind a wire. `run()` blocks until `stop()`, `duration`, or a
    vanish fault without return; `step(t_us)` runs one tick without waiting (tests)."""

    def __init__(self, cyl: Cylinder, effects: Sequence[Effect] = (), *, transport: str = "serial",
                 options: ServerOptions = ServerOptions(), faults: FaultSpec = FaultSpec(), seed: int = 0,
                 noise: bool = True, link_path: str | None = None, log: Log | None = None,
                 on_path: Callable[[str], None] | None = None, can_bus=None, progress: Log | None = None):
        if transport not in ("serial", "slcan", "can-bus"):
            raise ValueError(f"unknown transport {transport!r} (serial, slcan, can-bus)")
        if transport == "can-bus" and can_bus is None:
            raise ValueError("transport 'can-bus' needs a python-can bus")
        if faults.corrupt and transport != "serial":
            raise ValueError("corrupt applies to the serial transport only: CAN frames carry a hardware CRC, "
                             "so use drop")
        if link_path and transport != "can-bus":
            link = Path(link_path)
            if not link.parent.is_dir():
                raise ValueError(f"link_path {link_path}: the folder {link.parent} does not exist")
            if link.exists() and not link.is_symlink():
                raise ValueError(f"link_path {link_path} exists and is not a symbolic link; refusing to replace it")
        self.opts = options
        self.faults = faults
        self.transport = transport
        self.link_path = link_path
        self.on_path = on_path
        self._can_bus = can_bus
        self._log = log or (lambda msg: None)
        self._events = EventLimiter()
        self.stats = ServerStats()
        self._rng = np.random.default_rng(faults.seed)  # jitter and faults; the plant's noise has its own
        self.rig = VirtualRig(cyl, effects, rate=options.rate, seed=seed, noise=noise, progress=progress)
        self.rig.start()
        self.core = RigCore(self.rig, options, self.log, self.stats)
        self._stop = False
        self.failure: str | None = None  # why the rig stopped by itself (the plant diverged)
        self._last_status_us = -(10**12)
        self._last_tx_us: int | None = None
        self._stall_until_us: int | None = None
        self._vanished_at_us: int | None = None
        self._done_faults: set[str] = set()
        self._realtime_ok = False
        self._rx_corrupt_seen = 0  # damaged host frames of the current link already reported
        self._overrun_us = 0  # how late the last missed deadline was
        self.link: Link | None = self._new_link()

    # ---------------------------------------------------------------- public

    @property
    def path(self) -> str | None:
        """The pty path the host opens (or the bus channel)."""
        return None if self.link is None else self.link.path

    def log(self, msg: str) -> None:
        self._log(f"virtual rig: {msg}")

    def stop(self) -> None:
        """Ask run() to return (safe from a signal handler or another thread)."""
        self._stop = True

    def run(self, duration: float | None = None) -> ServerStats:
        """The real-time loop; returns the statistics when it ends."""
        period_ns = int(round(1e9 / self.opts.rate))
        spin_ns = int(self.opts.spin_us * 1000)
        sigma_ns = self.opts.jitter_us * 1000.0
        jmax = min(3 * sigma_ns, 0.25 * period_ns)
        if self.opts.realtime:
            self._realtime()
            # process-wide, meant for a dedicated server process: the objects alive now (the
            # plant's thousands) are left out of full collections, which took ms off the tick
            gc.freeze()
        t0 = time.perf_counter_ns()
        cpu0 = time.process_time()
        k = 0
        try:
            while not self._stop:
                k += 1
                jitter = float(np.clip(self._rng.normal(0.0, sigma_ns), -jmax, jmax)) if sigma_ns > 0 else 0.0
                target = t0 + k * period_ns + int(jitter)
                self._wait(target, spin_ns if self.core.running else 0)
                now = time.perf_counter_ns()
                overrun = now - target > period_ns
                if overrun:  # missed whole ticks: skip them rather than burst to catch up
                    k += max(int((now - t0) // period_ns - k), 0)
                if self.core.running:  # idle ticks only sleep: their timing does not matter
                    self.stats.late_us.append((now - target) / 1000.0)
                    if overrun:
                        self._overrun_us = (now - target) // 1000
                        self.stats.overruns += 1
                        self.stats.overrun_at.append(((now - t0) // 1000 * 1e-6, self._overrun_us * 1e-6))
                        self._events.count("overrun", 1, "virtual rig: {n} sampling deadline{s} missed in the "
                                                         "last second (the machine is busy)")
                if not self._tick((now - t0) // 1000, overrun):
                    break
                if self.core.running:
                    self.stats.busy_us.append((time.perf_counter_ns() - now) / 1000.0)
                if duration is not None and now - t0 >= duration * 1e9:
                    break
        finally:
            self.stats.wall_s = (time.perf_counter_ns() - t0) * 1e-9
            self.stats.cpu_s = time.process_time() - cpu0
            self._shutdown()
        return self.stats

    def step(self, t_us: int) -> bool:
        """One tick at rig time t_us, without waiting (deterministic tests); False once the rig is gone."""
        return self._tick(t_us, False)

    def close(self) -> None:
        self._shutdown()

    # ---------------------------------------------------------------- internals

    def _new_link(self) -> Link:
        args = (self.faults, self._rng, self.stats, self.opts.tx_limit)
        if self.transport == "serial":
            link: Link = SerialPtyLink(*args)
        elif self.transport == "slcan":
            link = SlcanPtyLink(*args, rate=self.opts.rate, log=self.log)
        else:
            link = CanBusLink(self._can_bus, *args)
        if self.link_path and self.transport != "can-bus":
            _replace_symlink(self.link_path, link.path)
        return link

    def _realtime(self) -> None:
        # this thread only; the kernel still keeps 5 % of each second for others
        why = make_realtime(10)
        self._realtime_ok = why is None
        if why is not None:
            self.log(f"runs without real-time priority ({why}); expect more jitter")
        self._realtime_helpers()

    def _realtime_helpers(self) -> None:
        """The pty reader thread too: preempted while holding the GIL it would stall the loop."""
        reader = getattr(self.link, "reader", None)
        if self._realtime_ok and reader is not None:
            make_realtime(9, reader)

    def _wait(self, target_ns: int, spin_ns: int) -> None:
        # sleep until shortly before the deadline, then spin: time.sleep alone overshoots by
        # 50-100 us; a rig's timer interrupt does not
        while True:
            left = target_ns - time.perf_counter_ns()
            if left <= spin_ns or self._stop:
                break
            time.sleep((left - spin_ns) * 1e-9)
        while time.perf_counter_ns() < target_ns and not self._stop:
            pass

    def _tick(self, t_us: int, overrun: bool) -> bool:
        self.stats.ticks += 1
        if not self._faults_at(t_us):
            return False
        link, core = self.link, self.core
        frames: list[Frame] = []
        flags = Status.OVERRUN if overrun else Status(0)
        if link is not None:
            for f in link.poll():
                frames += core.host_frame(f, t_us)
            if link.rx_corrupt > self._rx_corrupt_seen:
                core.errors.report(ErrorCode.RX_CORRUPT, t_us, link.rx_corrupt - self._rx_corrupt_seen, frames)
                self._rx_corrupt_seen = link.rx_corrupt
            if link.overflowed:  # frames dropped since the last tick
                flags |= Status.TX_OVERFLOW
                core.errors.report(ErrorCode.TX_OVERFLOW, t_us, link.overflowed, frames)
                self._events.count("overflow", link.overflowed, "virtual rig: {n} frame{s} dropped in the last "
                                                                 "second: the host does not read fast enough")
                link.overflowed = 0
        if overrun and core.running:
            core.errors.report(ErrorCode.OVERRUN, t_us, self._overrun_us, frames)
        try:
            sample, errors = core.tick(t_us, flags)
        except RuntimeError as e:  # the plant diverged: tell the host, then stop like firmware would
            self.failure = str(e)
            self.log(f"internal fault: {e}; stopping")
            if link is not None:
                link.send(ErrorFrame(ErrorCode.INTERNAL, t_us, 0))
                link.flush()
            return False
        frames += errors
        if link is not None:
            for f in frames:
                link.send(f)
            if core.running:
                link.send(sample)
                self.stats.samples_sent += 1
                if self._last_tx_us is not None:
                    self.stats.period_us.append(t_us - self._last_tx_us)
                self._last_tx_us = t_us
            else:
                self._last_tx_us = None
                if t_us - self._last_status_us >= self.opts.status_period_s * 1e6:
                    link.send(StatusFrame(sample.seq, t_us, sample.status))
                    self._last_status_us = t_us
            link.flush()
        self._events.flush()
        for line in self._events.pop_lines():
            self._log(line)
        return True

    def _faults_at(self, t_us: int) -> bool:
        """Start and end stalls and vanishings; False when the rig is gone for good."""
        f = self.faults
        t = t_us * 1e-6
        if f.stall_at is not None and "stall" not in self._done_faults and t >= f.stall_at and self.link:
            self._done_faults.add("stall")
            self._stall_until_us = t_us + int(f.stall_for * 1e6)
            self.link.stalled = True
            self.log(f"fault: link stalled for {f.stall_for:g} s (samples are delayed, not lost)")
        if self._stall_until_us is not None and t_us >= self._stall_until_us and self.link:
            self._stall_until_us = None
            self.link.stalled = False
            self.log("fault: stall over, sending the delayed frames")
        if f.vanish_at is not None and "vanish" not in self._done_faults and t >= f.vanish_at:
            self._done_faults.add("vanish")
            self._drop_link()
            self._vanished_at_us = t_us
            self.log("fault: the rig vanished (pty closed)" +
                     ("" if f.vanish_for is None else f"; back in {f.vanish_for:g} s"))
            if f.vanish_for is None:
                return False
        if self._vanished_at_us is not None and f.vanish_for is not None \
                and t_us - self._vanished_at_us >= f.vanish_for * 1e6:
            self._vanished_at_us = None
            self.link = self._new_link()
            self._rx_corrupt_seen = 0
            self._realtime_helpers()
            self.log(f"back on {self.link.path}")
            if self.on_path:
                self.on_path(self.link.path)
        return True

    def _drop_link(self) -> None:
        if self.link is None:
            return
        path = self.link.path
        self.link.close()
        self.link = None
        if self.link_path:
            _remove_symlink(self.link_path, path)

    def _shutdown(self) -> None:
        self._drop_link()
        self._events.flush(force=True)
        for line in self._events.pop_lines():
            self._log(line)


def _replace_symlink(link: str, target: str) -> None:
    """Point `link` at `target` atomically (like udev's /dev/serial/by-id links)."""
    tmp = f"{link}.{os.getpid()}.tmp"
    try:
        os.unlink(tmp)
    except FileNotFoundError:
        pass
    os.symlink(target, tmp)
    os.replace(tmp, link)


def _remove_symlink(link: str, target: str | None) -> None:
    """Remove `link` if it still points at our pty (another server may own it by now)."""
    try:
        if os.readlink(link) == target:
            os.unlink(link)
    except OSError:
        pass
