"""SerialRig and CanRig behind the Rig interface, and the rig's firmware logic, without real time.

CanRig talks to the virtual rig on python-can's `virtual` bus; the test steps the rig tick
by tick, so every check is exact. SerialRig talks to a pseudo-terminal the test writes.
"""
import math
import os
import time
import tty

import can
import numpy as np
import pytest

from combined_reality.live import PositionProgram
from hw.can_rig import CanRig
from hw.protocol import Command, ErrorCode, ErrorFrame, FrameDecoder, SampleFrame, Start, Stop, encode
from hw.rig import LinkLost, Rig, RigError, Status, bounded
from hw.rig_server import ErrorGate, RigCore, RigServer, ServerOptions
from hw.serial_rig import SerialRig
from hw.virtual_rig import VirtualRig


@pytest.fixture
def can_pair(cyl_a, request):
    channel = f"transports-{request.node.name}"
    events: list[str] = []
    with can.Bus(channel=channel, interface="virtual") as rig_bus:
        server = RigServer(cyl_a, transport="can-bus", can_bus=rig_bus, seed=3,
                           options=ServerOptions(watchdog_ms=50.0))
        rig = CanRig(channel, interface="virtual", on_event=events.append)
        try:
            yield server, rig, events
        finally:
            rig.stop()
            server.close()


def test_can_rig_closed_loop_over_the_virtual_bus(can_pair, cyl_a):
    server, rig, events = can_pair
    assert isinstance(rig, Rig)
    program = PositionProgram(cyl_a, 2.0, seed=4)
    rig.start()
    got, replies = [], {}
    for k in range(1, 1201):
        server.step(1000 * k)
        s = rig.read(timeout=2.0)
        assert s is not None
        got.append(s)
        u = program.command(s.t, s.x)
        rig.send(u)
        replies[s.seq] = rig.codec.quantise_u(bounded(u))
    seq = np.array([s.seq for s in got])
    assert np.all(np.diff(seq) == 1)
    assert np.allclose([s.t for s in got], 1e-3 * np.arange(1, 1201), atol=1e-9)
    # timing contract: the reply to sample k is what the valve holds from tick k+1 on
    assert all(s.u_applied == replies[s.seq - 1] for s in got[1:])
    assert np.ptp([s.x for s in got]) > 0.01  # it moved
    st = rig.stats
    assert st.samples == 1200 and st.samples_lost == 0 and st.commands_late == 0 and st.frames_corrupt == 0
    assert events == []


def test_watchdog_centres_the_valve_when_the_host_goes_silent(can_pair):
    server, rig, events = can_pair
    rig.start()
    got = []
    for k in range(1, 301):
        server.step(1000 * k)
        s = rig.read(timeout=2.0)
        got.append(s)
        if k <= 100:
            rig.send(0.03)
            last_reply = s.seq
        elif k >= 200:
            rig.send(-0.02)  # the host is back: only a command re-arms
    first_held = next(s for s in got if s.seq == last_reply + 1)
    tripped = next(s for s in got if s.status & Status.WATCHDOG)
    assert 0.05 < tripped.t - first_held.t <= 0.1  # rig timestamps
    for s in got:
        if first_held.seq <= s.seq < tripped.seq:
            assert s.u_applied == pytest.approx(0.03) and s.status == 0
        elif tripped.seq <= s.seq <= 200:
            assert s.u_applied == 0.0 and s.status & Status.WATCHDOG
        elif s.seq > 201:
            assert s.u_applied == pytest.approx(-0.02) and s.status == 0
    assert rig.stats.rig_errors == 1
    assert rig.read(timeout=0.01) is None  # delivers the event
    assert events == ["rig reports watchdog: valve centred after 51 ms of host silence"]


def test_heartbeat_keeps_the_watchdog_quiet(can_pair):
    server, rig, _ = can_pair
    rig.start()
    rig.send(0.1)
    for k in range(1, 201):
        server.step(1000 * k)
        s = rig.read(timeout=2.0)
        rig.heartbeat()
    assert s.status == 0 and s.u_applied == pytest.approx(0.1)


def _core(cyl, x0):
    rig = VirtualRig(cyl, x0=x0, noise=False)
    rig.start()
    return RigCore(rig, ServerOptions(), log=lambda m: None)


def test_rig_bounds_every_command_and_nan_centres(cyl_a):
    core = _core(cyl_a, 0.05)
    core.host_frame(Start(), 0)
    assert core.host_frame(Command(1, math.nan), 0) == [ErrorFrame(ErrorCode.BAD_COMMAND, 0, 1)]
    s, _ = core.tick(1000)
    assert s.u_applied == 0.0 and s.status & Status.CMD_CLIPPED
    errs = core.host_frame(Command(2, 7.0), 1000)
    s, _ = core.tick(2000)
    assert s.u_applied == 1.0 and s.status & Status.CMD_CLIPPED
    assert errs == []  # one BAD_COMMAND report per second: the NaN one was reported
    core.host_frame(Command(3, -0.3), 2000)
    s, _ = core.tick(3000)
    assert s.u_applied == pytest.approx(-0.3) and s.status == Status.RUNNING
    core.host_frame(Stop(), 3000)
    s, _ = core.tick(4000)
    assert s.u_applied == 0.0 and not s.status & Status.RUNNING


@pytest.mark.parametrize("x0, u, blocked", [(0.001, -0.5, True), (0.001, 0.5, False),
                                             (0.099, 0.5, True), (0.099, -0.5, False)])
def test_soft_stroke_limits_only_block_moves_further_in(cyl_a, x0, u, blocked):
    core = _core(cyl_a, x0)  # end zones: 3 % of the 100 mm stroke
    core.host_frame(Start(), 0)
    core.host_frame(Command(1, u), 0)
    s, errs = core.tick(1000)
    assert (s.u_applied == 0.0) == blocked
    assert bool(s.status & Status.SOFT_LIMIT) == blocked and len(errs) == blocked


def test_the_soft_limit_judges_the_position_just_sampled(cyl_a):
    core = _core(cyl_a, 0.01)  # 7 mm outside the 3 mm end zone
    lo = core.zone[0]
    core.host_frame(Start(), 0)
    samples, errors = [], []
    for k in range(1, 501):
        core.host_frame(Command(k, -1.0), 1000 * k - 500)  # full speed into the end zone
        s, errs = core.tick(1000 * k)
        samples.append(s)
        errors += errs
    inside = [s for s in samples if s.x < lo]
    assert inside, "the piston never reached the end zone"
    # the sample that first lies in the zone already has the command set to 0
    assert all(s.u_applied == 0.0 and s.status & Status.SOFT_LIMIT for s in inside)
    assert all(s.u_applied == -1.0 and not s.status & Status.SOFT_LIMIT for s in samples if s.x >= lo)
    first = inside[0]
    assert errors == [ErrorFrame(ErrorCode.SOFT_LIMIT, first.t_us, round(first.x * 1e6))]  # once a second


def test_a_start_while_streaming_does_not_feed_the_watchdog(cyl_a):
    core = _core(cyl_a, 0.05)
    core.host_frame(Start(), 0)
    core.host_frame(Command(1, 0.1), 0)
    held = []
    for k in range(1, 101):
        if k % 10 == 0:
            core.host_frame(Start(), 1000 * k)  # what a host re-sends while it sees no samples
        s, _ = core.tick(1000 * k)
        held.append(s.u_applied)
    assert held == [pytest.approx(0.1)] * 50 + [0.0] * 50  # tripped after 51 ms, STARTs or not


def test_error_frames_at_the_onset_then_once_a_second_with_the_counts_held_back():
    gate, out = ErrorGate(), []
    gate.report(ErrorCode.TX_OVERFLOW, 0, 3, out)
    gate.report(ErrorCode.TX_OVERFLOW, 1000, 2, out)  # held back
    gate.report(ErrorCode.WATCHDOG, 2000, 51, out)  # each code has its own second
    gate.report(ErrorCode.WATCHDOG, 3000, 52, out)  # not a count: only the status bits tell
    gate.flush(999_999, out)
    gate.report(ErrorCode.TX_OVERFLOW, 500_000, 4, out)
    gate.flush(1_000_000, out)
    gate.flush(2_500_000, out)  # nothing held: nothing sent
    assert out == [ErrorFrame(ErrorCode.TX_OVERFLOW, 0, 3), ErrorFrame(ErrorCode.WATCHDOG, 2000, 51),
                   ErrorFrame(ErrorCode.TX_OVERFLOW, 1_000_000, 6)]


def test_a_host_that_does_not_read_gets_overflow_reports_not_a_flood(cyl_a):
    server = RigServer(cyl_a, transport="serial", seed=1, options=ServerOptions(tx_limit=2000))
    fd = os.open(server.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        os.write(fd, encode(Start()))
        k, end = 0, time.monotonic() + 5
        while not server.core.running and time.monotonic() < end:  # the pty's reader thread has it
            k += 1
            server.step(1000 * k)
        n_quiet = 4000  # 4 s of rig time in which the host reads nothing (more than a pty buffers)
        for _ in range(n_quiet):
            k += 1
            server.step(1000 * k)
        dec, frames = FrameDecoder(), []
        for _ in range(3000):  # the host reads again while the rig runs on; the backlog drains
            k += 1
            server.step(1000 * k)
            try:
                frames += dec.feed(os.read(fd, 1 << 16))
            except BlockingIOError:
                pass
    finally:
        os.close(fd)
        server.close()
    assert dec.frames_corrupt == 0
    dropped = server.stats.tx_overflow
    assert dropped > 1000
    reports = [f for f in frames if isinstance(f, ErrorFrame) and f.code == ErrorCode.TX_OVERFLOW]
    assert 1 <= len(reports) <= n_quiet // 1000 + 2  # the onset, then once a second at most
    # the counts held back between reports are carried into the next one (the last second's may still wait)
    assert dropped - 1000 <= sum(f.value for f in reports) <= dropped
    samples = [f for f in frames if isinstance(f, SampleFrame)]
    # a sample carries TX_OVERFLOW exactly when samples before it were dropped
    for a, b in zip(samples, samples[1:]):
        assert bool(b.status & Status.TX_OVERFLOW) == (b.seq - a.seq > 1), (a, b)
    assert sum(b.seq - a.seq - 1 for a, b in zip(samples, samples[1:])) <= dropped


# ------------------------------------------------------------------ SerialRig on a bare pty


@pytest.fixture
def pty():
    master, slave = os.openpty()
    tty.setraw(slave)
    yield master, os.ttyname(slave)
    for fd in (master, slave):
        try:
            os.close(fd)
        except OSError:
            pass


def _drain(master, timeout=1.0):
    dec, out, end = FrameDecoder(), [], time.monotonic() + timeout
    os.set_blocking(master, False)
    while time.monotonic() < end:
        try:
            out += dec.feed(os.read(master, 4096))
        except BlockingIOError:
            time.sleep(0.01)
    return out


def test_serial_rig_speaks_the_protocol_and_rejects_damage(pty):
    master, path = pty
    events: list[str] = []
    rig = SerialRig(path, reconnect=False, on_event=events.append)
    rig.start()
    rig.send(math.nan)
    rig.send(5.0)
    host_frames = _drain(master, 0.3)
    assert host_frames[0] == Start() and [f.u for f in host_frames[1:3]] == [0.0, 1.0]
    frames = [encode(SampleFrame(k, 1000 * k, 0.05, 3e5, 2e5, None, 0.0, 1, 0)) for k in (1, 2, 3, 4)]
    bad = bytearray(frames[2])
    bad[7] ^= 0xFF
    os.write(master, b"\x13\x37garbage" + frames[0] + frames[1] + bytes(bad) + frames[3])
    got = [rig.read(timeout=2.0) for _ in range(3)]
    assert [s.seq for s in got] == [1, 2, 4] and [s.t for s in got] == [0.001, 0.002, 0.004]
    st = rig.stats
    assert st.frames_corrupt == 1 and st.samples_lost == 1 and st.bytes_discarded > 0
    rig.stop()
    assert Stop() in _drain(master, 0.3)
    assert sorted(events) == ["serial link: 1 corrupted frame rejected in the last second",
                              "serial link: 1 sample lost (sequence gaps) in the last second"]


def test_serial_rig_without_reconnect_raises_link_lost(pty):
    master, path = pty
    events: list[str] = []
    rig = SerialRig(path, reconnect=False, on_event=events.append)
    rig.start()
    os.write(master, encode(SampleFrame(1, 1000, 0.05, 3e5, 2e5, None, 0.0, 1, 0)))
    assert rig.read(timeout=2.0).seq == 1
    os.close(master)  # the rig vanishes
    with pytest.raises(LinkLost):
        rig.read(timeout=2.0)
    assert len(events) == 1 and events[0].startswith(f"serial link lost ({path}: ")
    rig.stop()


def test_a_missing_port_is_one_clear_error(tmp_path):
    with pytest.raises(RigError, match="cannot open serial port .*nope"):
        SerialRig(str(tmp_path / "nope"))


def test_serial_rig_retries_then_gives_up(pty):
    master, path = pty
    events: list[str] = []
    rig = SerialRig(path, give_up_after=0.3, on_event=events.append)
    rig.start()
    os.close(master)
    t0 = time.monotonic()
    assert rig.read(timeout=0.1) is None  # meanwhile: no samples, no exception
    with pytest.raises(LinkLost, match="gave up"):
        while time.monotonic() - t0 < 5:
            rig.read(timeout=0.1)
    assert events[0].startswith(f"serial link lost ({path}: ") and events[0].endswith("; retrying")
    assert "gave up" in events[-1]
    rig.stop()


def test_slcan_lines_are_read_in_whole_chunks_not_byte_by_byte():
    """python-can 4.6.1 reads SLCAN one byte per system call (a core at 1 kHz); CanRig's bus
    reads what the port holds: 100 frames and an error BEL, split across reads as they come."""
    import serial

    from hw.can_rig import ChunkedSlcanBus

    class CountingPort:
        def __init__(self):
            self.port, self.reads = serial.serial_for_url("loop://", timeout=0.01), 0

        @property
        def in_waiting(self):
            return self.port.in_waiting

        def read(self, n):
            self.reads += 1
            return self.port.read(n)

    bus = ChunkedSlcanBus.__new__(ChunkedSlcanBus)  # the read path only: no adapter to open
    bus.serialPortOrig, bus._buffer = CountingPort(), bytearray()
    frames = [f"t1{i % 100:02d}2AABB\r" for i in range(100)]
    bus.serialPortOrig.port.write("".join(frames[:60]).encode() + b"t7" + b"\a")  # a line cut short, then BEL
    lines = [bus._read(0.1) for _ in range(61)]
    bus.serialPortOrig.port.write("".join(frames[60:]).encode())
    lines += [bus._read(0.1) for _ in range(40)]
    assert lines == frames[:60] + ["t7\a"] + frames[60:]
    assert bus.serialPortOrig.reads <= 4  # python-can 4.6.1's own read: 1003, a byte per call
    assert bus._read(0.02) is None  # nothing left: the timeout, not a hang
