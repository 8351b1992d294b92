/* Configuration of the rig on an Arduino Due: edit it for your sensors and valve, then
 * flash (docs/firmware.md). Counts are the 12-bit ADC's (0 .. 4095 over 0 .. 3.3 V: the
 * Due's inputs take no more than 3.3 V, so 5 V sensor outputs go through a 2:3 divider).
 * Calibrate the zero and span of each sensor on your rig (docs/firmware.md) and write
 * the numbers here. */
#ifndef RIG_CONFIG_H
#define RIG_CONFIG_H

#define RIG_PERIOD_US 1000u        /* 1 kHz */
#define RIG_WATCHDOG_MS 50u        /* host silence that centres the valve */
#define RIG_STROKE_M 0.100f        /* your cylinder's stroke, m */
#define RIG_END_ZONE 0.03f         /* soft stroke limits: 3 % of the stroke at each end */
#define RIG_ATMOSPHERE_PA 101325.0f

/* position (A0): a potentiometer across 0 .. 3.3 V; counts retracted, extended minus retracted */
#define RIG_X_ZERO_COUNTS 80.0f
#define RIG_X_SPAN_COUNTS 3920.0f
#define RIG_X_VALID_MIN 20u        /* a broken wiper wire reads 0 (10 k pull-down) */
#define RIG_X_VALID_MAX 4095u

/* chamber pressures (A1 cap side, A2 rod side): 0-10 bar gauge, 0.5-4.5 V through the 2:3
 * divider (0.333-3.0 V): zero = the reading vented, span = counts for the full scale */
#define RIG_P1_ZERO_COUNTS 413.7f
#define RIG_P1_SPAN_COUNTS 3309.6f
#define RIG_P1_FULL_SCALE_PA 1.0e6f
#define RIG_P1_VALID_MIN 207u      /* below 0.25 V at the transducer: a broken wire */
#define RIG_P1_VALID_MAX 4095u
#define RIG_P2_ZERO_COUNTS 413.7f
#define RIG_P2_SPAN_COUNTS 3309.6f
#define RIG_P2_FULL_SCALE_PA 1.0e6f
#define RIG_P2_VALID_MIN 207u
#define RIG_P2_VALID_MAX 4095u

/* supply pressure (A3), optional: 0-16 bar gauge, 4-20 mA into 150 ohm (0.6-3.0 V) */
#define RIG_HAS_SUPPLY_SENSOR 0
#define RIG_PS_ZERO_COUNTS 744.7f
#define RIG_PS_SPAN_COUNTS 2978.9f
#define RIG_PS_FULL_SCALE_PA 1.6e6f
#define RIG_PS_VALID_MIN 670u      /* 3.6 mA: open loop */
#define RIG_PS_VALID_MAX 4095u
#define RIG_SUPPLY_MIN_PA 3.0e5f   /* absolute: SUPPLY_FAULT below */

/* valve (DAC0): 12 bits, 0.55-2.75 V, amplified to the valve's input (docs/firmware.md) */
#define RIG_VALVE_CENTRE 2048u
#define RIG_VALVE_SPAN 2000u
#define RIG_VALVE_MAX 4095u

#endif
