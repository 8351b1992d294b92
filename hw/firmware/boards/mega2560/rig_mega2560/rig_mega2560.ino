// Rig firmware for the Arduino Mega 2560: the servopneumatic rig of combined_reality
// (docs/firmware.md). Edit rig_config.h, then upload. The board talks docs/protocol.md on
// its USB port at 2 Mbaud; do not use Serial or the Serial Monitor with it.
#include "rig_board.h"

void setup() {
  rig_board_setup();
}

void loop() {
  rig_board_step();
}
