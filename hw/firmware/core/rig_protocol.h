/* The wire protocol of docs/protocol.md, version 1: frame layouts, CRC-16/CCITT-FALSE,
 * COBS framing and a stream decoder that behaves like hw.protocol.FrameDecoder byte for
 * byte (same frames accepted, same counts of corrupt frames and discarded bytes).
 *
 * Portable C99, no allocation, no floating-point formatting: it builds for AVR, ARM and
 * the host alike. All multi-byte fields are little-endian on the wire, whatever the CPU. */
#ifndef RIG_PROTOCOL_H
#define RIG_PROTOCOL_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" { /* the boards' sketches are C++ */
#endif

#define RIG_PROTOCOL_VERSION 1

/* frame types (type byte first) */
enum {
    RIG_START = 0x01, RIG_STOP = 0x02, RIG_COMMAND = 0x03, RIG_HEARTBEAT = 0x04,
    RIG_SAMPLE = 0x81, RIG_ERROR = 0x82, RIG_STATUS = 0x83
};

/* payload lengths, type byte included */
enum {
    RIG_LEN_START = 1, RIG_LEN_STOP = 1, RIG_LEN_COMMAND = 9, RIG_LEN_HEARTBEAT = 5,
    RIG_LEN_SAMPLE = 39, RIG_LEN_ERROR = 14, RIG_LEN_STATUS = 15
};

#define RIG_MAX_PAYLOAD (RIG_LEN_SAMPLE + 2)            /* the longest frame and its CRC */
#define RIG_MAX_ENCODED (RIG_MAX_PAYLOAD + 1)           /* COBS adds one byte per 254 */
#define RIG_MAX_WIRE (RIG_MAX_ENCODED + 2)              /* with both delimiters */

/* status bits of SAMPLE and STATUS frames */
enum {
    RIG_ST_RUNNING = 0x01, RIG_ST_WATCHDOG = 0x02, RIG_ST_CMD_CLIPPED = 0x04, RIG_ST_SOFT_LIMIT = 0x08,
    RIG_ST_SUPPLY_FAULT = 0x10, RIG_ST_OVERRUN = 0x20, RIG_ST_TX_OVERFLOW = 0x40
};

/* error codes of ERROR frames */
enum {
    RIG_ERR_WATCHDOG = 1, RIG_ERR_BAD_COMMAND = 2, RIG_ERR_SOFT_LIMIT = 3, RIG_ERR_SUPPLY = 4,
    RIG_ERR_OVERRUN = 5, RIG_ERR_TX_OVERFLOW = 6, RIG_ERR_RX_CORRUPT = 7, RIG_ERR_INTERNAL = 8,
    RIG_ERR_CODES = 9 /* one past the last */
};

typedef struct {
    uint32_t seq;
    uint64_t t_us;
    float x, p1, p2, ps; /* m, Pa absolute; ps NaN when not measured */
    float u_applied;
    uint16_t status;
    uint32_t cmd_seq;
} rig_sample_frame;

/* any decoded frame: `type` says which fields are set */
typedef struct {
    uint8_t type;
    uint32_t seq;      /* COMMAND, HEARTBEAT, SAMPLE, STATUS */
    float u;           /* COMMAND */
    uint8_t code;      /* ERROR */
    int32_t value;     /* ERROR */
    uint64_t t_us;     /* SAMPLE, ERROR, STATUS */
    uint16_t status;   /* SAMPLE, STATUS */
    rig_sample_frame sample; /* SAMPLE */
} rig_frame;

uint16_t rig_crc16(const uint8_t *data, size_t n);

/* COBS: encode n bytes into out (room for n + n/254 + 1); returns the encoded length */
size_t rig_cobs_encode(const uint8_t *in, size_t n, uint8_t *out);
/* decode in place is not allowed; returns the decoded length, or -1 when malformed */
int rig_cobs_decode(const uint8_t *in, size_t n, uint8_t *out, size_t out_size);

/* payloads (type byte first, no CRC); each returns its length */
size_t rig_pack_sample(const rig_sample_frame *f, uint8_t *out);
size_t rig_pack_error(uint8_t code, uint64_t t_us, int32_t value, uint8_t *out);
size_t rig_pack_status(uint32_t seq, uint64_t t_us, uint16_t status, uint8_t *out);
size_t rig_pack_command(uint32_t seq, float u, uint8_t *out);
size_t rig_pack_simple(uint8_t type, uint32_t seq, uint8_t *out); /* START, STOP, HEARTBEAT */
/* any frame back into its payload (the inverse of rig_unpack) */
size_t rig_pack(const rig_frame *f, uint8_t *out);

/* payload -> frame; 0 on success, -1 for an unknown type or a wrong length */
int rig_unpack(const uint8_t *payload, size_t n, rig_frame *f);

/* wire bytes of a payload: 0x00 | COBS(payload | CRC-16 LE) | 0x00; returns the length
 * (at most RIG_MAX_WIRE for the protocol's frames) */
size_t rig_encode(const uint8_t *payload, size_t n, uint8_t *out);

/* Bytes in, intact frames out; never fails on bad input, counts what it rejects.
 * Chunks between 0x00 delimiters are COBS-decoded and must carry a matching CRC, a known
 * type and that type's length; the bytes before the first delimiter are dropped unjudged. */
typedef struct {
    uint8_t buf[RIG_MAX_ENCODED];
    uint8_t len;
    uint8_t synced;
    uint8_t overlong;
    uint32_t frames_ok, frames_corrupt, bytes_discarded;
} rig_decoder;

void rig_decoder_init(rig_decoder *d);
/* one byte; returns 1 and fills *f when it completed an intact frame */
int rig_decoder_byte(rig_decoder *d, uint8_t byte, rig_frame *f);

#ifdef __cplusplus
}
#endif

#endif
