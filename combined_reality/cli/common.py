"""What every subcommand shares (the application itself is imported by a subcommand when it
runs, so that `--help` and process start stay fast): the bad-input error, output on stderr, the cylinder file
(or the built-in one), the --effect and --estimate lists, the --rerun mode, and the rig a
subcommand drives (--serial, --can or the virtual rig).

Exit status of every subcommand: 0 success, 2 bad input (files, options: one sentence),
1 a failure of the tool, 130 interrupted.
"""
from __future__ import annotations

import atexit
import argparse
import re
import sys
import threading
import time
from typing import Callable, Sequence

from sim.cylinder import Cylinder, load_cylinder

from ..errors import InputError

__all__ = ["UsageError", "OneLineParser", "typed", "check_paths", "add_max_rows", "read_runs", "eprint",
           "progress_printer", "ProgressView", "load_config",
           "preflight_runs", "parse_effects", "estimate_list", "rerun_mode", "open_rig",
           "EFFECT_HELP"]

EFFECT_HELP = ("an unmodelled effect, e.g. stiction:Fs_excess=8,v_stribeck=0.01 (repeatable; any word of the "
               "vocabulary, see docs/effects.md), a friction model of the family as the friction, e.g. "
               "cvs:Fc_pos=1.59,Fs_pos=6 (docs/friction.md), or a friction that changes during the run, e.g. "
               "friction_change:t_step=30,step_Fc=0.3,step_Fv=0.3 or friction_change:ramp_Fc=0.00667")


class UsageError(InputError):
    """Bad input from the command line (exit status 2)."""


class OneLineParser(argparse.ArgumentParser):
    """argparse that says a bad command line in one line on stderr (exit status 2), like every
    other refusal; the option rules' own sentences (combined_reality.options) stand alone."""

    def error(self, message: str):
        m = re.match(r"argument [^:]+: (-.*)", message, re.S)
        said = m[1] if m else message  # a rule's sentence already names its option
        eprint(f"{self.prog}: {said.rstrip('.')}" + ("." if m else f" (see {self.prog} --help)."))
        raise SystemExit(2)


def typed(rule: Callable, name: str | None = None, **kw) -> Callable[[str], object]:
    """An option rule of combined_reality.options as an argparse type: the value is checked as
    it is parsed, with the rule's sentence."""
    def convert(text: str):
        try:
            return rule(text, name, **kw) if name else rule(text, **kw)
        except InputError as e:
            raise argparse.ArgumentTypeError(str(e)) from None

    convert.__name__ = rule.__name__
    return convert


def check_paths(outputs: dict, inputs: Sequence = (), folders: dict | None = None) -> None:
    """The output options checked before any work (files.check_outputs): writable, not an input."""
    from ..files import check_outputs

    check_outputs(outputs, [p for p in inputs if p], folders)


def eprint(msg: str) -> None:
    """One line on stderr, at once (progress, warnings, errors)."""
    print(msg, file=sys.stderr, flush=True)


def progress_printer(quiet: bool) -> Callable[[str], None] | None:
    """Where progress goes: stderr (ProgressView), or nowhere with -q."""
    if quiet:
        return None
    view = ProgressView()
    atexit.register(view.close)
    return view


def _duration(s: float) -> str:
    s = max(0.0, s)
    return f"{s:.0f} s" if s < 90 else f"{s / 60:.1f} min" if s < 5400 else f"{s / 3600:.1f} h"


class ProgressView:
    """Progress on stderr: a library's lines as they come; its Steps (lines that count) on a
    terminal as a bar per task (tqdm: the count, the time left where the total is known, the
    cost beside), elsewhere as their lines with the time left. A plain line clears the bars
    and is printed above them."""

    def __init__(self) -> None:
        self.tty = sys.stderr.isatty()
        self.bars: dict = {}
        self.seen: dict[str, tuple[float, float]] = {}  # task -> (first time, count then)
        self.lock = threading.Lock()  # a calibration's first two stages report from two threads

    def __call__(self, line: str) -> None:
        from ..progress import Step

        with self.lock:
            if isinstance(line, Step):
                self._step(line)
            else:
                self._close_bars()
                eprint(str(line))

    def _step(self, s) -> None:
        now = time.perf_counter()
        t0, d0 = self.seen.setdefault(s.task, (now, s.done))
        left = None
        if s.total is not None and s.done < s.total and s.done > d0 and now > t0:
            left = (s.total - s.done) * (now - t0) / (s.done - d0)
        if not self.tty:
            eprint(str(s) + (f" (about {_duration(left)} left)" if left is not None else ""))
            return
        from tqdm import tqdm

        bar = self.bars.get(s.task)
        if bar is None:
            fmt = ("{desc}: {n_fmt}/{total_fmt} |{bar}| [{elapsed}<{remaining}]{postfix}" if s.total is not None
                   else "{desc}: {n_fmt} [{elapsed}, {rate_fmt}]{postfix}")
            bar = self.bars[s.task] = tqdm(total=s.total, desc=s.task.strip(), file=sys.stderr, leave=False,
                                           dynamic_ncols=True, position=len(self.bars), bar_format=fmt,
                                           unit="", mininterval=0.2)
        if "cost" in s.figures:
            bar.set_postfix_str(f"cost {s.figures['cost']:.4g}", refresh=False)
        bar.update(s.done - bar.n)
        bar.refresh()

    def _close_bars(self) -> None:
        for bar in self.bars.values():
            bar.close()
        self.bars.clear()

    def close(self) -> None:
        with self.lock:
            self._close_bars()


def load_config(path: str | None) -> Cylinder:
    """The cylinder file given with --config, else the built-in one (files.BUILT_IN says so)."""
    from ..files.cylinder_choice import default_config_path

    return load_cylinder(path if path else default_config_path())


def preflight_runs(cyl: Cylinder, runs: Sequence, estimate: Sequence[str] = (), held_out: Sequence = ()):
    """identify.preflight (refuses what it is sure of: exit status 2), its notes on stderr."""
    from ..identify import preflight

    found = preflight(cyl, runs, estimate, held_out)
    for note in found.notes:
        eprint(f"note: {note}.")
    return found


def parse_effects(specs: Sequence[str] | None) -> list:
    """--effect values: words of the effect vocabulary, or a friction model of the family
    (which replaces the cylinder file's friction), each as 'name:k=v,k=v'."""
    from sim.extension import check_combination
    from sim.friction_models import parse_truth_spec

    effects = []
    for spec in specs or ():
        try:
            effects.append(parse_truth_spec(spec))
        except ValueError as e:
            raise UsageError(f"--effect {spec}: {e}.") from None
    try:
        check_combination(effects)
    except ValueError as e:
        raise UsageError(f"--effect: {e}.") from None
    return effects


def estimate_list(arg, cyl: Cylinder, known: Sequence[str] | None = None) -> tuple[str, ...]:
    """--estimate NAME,NAME (checked as parsed: options.parameter_names): the parameters to
    estimate (default: the cylinder file's [identify]), each among `known` (default: every
    estimable parameter)."""
    from sim.cylinder import ESTIMABLE

    from .. import options

    if arg is None:
        return cyl.identify.estimate
    names = options.parameter_names(arg)
    options.check_estimable(names, ESTIMABLE if known is None else known)
    return names


def add_max_rows(p) -> None:
    """--max-rows: the reader's limit of a run file's lines (docs/formats.md, "Limits")."""
    from .. import options

    p.add_argument("--max-rows", type=typed(options.max_rows), default=options.MAX_ROWS, metavar="N",
                   help=f"refuse a run file of more than N lines before reading it (default {options.MAX_ROWS}, "
                        "83 min at 1 kHz)")


def read_runs(paths: Sequence[str], args) -> list:
    """The runs named on the command line, read within --max-rows, the same data given twice refused."""
    from ..files import check_distinct_runs, read_run

    runs = [read_run(p, args.max_rows) for p in paths]
    check_distinct_runs(runs, [str(p) for p in paths])
    return runs


def rerun_mode(words: Sequence[str]) -> tuple[str, str | None]:
    """--rerun spawn | connect [ADDR] | save FILE | off, as (mode, target)."""
    mode, *rest = words
    if mode not in ("spawn", "connect", "save", "off"):
        raise UsageError(f"--rerun {mode}: use spawn, connect ADDR, save FILE or off.")
    if mode == "save" and len(rest) != 1:
        raise UsageError("--rerun save needs exactly one file name (--rerun save session.rrd).")
    if mode in ("spawn", "off") and rest or len(rest) > 1:
        raise UsageError(f"--rerun {' '.join(words)}: too many arguments.")
    if mode != "off":
        from importlib.util import find_spec

        if find_spec("rerun") is None:
            raise UsageError(f"--rerun {mode} needs the Rerun SDK and viewer, which this installation lacks: "
                             "pip install rerun-sdk.")
    return mode, (rest[0] if rest else None)


def open_rig(args, cyl: Cylinder, effects: Sequence = (), *, rate: float = 1000.0, paced: bool = True,
             on_event: Callable[[str], None] = eprint):
    """The rig named by --serial PORT, --can CH [--interface], else the virtual rig in this
    process (paced to real time, or as fast as the CPU allows). `on_event` takes the link's
    one-line fault messages."""
    from hw.rig import RigError

    try:
        if args.serial:
            from hw.serial_rig import SerialRig

            return SerialRig(args.serial, on_event=on_event)
        if args.can:
            from hw.can_rig import CanRig

            # python-can's slcan waits 2 s after opening unless told otherwise
            extra = {"sleep_after_open": 0.1} if args.interface == "slcan" else {}
            return CanRig(args.can, interface=args.interface, on_event=on_event, **extra)
    except RigError as e:
        raise UsageError(f"{e}.") from None
    from hw.virtual_rig import VirtualRig

    rig = VirtualRig(cyl, effects, rate=rate, seed=args.seed)
    if paced:
        from ..live import PacedRig

        return PacedRig(rig)
    return rig
