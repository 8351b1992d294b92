/* The board's two entry points: the sketch's setup() and loop(), or main() in a bare build. */
#ifndef RIG_BOARD_H
#define RIG_BOARD_H

#ifdef __cplusplus
extern "C" {
#endif

/* the hardware watchdog's one write (under the Arduino core: from watchdogSetup()) */
void rig_board_watchdog(void);
void rig_board_setup(void);
void rig_board_step(void);

#ifdef __cplusplus
}
#endif

#endif
