"""What a live session says on stderr: one status line, and warnings that do not flood it.

On a terminal the status line is rewritten in place (carriage return, erase to the end of
the line) at most `refresh_s` apart; otherwise (a log file, a pipe, CI) it is printed as a
plain line every `plain_every_s`. A warning of a kind not seen before is printed at once on
its own line; the same kind again (the same words, whatever numbers they carry) is held
back for `quiet_s` and then printed with the count of those held back; `summary()` sums up
every kind at the end. Warnings arrive from the rig's reader and the session alike.
"""
from __future__ import annotations

import re
import sys
import time
from dataclasses import dataclass
from typing import Callable, TextIO

__all__ = ["Console"]

_NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?(?:e[-+]?\d+)?")


@dataclass
class _Kind:
    first: str  # the first message of this kind, as printed
    count: int = 1  # messages of this kind so far
    held: int = 0  # held back since the last one printed
    last_printed: float = 0.0


class Console:
    def __init__(self, stream: TextIO | None = None, *, status: bool = True, refresh_s: float = 0.2,
                 plain_every_s: float = 5.0, quiet_s: float = 10.0, clock: Callable[[], float] = time.monotonic):
        self.stream = stream if stream is not None else sys.stderr
        self.show_status = status
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.refresh_s = refresh_s if self.tty else plain_every_s
        self.quiet_s, self.clock = quiet_s, clock
        self._kinds: dict[str, _Kind] = {}
        self._status = ""  # the status line as last drawn (terminal only)
        self._status_t = -float("inf")

    # ---------------------------------------------------------------- status
    def status(self, text: str, force: bool = False) -> None:
        """The current state in one line (drawn at most every refresh_s unless forced)."""
        if not self.show_status:
            return
        now = self.clock()
        if not force and now - self._status_t < self.refresh_s:
            return
        self._status_t = now
        if self.tty:
            self._status = text
            self._write("\r" + text + "\x1b[K")
        else:
            self._write(text + "\n")

    # ---------------------------------------------------------------- messages
    def say(self, msg: str) -> None:
        """A line that is always printed (a session event, the summary)."""
        self._line(msg)

    def warn(self, msg: str) -> None:
        """A warning: printed when its kind is new or quiet for quiet_s, else counted."""
        key = _NUMBER.sub("#", msg)
        now = self.clock()
        kind = self._kinds.get(key)
        if kind is None:
            self._kinds[key] = _Kind(msg, last_printed=now)
            self._line(msg)
            return
        kind.count += 1
        if now - kind.last_printed < self.quiet_s:
            kind.held += 1
            return
        note = f" ({kind.held} more like it in the last {now - kind.last_printed:.0f} s)" if kind.held else ""
        kind.held, kind.last_printed = 0, now
        self._line(msg + note)

    def summary(self) -> list[str]:
        """One line per kind of warning that came more than once: how often in all."""
        return [f"{k.count} × '{k.first}' (and the like)" for k in self._kinds.values() if k.count > 1]

    def close(self) -> None:
        """End the status line on a terminal so the next output starts on a fresh line."""
        if self.tty and self._status:
            self._write("\n")
            self._status = ""

    # ---------------------------------------------------------------- output
    def _line(self, msg: str) -> None:
        if self.tty and self._status:  # the message above, the status line below it again
            self._write("\r\x1b[K" + msg + "\n" + self._status + "\x1b[K")
        else:
            self._write(msg + "\n")

    def _write(self, text: str) -> None:
        try:
            self.stream.write(text)
            self.stream.flush()
        except (OSError, ValueError):  # a closed or broken stderr must not end the session
            pass
