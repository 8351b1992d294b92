"""The rules of the options, one function per option, used wherever the option appears: the
command line's flags (as their argparse types, so that a bad value is refused as it is
parsed), a batch manifest's rows, the library's option records. Each takes the value (text
from the command line, a number from a TOML file) and the name to say it by ("--seed",
"simulate.seed"), and returns the value or raises OptionError, one sentence naming it.

The limits are documented in docs/formats.md ("Limits") and in each option's --help."""
from __future__ import annotations

import math
import re
from typing import Iterable, Sequence

from sim.cylinder import parameter_list_problem

from .errors import InputError, shorten

__all__ = ["OptionError", "SEED_MAX", "RATE_MIN", "RATE_MAX", "INTERVAL_MAX", "MIN_SAMPLES", "MAX_SIMULATED_SAMPLES",
           "MAX_LIVE_DURATION", "MAX_ITER", "MAX_ROWS", "MAX_WINDOW", "MIN_UPDATE", "seed", "sample_rate",
           "positive_number", "load", "replay_speed", "report_file", "positive_seconds", "interval", "whole_number",
           "simulated_samples", "window", "update", "live_duration",
           "parameter_names", "check_estimable", "scheduler_address", "max_rows"]

SEED_MAX = 2**32 - 1
RATE_MIN, RATE_MAX = 10.0, 100_000.0  # Hz: sample rates of a rig, a simulation, a resampling
INTERVAL_MAX = 10.0  # s: a shooting interval longer than this no model follows open loop
MIN_SAMPLES = 10  # a run shorter than this is nothing to read, fit or replay
# samples of one simulated run: an hour at 1 kHz and more (0.2 GB in memory), and fewer than a
# run file may have lines (files.MAX_ROWS), so that what is simulated can be read back
MAX_SIMULATED_SAMPLES = 4_000_000
MAX_LIVE_DURATION = 86_400.0  # s: a live session or procedure runs at most a day
MAX_ITER = 10_000
MAX_WINDOW = 600.0  # s: the online estimator's moving horizon (600k samples at 1 kHz in one window)
MIN_UPDATE = 1e-3  # s: the online estimator updates at most every millisecond of data
MAX_ROWS = 5_000_000  # lines of a run file by default (83 min at 1 kHz); --max-rows changes it


class OptionError(InputError):
    """An option value outside its rule: one sentence naming the option (exit status 2)."""


def _number(value, name: str) -> float:
    if isinstance(value, bool):
        raise OptionError(f"{name} must be a number, not {value!r}.")
    if isinstance(value, (int, float)):
        return float(value)
    try:
        return float(str(value).strip())
    except ValueError:
        raise OptionError(f"{name} must be a number, not {shorten(repr(value))}.") from None


def whole_number(value, name: str, lo: int, hi: int | None = None) -> int:
    """A whole number in [lo, hi]."""
    if isinstance(value, bool) or isinstance(value, float) and not value.is_integer():
        raise OptionError(f"{name} must be a whole number, not {value!r}.")
    try:
        n = int(value) if isinstance(value, (int, float)) else int(str(value).strip())
    except (ValueError, OverflowError):
        raise OptionError(f"{name} must be a whole number, not {shorten(repr(value))}.") from None
    if n < lo or hi is not None and n > hi:
        span = f"at least {lo}" if hi is None else f"from {lo} to {hi}"
        raise OptionError(f"{name} must be a whole number {span}, not {n}.")
    return n


def seed(value, name: str = "--seed") -> int:
    """A seed of the random generators: a whole number from 0 to 2^32 - 1."""
    return whole_number(value, name, 0, SEED_MAX)


def sample_rate(value, name: str = "--rate") -> float:
    """A sample rate in Hz, from 10 to 100000."""
    v = _number(value, name)
    if not RATE_MIN <= v <= RATE_MAX:
        raise OptionError(f"{name} must lie between {RATE_MIN:g} and {RATE_MAX:g} Hz, not {shorten(value)}.")
    return v


def positive_number(value, name: str) -> float:
    """A positive, finite number (a speed in m/s, a relative spread)."""
    v = _number(value, name)
    if not (v > 0 and math.isfinite(v)):
        raise OptionError(f"{name} must be a positive number, not {shorten(value)}.")
    return v


def load(value, name: str = "--load") -> float:
    """A constant normal load on the seals and guides: a finite force of at least 0 N."""
    v = _number(value, name)
    if not (v >= 0 and math.isfinite(v)):
        raise OptionError(f"{name} must be a non-negative force in N, not {shorten(value)}.")
    return v


def replay_speed(value, name: str = "--speed") -> float:
    """How fast a run is replayed: a positive, finite factor of real time, or max (infinity)."""
    if str(value).strip() == "max":
        return math.inf
    try:
        v = float(str(value).strip())
    except ValueError:
        raise OptionError(f"{name} {shorten(value)}: give a number or max.") from None
    if not (v > 0 and math.isfinite(v)):
        raise OptionError(f"{name} must be positive, not {shorten(value)}.")
    return v


def report_file(value, name: str = "--report") -> str:
    """An HTML report's file name: it ends in .html or .htm."""
    text = str(value)
    if not text.lower().endswith((".html", ".htm")):
        raise OptionError(f"{name} {shorten(text)}: the report is HTML; name it REPORT.html.")
    return text


def positive_seconds(value, name: str, allow_inf: bool = False) -> float:
    """A positive, finite number of seconds (or infinity where `allow_inf`)."""
    v = _number(value, name)
    if not (v > 0 and (math.isfinite(v) or allow_inf and v == math.inf)):
        extra = " (or inf)" if allow_inf else ""
        raise OptionError(f"{name} must be a positive number of seconds{extra}, not {shorten(value)}.")
    return v


def interval(value, name: str = "--interval") -> float:
    """A shooting interval: more than 0 and at most 10 s."""
    v = positive_seconds(value, name)
    if v > INTERVAL_MAX:
        raise OptionError(f"{name} must be at most {INTERVAL_MAX:g} s (a multiple-shooting interval; the model "
                          f"runs open loop over it), not {shorten(value)}.")
    return v


def simulated_samples(duration: float, rate: float, name: str = "--duration", runs: int = 1) -> int:
    """The samples of a simulated run of `duration` s at `rate` Hz, refused outside [MIN_SAMPLES,
    MAX_SIMULATED_SAMPLES] (a run too short to read, or too long for the memory)."""
    n = duration * rate
    if n < MIN_SAMPLES:
        raise OptionError(f"{name} {duration:g} s at {rate:g} Hz gives {n:.3g} samples; a run needs at least "
                          f"{MIN_SAMPLES} (at least {MIN_SAMPLES / rate:g} s).")
    if n * runs > MAX_SIMULATED_SAMPLES:
        raise OptionError(f"{name} {duration:g} s at {rate:g} Hz gives {n * runs:.3g} samples; at most "
                          f"{MAX_SIMULATED_SAMPLES:.0e} are simulated at once (at most "
                          f"{MAX_SIMULATED_SAMPLES / rate / runs:g} s at this rate).")
    return int(n)


def window(value, name: str = "--window") -> float:
    """The online estimator's moving horizon: more than 0, at most 600 s."""
    v = positive_seconds(value, name)
    if v > MAX_WINDOW:
        raise OptionError(f"{name} must be at most {MAX_WINDOW:g} s, not {shorten(value)}.")
    return v


def update(value, name: str = "--update") -> float:
    """Data between the online estimator's updates: at least 1 ms."""
    v = positive_seconds(value, name)
    if v < MIN_UPDATE:
        raise OptionError(f"{name} must be at least {MIN_UPDATE:g} s, not {shorten(value)}.")
    return v


def live_duration(value, name: str = "--duration") -> float:
    """Seconds of a session on a rig: positive, at most a day."""
    v = positive_seconds(value, name)
    if v > MAX_LIVE_DURATION:
        raise OptionError(f"{name} must be at most {MAX_LIVE_DURATION:g} s (a day) on a rig, not {shorten(value)}.")
    return v


def parameter_names(value, name: str = "--estimate") -> tuple[str, ...]:
    """A comma-separated list of names (or a list): at least one, each once (parameters to
    estimate, effects to try; sim.cylinder.parameter_list_problem, as a cylinder file's)."""
    items = value.split(",") if isinstance(value, str) else list(value)
    names = tuple(str(s).strip() for s in items if str(s).strip())
    if not names:
        raise OptionError(f"{name} needs at least one name.")
    problem = parameter_list_problem(names)
    if problem:
        raise OptionError(f"{name} {problem}.")
    return names


def check_estimable(names: Sequence[str], known: Iterable[str], name: str = "--estimate") -> None:
    """Refuse a parameter that is not among `known`, listing those that are."""
    problem = parameter_list_problem(names, tuple(known))
    if problem:
        raise OptionError(f"{name} {problem}.")


_SCHEMES = ("tcp", "tls", "ws", "wss", "ucx", "inproc")
_HOST_PORT = re.compile(r"^(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9._-]+)(:(?P<port>\d{1,5}))?/?$")


def scheduler_address(value, name: str = "--scheduler") -> str:
    """A dask scheduler's address: SCHEME://HOST[:PORT] (tcp, tls, ws, wss, ucx, inproc) or HOST:PORT."""
    text = str(value).strip()
    scheme, sep, rest = text.partition("://")
    if not sep:
        scheme, rest = "tcp", text
        if ":" not in rest:
            rest = ""  # without a scheme, the port must be given
    m = _HOST_PORT.match(rest) if scheme in _SCHEMES else None
    if scheme == "inproc" and rest:
        return text
    if m is None or m["port"] is not None and not 0 < int(m["port"]) < 65536:
        raise OptionError(f"{name} {shorten(repr(text))} is not a scheduler address; give one as "
                          f"tcp://HOST:PORT (e.g. tcp://10.0.0.5:8786) or HOST:PORT.")
    return text


def max_rows(value, name: str = "--max-rows") -> int:
    """The most lines a run file may have."""
    return whole_number(value, name, 2)
