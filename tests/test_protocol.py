"""The wire protocol (docs/protocol.md): serial framing, the CAN mapping, the host's bookkeeping."""
import math

import can
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hw.can_mapping import SAMPLE_IDS, CanCodec, SampleAssembler, load_dbc
from hw.protocol import (MAX_ENCODED, Command, ErrorFrame, EventLimiter, FrameDecoder, Heartbeat, HostSession,
                         SampleFrame, Start, StatusFrame, Stop, crc16, encode, pack, unpack)
from hw.rig import Status

# deterministic examples: a random corruption passes CRC-16 with probability 2^-16, which
# a randomised run would eventually hit; these properties are about everything else
PROPS = settings(derandomize=True, max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])

u32 = st.integers(0, 2**32 - 1)
f32 = st.floats(width=32, allow_nan=False)
commands = st.builds(Command, seq=u32, u=f32)
samples = st.builds(SampleFrame, seq=u32, t_us=st.integers(0, 2**64 - 1), x=f32, p1=f32, p2=f32,
                    ps=st.none() | f32, u_applied=f32, status=st.integers(0, 0xFFFF), cmd_seq=u32)
errors = st.builds(ErrorFrame, code=st.integers(0, 255), t_us=st.integers(0, 2**64 - 1),
                   value=st.integers(-2**31, 2**31 - 1))
statuses = st.builds(StatusFrame, seq=u32, t_us=st.integers(0, 2**64 - 1), status=st.integers(0, 0xFFFF))
frames = st.one_of(st.just(Start()), st.just(Stop()), commands, st.builds(Heartbeat, seq=u32), samples, errors,
                   statuses)


def decode_all(data: bytes, chunks: list[int] | None = None) -> tuple[list, FrameDecoder]:
    dec = FrameDecoder()
    out = []
    if chunks is None:
        out = dec.feed(data)
    else:
        pos = 0
        for n in chunks:
            out += dec.feed(data[pos:pos + n])
            pos += n
        out += dec.feed(data[pos:])
    return out, dec


def test_crc_is_ccitt_false():
    assert crc16(b"123456789") == 0x29B1  # the catalogue check value of CRC-16/CCITT-FALSE


def test_sample_layout_is_documented_size():
    payload = pack(SampleFrame(1, 2, 0.1, 2e5, 3e5, None, 0.5, 1, 7))
    assert len(payload) == 39 and payload[0] == 0x81
    # docs/protocol.md: SAMPLE 44 bytes, COMMAND 14 bytes on the wire (COBS adds one byte below 254)
    assert len(encode(SampleFrame(1, 2, 0.1, 2e5, 3e5, None, 0.5, 1, 7))) == 44
    assert len(encode(Command(1, 0.5))) == 14
    assert pack(Command(1, 0.5)) == bytes([0x03, 1, 0, 0, 0]) + np.float32(0.5).tobytes()  # little-endian


@PROPS
@given(frames)
def test_every_frame_type_round_trips(frame):
    assert unpack(pack(frame)) == frame
    out, dec = decode_all(encode(frame))
    assert out == [frame]
    assert dec.frames_ok == 1 and dec.frames_corrupt == 0 and dec.bytes_discarded == 0


@PROPS
@given(st.lists(frames, min_size=1, max_size=8), st.data())
def test_garbage_before_and_between_frames_costs_nothing(sent, data):
    stream = b""
    for f in sent:
        stream += data.draw(st.binary(max_size=60), label="garbage") + encode(f)
    splits = data.draw(st.lists(st.integers(0, 30), max_size=20), label="read sizes")
    out, dec = decode_all(stream, splits)
    assert out == sent  # the leading delimiter of each frame ends the garbage before it
    assert dec.frames_ok == len(sent)


@st.composite
def damaged_streams(draw):
    """Encoded frames with bytes flipped, inserted or cut; returns which frames were touched."""
    sent = draw(st.lists(frames, min_size=1, max_size=8))
    parts = [bytearray(encode(f)) for f in sent]
    touched = set()
    for _ in range(draw(st.integers(1, 4))):
        j = draw(st.integers(0, len(parts) - 1))
        part = parts[j]
        kind = draw(st.sampled_from(["flip", "cut", "insert", "cut across"]))
        if not part:
            continue
        i = draw(st.integers(0, len(part) - 1))
        if kind == "flip":
            part[i] = draw(st.integers(0, 255))
        elif kind == "insert":
            part[i:i] = draw(st.binary(min_size=1, max_size=10))
        else:
            del part[i:i + draw(st.integers(1, 50))]
            if kind == "cut across" and j + 1 < len(parts):  # the tail of one frame and the head of the next
                del parts[j + 1][:draw(st.integers(1, 50))]
                touched.add(j + 1)
        touched.add(j)
    return sent, b"".join(parts), touched


@PROPS
@given(damaged_streams(), st.lists(st.integers(0, 40), max_size=10))
def test_corruption_and_truncation_never_yield_a_wrong_frame(case, splits):
    sent, stream, touched = case
    out, dec = decode_all(stream, splits)  # must not raise
    # whatever comes out is what was sent, in order (a subsequence)
    it = iter(sent)
    assert all(any(f == g for g in it) for f in out)
    # and every frame the damage did not touch comes through
    intact = [f for j, f in enumerate(sent) if j not in touched]
    it = iter(out)
    assert all(any(f == g for g in it) for f in intact)
    # every byte is accounted for: a delimiter, part of a frame that came out, discarded and
    # counted, or waiting for its delimiter
    delivered = sum(len(encode(f)) - 2 for f in out)
    assert len(stream) == stream.count(0) + delivered + dec.bytes_discarded + len(dec._buf)


def test_a_corrupted_frame_is_rejected_counted_and_the_next_decodes():
    a, b = SampleFrame(1, 1000, 0.05, 3e5, 3e5, None, 0.1, 1, 1), SampleFrame(2, 2000, 0.05, 3e5, 3e5, None, 0.1, 1, 2)
    bad = bytearray(encode(a))
    bad[10] ^= 0x5A
    out, dec = decode_all(bytes(bad) + encode(b))
    assert out == [unpack(pack(b))]  # b as float32 carries it
    assert dec.frames_corrupt == 1 and dec.bytes_discarded > 0


@PROPS
@given(st.binary(max_size=2000), st.lists(st.integers(0, 300), max_size=10))
def test_random_bytes_never_raise_and_the_buffer_stays_bounded(noise, splits):
    dec = FrameDecoder()
    pos = 0
    for n in splits + [len(noise)]:
        dec.feed(noise[pos:pos + n])
        pos += n
        assert len(dec._buf) <= MAX_ENCODED


def test_a_frame_follows_an_overlong_chunk():
    f = Command(3, 0.25)
    out, dec = decode_all(b"\x00" + b"\x01" * 1000 + encode(f))
    assert out == [f] and dec.frames_corrupt == 1


# ------------------------------------------------------------------ CAN mapping


def test_dbc_loads_with_the_documented_resolution():
    db = load_dbc()
    ids = {m.name: m.frame_id for m in db.messages}
    assert ids == {"RigError": 0x080, "RigCommand": 0x100, "RigControl": 0x101, "RigSampleTime": 0x180,
                   "RigSamplePosition": 0x181, "RigSamplePressure": 0x182, "RigStatus": 0x1F0}
    assert all(m.length <= 8 for m in db.messages)
    sig = {(m.name, s.name): s for m in db.messages for s in m.signals}
    x, p = sig["RigSamplePosition", "X"], sig["RigSamplePressure", "P1"]
    # quantisation (step / sqrt 12) far below the sensor noise (5 um, 300 Pa)
    assert x.scale / math.sqrt(12) < 0.01 * 5e-6
    assert p.scale / math.sqrt(12) < 0.03 * 300.0
    assert p.maximum >= 1.2e6  # 12 bar absolute
    assert sig["RigCommand", "U"].scale <= 1e-4


def test_dbc_signals_fit_their_frames_and_their_ranges_fit_their_bits():
    """CanCodec saturates values at the signal ranges: those must be encodable, without overlaps."""
    for m in load_dbc().messages:
        used = set()
        for s in m.signals:
            assert s.byte_order == "little_endian", (m.name, s.name)
            bits = set(range(s.start, s.start + s.length))  # Intel: start is the least significant bit
            assert not used & bits and max(bits) < 8 * m.length, (m.name, s.name)
            used |= bits
            raw_lo, raw_hi = ((-(1 << (s.length - 1)), (1 << (s.length - 1)) - 1) if s.is_signed
                              else (0, (1 << s.length) - 1))
            tol = 1e-9 * max(abs(s.minimum), abs(s.maximum), 1.0)
            assert raw_lo * s.scale + s.offset <= s.minimum + tol, (m.name, s.name)
            assert s.maximum - tol <= raw_hi * s.scale + s.offset, (m.name, s.name)
    codec = CanCodec()
    assert codec.quantise_u(5.0) == 1.0 and codec.quantise_u(-5.0) == -1.0  # U: [-1, 1] as the rig clips


def test_sample_frames_round_trip_through_can_within_resolution():
    codec = CanCodec()
    asm = SampleAssembler(codec)
    rng = np.random.default_rng(0)
    for k in range(300):
        f = SampleFrame(seq=1000 + k, t_us=2**32 - 150_000 + 1000 * k, x=float(rng.uniform(-0.01, 0.5)),
                        p1=float(rng.uniform(1e5, 1e6)), p2=float(rng.uniform(1e5, 1e6)),
                        ps=None if k % 2 else 7e5, u_applied=float(rng.uniform(-1, 1)),
                        status=int(Status.RUNNING | Status.WATCHDOG), cmd_seq=70_000 + k)
        msgs = codec.rig_messages(f)
        assert [m.arbitration_id for m in msgs] == list(SAMPLE_IDS) and all(m.dlc == 8 for m in msgs)
        got = [g for m in msgs[::-1] for g in asm.feed(m)]  # parts in any order
        assert len(got) == 1
        g = got[0]
        assert g.seq == f.seq & 0xFF and g.t_us == f.t_us & 0xFFFFFFFF and g.cmd_seq == f.cmd_seq & 0xFFFF
        assert abs(g.x - f.x) <= 5e-9 + 1e-15 and abs(g.p1 - f.p1) <= 10 and abs(g.p2 - f.p2) <= 10
        assert abs(g.u_applied - f.u_applied) <= 5e-5 and g.status == f.status
        assert (g.ps is None) == (f.ps is None)
    # out-of-range values saturate instead of wrapping
    big = codec.rig_messages(SampleFrame(1, 0, 30.0, 2e6, -5.0, None, 3.0, 0, 0))
    g = [x for m in big for x in asm.feed(m)][0]
    assert g.x == pytest.approx(21.47483647) and g.p1 == pytest.approx(1310700) and g.p2 == 0 and g.u_applied == 1.0


def test_host_frames_round_trip_through_can():
    codec = CanCodec()
    for f in (Start(), Stop(), Heartbeat(7), Command(65_537, -0.25)):
        (msg,) = codec.host_messages(f)
        back = codec.host_frame(msg)
        assert back == (Command(1, -0.25) if isinstance(f, Command) else f)
    assert codec.quantise_u(0.123456) == pytest.approx(0.1235, abs=1e-12)
    assert codec.host_frame(can.Message(arbitration_id=0x100, data=b"\x01")) is None  # wrong length


def test_samples_reassemble_over_a_virtual_bus_and_losses_are_counted():
    codec = CanCodec()
    with can.Bus(channel="proto-test", interface="virtual") as rig_bus, \
            can.Bus(channel="proto-test", interface="virtual") as host_bus:
        n, lost_part = 600, 300  # more than 256: the 8-bit sequence wraps
        for k in range(n):
            f = SampleFrame(k, 1000 * k, 0.05, 3e5, 2e5, None, 0.1, int(Status.RUNNING), k)
            for i, msg in enumerate(codec.rig_messages(f)):
                if not (k == lost_part and i == 1):
                    rig_bus.send(msg)
        rig_bus.send(codec.rig_messages(ErrorFrame(1, 0, 51))[0])
        asm = SampleAssembler(codec)
        session = HostSession("CAN", EventLimiter(), seq_bits=8, t_bits=32)
        got, errs = [], []
        while (msg := host_bus.recv(0.5)) is not None:
            for f in asm.feed(msg):
                if isinstance(f, SampleFrame):
                    got.append(session.sample(f.seq, f.t_us, f.x, f.p1, f.p2, f.ps, f.u_applied, f.status,
                                              f.cmd_seq))
                else:
                    errs.append(f)
    assert [s.seq for s in got] == [k for k in range(n) if k != lost_part]
    assert asm.incomplete == 1 and session.samples_lost == 1
    assert got[-1].t == pytest.approx((n - 1) * 1e-3) and got[0].status == 0  # RUNNING is stripped
    assert errs == [ErrorFrame(1, 0, 51)]


# ------------------------------------------------------------------ host bookkeeping


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def feed(session, clock, seq, t_us, cmd_seq=0, status=1):
    return session.sample(seq, t_us, 0.05, 3e5, 3e5, None, 0.0, status, cmd_seq)


def test_narrow_sequence_numbers_unwrap_with_the_clock():
    clock = Clock()
    s = HostSession("CAN", EventLimiter(clock=clock), seq_bits=8, t_bits=32, clock=clock)
    out = []
    for k in list(range(100)) + list(range(700, 800)):  # a gap of 600 samples: more than 2 wraps
        clock.t = k * 1e-3
        out.append(feed(s, clock, k & 0xFF, (1000 * k + 2**32 - 50_000) & 0xFFFFFFFF))
    assert [o.seq for o in out] == list(range(100)) + list(range(700, 800))
    assert s.samples_lost == 600
    assert np.all(np.diff([o.t for o in out]) > 0)  # the 32-bit microsecond clock wrapped too


def test_a_restarted_rig_does_not_send_time_backwards_and_start_resets_the_gap():
    clock = Clock()
    ev = EventLimiter(clock=clock)
    s = HostSession("serial", ev, clock=clock)
    for k in range(10):
        clock.t = k * 1e-3
        feed(s, clock, 5000 + k, 9_000_000 + 1000 * k)
    s.link_lost("gone", retrying=True)
    clock.t += 2.0
    a = feed(s, clock, 3, 50_000)  # the new rig starts from scratch
    b = feed(s, clock, 4, 51_000)
    assert a.t > 9.009 and b.t - a.t == pytest.approx(1e-3)
    assert 1900 < s.samples_lost < 2100  # estimated from the outage
    lines = ev.pop_lines()
    assert lines[0] == "serial link lost (gone); retrying"
    assert lines[1].startswith("serial link back after 2.0 s; about ")
    s.restart()  # START: a gap to the samples before it is no loss
    lost = s.samples_lost
    feed(s, clock, 500, 600_000)
    assert s.samples_lost == lost


def test_late_replies_are_counted():
    clock = Clock()
    s = HostSession("serial", EventLimiter(clock=clock), clock=clock)
    feed(s, clock, 1, 1000, cmd_seq=0)
    s.command_sent(1, reply_to=1)
    feed(s, clock, 2, 2000, cmd_seq=1)  # latched at the next tick: in time
    s.command_sent(2, reply_to=2)
    feed(s, clock, 3, 3000, cmd_seq=1)  # missed tick 3
    feed(s, clock, 4, 4000, cmd_seq=2)
    s.command_sent(3, reply_to=3)  # sample 4 already here: late for sure
    assert s.commands_late == 2


def test_event_limiter_sums_and_rate_limits():
    clock = Clock()
    ev = EventLimiter(clock=clock)
    for _ in range(3):
        ev.count("c", 1, "serial link: {n} corrupted frame{s} rejected in the last second")
    ev.say("w", "rig reports watchdog")
    ev.say("w", "rig reports watchdog")
    ev.flush()
    assert ev.pop_lines() == ["rig reports watchdog"]
    clock.t = 1.0
    ev.flush()
    ev.say("w", "rig reports watchdog")
    assert ev.pop_lines() == ["serial link: 3 corrupted frames rejected in the last second",
                              "rig reports watchdog (1 similar message(s) suppressed)"]


def test_a_restarted_rig_whose_clock_is_ahead_is_still_recognised():
    clock = Clock()
    s = HostSession("serial", EventLimiter(clock=clock), clock=clock)
    for k in range(10):
        clock.t = k * 1e-3
        feed(s, clock, 5000 + k, 1_000_000 + 1000 * k)
    s.link_lost("gone", retrying=True)
    clock.t += 1.0
    a = feed(s, clock, 20, 3_000_000)  # new rig: later clock, far smaller counter
    assert 900 < s.samples_lost < 1100 and a.t == pytest.approx(1.009 + 1.0, abs=1e-3)  # + the host's gap


def test_error_lines_name_what_the_rig_reports():
    from hw.protocol import describe_error

    assert describe_error(1, 51) == "watchdog: valve centred after 51 ms of host silence"
    assert describe_error(8, 0) == "internal fault: the rig stopped"
    assert describe_error(8, 3) == "internal fault: the rig stopped (sensor p2 reads outside its range: a broken wire?)"
    assert describe_error(8, 9) == "internal fault: the rig stopped"
    assert describe_error(42, 7) == "unknown error code 42 (value 7)"
