/* Turns the RIG_* settings of a board's rig_config.h into a rig_config. Include it after
 * rig_config.h, in the one file that calls rig_init (the board's main or sketch):
 *
 *     #include "rig_config.h"
 *     #include "rig_config_init.h"
 *     static const rig_config config = RIG_CONFIG_INIT;
 *
 * Settings with a default here may be left out of rig_config.h. */
#ifndef RIG_CONFIG_INIT_H
#define RIG_CONFIG_INIT_H

#include "rig_core.h"

#ifndef RIG_PERIOD_US
#define RIG_PERIOD_US 1000u
#endif
#ifndef RIG_WATCHDOG_MS
#define RIG_WATCHDOG_MS 50u
#endif
#ifndef RIG_END_ZONE
#define RIG_END_ZONE 0.03f
#endif
#ifndef RIG_ATMOSPHERE_PA
#define RIG_ATMOSPHERE_PA 101325.0f
#endif
#ifndef RIG_HAS_SUPPLY_SENSOR
#define RIG_HAS_SUPPLY_SENSOR 0
#endif
#if !RIG_HAS_SUPPLY_SENSOR
#undef RIG_PS_ZERO_COUNTS
#undef RIG_PS_SPAN_COUNTS
#undef RIG_PS_FULL_SCALE_PA
#undef RIG_PS_VALID_MIN
#undef RIG_PS_VALID_MAX
#undef RIG_SUPPLY_MIN_PA
#define RIG_PS_ZERO_COUNTS 0.0f
#define RIG_PS_SPAN_COUNTS 1.0f
#define RIG_PS_FULL_SCALE_PA 1.0f
#define RIG_PS_VALID_MIN 0u
#define RIG_PS_VALID_MAX 65535u
#define RIG_SUPPLY_MIN_PA 0.0f
#endif

#if (RIG_VALVE_CENTRE) < (RIG_VALVE_SPAN) || (RIG_VALVE_CENTRE) + (RIG_VALVE_SPAN) > (RIG_VALVE_MAX)
#error "rig_config.h: RIG_VALVE_CENTRE +- RIG_VALVE_SPAN must lie within 0 .. RIG_VALVE_MAX"
#endif
#if (RIG_WATCHDOG_MS) < 2 || (RIG_WATCHDOG_MS) > 1000
#error "rig_config.h: RIG_WATCHDOG_MS must lie between 2 and 1000"
#endif

#define RIG_CONFIG_INIT { \
    RIG_PERIOD_US, (uint32_t)(RIG_WATCHDOG_MS) * 1000u, RIG_STROKE_M, RIG_END_ZONE, RIG_ATMOSPHERE_PA, \
    { RIG_X_ZERO_COUNTS, RIG_X_SPAN_COUNTS, 0.0f, RIG_X_VALID_MIN, RIG_X_VALID_MAX }, \
    { RIG_P1_ZERO_COUNTS, RIG_P1_SPAN_COUNTS, RIG_P1_FULL_SCALE_PA, RIG_P1_VALID_MIN, RIG_P1_VALID_MAX }, \
    { RIG_P2_ZERO_COUNTS, RIG_P2_SPAN_COUNTS, RIG_P2_FULL_SCALE_PA, RIG_P2_VALID_MIN, RIG_P2_VALID_MAX }, \
    { RIG_PS_ZERO_COUNTS, RIG_PS_SPAN_COUNTS, RIG_PS_FULL_SCALE_PA, RIG_PS_VALID_MIN, RIG_PS_VALID_MAX }, \
    RIG_HAS_SUPPLY_SENSOR, RIG_SUPPLY_MIN_PA, \
    RIG_VALVE_CENTRE, RIG_VALVE_SPAN, RIG_VALVE_MAX }

#endif
