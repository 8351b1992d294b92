/* The firmware core's rules, tick by tick on a simulated clock (no timer, no plant): the
 * watchdog, command bounds, soft stroke limits, sensor scaling and faults, the error
 * reports and the transmit buffer, as docs/protocol.md states them. The configuration is
 * the host build's (host/rig_config.h).
 *
 *     build/test-core      -> "test-core: N passed, M failed"; exit status 1 when any failed */
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "rig_config.h"
#include "rig_config_init.h"
#include "rig_core.h"

static int passed, failed;
#define CHECK(cond) check((cond), __LINE__, #cond)

static void check(int ok, int line, const char *what)
{
    if (ok) {
        passed++;
    } else {
        failed++;
        printf("test_core.c:%d: %s\n", line, what);
    }
}

/* ------------------------------------------------------------------ the fake hardware */

static uint8_t tx[4096];
static size_t tx_len, tx_limit = sizeof tx;
static uint16_t valve;

void hal_wait_tick(rig_tick_info *tick) { memset(tick, 0, sizeof *tick); }
int hal_read_sensors(rig_counts *counts) { memset(counts, 0, sizeof *counts); return RIG_SENSORS_FAILED; }
size_t hal_serial_read(uint8_t *buf, size_t n) { (void)buf; (void)n; return 0; }
size_t hal_serial_room(void) { return tx_limit - tx_len; }
void hal_serial_flush(void) {}
void hal_tick_done(const rig_tick_report *report) { (void)report; }
void hal_valve_write(uint16_t out) { valve = out; }

void hal_serial_write(const uint8_t *buf, size_t n)
{
    memcpy(tx + tx_len, buf, n);
    tx_len += n;
}

/* ------------------------------------------------------------------ helpers */

static const rig_config CONFIG = RIG_CONFIG_INIT;
static rig_state rig;

/* what one tick sent */
static rig_frame out[16];
static int n_out;

static rig_counts at(float x, float p1, float p2, float ps)
{
    rig_counts c;
    c.x = (uint16_t)(RIG_X_ZERO_COUNTS + x / RIG_STROKE_M * RIG_X_SPAN_COUNTS + 0.5f);
    c.p1 = (uint16_t)(RIG_P1_ZERO_COUNTS + (p1 - RIG_ATMOSPHERE_PA) / RIG_P1_FULL_SCALE_PA * RIG_P1_SPAN_COUNTS + 0.5f);
    c.p2 = (uint16_t)(RIG_P2_ZERO_COUNTS + (p2 - RIG_ATMOSPHERE_PA) / RIG_P2_FULL_SCALE_PA * RIG_P2_SPAN_COUNTS + 0.5f);
    c.ps = (uint16_t)(RIG_PS_ZERO_COUNTS + (ps - RIG_ATMOSPHERE_PA) / RIG_PS_FULL_SCALE_PA * RIG_PS_SPAN_COUNTS + 0.5f);
    return c;
}

static rig_counts mid(void) { return at(0.05f, 3e5f, 3e5f, 7e5f); }

static void reset(void)
{
    tx_len = 0;
    tx_limit = sizeof tx;
    rig_init(&rig, &CONFIG);
}

static void send_host(const uint8_t *payload, size_t n, uint64_t t_us)
{
    uint8_t wire[RIG_MAX_WIRE];
    rig_receive(&rig, wire, rig_encode(payload, n, wire), t_us);
}

static void command(uint32_t seq, float u, uint64_t t_us)
{
    uint8_t p[RIG_LEN_COMMAND];
    send_host(p, rig_pack_command(seq, u, p), t_us);
}

static void simple(uint8_t type, uint64_t t_us)
{
    uint8_t p[RIG_LEN_HEARTBEAT];
    send_host(p, rig_pack_simple(type, 1, p), t_us);
}

static void tick_with(uint64_t t_us, rig_counts c, uint32_t missed)
{
    rig_tick_info info;
    rig_decoder dec;
    size_t i;
    info.t_us = t_us;
    info.missed = missed;
    info.late_us = missed * 1000u + 500u;
    rig_tick(&rig, &info, &c, 1);
    /* what went out since the last tick: errors about host frames, then the tick's own */
    rig_decoder_init(&dec);
    dec.synced = 1;
    n_out = 0;
    for (i = 0; i < tx_len; i++)
        if (rig_decoder_byte(&dec, tx[i], &out[n_out]) && n_out < 15)
            n_out++;
    tx_len = 0;
}

static void tick(uint64_t t_us) { tick_with(t_us, mid(), 0); }

static const rig_frame *find(uint8_t type)
{
    int i;
    for (i = 0; i < n_out; i++)
        if (out[i].type == type)
            return &out[i];
    return NULL;
}

static const rig_sample_frame *sample(void)
{
    const rig_frame *f = find(RIG_SAMPLE);
    return f ? &f->sample : NULL;
}

/* the ERROR frame of `code` this tick, or NULL */
static const rig_frame *error(uint8_t code)
{
    int i;
    for (i = 0; i < n_out; i++)
        if (out[i].type == RIG_ERROR && out[i].code == code)
            return &out[i];
    return NULL;
}

static void streaming(void)
{
    reset();
    simple(RIG_START, 1000);
    tick(1000);
}

/* ------------------------------------------------------------------ the rules */

static void idle_rig_sends_status_every_100_ms(void)
{
    uint64_t t;
    int statuses = 0;
    reset();
    for (t = 1000; t <= 300000; t += 1000) {
        tick(t);
        CHECK(sample() == NULL);
        statuses += find(RIG_STATUS) != NULL;
    }
    CHECK(statuses == 3);
    CHECK(valve == RIG_VALVE_CENTRE);
}

static void commands_are_latched_at_the_next_tick(void)
{
    streaming();
    CHECK(sample() && sample()->status == RIG_ST_RUNNING && sample()->u_applied == 0.0f && sample()->seq == 1);
    command(1, 0.5f, 1500);
    tick(2000);
    CHECK(sample() && sample()->u_applied == 0.5f && sample()->cmd_seq == 1);
    CHECK(valve == RIG_VALVE_CENTRE + RIG_VALVE_SPAN / 2);
    command(2, -0.25f, 2500);
    tick(3000);
    CHECK(sample() && sample()->u_applied == -0.25f && sample()->cmd_seq == 2 && sample()->seq == 3);
}

static void watchdog_centres_the_valve_after_50_ms_of_silence(void)
{
    uint64_t t;
    streaming();
    command(1, 0.5f, 2000);
    for (t = 2000; t <= 52000; t += 1000) {
        tick(t);
        CHECK(sample() && sample()->u_applied == 0.5f && !(sample()->status & RIG_ST_WATCHDOG));
    }
    tick(53000); /* 51 ms of silence */
    CHECK(sample() && sample()->u_applied == 0.0f && (sample()->status & RIG_ST_WATCHDOG));
    CHECK(error(RIG_ERR_WATCHDOG) && error(RIG_ERR_WATCHDOG)->value == 51);
    CHECK(valve == RIG_VALVE_CENTRE);
    simple(RIG_HEARTBEAT, 54000); /* a heartbeat does not revive a stale command */
    tick(54000);
    CHECK(sample() && sample()->u_applied == 0.0f && (sample()->status & RIG_ST_WATCHDOG));
    CHECK(error(RIG_ERR_WATCHDOG) == NULL); /* one report per trip */
    command(2, 0.25f, 55000); /* only a new command re-arms it */
    tick(55000);
    CHECK(sample() && sample()->u_applied == 0.25f && !(sample()->status & RIG_ST_WATCHDOG));
}

static void heartbeats_keep_the_watchdog_quiet_but_start_does_not(void)
{
    uint64_t t;
    streaming();
    command(1, 0.5f, 2000);
    for (t = 2000; t <= 200000; t += 1000) {
        if (t % 40000 == 0)
            simple(RIG_HEARTBEAT, t);
        tick(t);
        CHECK(sample() && !(sample()->status & RIG_ST_WATCHDOG));
    }
    for (t = 201000; t <= 260000; t += 1000) {
        if (t % 20000 == 0)
            simple(RIG_START, t); /* the host re-sending START while streaming feeds nothing */
        tick(t);
    }
    CHECK(sample() && (sample()->status & RIG_ST_WATCHDOG) && sample()->u_applied == 0.0f);
}

static void commands_beyond_the_bounds_are_bounded_and_reported(void)
{
    const rig_frame *e;
    streaming();
    command(1, 1.7f, 2000);
    tick(2000);
    CHECK(sample() && sample()->u_applied == 1.0f && (sample()->status & RIG_ST_CMD_CLIPPED));
    CHECK(valve == RIG_VALVE_CENTRE + RIG_VALVE_SPAN);
    e = error(RIG_ERR_BAD_COMMAND);
    CHECK(e && e->value == 1);
    command(2, (float)NAN, 3000);
    tick(3000);
    CHECK(sample() && sample()->u_applied == 0.0f && (sample()->status & RIG_ST_CMD_CLIPPED));
    CHECK(error(RIG_ERR_BAD_COMMAND) == NULL); /* held back: one report per second */
    command(3, -3.0f, 4000);
    tick(4000);
    CHECK(sample() && sample()->u_applied == -1.0f && (sample()->status & RIG_ST_CMD_CLIPPED));
    command(4, 0.5f, 5000);
    tick(5000);
    CHECK(sample() && sample()->u_applied == 0.5f && sample()->status == RIG_ST_RUNNING);
    for (uint64_t t = 6000; t <= 1010000; t += 1000) {
        command((uint32_t)(t / 1000), 0.5f, t);
        tick(t);
        if (error(RIG_ERR_BAD_COMMAND))
            break;
    }
    e = error(RIG_ERR_BAD_COMMAND);
    CHECK(e && e->value == 2 && e->t_us == 1002000); /* the held-back two, once the second is over */
}

static void soft_limits_stop_commands_into_an_end_zone(void)
{
    const rig_frame *e;
    streaming();
    command(1, -0.5f, 2000);
    tick_with(2000, at(0.002f, 3e5f, 3e5f, 7e5f), 0); /* 2 mm: inside the 3 mm end zone */
    CHECK(sample() && sample()->u_applied == 0.0f && (sample()->status & RIG_ST_SOFT_LIMIT));
    e = error(RIG_ERR_SOFT_LIMIT);
    CHECK(e && e->value >= 1998 && e->value <= 2002);
    tick_with(3000, at(0.0019f, 3e5f, 3e5f, 7e5f), 0);
    CHECK(sample() && (sample()->status & RIG_ST_SOFT_LIMIT) && error(RIG_ERR_SOFT_LIMIT) == NULL);
    command(2, 0.5f, 4000); /* out of the zone: allowed */
    tick_with(4000, at(0.0019f, 3e5f, 3e5f, 7e5f), 0);
    CHECK(sample() && sample()->u_applied == 0.5f && !(sample()->status & RIG_ST_SOFT_LIMIT));
    tick_with(5000, at(0.098f, 3e5f, 3e5f, 7e5f), 0); /* the other end */
    CHECK(sample() && sample()->u_applied == 0.0f && (sample()->status & RIG_ST_SOFT_LIMIT));
    CHECK(valve == RIG_VALVE_CENTRE);
}

static void readings_are_scaled_with_the_calibration(void)
{
    rig_counts c;
    streaming();
    c.x = 3000 + 29000; /* half the span: half the stroke */
    c.p1 = (uint16_t)(RIG_P1_ZERO_COUNTS + 0.25f * RIG_P1_SPAN_COUNTS); /* 2.5 bar gauge */
    c.p2 = (uint16_t)RIG_P2_ZERO_COUNTS; /* vented */
    c.ps = (uint16_t)(RIG_PS_ZERO_COUNTS + RIG_PS_SPAN_COUNTS * 0.375f); /* 6 bar gauge */
    tick_with(2000, c, 0);
    CHECK(sample() != NULL);
    if (sample()) {
        CHECK(fabsf(sample()->x - 0.05f) < 1e-7f);
        CHECK(fabsf(sample()->p1 - (RIG_ATMOSPHERE_PA + 2.5e5f)) < 25.0f);
        CHECK(fabsf(sample()->p2 - RIG_ATMOSPHERE_PA) < 0.5f);
        CHECK(fabsf(sample()->ps - (RIG_ATMOSPHERE_PA + 6e5f)) < 35.0f);
    }
}

static void a_broken_sensor_stops_the_rig(void)
{
    rig_counts c = mid();
    const rig_frame *e;
    streaming();
    command(1, 0.5f, 2000);
    c.p1 = 100; /* below 0.25 V: a broken wire */
    tick_with(2000, c, 0);
    CHECK(sample() == NULL && valve == RIG_VALVE_CENTRE);
    e = error(RIG_ERR_INTERNAL);
    CHECK(e && e->value == 2);
    simple(RIG_START, 3000); /* the host asks again while the wire is still broken */
    tick_with(3000, c, 0);
    CHECK(sample() == NULL && valve == RIG_VALVE_CENTRE);
    simple(RIG_START, 4000); /* mended */
    tick(4000);
    CHECK(sample() && sample()->u_applied == 0.0f); /* the old command is gone */
}

static void a_full_transmit_buffer_drops_samples_and_says_so(void)
{
    const rig_frame *e;
    streaming();
    tx_limit = 50; /* room for one error frame, not for a sample and the error reserve */
    tick(2000);
    CHECK(sample() == NULL && rig.stats.frames_dropped == 1 && rig.stats.samples_dropped == 1);
    command(1, 2.0f, 3000); /* error frames still go out */
    tick(3000);
    e = error(RIG_ERR_TX_OVERFLOW);
    CHECK(error(RIG_ERR_BAD_COMMAND) != NULL && e && e->value == 1 && sample() == NULL);
    CHECK(rig.stats.frames_dropped == 2);
    tx_limit = sizeof tx;
    tick(4000);
    CHECK(sample() && (sample()->status & RIG_ST_TX_OVERFLOW)); /* the second drop, reported in a second */
    CHECK(error(RIG_ERR_TX_OVERFLOW) == NULL);
    tick(5000);
    CHECK(sample() && !(sample()->status & RIG_ST_TX_OVERFLOW));
}

static void corrupted_host_frames_are_rejected_and_counted(void)
{
    uint8_t p[RIG_LEN_COMMAND], wire[RIG_MAX_WIRE];
    size_t n;
    const rig_frame *e;
    streaming();
    command(1, 0.25f, 1500);
    tick(2000);
    n = rig_encode(p, rig_pack_command(2, 0.9f, p), wire);
    wire[7] ^= 0x10; /* a bit of the command's float */
    rig_receive(&rig, wire, n, 2500);
    rig_receive(&rig, (const uint8_t *)"\x13\x37\x00\x42\x00", 5, 2600); /* line noise */
    tick(3000);
    CHECK(sample() && sample()->u_applied == 0.25f && sample()->cmd_seq == 1);
    e = error(RIG_ERR_RX_CORRUPT);
    CHECK(e && e->value == 3 && rig.decoder.frames_corrupt == 3); /* the command, and two chunks of noise */
    command(3, -0.5f, 3500); /* the next intact frame is taken */
    tick(4000);
    CHECK(sample() && sample()->u_applied == -0.5f);
}

static void stop_centres_the_valve_and_ends_streaming(void)
{
    streaming();
    command(1, 0.5f, 2000);
    tick(2000);
    simple(RIG_STOP, 3000);
    tick(3000);
    CHECK(sample() == NULL && find(RIG_STATUS) != NULL && valve == RIG_VALVE_CENTRE);
    simple(RIG_START, 4000); /* a new START does not bring the old command back */
    tick(4000);
    CHECK(sample() && sample()->u_applied == 0.0f);
}

static void a_missed_deadline_is_flagged_and_reported(void)
{
    const rig_frame *e;
    streaming();
    tick_with(4000, mid(), 2);
    CHECK(sample() && (sample()->status & RIG_ST_OVERRUN) && sample()->seq == 2);
    e = error(RIG_ERR_OVERRUN);
    CHECK(e && e->value == 2500);
}

static void low_supply_pressure_is_flagged_and_reported(void)
{
    const rig_frame *e;
    streaming();
    tick_with(2000, at(0.05f, 3e5f, 3e5f, 2e5f), 0);
    CHECK(sample() && (sample()->status & RIG_ST_SUPPLY_FAULT));
    e = error(RIG_ERR_SUPPLY);
    CHECK(e && e->value > 199000 && e->value < 201000);
    tick_with(3000, at(0.05f, 3e5f, 3e5f, 2e5f), 0);
    CHECK(sample() && (sample()->status & RIG_ST_SUPPLY_FAULT) && error(RIG_ERR_SUPPLY) == NULL);
    tick(4000);
    CHECK(sample() && !(sample()->status & RIG_ST_SUPPLY_FAULT));
}

int main(void)
{
    CHECK(rig_config_check(&CONFIG) == 0);
    idle_rig_sends_status_every_100_ms();
    commands_are_latched_at_the_next_tick();
    watchdog_centres_the_valve_after_50_ms_of_silence();
    heartbeats_keep_the_watchdog_quiet_but_start_does_not();
    commands_beyond_the_bounds_are_bounded_and_reported();
    soft_limits_stop_commands_into_an_end_zone();
    readings_are_scaled_with_the_calibration();
    a_broken_sensor_stops_the_rig();
    a_full_transmit_buffer_drops_samples_and_says_so();
    corrupted_host_frames_are_rejected_and_counted();
    stop_centres_the_valve_and_ends_streaming();
    a_missed_deadline_is_flagged_and_reported();
    low_supply_pressure_is_flagged_and_reported();
    printf("test-core: %d passed, %d failed\n", passed, failed);
    return failed ? 1 : 0;
}
