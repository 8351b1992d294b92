/* The board's two entry points: the sketch's setup() and loop(), or main() in a bare build. */
#ifndef RIG_BOARD_H
#define RIG_BOARD_H

#ifdef __cplusplus
extern "C" {
#endif

void rig_board_setup(void);
void rig_board_step(void);

#ifdef __cplusplus
}
#endif

#endif
