"""Progress for people, said by the library and drawn by whoever called it.

A progress callback takes lines (`Callable[[str], None]`: a printer, a logger, nothing). A
`Step` is such a line that also counts: `done` of `total` (None: open-ended, like a fit's
iterations) of a `task` ("iterations", "candidate fits", "s simulated"). A callback that only
prints lines prints it as the line it is; the command line draws a bar with the time left
from it. The library never prints."""
from __future__ import annotations

from typing import Callable

__all__ = ["Step", "Say", "stage_steps", "counter"]

Say = Callable[[str], None]


class Step(str):
    """A progress line that counts `done` of `total` of `task`; `figures` hold numbers worth
    showing beside the count (a fit's cost)."""

    task: str
    done: float
    total: float | None
    figures: dict

    def __new__(cls, text: str, task: str, done: float, total: float | None = None, **figures: float) -> "Step":
        self = super().__new__(cls, text)
        self.task, self.done, self.total, self.figures = task, done, total, figures
        return self


def counter(say: Say | None, task: str, total: int) -> Callable[..., None] | None:
    """A callback for each piece of `total` done (any arguments ignored): '3/12 candidate fits'."""
    if say is None:
        return None
    done = [0]

    def tick(*_args) -> None:
        done[0] += 1
        say(Step(f"  {done[0]}/{total} {task}", task, done[0], total))

    return tick


def stage_steps(say: Say | None, stage: str) -> Say | None:
    """A fit's progress within a stage of a larger piece of work: its Steps under the stage's
    name, its other lines left out (the stage says what it did when it ends)."""
    if say is None:
        return None

    def forward(line: str) -> None:
        if isinstance(line, Step):
            text = f"{line.task[:-1] if line.task.endswith('s') else line.task} {line.done:g}" + "".join(
                f", {k} {v:.6g}" for k, v in line.figures.items())  # the stage's line, short: its figures only
            say(Step(f"  {stage}: {text}", f"{stage}: {line.task}", line.done, line.total, **line.figures))

    return forward
