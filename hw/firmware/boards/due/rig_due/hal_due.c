/* The hardware layer on the Arduino Due (SAM3X8E, Cortex-M3), on the chip's registers so
 * that the same file builds as an Arduino sketch and bare (make arm):
 *
 *   clock     12 MHz crystal, PLLA 96 MHz, MCK 32 MHz: the UART's 2 Mbaud exactly (MCK/16)
 *   TC0 ch0   the sampling period; its interrupt starts the ADC's scan of the channels
 *   ADC       A0 x (AD7), A1 p1 (AD6), A2 p2 (AD5), A3 ps (AD4): 12 bits, 3.3 V reference
 *   DACC      DAC0: the valve output (12 bits, 0.55-2.75 V)
 *   UART      the Programming Port (through the board's USB interface) at 2 Mbaud 8N1, both
 *             directions by DMA (PDC): no UART interrupt, which the Arduino core owns
 *   pin 7     valve enable (PC23): high once the valve output is centred
 *   pin 13    LED (PB27): lit while a safety rule holds the valve
 *   WDT       about 100 ms: a hung loop resets the board (the enable pin drops with it)
 */
#include <stdint.h>

#include "rig_board.h"
#include "rig_config.h"
#include "rig_config_init.h"
#include "rig_core.h"

#define REG(addr) (*(volatile uint32_t *)(addr))

/* power management, flash, watchdog */
#define PMC_PCER0 REG(0x400E0610u)
#define PMC_PCER1 REG(0x400E0700u)
#define CKGR_MOR REG(0x400E0620u)
#define CKGR_PLLAR REG(0x400E0628u)
#define PMC_MCKR REG(0x400E0630u)
#define PMC_SR REG(0x400E0668u)
#define EEFC0_FMR REG(0x400E0A00u)
#define EEFC1_FMR REG(0x400E0C00u)
#define WDT_CR REG(0x400E1A50u)
#define WDT_MR REG(0x400E1A54u)
/* parallel I/O */
#define PIOA_PDR REG(0x400E0E04u)
#define PIOA_ABSR REG(0x400E0E70u)
#define PIOB_PER REG(0x400E1000u)
#define PIOB_OER REG(0x400E1010u)
#define PIOB_SODR REG(0x400E1030u)
#define PIOB_CODR REG(0x400E1034u)
#define PIOC_PER REG(0x400E1200u)
#define PIOC_OER REG(0x400E1210u)
#define PIOC_SODR REG(0x400E1230u)
#define PIOC_CODR REG(0x400E1234u)
/* UART and its DMA channel */
#define UART_CR REG(0x400E0800u)
#define UART_MR REG(0x400E0804u)
#define UART_IDR REG(0x400E080Cu)
#define UART_BRGR REG(0x400E0820u)
#define UART_RPR REG(0x400E0900u)
#define UART_RCR REG(0x400E0904u)
#define UART_TPR REG(0x400E0908u)
#define UART_TCR REG(0x400E090Cu)
#define UART_RNPR REG(0x400E0910u)
#define UART_RNCR REG(0x400E0914u)
#define UART_TNPR REG(0x400E0918u)
#define UART_TNCR REG(0x400E091Cu)
#define UART_PTCR REG(0x400E0920u)
/* timer counter 0, channel 0 */
#define TC0_CCR REG(0x40080000u)
#define TC0_CMR REG(0x40080004u)
#define TC0_RC REG(0x4008001Cu)
#define TC0_SR REG(0x40080020u)
#define TC0_IER REG(0x40080024u)
/* ADC and DAC */
#define ADC_CR REG(0x400C0000u)
#define ADC_MR REG(0x400C0004u)
#define ADC_CHER REG(0x400C0010u)
#define ADC_ISR REG(0x400C0030u)
#define ADC_CDR(ch) REG(0x400C0050u + 4u * (ch))
#define DACC_CR REG(0x400C8000u)
#define DACC_MR REG(0x400C8004u)
#define DACC_CHER REG(0x400C8010u)
#define DACC_CDR REG(0x400C8020u)
/* Cortex-M3 */
#define NVIC_ISER0 REG(0xE000E100u)

#define ID_PIOA 11u
#define ID_PIOB 12u
#define ID_PIOC 13u
#define ID_UART 8u
#define ID_TC0 27u
#define ID_ADC 37u
#define ID_DACC 38u

#define MCK_HZ 32000000u
#define RX_HALF 128u
#define TX_SIZE 1024u

static const rig_config config = RIG_CONFIG_INIT;
static rig_state rig;
static const uint8_t adc_channel[4] = {7u, 6u, 5u, 4u}; /* A0 .. A3 */
#define ADC_CHANNELS ((1u << 7) | (1u << 6) | (1u << 5) | (RIG_HAS_SUPPLY_SENSOR ? (1u << 4) : 0u))

static volatile uint32_t tick_count;
static uint32_t last_tick;
static uint16_t last_counts[4];
static uint8_t rx_dma[2][RX_HALF];
static uint8_t rx_half;     /* the half the DMA fills now */
static uint32_t rx_taken;   /* bytes of that half already read */
static uint8_t tx_ring[TX_SIZE];
static uint32_t tx_head, tx_tail, tx_flight;

/* ------------------------------------------------------------------ interrupt */

void TC0_Handler(void);
void TC0_Handler(void)
{
    (void)TC0_SR; /* reading clears the compare flag */
    tick_count++;
    ADC_CR = 1u << 1; /* START: a scan of the enabled channels, sampled now */
}

/* ------------------------------------------------------------------ HAL */

void hal_wait_tick(rig_tick_info *tick)
{
    uint32_t at, ch;
    while (tick_count == last_tick) {
    }
    at = tick_count;
    while ((ADC_ISR & ADC_CHANNELS) != ADC_CHANNELS) { /* a few microseconds of conversions */
    }
    for (ch = 0; ch < 4; ch++)
        last_counts[ch] = (uint16_t)(ADC_CDR(adc_channel[ch]) & 0xFFFu); /* reading clears its flag */
    WDT_CR = (0xA5u << 24) | 1u; /* the loop keeps up: restart the hardware watchdog */
    tick->missed = at - last_tick - 1u;
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
    DACC_CDR = out;
}

size_t hal_serial_read(uint8_t *buf, size_t n)
{
    size_t got = 0;
    for (;;) {
        uint32_t base = (uint32_t)(uintptr_t)rx_dma[rx_half];
        uint32_t filled = UART_RPR - base; /* past the half (or before it): the DMA moved on */
        if (filled > RX_HALF)
            filled = RX_HALF;
        while (rx_taken < filled && got < n)
            buf[got++] = rx_dma[rx_half][rx_taken++];
        if (rx_taken < RX_HALF || got == n)
            return got;
        /* this half is read and the DMA is in the other one: it comes next again */
        UART_RNPR = base;
        UART_RNCR = RX_HALF;
        rx_half ^= 1u;
        rx_taken = 0;
    }
}

size_t hal_serial_room(void)
{
    return TX_SIZE - 1u - ((tx_head - tx_tail) & (TX_SIZE - 1u));
}

void hal_serial_write(const uint8_t *buf, size_t n)
{
    size_t i;
    for (i = 0; i < n; i++) {
        tx_ring[tx_head] = buf[i];
        tx_head = (tx_head + 1u) & (TX_SIZE - 1u);
    }
}

void hal_serial_flush(void)
{
    uint32_t used, first;
    if (UART_TCR != 0 || UART_TNCR != 0)
        return; /* the last batch is still going out */
    tx_tail = (tx_tail + tx_flight) & (TX_SIZE - 1u);
    used = (tx_head - tx_tail) & (TX_SIZE - 1u);
    tx_flight = used;
    if (!used)
        return;
    first = used < TX_SIZE - tx_tail ? used : TX_SIZE - tx_tail;
    UART_TPR = (uint32_t)(uintptr_t)&tx_ring[tx_tail]; /* the current transfer first, then the wrap */
    UART_TCR = first;
    if (used > first) {
        UART_TNPR = (uint32_t)(uintptr_t)tx_ring;
        UART_TNCR = used - first;
    }
}

void hal_tick_done(const rig_tick_report *report)
{
    if (report->status & (RIG_ST_WATCHDOG | RIG_ST_SOFT_LIMIT | RIG_ST_SUPPLY_FAULT) || rig.fault)
        PIOB_SODR = 1u << 27;
    else
        PIOB_CODR = 1u << 27;
}

/* ------------------------------------------------------------------ setup */

void rig_board_watchdog(void)
{
    /* 100 ms (26 x 128 slow-clock cycles), reset on expiry, halted in debug and idle */
    WDT_MR = 26u | (0xFFFu << 16) | (1u << 13) | (1u << 28) | (1u << 29);
}

static void clock_32mhz(void)
{
    /* flash wait states for up to 84 MHz while the clock changes (the Arduino core runs at
     * 84 MHz before setup()), 2 once it runs at 32 MHz */
    EEFC0_FMR = 4u << 8;
    EEFC1_FMR = 4u << 8;
    CKGR_MOR = (0x37u << 16) | (0x8u << 8) | (1u << 3) | (1u << 0); /* crystal on, RC stays on */
    while (!(PMC_SR & (1u << 0))) {
    }
    CKGR_MOR = (0x37u << 16) | (0x8u << 8) | (1u << 3) | (1u << 0) | (1u << 24); /* select the crystal */
    while (!(PMC_SR & (1u << 16))) {
    }
    PMC_MCKR = (PMC_MCKR & ~3u) | 1u; /* run from the crystal while the PLL changes */
    while (!(PMC_SR & (1u << 3))) {
    }
    CKGR_PLLAR = (1u << 29) | (7u << 16) | (0x3Fu << 8) | 1u; /* 12 MHz x 8 = 96 MHz */
    while (!(PMC_SR & (1u << 1))) {
    }
    PMC_MCKR = (PMC_MCKR & ~(7u << 4)) | (7u << 4); /* prescaler /3 */
    while (!(PMC_SR & (1u << 3))) {
    }
    PMC_MCKR = (PMC_MCKR & ~3u) | 2u; /* PLLA: 32 MHz */
    while (!(PMC_SR & (1u << 3))) {
    }
    EEFC0_FMR = 2u << 8;
    EEFC1_FMR = 2u << 8;
}

void rig_board_setup(void)
{
    clock_32mhz();
    PMC_PCER0 = (1u << ID_PIOA) | (1u << ID_PIOB) | (1u << ID_PIOC) | (1u << ID_UART) | (1u << ID_TC0);
    PMC_PCER1 = (1u << (ID_ADC - 32u)) | (1u << (ID_DACC - 32u));
    /* valve output first: DAC0, free running, centred */
    PIOC_PER = 1u << 23; /* pin 7: valve enable, low until the output is centred */
    PIOC_CODR = 1u << 23;
    PIOC_OER = 1u << 23;
    DACC_CR = 1u; /* reset */
    DACC_MR = (1u << 8) | (8u << 24); /* refresh, start-up time */
    DACC_CHER = 1u;
    rig_init(&rig, &config); /* latches u = 0: the centre */
    PIOB_PER = 1u << 27;
    PIOB_OER = 1u << 27;
    /* UART: PA8 URXD, PA9 UTXD (peripheral A); 2 Mbaud = MCK / (16 x 1); DMA both ways */
    PIOA_ABSR &= ~((1u << 8) | (1u << 9));
    PIOA_PDR = (1u << 8) | (1u << 9);
    UART_CR = (1u << 2) | (1u << 3) | (1u << 8); /* reset receiver, transmitter, status */
    UART_IDR = 0xFFFFFFFFu;
    UART_MR = 4u << 9; /* no parity, normal mode */
    UART_BRGR = MCK_HZ / (16u * 2000000u);
    UART_RPR = (uint32_t)(uintptr_t)rx_dma[0];
    UART_RCR = RX_HALF;
    UART_RNPR = (uint32_t)(uintptr_t)rx_dma[1];
    UART_RNCR = RX_HALF;
    UART_PTCR = (1u << 0) | (1u << 8); /* receive and transmit DMA on */
    UART_CR = (1u << 4) | (1u << 6); /* receiver and transmitter on */
    /* ADC: 32 MHz / 6 = 5.3 MHz clock, channels A0 .. A2 (A3) */
    ADC_CR = 1u; /* reset */
    ADC_MR = (2u << 8) | (8u << 16) | (3u << 20) | (1u << 24) | (1u << 28);
    ADC_CHER = ADC_CHANNELS;
    /* TC0 channel 0: MCK / 2 = 16 counts per us, restart at RC, interrupt at RC */
    TC0_CMR = 1u << 14;
    TC0_RC = (MCK_HZ / 2000000u) * RIG_PERIOD_US;
    TC0_IER = 1u << 4;
    NVIC_ISER0 = 1u << ID_TC0;
    TC0_CCR = (1u << 0) | (1u << 2); /* enable, start */
    PIOC_SODR = 1u << 23; /* the valve may be driven now */
}

void rig_board_step(void)
{
    rig_step(&rig);
}
