/* Configuration of the host build: the sensors and the valve driver the simulated plant
 * is wired to. It reads like a real rig's: a 16-bit ADC (0 .. 65535 counts, 0 .. 5 V),
 * a linear position transducer, 0-10 bar transducers with 0.5-4.5 V outputs, a 0-16 bar
 * 4-20 mA supply transducer on 250 ohm, and a 16-bit DAC for the valve. The Python side
 * (hw/firmware_link.py) gets the resulting scaling from the firmware when it starts and
 * turns the plant's SI values into counts with it. The stroke, the watchdog time and the
 * sampling period can be overridden on rig-host's command line (the stroke follows the
 * cylinder file). */
#ifndef RIG_CONFIG_H
#define RIG_CONFIG_H

#define RIG_PERIOD_US 1000u        /* 1 kHz */
#define RIG_WATCHDOG_MS 50u
#define RIG_STROKE_M 0.100f
#define RIG_END_ZONE 0.03f         /* soft stroke limits: 3 % of the stroke at each end */
#define RIG_ATMOSPHERE_PA 101325.0f

/* position: counts with the piston fully retracted, and extended minus retracted */
#define RIG_X_ZERO_COUNTS 3000.0f
#define RIG_X_SPAN_COUNTS 58000.0f
#define RIG_X_VALID_MIN 500u       /* beyond about 4 % outside the stroke: a broken wire */
#define RIG_X_VALID_MAX 64500u

/* chamber pressures: 0.5 V (vented) to 4.5 V (10 bar gauge), calibrated per transducer */
#define RIG_P1_ZERO_COUNTS 6580.0f
#define RIG_P1_SPAN_COUNTS 52390.0f
#define RIG_P1_FULL_SCALE_PA 1.0e6f
#define RIG_P1_VALID_MIN 3277u     /* below 0.25 V: a broken wire (the input's pull-down wins) */
#define RIG_P1_VALID_MAX 65535u    /* over-range is real (a piston hitting its end stop): never a fault */
#define RIG_P2_ZERO_COUNTS 6531.0f
#define RIG_P2_SPAN_COUNTS 52460.0f
#define RIG_P2_FULL_SCALE_PA 1.0e6f
#define RIG_P2_VALID_MIN 3277u
#define RIG_P2_VALID_MAX 65535u

/* supply pressure: 4 mA (1 V, vented) to 20 mA (5 V, 16 bar gauge) */
#define RIG_HAS_SUPPLY_SENSOR 1
#define RIG_PS_ZERO_COUNTS 13107.0f
#define RIG_PS_SPAN_COUNTS 52428.0f
#define RIG_PS_FULL_SCALE_PA 1.6e6f
#define RIG_PS_VALID_MIN 11796u    /* 3.6 mA: open loop */
#define RIG_PS_VALID_MAX 65535u
#define RIG_SUPPLY_MIN_PA 3.0e5f   /* absolute: SUPPLY_FAULT below 2 bar gauge */

/* valve: 16-bit DAC; the spool centres at 32800 (calibrated), +-32000 counts is full flow */
#define RIG_VALVE_CENTRE 32800u
#define RIG_VALVE_SPAN 32000u
#define RIG_VALVE_MAX 65535u

#endif
