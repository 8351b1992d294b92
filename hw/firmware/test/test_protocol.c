/* The C protocol implementation against the golden vectors made by the Python one
 * (tests/firmware_golden.py -> tests/data/firmware_golden.txt):
 *
 *     build/test-protocol ../../tests/data/firmware_golden.txt
 *
 * Prints one line per failing vector and closes with "N passed, M failed"; exit status 1
 * when any failed. */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "rig_protocol.h"

#define MAX_BYTES 4096

static int passed, failed;

static size_t unhex(const char *s, uint8_t *out)
{
    size_t n = 0;
    unsigned v;
    if (!strcmp(s, "-"))
        return 0;
    while (s[0] && s[1] && n < MAX_BYTES && sscanf(s, "%2x", &v) == 1) {
        out[n++] = (uint8_t)v;
        s += 2;
    }
    return n;
}

static void check(int ok, int line, const char *what)
{
    if (ok) {
        passed++;
    } else {
        failed++;
        printf("line %d: %s\n", line, what);
    }
}

static int same(const uint8_t *a, size_t na, const uint8_t *b, size_t nb)
{
    return na == nb && (na == 0 || memcmp(a, b, na) == 0);
}

static void crc_vector(int line, char **f)
{
    static uint8_t data[MAX_BYTES];
    size_t n = unhex(f[1], data);
    check(rig_crc16(data, n) == (uint16_t)strtoul(f[2], NULL, 16), line, "CRC-16 differs");
}

static void cobs_vector(int line, char **f)
{
    static uint8_t data[MAX_BYTES], enc[MAX_BYTES], mine[MAX_BYTES + MAX_BYTES / 254 + 2], back[MAX_BYTES];
    size_t n = unhex(f[1], data), m = unhex(f[2], enc);
    size_t k = rig_cobs_encode(data, n, mine);
    int d = rig_cobs_decode(enc, m, back, sizeof back);
    check(same(mine, k, enc, m), line, "COBS encoding differs");
    check(d >= 0 && same(back, (size_t)d, data, n), line, "COBS decoding differs");
}

static void frame_vector(int line, char **f)
{
    static uint8_t payload[MAX_BYTES], wire[MAX_BYTES];
    uint8_t mine[RIG_MAX_WIRE], again[RIG_MAX_PAYLOAD];
    rig_frame fr;
    size_t n = unhex(f[1], payload), m = unhex(f[2], wire);
    size_t k = rig_encode(payload, n, mine);
    check(same(mine, k, wire, m), line, "wire bytes differ");
    check(rig_unpack(payload, n, &fr) == 0 && same(again, rig_pack(&fr, again), payload, n), line,
          "the payload does not round-trip through the frame's fields");
}

static void stream_vector(int line, char **f)
{
    static uint8_t data[MAX_BYTES], expect[MAX_BYTES];
    uint8_t mine[RIG_MAX_PAYLOAD];
    rig_decoder dec;
    rig_frame fr;
    size_t n = unhex(f[1], data), i, e = 0, k;
    char *payloads = f[5], *tok;
    int ok = 1;
    rig_decoder_init(&dec);
    tok = strcmp(payloads, "-") ? strtok(payloads, ",") : NULL;
    for (i = 0; i < n; i++) {
        if (!rig_decoder_byte(&dec, data[i], &fr))
            continue;
        k = rig_pack(&fr, mine);
        e = tok ? unhex(tok, expect) : 0;
        if (!tok || !same(mine, k, expect, e))
            ok = 0;
        tok = tok ? strtok(NULL, ",") : NULL;
    }
    check(ok && tok == NULL, line, "decoded frames differ");
    check(dec.frames_ok == strtoul(f[2], NULL, 10) && dec.frames_corrupt == strtoul(f[3], NULL, 10)
              && dec.bytes_discarded == strtoul(f[4], NULL, 10),
          line, "decoder counters (ok, corrupt, discarded) differ");
}

int main(int argc, char **argv)
{
    static char buf[3 * MAX_BYTES + 256];
    char *fields[6];
    int line = 0, nf;
    FILE *in;
    if (argc != 2 || !(in = fopen(argv[1], "r"))) {
        fprintf(stderr, "usage: test-protocol GOLDEN.txt (tests/data/firmware_golden.txt)\n");
        return 2;
    }
    while (fgets(buf, sizeof buf, in)) {
        line++;
        if (buf[0] == '#' || buf[0] == '\n')
            continue;
        buf[strcspn(buf, "\n")] = 0;
        for (nf = 0; nf < 6 && (fields[nf] = strtok(nf ? NULL : buf, " ")) != NULL; nf++) {
        }
        if (nf == 3 && !strcmp(fields[0], "CRC"))
            crc_vector(line, fields);
        else if (nf == 3 && !strcmp(fields[0], "COBS"))
            cobs_vector(line, fields);
        else if (nf == 3 && !strcmp(fields[0], "FRAME"))
            frame_vector(line, fields);
        else if (nf == 6 && !strcmp(fields[0], "STREAM"))
            stream_vector(line, fields);
        else
            check(0, line, "not a vector");
    }
    fclose(in);
    printf("test-protocol: %d passed, %d failed\n", passed, failed);
    return failed ? 1 : 0;
}
