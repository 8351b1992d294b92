/* The host build of the rig firmware: the portable core with a hardware layer whose
 * sensors and valve are the project's simulated plant and whose serial port is a
 * pseudo-terminal. `combined-reality virtual-rig --serial --firmware build/rig-host` starts
 * it; it is not meant to be run by hand.
 *
 *     rig-host --plant-fd N [--stroke M] [--watchdog-ms MS] [--rate HZ]
 *
 * The plant channel (fd N, a SOCK_SEQPACKET socket) carries fixed little-endian records:
 *   hello   rig -> plant, once: "RIGF", version, the configuration and the scaling of every
 *           channel, the rig clock's origin (CLOCK_MONOTONIC ns) and the pty path;
 *   request rig -> plant, at each tick k: t_us of tick k, and the outcome of tick k-1 (seq,
 *           the valve output held since then, status bits, u_applied, cmd_seq); the plant
 *           integrates over [t_k-1, t_k) with that output;
 *   reply   plant -> rig: the ADC counts of x, p1, p2, ps at t_k, and ok (0: the plant failed).
 * The firmware's timer drives the clock. If the plant does not answer for 2 s, or is gone,
 * the firmware stops streaming, centres the valve and exits (status 1); SIGTERM or SIGINT
 * end it the same way with status 0. */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <poll.h>
#include <sched.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "rig_config.h"
#include "rig_config_init.h"
#include "rig_core.h"

#define EXCHANGE_VERSION 1
#define PLANT_TIMEOUT_MS 2000
#define TX_SIZE 65536u /* like a USB-serial driver's buffer: the Python rig's tx_limit */

static volatile sig_atomic_t stop_requested;
static int plant_fd = -1;
static int pty_master = -1, pty_slave = -1;
static uint64_t t0_ns, period_ns, tick_k, tick_us;
static uint16_t valve_out;
static rig_tick_report last_report;
static int plant_failed; /* 1: gone or silent (exit status 1) */
static uint8_t tx_buf[TX_SIZE];
static size_t tx_head, tx_len;

static uint64_t now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000000u + (uint64_t)ts.tv_nsec;
}

static void put(uint8_t *buf, size_t *at, const void *v, size_t n)
{
    memcpy(buf + *at, v, n); /* the host is little-endian (x86-64, arm64), as the records are */
    *at += n;
}

/* ------------------------------------------------------------------ HAL */

void hal_wait_tick(rig_tick_info *tick)
{
    uint64_t target, now;
    struct timespec ts;
    tick_k++;
    target = t0_ns + tick_k * period_ns;
    ts.tv_sec = (time_t)(target / 1000000000u);
    ts.tv_nsec = (long)(target % 1000000000u);
    while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL) == EINTR && !stop_requested) {
    }
    now = now_ns();
    tick->missed = 0;
    tick->late_us = 0;
    if (now > target + period_ns) { /* missed whole periods: skip them, never catch up in a burst */
        tick->missed = (uint32_t)((now - target) / period_ns);
        tick->late_us = (uint32_t)((now - target) / 1000u);
        tick_k += tick->missed;
    }
    tick->t_us = tick_us = (now - t0_ns) / 1000u; /* the actual instant, as a timer capture would give */
}

static void plant_lost(const char *why)
{
    if (!plant_failed)
        fprintf(stderr, "rig-host: %s; valve centred, stopping\n", why);
    plant_failed = 1;
    stop_requested = 1;
}

int hal_read_sensors(rig_counts *counts)
{
    uint8_t req[24], rep[16];
    size_t at = 0;
    struct pollfd pfd;
    ssize_t n;
    uint8_t ok;
    if (plant_failed)
        return RIG_SENSORS_FAILED;
    if (stop_requested)
        return RIG_SENSORS_SHUTDOWN;
    put(req, &at, &tick_us, 8);
    put(req, &at, &last_report.seq, 4);
    put(req, &at, &valve_out, 2);
    put(req, &at, &last_report.status, 2);
    put(req, &at, &last_report.u_applied, 4);
    put(req, &at, &last_report.cmd_seq, 4);
    if (send(plant_fd, req, at, MSG_NOSIGNAL) != (ssize_t)at) {
        plant_lost("the plant is gone");
        return RIG_SENSORS_FAILED;
    }
    pfd.fd = plant_fd;
    pfd.events = POLLIN;
    for (;;) {
        int r = poll(&pfd, 1, PLANT_TIMEOUT_MS);
        if (r > 0)
            break;
        if (r == 0) {
            plant_lost("the plant did not answer for 2 s");
            return RIG_SENSORS_FAILED;
        }
        if (errno != EINTR) {
            plant_lost("the plant channel failed");
            return RIG_SENSORS_FAILED;
        }
        if (stop_requested)
            return RIG_SENSORS_SHUTDOWN; /* SIGTERM while waiting: a clean stop, not a fault */
    }
    n = recv(plant_fd, rep, sizeof rep, 0);
    if (n != 9) {
        plant_lost(n <= 0 ? "the plant is gone" : "the plant sent a malformed reply");
        return RIG_SENSORS_FAILED;
    }
    memcpy(&counts->x, rep, 2);
    memcpy(&counts->p1, rep + 2, 2);
    memcpy(&counts->p2, rep + 4, 2);
    memcpy(&counts->ps, rep + 6, 2);
    ok = rep[8];
    return ok ? RIG_SENSORS_OK : RIG_SENSORS_FAILED;
}

void hal_valve_write(uint16_t out)
{
    valve_out = out;
}

size_t hal_serial_read(uint8_t *buf, size_t n)
{
    ssize_t r = read(pty_master, buf, n);
    return r > 0 ? (size_t)r : 0;
}

size_t hal_serial_room(void)
{
    return TX_SIZE - tx_len;
}

void hal_serial_write(const uint8_t *buf, size_t n)
{
    size_t i;
    for (i = 0; i < n && tx_len < TX_SIZE; i++, tx_len++)
        tx_buf[(tx_head + tx_len) % TX_SIZE] = buf[i];
}

void hal_serial_flush(void)
{
    while (tx_len) {
        size_t chunk = tx_head + tx_len <= TX_SIZE ? tx_len : TX_SIZE - tx_head;
        ssize_t w = write(pty_master, tx_buf + tx_head, chunk);
        if (w <= 0)
            return; /* the host does not read: keep it for the next tick */
        tx_head = (tx_head + (size_t)w) % TX_SIZE;
        tx_len -= (size_t)w;
    }
}

void hal_tick_done(const rig_tick_report *report)
{
    last_report = *report;
}

/* ------------------------------------------------------------------ setup */

static void on_signal(int sig)
{
    (void)sig;
    stop_requested = 1;
}

static int open_pty(char *path, size_t size)
{
    struct termios tio;
    pty_master = posix_openpt(O_RDWR | O_NOCTTY);
    if (pty_master < 0 || grantpt(pty_master) || unlockpt(pty_master) || ptsname_r(pty_master, path, size))
        return -1;
    /* the slave stays open here too, so the pty survives the host closing and reopening it */
    pty_slave = open(path, O_RDWR | O_NOCTTY);
    if (pty_slave < 0)
        return -1;
    if (tcgetattr(pty_slave, &tio) == 0) { /* raw: bytes pass unchanged */
        cfmakeraw(&tio);
        tcsetattr(pty_slave, TCSANOW, &tio);
    }
    if (tcgetattr(pty_master, &tio) == 0) {
        cfmakeraw(&tio);
        tcsetattr(pty_master, TCSANOW, &tio);
    }
    return fcntl(pty_master, F_SETFL, fcntl(pty_master, F_GETFL) | O_NONBLOCK);
}

static void channel_record(uint8_t *buf, size_t *at, const rig_channel *ch)
{
    put(buf, at, &ch->offset, 4);
    put(buf, at, &ch->scale, 4);
    put(buf, at, &ch->valid_min, 2);
    put(buf, at, &ch->valid_max, 2);
}

static int send_hello(const rig_state *rig, const char *path)
{
    uint8_t buf[512];
    size_t at = 0, n = strlen(path);
    uint16_t version = EXCHANGE_VERSION;
    const rig_config *c = &rig->cfg;
    put(buf, &at, "RIGF", 4);
    put(buf, &at, &version, 2);
    put(buf, &at, &c->period_us, 4);
    put(buf, &at, &c->watchdog_us, 4);
    put(buf, &at, &c->stroke, 4);
    put(buf, &at, &c->end_zone, 4);
    put(buf, &at, &t0_ns, 8);
    put(buf, &at, &c->has_supply, 1);
    put(buf, &at, &c->supply_min, 4);
    put(buf, &at, &c->valve_centre, 2);
    put(buf, &at, &c->valve_span, 2);
    put(buf, &at, &c->valve_max, 2);
    channel_record(buf, &at, &rig->ch_x);
    channel_record(buf, &at, &rig->ch_p1);
    channel_record(buf, &at, &rig->ch_p2);
    channel_record(buf, &at, &rig->ch_ps);
    if (n > sizeof buf - at)
        return -1;
    put(buf, &at, path, n);
    return send(plant_fd, buf, at, MSG_NOSIGNAL) == (ssize_t)at ? 0 : -1;
}

static int usage(const char *msg)
{
    fprintf(stderr, "rig-host: %s\nusage: rig-host --plant-fd N [--stroke M] [--watchdog-ms MS] [--rate HZ]\n"
                    "(started by `combined-reality virtual-rig --serial --firmware PATH`)\n", msg);
    return 2;
}

int main(int argc, char **argv)
{
    static const rig_config defaults = RIG_CONFIG_INIT;
    static rig_state rig;
    rig_config cfg = defaults;
    char path[256];
    struct sigaction sa;
    struct sched_param sp;
    int i;

    for (i = 1; i < argc; i++) {
        char *end;
        double v;
        if (i + 1 >= argc)
            return usage("every option takes a value");
        v = strtod(argv[i + 1], &end);
        if (*end || end == argv[i + 1] || !isfinite(v))
            return usage("option values are numbers");
        if (!strcmp(argv[i], "--plant-fd") && v >= 0)
            plant_fd = (int)v;
        else if (!strcmp(argv[i], "--stroke") && v > 0)
            cfg.stroke = (float)v;
        else if (!strcmp(argv[i], "--watchdog-ms") && v >= 1 && v <= 60000)
            cfg.watchdog_us = (uint32_t)(v * 1000.0 + 0.5);
        else if (!strcmp(argv[i], "--rate") && v >= 10 && v <= 100000)
            cfg.period_us = (uint32_t)(1e6 / v + 0.5);
        else
            return usage("unknown option or value out of range");
        i++;
    }
    if (plant_fd < 0)
        return usage("--plant-fd is required");
    if (rig_config_check(&cfg))
        return usage("the configuration is not usable (check rig_config.h)");

    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    signal(SIGPIPE, SIG_IGN);
    if (open_pty(path, sizeof path)) {
        fprintf(stderr, "rig-host: cannot open a pseudo-terminal: %s\n", strerror(errno));
        return 1;
    }
    /* a rig's timer interrupt is not preempted by other programs; ask for the same */
    sp.sched_priority = 10;
    if (sched_setscheduler(0, SCHED_FIFO, &sp))
        fprintf(stderr, "rig-host: runs without real-time priority (%s); expect more jitter\n", strerror(errno));

    period_ns = (uint64_t)cfg.period_us * 1000u;
    rig_init(&rig, &cfg);
    t0_ns = now_ns();
    if (send_hello(&rig, path)) {
        fprintf(stderr, "rig-host: cannot reach the plant on fd %d: %s\n", plant_fd, strerror(errno));
        return 1;
    }
    while (rig_step(&rig) == 0 && !stop_requested) {
    }
    rig_halt(&rig);
    hal_serial_flush();
    fprintf(stderr, "rig-host: stopped after %lu ticks: %lu samples sent, %lu samples dropped for a slow host "
                    "(%lu frames in all), %lu overruns, %lu watchdog trips, %lu corrupted host frames rejected\n",
            (unsigned long)rig.stats.ticks, (unsigned long)rig.stats.samples_sent,
            (unsigned long)rig.stats.samples_dropped, (unsigned long)rig.stats.frames_dropped,
            (unsigned long)rig.stats.overruns, (unsigned long)rig.stats.watchdog_trips,
            (unsigned long)rig.decoder.frames_corrupt);
    close(pty_master);
    close(pty_slave);
    return plant_failed ? 1 : 0;
}
