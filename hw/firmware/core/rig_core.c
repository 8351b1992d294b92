/* The rig firmware's logic (see rig_core.h); the reference for its behaviour is the
 * Python virtual rig, hw/rig_server.py (RigCore, ErrorGate, RigServer._tick). */
#include "rig_core.h"

#include <math.h>
#include <string.h>

#define ERROR_INTERVAL_US 1000000u /* at most one ERROR frame per code per second */
#define STATUS_PERIOD_US 100000u   /* STATUS frames while not streaming */
/* room kept free for ERROR frames: they never wait for a full transmit buffer */
#define ERROR_RESERVE (2u * (RIG_LEN_ERROR + 2u + 1u + 2u))

static const uint16_t COUNTED = (1u << RIG_ERR_BAD_COMMAND) | (1u << RIG_ERR_TX_OVERFLOW) | (1u << RIG_ERR_RX_CORRUPT);

/* ------------------------------------------------------------------ configuration */

static rig_channel channel(const rig_calibration *cal, float value_at_zero, float full_scale)
{
    rig_channel ch;
    ch.scale = full_scale / cal->span_counts;
    ch.offset = value_at_zero - cal->zero_counts * ch.scale;
    ch.valid_min = cal->valid_min;
    ch.valid_max = cal->valid_max;
    return ch;
}

int rig_config_check(const rig_config *cfg)
{
    if (cfg->period_us == 0 || cfg->watchdog_us == 0 || !(cfg->stroke > 0.0f))
        return -1;
    if (!(cfg->end_zone >= 0.0f && cfg->end_zone < 0.5f))
        return -1;
    if (cfg->x.span_counts == 0.0f || cfg->p1.span_counts == 0.0f || cfg->p2.span_counts == 0.0f
        || (cfg->has_supply && cfg->ps.span_counts == 0.0f))
        return -1;
    if (cfg->valve_span == 0 || cfg->valve_centre < cfg->valve_span
        || (uint32_t)cfg->valve_centre + cfg->valve_span > cfg->valve_max)
        return -1;
    return 0;
}

static float to_si(const rig_channel *ch, uint16_t counts)
{
    return ch->offset + ch->scale * (float)counts;
}

static uint16_t valve_output(const rig_state *rig, float u)
{
    float v = (float)rig->cfg.valve_centre + u * (float)rig->cfg.valve_span + 0.5f;
    if (v <= 0.0f)
        return 0;
    if (v >= (float)rig->cfg.valve_max)
        return rig->cfg.valve_max;
    return (uint16_t)v;
}

static void latch(rig_state *rig, float u)
{
    rig->valve_out = valve_output(rig, u);
    /* what the valve really holds, in command units (0 exactly at the centre) */
    rig->u_applied = (float)((int32_t)rig->valve_out - (int32_t)rig->cfg.valve_centre) / (float)rig->cfg.valve_span;
    hal_valve_write(rig->valve_out);
}

void rig_init(rig_state *rig, const rig_config *cfg)
{
    memset(rig, 0, sizeof *rig);
    rig->cfg = *cfg;
    rig->ch_x = channel(&cfg->x, 0.0f, cfg->stroke);
    rig->ch_p1 = channel(&cfg->p1, cfg->atmosphere, cfg->p1.full_scale);
    rig->ch_p2 = channel(&cfg->p2, cfg->atmosphere, cfg->p2.full_scale);
    if (cfg->has_supply)
        rig->ch_ps = channel(&cfg->ps, cfg->atmosphere, cfg->ps.full_scale);
    rig->zone_lo = cfg->end_zone * cfg->stroke;
    rig->zone_hi = (1.0f - cfg->end_zone) * cfg->stroke;
    rig_decoder_init(&rig->decoder);
    latch(rig, 0.0f);
}

void rig_halt(rig_state *rig)
{
    rig->running = 0;
    rig->cmd_u = 0.0f;
    rig->cmd_clipped = 0;
    latch(rig, 0.0f);
}

/* ------------------------------------------------------------------ sending */

/* 1 when the frame was queued, 0 when it was dropped for lack of room (and counted) */
static int send_payload(rig_state *rig, const uint8_t *payload, size_t n, int is_error)
{
    uint8_t wire[RIG_MAX_WIRE];
    size_t m = rig_encode(payload, n, wire);
    size_t room = hal_serial_room();
    if (room < m + (is_error ? 0u : ERROR_RESERVE)) {
        rig->tx_dropped++;
        rig->stats.frames_dropped++;
        return 0;
    }
    hal_serial_write(wire, m);
    return 1;
}

static void send_error(rig_state *rig, uint8_t code, uint64_t t_us, int32_t value)
{
    uint8_t p[RIG_LEN_ERROR];
    send_payload(rig, p, rig_pack_error(code, t_us, value, p), 1);
}

/* A fault of `code` (value: its detail, or the number of occurrences for a counting code):
 * reported at its onset, then at most once per second. */
static void report(rig_state *rig, uint8_t code, uint64_t t_us, int32_t value)
{
    uint16_t bit = (uint16_t)(1u << code);
    if (COUNTED & bit) {
        if (rig->err_held_mask & bit)
            value += rig->err_held[code];
        rig->err_held_mask &= (uint16_t)~bit;
    }
    if (!(rig->err_sent_mask & bit) || t_us - rig->err_sent_us[code] >= ERROR_INTERVAL_US) {
        rig->err_sent_mask |= bit;
        rig->err_sent_us[code] = t_us;
        send_error(rig, code, t_us, value);
    } else if (COUNTED & bit) {
        rig->err_held_mask |= bit;
        rig->err_held[code] = value;
    }
}

/* report the counts held back whose second is over */
static void flush_errors(rig_state *rig, uint64_t t_us)
{
    uint8_t code;
    for (code = 0; code < RIG_ERR_CODES && rig->err_held_mask; code++)
        if ((rig->err_held_mask & (1u << code)) && t_us - rig->err_sent_us[code] >= ERROR_INTERVAL_US)
            report(rig, code, t_us, 0);
}

/* ------------------------------------------------------------------ the host's frames */

static float bounded(float u)
{
    if (u != u) /* NaN centres the valve */
        return 0.0f;
    return u > 1.0f ? 1.0f : (u < -1.0f ? -1.0f : u);
}

static void host_frame(rig_state *rig, const rig_frame *f, uint64_t t_us)
{
    switch (f->type) {
    case RIG_COMMAND:
        rig->last_host_us = t_us;
        rig->cmd_u = bounded(f->u); /* never trust the wire */
        rig->cmd_clipped = rig->cmd_u != f->u; /* NaN differs from everything */
        if (rig->cmd_clipped)
            report(rig, RIG_ERR_BAD_COMMAND, t_us, 1);
        rig->cmd_seq = f->seq;
        rig->watchdog = 0; /* only a new command re-arms a tripped watchdog */
        break;
    case RIG_HEARTBEAT:
        rig->last_host_us = t_us;
        break;
    case RIG_START:
        /* only the START that starts streaming feeds the watchdog: a host re-sends START
         * while it sees no samples, which must not keep a stale command alive */
        if (!rig->running) {
            rig->last_host_us = t_us;
            rig->running = 1;
        }
        break;
    case RIG_STOP:
        rig->running = 0;
        rig->cmd_u = 0.0f;
        rig->cmd_clipped = 0;
        break;
    default: /* the rig's own frame types echoed back: ignored */
        break;
    }
}

void rig_receive(rig_state *rig, const uint8_t *data, size_t n, uint64_t t_us)
{
    rig_frame f;
    size_t i;
    for (i = 0; i < n; i++)
        if (rig_decoder_byte(&rig->decoder, data[i], &f))
            host_frame(rig, &f, t_us);
}

/* ------------------------------------------------------------------ the tick */

static int32_t round_i32(float v)
{
    return (int32_t)(v >= 0.0f ? v + 0.5f : v - 0.5f);
}

/* 0, or 1 + the index (x, p1, p2, ps) of the first reading outside its valid range */
static int32_t broken_sensor(const rig_state *rig, const rig_counts *c)
{
    const rig_channel *ch[4];
    uint16_t v[4];
    int32_t i, n = rig->cfg.has_supply ? 4 : 3;
    ch[0] = &rig->ch_x; ch[1] = &rig->ch_p1; ch[2] = &rig->ch_p2; ch[3] = &rig->ch_ps;
    v[0] = c->x; v[1] = c->p1; v[2] = c->p2; v[3] = c->ps;
    for (i = 0; i < n; i++)
        if (v[i] < ch[i]->valid_min || v[i] > ch[i]->valid_max)
            return i + 1;
    return 0;
}

void rig_tick(rig_state *rig, const rig_tick_info *tick, const rig_counts *c, int sensors_ok)
{
    uint64_t t = tick->t_us;
    uint16_t status = 0;
    rig_sample_frame s;
    rig_tick_report rep;
    uint8_t payload[RIG_LEN_SAMPLE];
    float u, x;
    int32_t broken;
    int into;

    rig->stats.ticks++;
    /* what the I/O side saw since the last tick */
    if (rig->decoder.frames_corrupt != rig->rx_corrupt_seen) {
        report(rig, RIG_ERR_RX_CORRUPT, t, (int32_t)(rig->decoder.frames_corrupt - rig->rx_corrupt_seen));
        rig->rx_corrupt_seen = rig->decoder.frames_corrupt;
    }
    if (rig->tx_dropped) {
        uint32_t dropped = rig->tx_dropped;
        rig->tx_dropped = 0;
        status |= RIG_ST_TX_OVERFLOW;
        report(rig, RIG_ERR_TX_OVERFLOW, t, (int32_t)dropped);
    }
    if (tick->missed) {
        status |= RIG_ST_OVERRUN;
        rig->stats.overruns++;
        if (rig->running)
            report(rig, RIG_ERR_OVERRUN, t, (int32_t)tick->late_us);
    }

    rig->seq++;
    x = to_si(&rig->ch_x, c->x);
    s.seq = rig->seq;
    s.t_us = t;
    s.x = x;
    s.p1 = to_si(&rig->ch_p1, c->p1);
    s.p2 = to_si(&rig->ch_p2, c->p2);
    s.ps = rig->cfg.has_supply ? to_si(&rig->ch_ps, c->ps) : (float)NAN;

    /* a sensor that cannot be read, or reads outside its range: stop, valve centred */
    broken = sensors_ok ? broken_sensor(rig, c) : 0;
    if (!sensors_ok || broken) {
        if (!rig->fault || rig->running)
            report(rig, RIG_ERR_INTERNAL, t, broken);
        rig->fault = 1;
        rig->running = 0;
        rig->cmd_u = 0.0f;
        rig->cmd_clipped = 0;
    } else {
        rig->fault = 0;
    }
    if (rig->cfg.has_supply && sensors_ok) {
        int low = s.ps < rig->cfg.supply_min;
        if (low) {
            status |= RIG_ST_SUPPLY_FAULT;
            if (!rig->supply_low)
                report(rig, RIG_ERR_SUPPLY, t, round_i32(s.ps));
        }
        rig->supply_low = (uint8_t)low;
    }

    if (rig->running && !rig->watchdog && t - rig->last_host_us > rig->cfg.watchdog_us) {
        rig->watchdog = 1;
        rig->stats.watchdog_trips++;
        report(rig, RIG_ERR_WATCHDOG, t, (int32_t)((t - rig->last_host_us + 500u) / 1000u));
    }
    u = (rig->running && !rig->watchdog) ? rig->cmd_u : 0.0f;
    if (rig->watchdog)
        status |= RIG_ST_WATCHDOG;
    if (rig->cmd_clipped && u == rig->cmd_u)
        status |= RIG_ST_CMD_CLIPPED;
    /* soft stroke limits on the position just measured: never drive further into an end zone */
    into = (x < rig->zone_lo && u < 0.0f) || (x > rig->zone_hi && u > 0.0f);
    if (into) {
        u = 0.0f;
        status |= RIG_ST_SOFT_LIMIT;
        if (!rig->in_zone)
            report(rig, RIG_ERR_SOFT_LIMIT, t, round_i32(x * 1e6f));
    }
    rig->in_zone = (uint8_t)into;
    latch(rig, u);
    if (rig->running)
        status |= RIG_ST_RUNNING;
    flush_errors(rig, t);

    s.u_applied = rig->u_applied;
    s.status = status;
    s.cmd_seq = rig->cmd_seq;
    if (rig->running) {
        if (send_payload(rig, payload, rig_pack_sample(&s, payload), 0))
            rig->stats.samples_sent++;
        else
            rig->stats.samples_dropped++;
        rig->status_sent = 0;
    } else if (!rig->status_sent || t - rig->last_status_us >= STATUS_PERIOD_US) {
        send_payload(rig, payload, rig_pack_status(s.seq, t, status, payload), 0);
        rig->last_status_us = t;
        rig->status_sent = 1;
    }
    hal_serial_flush();

    rep.seq = s.seq;
    rep.t_us = t;
    rep.status = status;
    rep.valve_out = rig->valve_out;
    rep.u_applied = rig->u_applied;
    rep.cmd_seq = rig->cmd_seq;
    hal_tick_done(&rep);
}

int rig_step(rig_state *rig)
{
    rig_tick_info tick;
    rig_counts counts;
    uint8_t buf[32];
    size_t n;
    int read;

    hal_wait_tick(&tick);
    read = hal_read_sensors(&counts);
    if (read == RIG_SENSORS_SHUTDOWN)
        return -1;
    /* host frames that arrived since the last tick are taken now: latched at this tick */
    while ((n = hal_serial_read(buf, sizeof buf)) > 0)
        rig_receive(rig, buf, n, tick.t_us);
    rig_tick(rig, &tick, &counts, read == RIG_SENSORS_OK);
    return 0;
}
