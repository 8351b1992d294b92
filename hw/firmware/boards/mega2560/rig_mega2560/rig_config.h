/* Configuration of the rig on an Arduino Mega 2560: edit it for your sensors and valve,
 * then flash (docs/firmware.md). Counts are the 10-bit ADC's (0 .. 1023 over 0 .. 5 V);
 * calibrate the zero and span of each sensor on your rig (docs/firmware.md, "First
 * power-up") and write the numbers here. */
#ifndef RIG_CONFIG_H
#define RIG_CONFIG_H

#define RIG_PERIOD_US 1000u        /* 1 kHz; any period up to 32000 us */
#define RIG_WATCHDOG_MS 50u        /* host silence that centres the valve */
#define RIG_STROKE_M 0.100f        /* your cylinder's stroke, m */
#define RIG_END_ZONE 0.03f         /* soft stroke limits: 3 % of the stroke at each end */
#define RIG_ATMOSPHERE_PA 101325.0f

/* position (A0): a potentiometer or linear transducer over 0 .. 5 V; counts with the piston
 * fully retracted, and fully extended minus retracted (negative if it counts down) */
#define RIG_X_ZERO_COUNTS 20.0f
#define RIG_X_SPAN_COUNTS 980.0f
#define RIG_X_VALID_MIN 5u         /* a broken wiper wire reads 0 (10 k pull-down) */
#define RIG_X_VALID_MAX 1023u

/* chamber pressures (A1 cap side, A2 rod side): 0-10 bar gauge, 0.5-4.5 V outputs;
 * zero = the reading vented, span = counts for the full scale (4 V = 818.4 counts) */
#define RIG_P1_ZERO_COUNTS 102.4f
#define RIG_P1_SPAN_COUNTS 818.4f
#define RIG_P1_FULL_SCALE_PA 1.0e6f
#define RIG_P1_VALID_MIN 51u       /* below 0.25 V: a broken wire */
#define RIG_P1_VALID_MAX 1023u
#define RIG_P2_ZERO_COUNTS 102.4f
#define RIG_P2_SPAN_COUNTS 818.4f
#define RIG_P2_FULL_SCALE_PA 1.0e6f
#define RIG_P2_VALID_MIN 51u
#define RIG_P2_VALID_MAX 1023u

/* supply pressure (A3), optional: 0-16 bar gauge, 4-20 mA into 250 ohm (1-5 V) */
#define RIG_HAS_SUPPLY_SENSOR 0
#define RIG_PS_ZERO_COUNTS 204.8f
#define RIG_PS_SPAN_COUNTS 818.4f
#define RIG_PS_FULL_SCALE_PA 1.6e6f
#define RIG_PS_VALID_MIN 184u      /* 3.6 mA: open loop */
#define RIG_PS_VALID_MAX 1023u
#define RIG_SUPPLY_MIN_PA 3.0e5f   /* absolute: SUPPLY_FAULT below */

/* valve (pin 6, OC4A): 11-bit PWM at 7.8 kHz, filtered and amplified to the valve's input
 * (docs/firmware.md, "Valve driver"); the output that centres the spool, and the counts
 * from there to full flow */
#define RIG_VALVE_CENTRE 1024u
#define RIG_VALVE_SPAN 1000u
#define RIG_VALVE_MAX 2047u

#endif
