"""Golden vectors of the wire protocol, made by the Python implementation (hw.protocol) and
checked against the C one (hw/firmware/test/test_protocol.c) by tests/test_firmware.py.

    PYTHONPATH=. python tests/firmware_golden.py     # rewrites tests/data/firmware_golden.txt

One vector a line, fields separated by spaces, bytes in hex ('-' for none):
    CRC    data crc16                  CRC-16/CCITT-FALSE of data (4 hex digits)
    COBS   data encoded                COBS of data, and back
    FRAME  payload wire                a frame's payload (type byte first) and its wire bytes
    STREAM bytes ok corrupt discarded payloads
                                       what a decoder makes of a byte stream: the intact
                                       frames (comma-separated payloads) and its counters
"""
from __future__ import annotations

import math
import random
from pathlib import Path

from cobs import cobs

from hw.protocol import (MAX_ENCODED, Command, ErrorCode, ErrorFrame, FrameDecoder, Heartbeat, SampleFrame, Start,
                         StatusFrame, Stop, crc16, encode, pack)

ROOT = Path(__file__).resolve().parents[1]
GOLDEN = ROOT / "tests" / "data" / "firmware_golden.txt"


def _hex(b: bytes) -> str:
    return b.hex() if b else "-"


def frames() -> list:
    """One of every frame type, and the edge cases of their fields."""
    out = [Start(), Stop(), Command(1, 0.5), Command(0, 0.0), Command(0xFFFFFFFF, -1.0), Command(7, 1.7),
           Command(8, -3.5), Command(9, math.nan), Command(10, math.inf), Command(11, 1e-40),
           Heartbeat(0), Heartbeat(0xFFFFFFFF),
           SampleFrame(1, 1000, 0.05, 3.5e5, 4.2e5, None, 0.25, 0x01, 1),
           SampleFrame(0xFFFFFFFF, 2**64 - 1, 0.1, 7.013e5, 1.013e5, 7.0e5, -1.0, 0x7F, 0xFFFFFFFF),
           SampleFrame(0, 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 0),
           SampleFrame(123456, 123456789, -0.001, 1e6, 2e5, None, 0.0, 0x0B, 4242),
           StatusFrame(0, 0, 0), StatusFrame(77, 100_000, 0x02), StatusFrame(0xFFFFFFFF, 2**64 - 1, 0xFFFF)]
    out += [ErrorFrame(int(code), 10_000 * int(code), v) for code, v in
            zip(ErrorCode, (51, 3, 2900, 250_000, 1200, 17, 4, 0))]
    out += [ErrorFrame(3, 5, -1500), ErrorFrame(255, 2**63, -2**31), ErrorFrame(0, 0, 2**31 - 1)]
    # commands whose CRC holds a 0x00 byte (low, then high): COBS must stuff the CRC too
    for pick in (lambda c: c & 0xFF == 0, lambda c: c >> 8 == 0):
        out.append(next(Command(s, 0.25) for s in range(1, 1 << 20) if pick(crc16(pack(Command(s, 0.25))))))
    return out


def cobs_cases() -> list[bytes]:
    rng = random.Random(18)
    nonzero = bytes(range(1, 256))
    return [b"", b"\x00", b"\x00\x00", b"\x11\x22\x00\x33", b"\x11\x22\x33\x44", b"\x11\x00\x00\x00",
            nonzero[:253], nonzero[:254], nonzero[:255], nonzero[:254] + b"\x00", nonzero[:254] + b"\x00\x01",
            nonzero[:253] + b"\x00" + nonzero[:3], bytes(range(256)), nonzero * 3,
            bytes(rng.randrange(1, 256) for _ in range(600)),
            bytes(rng.choice((0, 0, rng.randrange(256))) for _ in range(300))]


def streams() -> list[bytes]:
    """Byte streams a decoder must take apart as FrameDecoder does."""
    rng = random.Random(1818)
    cmd, hb, smp = encode(Command(5, 0.75)), encode(Heartbeat(3)), encode(SampleFrame(9, 9000, 0.02, 3e5, 3e5,
                                                                                       None, 0.1, 1, 5))

    def with_crc(payload: bytes) -> bytes:
        raw = payload + crc16(payload).to_bytes(2, "little")
        return b"\x00" + cobs.encode(raw) + b"\x00"

    flipped = bytearray(cmd)
    flipped[6] ^= 0x01  # a bit of the command's float
    crc_hit = bytearray(cmd)
    crc_hit[-2] ^= 0x80  # a bit of the CRC
    noise = bytes(rng.randrange(256) for _ in range(300))
    return [
        cmd,  # one frame
        b"\x11\x22" + cmd,  # garbage before the first delimiter: dropped unjudged
        cmd[1:] + hb,  # joined mid-frame: the first chunk is dropped unjudged, the next decodes
        cmd + cmd + b"\x00\x00\x00" + hb,  # back to back, with idle fill
        b"\x00" + bytes(flipped[1:]) + hb,  # a damaged float: CRC rejects it, the next decodes
        b"\x00" + bytes(crc_hit[1:]) + hb,  # a damaged CRC
        cmd[:7] + cmd,  # a truncated frame, then a whole one
        b"\x00\x09\x01\x02\x00" + cmd,  # COBS code pointing past the end of the chunk
        with_crc(b"\x05") + cmd,  # intact CRC, unknown type
        with_crc(pack(Command(1, 0.5))[:-1]) + cmd,  # intact CRC, known type, wrong length
        b"\x00\x02\x01\x00" + cmd,  # too short to hold a CRC
        b"\x00" + bytes(range(1, 61)) + cmd,  # overlong chunk, then a frame
        bytes(range(1, 101)) + cmd,  # overlong before the first delimiter
        b"\x00" + b"\x07" * MAX_ENCODED + cmd,  # the longest chunk still judged
        b"\x00" + b"\x07" * (MAX_ENCODED + 1) + cmd,  # one byte longer: dropped as overlong
        noise[:150] + smp + noise[150:] + cmd,  # line noise around frames
        smp + encode(ErrorFrame(1, 5, 51)) + encode(StatusFrame(1, 2, 3)) + encode(Start()) + encode(Stop()),
        bytes(rng.choice((0, rng.randrange(256))) for _ in range(400)) + cmd,  # noise full of delimiters
    ]


def decode(data: bytes, chunk: int | None = None) -> tuple[list[bytes], FrameDecoder]:
    dec = FrameDecoder()
    out = []
    step = chunk or max(len(data), 1)
    for i in range(0, len(data), step):
        out += dec.feed(data[i:i + step])
    return [pack(f) for f in out], dec


def vectors() -> str:
    lines = [__doc__.strip().splitlines()[0].join(["# ", ""]), "# made by tests/firmware_golden.py: do not edit"]
    for data in [b"", b"123456789", b"\x00", b"\xff" * 4] + [pack(f) for f in frames()]:
        lines.append(f"CRC {_hex(data)} {crc16(data):04x}")
    for data in cobs_cases():
        lines.append(f"COBS {_hex(data)} {_hex(cobs.encode(data))}")
    for f in frames():
        lines.append(f"FRAME {_hex(pack(f))} {_hex(encode(f))}")
    for data in streams():
        payloads, dec = decode(data)
        lines.append(f"STREAM {_hex(data)} {dec.frames_ok} {dec.frames_corrupt} {dec.bytes_discarded} "
                     f"{','.join(p.hex() for p in payloads) or '-'}")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    GOLDEN.parent.mkdir(exist_ok=True)
    GOLDEN.write_text(vectors())
    print(f"wrote {GOLDEN}")
