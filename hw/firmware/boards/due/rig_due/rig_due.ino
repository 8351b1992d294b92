// Rig firmware for the Arduino Due: the servopneumatic rig of combined_reality
// (docs/firmware.md). Edit rig_config.h, then upload through the Programming Port. The
// board talks docs/protocol.md on the Programming Port at 2 Mbaud; do not use Serial or
// the Serial Monitor with it. The firmware runs the Due at 32 MHz (delay() and millis()
// are not used, and run slow).
#include "rig_board.h"

// the core calls this before setup(); the watchdog's mode register can be written once
void watchdogSetup(void) {
  rig_board_watchdog();
}

void setup() {
  rig_board_setup();
}

void loop() {
  rig_board_step();
}
