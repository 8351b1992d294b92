/* The hardware layer on the Arduino Mega 2560 (ATmega2560, 16 MHz), written against
 * avr-libc's registers so that the same file builds as an Arduino sketch and bare:
 *
 *   Timer1    CTC at the sampling period; its compare match B starts the ADC: the sensors
 *             are sampled by hardware at the tick, whatever the main loop is doing
 *   ADC       A0 x, A1 p1, A2 p2 (A3 ps): a chain of conversions from the ADC interrupt,
 *             AVcc reference, 250 kHz ADC clock (52 us per channel)
 *   Timer4    11-bit fast PWM on pin 6 (OC4A) at 7.8 kHz: the valve output
 *   USART0    2 Mbaud 8N1 through the board's USB interface; interrupt-driven rings
 *   pin 7     valve enable: high once the valve output is centred (drive the valve driver's
 *             enable or a supply shut-off relay with it; low in reset and while unpowered)
 *   pin 13    LED: lit while a safety rule holds the valve (watchdog, soft limit, fault)
 *   WDT       120 ms: a hung loop resets the board (the enable pin drops with it)
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/wdt.h>
#include <util/atomic.h>

#include "rig_board.h"
#include "rig_config.h"
#include "rig_config_init.h"
#include "rig_core.h"

#define N_CHANNELS (RIG_HAS_SUPPLY_SENSOR ? 4u : 3u)
#define RX_SIZE 128u /* powers of two */
#define TX_SIZE 256u

static const rig_config config = RIG_CONFIG_INIT;
static rig_state rig;

/* written by the interrupts */
static volatile uint32_t tick_count;        /* timer periods since power-up */
static volatile uint16_t conversion[4];     /* the chain in progress */
static volatile uint8_t channel;
static volatile uint16_t snapshot[4];       /* the last complete set */
static volatile uint32_t snapshot_tick;
static volatile uint8_t snapshot_ready;
static volatile uint8_t rx_buf[RX_SIZE], tx_buf[TX_SIZE];
static volatile uint8_t rx_head, rx_tail, tx_head, tx_tail;
static uint32_t last_tick;
static uint16_t last_counts[4];

/* ------------------------------------------------------------------ interrupts */

ISR(TIMER1_COMPB_vect)
{
    /* entering clears OCF1B, so that the next compare match is an edge that starts the ADC */
    tick_count++;
    channel = 0;
}

ISR(ADC_vect)
{
    uint8_t ch = channel;
    conversion[ch] = ADC;
    if (++ch < N_CHANNELS) {
        ADMUX = (uint8_t)(_BV(REFS0) | ch); /* the conversion just ended: the next may start */
        ADCSRA |= _BV(ADSC);
        channel = ch;
        return;
    }
    ADMUX = _BV(REFS0); /* channel 0 for the next tick's hardware-started conversion */
    for (ch = 0; ch < N_CHANNELS; ch++)
        snapshot[ch] = conversion[ch];
    snapshot_tick = tick_count;
    snapshot_ready = 1;
}

ISR(USART0_RX_vect)
{
    uint8_t b = UDR0;
    uint8_t next = (uint8_t)((rx_head + 1u) & (RX_SIZE - 1u));
    if (next != rx_tail) { /* a full ring drops the byte: the decoder sees a damaged frame */
        rx_buf[rx_head] = b;
        rx_head = next;
    }
}

ISR(USART0_UDRE_vect)
{
    if (tx_tail == tx_head) {
        UCSR0B &= (uint8_t)~_BV(UDRIE0);
        return;
    }
    UDR0 = tx_buf[tx_tail];
    tx_tail = (uint8_t)((tx_tail + 1u) & (TX_SIZE - 1u));
}

/* ------------------------------------------------------------------ HAL */

void hal_wait_tick(rig_tick_info *tick)
{
    uint32_t at;
    uint8_t ch;
    while (!snapshot_ready) {
    }
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE) {
        at = snapshot_tick;
        for (ch = 0; ch < 4; ch++)
            last_counts[ch] = snapshot[ch];
        snapshot_ready = 0;
    }
    wdt_reset(); /* the loop keeps up: the hardware watchdog stays quiet */
    tick->missed = at - last_tick > 1u ? at - last_tick - 1u : 0u;
    tick->late_us = tick->missed * RIG_PERIOD_US;
    tick->t_us = (uint64_t)at * RIG_PERIOD_US;
    last_tick = at;
}

int hal_read_sensors(rig_counts *counts)
{
    counts->x = last_counts[0];
    counts->p1 = last_counts[1];
    counts->p2 = last_counts[2];
    counts->ps = last_counts[3];
    return RIG_SENSORS_OK;
}

void hal_valve_write(uint16_t out)
{
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE) { /* 16-bit register: one access at a time */
        OCR4A = out;
    }
}

size_t hal_serial_read(uint8_t *buf, size_t n)
{
    size_t i = 0;
    while (i < n && rx_tail != rx_head) {
        buf[i++] = rx_buf[rx_tail];
        rx_tail = (uint8_t)((rx_tail + 1u) & (RX_SIZE - 1u));
    }
    return i;
}

size_t hal_serial_room(void)
{
    return (size_t)(TX_SIZE - 1u - ((uint8_t)(tx_head - tx_tail)));
}

void hal_serial_write(const uint8_t *buf, size_t n)
{
    size_t i;
    for (i = 0; i < n; i++) {
        tx_buf[tx_head] = buf[i];
        tx_head = (uint8_t)((tx_head + 1u) & (TX_SIZE - 1u));
    }
}

void hal_serial_flush(void)
{
    UCSR0B |= _BV(UDRIE0);
}

void hal_tick_done(const rig_tick_report *report)
{
    if (report->status & (RIG_ST_WATCHDOG | RIG_ST_SOFT_LIMIT | RIG_ST_SUPPLY_FAULT) || rig.fault)
        PORTB |= _BV(PB7);
    else
        PORTB &= (uint8_t)~_BV(PB7);
}

/* ------------------------------------------------------------------ setup */

void rig_board_setup(void)
{
    cli();
    MCUSR = 0;
    wdt_disable();
    /* valve output first: 11-bit fast PWM (mode 14, TOP = ICR4), no prescaler, centred */
    DDRH |= _BV(PH3) | _BV(PH4); /* pin 6 OC4A, pin 7 valve enable */
    PORTH &= (uint8_t)~_BV(PH4);
    TCCR4A = _BV(COM4A1) | _BV(WGM41);
    TCCR4B = _BV(WGM43) | _BV(WGM42) | _BV(CS40);
    ICR4 = RIG_VALVE_MAX;
    rig_init(&rig, &config); /* latches u = 0: the centre */
    DDRB |= _BV(PB7);
    /* USART0: 2 Mbaud (U2X, UBRR 0 at 16 MHz), 8N1 */
    UBRR0 = 0;
    UCSR0A = _BV(U2X0);
    UCSR0C = _BV(UCSZ01) | _BV(UCSZ00);
    UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);
    /* ADC: AVcc reference, channel 0, started by Timer1 compare B, 250 kHz clock */
    ADMUX = _BV(REFS0);
    ADCSRB = _BV(ADTS2) | _BV(ADTS0);
    ADCSRA = _BV(ADEN) | _BV(ADATE) | _BV(ADIE) | _BV(ADPS2) | _BV(ADPS1);
    DIDR0 = (uint8_t)((1u << N_CHANNELS) - 1u); /* no digital input buffers on the analog pins */
    /* Timer1: CTC (TOP = OCR1A) with /8: 2 counts per us */
    TCCR1A = 0;
    TCCR1B = _BV(WGM12) | _BV(CS11);
    OCR1A = (uint16_t)((F_CPU / 8000000UL) * RIG_PERIOD_US - 1u);
    OCR1B = OCR1A;
    TCNT1 = 0;
    TIMSK1 = _BV(OCIE1B);
    PORTH |= _BV(PH4); /* the valve may be driven now */
    wdt_enable(WDTO_120MS);
    sei();
}

void rig_board_step(void)
{
    rig_step(&rig);
}
