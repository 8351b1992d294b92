/* The entry point of a bare build (make avr): what the Arduino core's main() does for the
 * sketch, without the rest of the core. */
#include "rig_board.h"

int main(void)
{
    rig_board_setup();
    for (;;)
        rig_board_step();
}
