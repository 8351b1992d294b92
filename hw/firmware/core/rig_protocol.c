/* The wire protocol of docs/protocol.md (see rig_protocol.h). */
#include "rig_protocol.h"

#include <string.h>

/* ------------------------------------------------------------------ little-endian fields */

static void put_u16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
}

static void put_u32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
    p[2] = (uint8_t)(v >> 16);
    p[3] = (uint8_t)(v >> 24);
}

static void put_u64(uint8_t *p, uint64_t v)
{
    put_u32(p, (uint32_t)v);
    put_u32(p + 4, (uint32_t)(v >> 32));
}

/* float32 bits through memcpy: no aliasing, and the CPU's byte order does not matter */
static void put_f32(uint8_t *p, float v)
{
    uint32_t bits;
    memcpy(&bits, &v, sizeof bits);
    put_u32(p, bits);
}

static uint16_t get_u16(const uint8_t *p)
{
    return (uint16_t)(p[0] | ((uint16_t)p[1] << 8));
}

static uint32_t get_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

static uint64_t get_u64(const uint8_t *p)
{
    return (uint64_t)get_u32(p) | ((uint64_t)get_u32(p + 4) << 32);
}

static float get_f32(const uint8_t *p)
{
    uint32_t bits = get_u32(p);
    float v;
    memcpy(&v, &bits, sizeof v);
    return v;
}

/* ------------------------------------------------------------------ CRC and COBS */

uint16_t rig_crc16(const uint8_t *data, size_t n)
{
    uint16_t crc = 0xFFFF; /* CCITT-FALSE: poly 0x1021, no reflection, no final XOR */
    size_t i;
    uint8_t bit;
    for (i = 0; i < n; i++) {
        crc ^= (uint16_t)((uint16_t)data[i] << 8);
        for (bit = 0; bit < 8; bit++)
            crc = (crc & 0x8000u) ? (uint16_t)((crc << 1) ^ 0x1021u) : (uint16_t)(crc << 1);
    }
    return crc;
}

size_t rig_cobs_encode(const uint8_t *in, size_t n, uint8_t *out)
{
    size_t code_at = 0, o = 1, i;
    uint8_t code = 1;
    for (i = 0; i < n; i++) {
        if (in[i] == 0) {
            out[code_at] = code;
            code_at = o++;
            code = 1;
        } else {
            out[o++] = in[i];
            if (++code == 0xFF && i + 1 < n) { /* a full block of 254: no zero implied */
                out[code_at] = code;
                code_at = o++;
                code = 1;
            }
        }
    }
    out[code_at] = code;
    return o;
}

int rig_cobs_decode(const uint8_t *in, size_t n, uint8_t *out, size_t out_size)
{
    size_t i = 0, o = 0, end;
    uint8_t code;
    if (n == 0)
        return 0;
    for (;;) {
        code = in[i];
        if (code == 0)
            return -1;
        i++;
        end = i + code - 1;
        if (end > n)
            return -1; /* the code points past the end */
        for (; i < end; i++) {
            if (in[i] == 0 || o >= out_size)
                return -1;
            out[o++] = in[i];
        }
        if (i >= n)
            break;
        if (code < 0xFF) {
            if (o >= out_size)
                return -1;
            out[o++] = 0;
        }
    }
    return (int)o;
}

/* ------------------------------------------------------------------ payloads */

size_t rig_pack_sample(const rig_sample_frame *f, uint8_t *out)
{
    out[0] = RIG_SAMPLE;
    put_u32(out + 1, f->seq);
    put_u64(out + 5, f->t_us);
    put_f32(out + 13, f->x);
    put_f32(out + 17, f->p1);
    put_f32(out + 21, f->p2);
    put_f32(out + 25, f->ps);
    put_f32(out + 29, f->u_applied);
    put_u16(out + 33, f->status);
    put_u32(out + 35, f->cmd_seq);
    return RIG_LEN_SAMPLE;
}

size_t rig_pack_error(uint8_t code, uint64_t t_us, int32_t value, uint8_t *out)
{
    out[0] = RIG_ERROR;
    out[1] = code;
    put_u64(out + 2, t_us);
    put_u32(out + 10, (uint32_t)value);
    return RIG_LEN_ERROR;
}

size_t rig_pack_status(uint32_t seq, uint64_t t_us, uint16_t status, uint8_t *out)
{
    out[0] = RIG_STATUS;
    put_u32(out + 1, seq);
    put_u64(out + 5, t_us);
    put_u16(out + 13, status);
    return RIG_LEN_STATUS;
}

size_t rig_pack_command(uint32_t seq, float u, uint8_t *out)
{
    out[0] = RIG_COMMAND;
    put_u32(out + 1, seq);
    put_f32(out + 5, u);
    return RIG_LEN_COMMAND;
}

size_t rig_pack_simple(uint8_t type, uint32_t seq, uint8_t *out)
{
    out[0] = type;
    if (type == RIG_HEARTBEAT) {
        put_u32(out + 1, seq);
        return RIG_LEN_HEARTBEAT;
    }
    return 1;
}

size_t rig_pack(const rig_frame *f, uint8_t *out)
{
    switch (f->type) {
    case RIG_COMMAND:
        return rig_pack_command(f->seq, f->u, out);
    case RIG_SAMPLE:
        return rig_pack_sample(&f->sample, out);
    case RIG_ERROR:
        return rig_pack_error(f->code, f->t_us, f->value, out);
    case RIG_STATUS:
        return rig_pack_status(f->seq, f->t_us, f->status, out);
    default:
        return rig_pack_simple(f->type, f->seq, out);
    }
}

static size_t frame_length(uint8_t type)
{
    switch (type) {
    case RIG_START: return RIG_LEN_START;
    case RIG_STOP: return RIG_LEN_STOP;
    case RIG_COMMAND: return RIG_LEN_COMMAND;
    case RIG_HEARTBEAT: return RIG_LEN_HEARTBEAT;
    case RIG_SAMPLE: return RIG_LEN_SAMPLE;
    case RIG_ERROR: return RIG_LEN_ERROR;
    case RIG_STATUS: return RIG_LEN_STATUS;
    default: return 0;
    }
}

int rig_unpack(const uint8_t *p, size_t n, rig_frame *f)
{
    if (n == 0 || frame_length(p[0]) != n)
        return -1;
    memset(f, 0, sizeof *f);
    f->type = p[0];
    switch (f->type) {
    case RIG_COMMAND:
        f->seq = get_u32(p + 1);
        f->u = get_f32(p + 5);
        break;
    case RIG_HEARTBEAT:
        f->seq = get_u32(p + 1);
        break;
    case RIG_SAMPLE:
        f->seq = f->sample.seq = get_u32(p + 1);
        f->t_us = f->sample.t_us = get_u64(p + 5);
        f->sample.x = get_f32(p + 13);
        f->sample.p1 = get_f32(p + 17);
        f->sample.p2 = get_f32(p + 21);
        f->sample.ps = get_f32(p + 25);
        f->sample.u_applied = get_f32(p + 29);
        f->status = f->sample.status = get_u16(p + 33);
        f->sample.cmd_seq = get_u32(p + 35);
        break;
    case RIG_ERROR:
        f->code = p[1];
        f->t_us = get_u64(p + 2);
        f->value = (int32_t)get_u32(p + 10);
        break;
    case RIG_STATUS:
        f->seq = get_u32(p + 1);
        f->t_us = get_u64(p + 5);
        f->status = get_u16(p + 13);
        break;
    default: /* START, STOP: the type is all */
        break;
    }
    return 0;
}

size_t rig_encode(const uint8_t *payload, size_t n, uint8_t *out)
{
    uint8_t raw[RIG_MAX_PAYLOAD];
    uint16_t crc;
    size_t m;
    if (n + 2 > sizeof raw)
        return 0;
    memcpy(raw, payload, n);
    crc = rig_crc16(payload, n);
    put_u16(raw + n, crc);
    out[0] = 0;
    m = rig_cobs_encode(raw, n + 2, out + 1);
    out[m + 1] = 0;
    return m + 2;
}

/* ------------------------------------------------------------------ stream decoder */

void rig_decoder_init(rig_decoder *d)
{
    memset(d, 0, sizeof *d);
}

static int judge(const uint8_t *chunk, size_t n, rig_frame *f)
{
    uint8_t raw[RIG_MAX_ENCODED];
    int m = rig_cobs_decode(chunk, n, raw, sizeof raw);
    if (m < 3)
        return -1;
    if (get_u16(raw + m - 2) != rig_crc16(raw, (size_t)m - 2))
        return -1;
    return rig_unpack(raw, (size_t)m - 2, f);
}

int rig_decoder_byte(rig_decoder *d, uint8_t byte, rig_frame *f)
{
    if (byte != 0) {
        if (!d->synced || d->overlong) {
            d->bytes_discarded++; /* joined mid-frame, or inside a chunk too long to be a frame */
        } else if (d->len < sizeof d->buf) {
            d->buf[d->len++] = byte;
        } else { /* no delimiter in sight: drop, never buffer without bound */
            d->bytes_discarded += (uint32_t)d->len + 1;
            d->frames_corrupt++;
            d->overlong = 1;
            d->len = 0;
        }
        return 0;
    }
    if (!d->synced || d->overlong) {
        d->synced = 1;
        d->overlong = 0;
        return 0;
    }
    if (d->len == 0)
        return 0; /* idle fill, or the leading delimiter of the next frame */
    if (judge(d->buf, d->len, f) == 0) {
        d->frames_ok++;
        d->len = 0;
        return 1;
    }
    d->frames_corrupt++;
    d->bytes_discarded += d->len;
    d->len = 0;
    return 0;
}
