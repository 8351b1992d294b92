"""What every subcommand shares (the application itself is imported by a subcommand when it
runs, so that `--help` and process start stay fast): the bad-input error, output on stderr, the cylinder file
(or the built-in one), the --effect and --estimate lists, the --rerun mode, and the rig a
subcommand drives (--serial, --can or the virtual rig).

Exit status of every subcommand: 0 success, 2 bad input (files, options: one sentence),
1 a failure of the tool, 130 interrupted.
"""
from __future__ import annotations

import argparse
import math
import re
import sys
from importlib import resources
from pathlib import Path
from typing import Callable, Sequence

from sim.cylinder import Cylinder, load_cylinder

__all__ = ["UsageError", "OneLineParser", "typed", "check_paths", "add_max_rows", "read_runs", "eprint",
           "progress_printer", "default_config_path", "load_config", "parse_effects", "estimate_list",
           "positive_float", "rerun_mode", "open_rig", "EFFECT_HELP"]

EFFECT_HELP = ("an unmodelled effect, e.g. stiction:Fs_excess=8,v_stribeck=0.01 (repeatable; any word of the "
               "vocabulary, see docs/effects.md), or a friction model of the family as the friction, e.g. "
               "cvs:Fc_pos=1.59,Fs_pos=6 (docs/friction.md)")


class UsageError(ValueError):
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
    from ..errors import InputError

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
    """Where progress lines go: stderr, or nowhere with -q."""
    return None if quiet else eprint


def default_config_path() -> Path:
    """The built-in cylinder A (32 mm x 100 mm) of the combined-reality paper."""
    return Path(str(resources.files("combined_reality") / "data" / "cyl_a_32x100.toml"))


def load_config(path: str | None) -> Cylinder:
    """The cylinder file given with --config, else the built-in one."""
    return load_cylinder(path if path else default_config_path())


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


def positive_float(text: str, what: str) -> float:
    """A positive, finite number given as text, or a UsageError naming the option."""
    try:
        v = float(text)
    except ValueError:
        raise UsageError(f"{what} {text}: give a number or max.") from None
    if not (v > 0 and math.isfinite(v)):
        raise UsageError(f"{what} must be positive, not {text}.")
    return v


def rerun_mode(words: Sequence[str]) -> tuple[str, str | None]:
    """--rerun spawn | connect [ADDR] | save FILE | off, as (mode, target)."""
    mode, *rest = words
    if mode not in ("spawn", "connect", "save", "off"):
        raise UsageError(f"--rerun {mode}: use spawn, connect ADDR, save FILE or off.")
    if mode == "save" and len(rest) != 1:
        raise UsageError("--rerun save needs exactly one file name (--rerun save session.rrd).")
    if mode in ("spawn", "off") and rest or len(rest) > 1:
        raise UsageError(f"--rerun {' '.join(words)}: too many arguments.")
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
