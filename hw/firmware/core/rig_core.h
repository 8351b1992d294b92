/* The rig firmware's logic, the same on every board: the 1 kHz tick (sample, check, latch,
 * send), the host's frames (START, STOP, COMMAND, HEARTBEAT), the watchdog that centres the
 * valve, command bounds, soft stroke limits, sensor scaling and the error reports of
 * docs/protocol.md. It reaches the hardware only through hal/rig_hal.h. */
#ifndef RIG_CORE_H
#define RIG_CORE_H

#include <stdint.h>

#include "rig_hal.h"
#include "rig_protocol.h"

#ifdef __cplusplus
extern "C" { /* the boards' sketches are C++ */
#endif

/* One sensor's calibration: the reading at its zero point and how many counts its full
 * scale adds (negative when the reading falls as the quantity rises). Readings outside
 * [valid_min, valid_max] mean a broken wire or an unpowered sensor: the rig stops. */
typedef struct {
    float zero_counts;  /* x: piston fully retracted; pressures: chamber vented (gauge 0) */
    float span_counts;  /* x: fully extended minus retracted; pressures: at full scale minus zero */
    float full_scale;   /* pressures: gauge Pa at zero + span (x: the stroke, set from rig_config.stroke) */
    uint16_t valid_min, valid_max;
} rig_calibration;

/* A channel as the core uses it: SI = offset + scale * counts. */
typedef struct {
    float offset, scale;
    uint16_t valid_min, valid_max;
} rig_channel;

typedef struct {
    uint32_t period_us;     /* sampling period: 1000 = 1 kHz */
    uint32_t watchdog_us;   /* host silence that centres the valve */
    float stroke;           /* m */
    float end_zone;         /* soft stroke limits: this fraction of the stroke at each end */
    float atmosphere;       /* Pa: added to the gauge pressures the transducers measure */
    rig_calibration x, p1, p2, ps;
    uint8_t has_supply;     /* a supply pressure transducer is fitted (ps) */
    float supply_min;       /* Pa absolute: SUPPLY_FAULT below this */
    uint16_t valve_centre;  /* output that centres the spool (u = 0) */
    uint16_t valve_span;    /* output counts from the centre to u = +-1 */
    uint16_t valve_max;     /* the largest output the DAC or PWM takes */
} rig_config;

/* the rig's counters since power-up (the host build prints them when it ends) */
typedef struct {
    uint32_t ticks, samples_sent, samples_dropped, overruns, watchdog_trips, frames_dropped;
} rig_stats;

typedef struct {
    rig_config cfg;
    rig_channel ch_x, ch_p1, ch_p2, ch_ps;
    float zone_lo, zone_hi;     /* m: soft stroke limits */
    rig_decoder decoder;
    /* host side */
    uint8_t running, watchdog, cmd_clipped, in_zone, supply_low, fault;
    float cmd_u;
    uint32_t cmd_seq;
    uint64_t last_host_us;
    /* tick side */
    uint32_t seq;
    uint64_t last_status_us;
    uint8_t status_sent;
    uint16_t valve_out;
    float u_applied;
    uint32_t rx_corrupt_seen;   /* decoder.frames_corrupt already reported */
    uint32_t tx_dropped;        /* frames dropped for lack of room since the last tick */
    /* error gate: one report per code per second, counting codes sum what is held back */
    uint64_t err_sent_us[RIG_ERR_CODES];
    int32_t err_held[RIG_ERR_CODES];
    uint16_t err_sent_mask;
    uint16_t err_held_mask;
    rig_stats stats;
} rig_state;

/* 0, or -1 when the configuration is unusable (spans of 0, centre +- span outside the output) */
int rig_config_check(const rig_config *cfg);

/* Set up the state and centre the valve. */
void rig_init(rig_state *rig, const rig_config *cfg);

/* One pass of the main loop: wait for the timer, read the sensors, take the host's
 * frames, decide, write the valve, send. Boards call it forever; it returns 0, or -1
 * when the hardware layer says the program is ending (host build). */
int rig_step(rig_state *rig);

/* The parts of rig_step (the test program drives them without a timer). */
void rig_receive(rig_state *rig, const uint8_t *data, size_t n, uint64_t t_us);
void rig_tick(rig_state *rig, const rig_tick_info *tick, const rig_counts *counts, int sensors_ok);

/* Centre the valve and stop streaming (power-down, a signal to the host build). */
void rig_halt(rig_state *rig);

#ifdef __cplusplus
}
#endif

#endif
