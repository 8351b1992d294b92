/* The thin hardware layer: what a board (or the host build) provides to the portable core.
 *
 * One implementation per board family (boards/<board>/) and one for the host build
 * (host/hal_host.c), where the sensors and the valve are the project's simulated plant and
 * the serial port is a pseudo-terminal. The core calls these from its main loop only,
 * never from an interrupt. */
#ifndef RIG_HAL_H
#define RIG_HAL_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" { /* the boards' sketches are C++ */
#endif

/* the sampling instant the hardware timer just marked */
typedef struct {
    uint64_t t_us;   /* the rig clock at the sampling instant, us since power-up */
    uint32_t missed; /* timer periods that passed unprocessed before this one (0: on time) */
    uint32_t late_us;/* how late the loop came to this instant (the OVERRUN error's value) */
} rig_tick_info;

/* ADC counts at the sampling instant (ps: 0 when the board has no supply sensor) */
typedef struct {
    uint16_t x, p1, p2, ps;
} rig_counts;

/* what one tick decided, for boards that show it (LEDs) and for the host build's plant */
typedef struct {
    uint32_t seq;
    uint64_t t_us;
    uint16_t status;   /* status bits of the sample (RIG_ST_*) */
    uint16_t valve_out;/* the output just written */
    float u_applied;
    uint32_t cmd_seq;
} rig_tick_report;

/* Block until the next sampling instant of the 1 kHz timer (a period of `period_us`);
 * sensors are sampled at that instant. */
void hal_wait_tick(rig_tick_info *tick);

/* The readings taken at the last instant; returns RIG_SENSORS_OK, RIG_SENSORS_FAILED when
 * they cannot be read at all (the rig then stops: ERROR INTERNAL), or RIG_SENSORS_SHUTDOWN
 * when the program is ending (host build: SIGTERM) and the tick is to be dropped. */
enum { RIG_SENSORS_OK = 0, RIG_SENSORS_FAILED = -1, RIG_SENSORS_SHUTDOWN = 1 };
int hal_read_sensors(rig_counts *counts);

/* Set the valve output (DAC or PWM counts; the centre holds the spool in the middle). */
void hal_valve_write(uint16_t out);

/* Serial link: take up to n received bytes (returns how many); free room in the transmit
 * buffer; queue bytes (never more than the room); start sending what was queued. */
size_t hal_serial_read(uint8_t *buf, size_t n);
size_t hal_serial_room(void);
void hal_serial_write(const uint8_t *buf, size_t n);
void hal_serial_flush(void);

/* After every tick: the board shows it (e.g. a fault LED), the host build tells the plant. */
void hal_tick_done(const rig_tick_report *report);

#ifdef __cplusplus
}
#endif

#endif
