"""What every reader returns, and the alignment of channels recorded on their own time bases
(TDMS groups at other rates, MDF channel groups, CAN messages) onto the rows of the time
channel."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Mapping

import numpy as np

from .mapping import ImportMapping, MappingError

__all__ = ["RawTable", "Signal", "align_signals", "optional_reader", "require_file", "require_column_time",
           "require_finite"]


@dataclass(frozen=True)
class RawTable:
    """The recording's mapped channels, raw (in the recording's units), one row per sample."""

    columns: dict[str, np.ndarray]  # run channel name (t, u, x, ...) -> raw values, equal lengths
    locate: Callable[[int], str]  # row index -> where it is in the recording ("line 17", "row 16", ...)
    describe: str  # the format and how it was read, for the run's header
    notes: tuple[str, ...] = ()  # what reading did that the user should know (rows dropped by alignment)
    digest: str | None = None  # the recording's sha256 (hex), where the reader took it as it read the bytes


@dataclass(frozen=True)
class Signal:
    """A channel with its own time stamps (s, in the recording's clock)."""

    values: np.ndarray
    times: np.ndarray


def align_signals(mapping: ImportMapping, signals: Mapping[str, Signal], time_track: np.ndarray,
                  method: str = "interpolate") -> tuple[dict[str, np.ndarray], np.ndarray, str | None]:
    """Every channel at the instants of `time_track` (the rows). The command is held from its
    last sample (zero-order hold: it is what the valve got); measurements are interpolated
    linearly, or with method "nearest" taken from the sample nearest in time (CAN frames of
    one sample arrive a fraction of a period apart). Rows outside a channel's recorded span are
    dropped. Returns the columns, the row indices kept (into time_track) and a note, if rows
    were dropped."""
    tt = np.asarray(time_track, float)
    keep = np.ones(tt.size, bool)
    out: dict[str, np.ndarray] = {}
    for name, sig in signals.items():
        times, vals = np.asarray(sig.times, float), np.asarray(sig.values, float)
        if times.size == 0:
            raise MappingError(f"{mapping.path}: key 'columns.{name}': the channel has no samples.")
        if times.size == tt.size and np.array_equal(times, tt):
            out[name] = vals
            continue
        if np.any(np.diff(times) < 0):
            order = np.argsort(times, kind="stable")
            times, vals = times[order], vals[order]
        if name == "u":
            idx = np.searchsorted(times, tt, side="right") - 1
            keep &= idx >= 0
            out[name] = vals[np.clip(idx, 0, None)]
        elif method == "nearest":
            idx = np.clip(np.searchsorted(times, tt), 1, max(1, times.size - 1))
            left = np.clip(idx - 1, 0, None)
            closer = np.abs(tt - times[left]) <= np.abs(times[np.minimum(idx, times.size - 1)] - tt)
            pick = np.where(closer, left, np.minimum(idx, times.size - 1))
            half = _half_period(times)
            keep &= (tt >= times[0] - half) & (tt <= times[-1] + half)
            out[name] = vals[pick]
        else:
            keep &= (tt >= times[0]) & (tt <= times[-1])
            out[name] = np.interp(tt, times, vals)
    kept = np.flatnonzero(keep)
    note = None
    if kept.size < tt.size:
        note = (f"{tt.size - kept.size} of {tt.size} rows left out where a channel had not been recorded yet "
                f"(or any more)")
    return {k: v[kept] for k, v in out.items()}, kept, note


def _half_period(times: np.ndarray) -> float:
    return 0.5 * float(np.median(np.diff(times))) if times.size > 1 else 0.0


def optional_reader(module: str, extra: str, what: str):
    """Import a reader's library, or say which extra installs it."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise MappingError(f"reading {what} needs the package '{module.split('.')[0]}', which is not installed: "
                           f"pip install 'combined-reality[{extra}]'.") from None


def require_file(path: Path) -> None:
    """A recording that is not there (or a folder) in one sentence."""
    if not path.is_file():
        raise MappingError(f"{path}: file not found." if not path.exists() else f"{path}: not a file.")


def require_column_time(mapping: ImportMapping, what: str) -> None:
    """Formats without time tracks need the time as a column (from = ...), not time_of."""
    if mapping.channel("t").time_of is not None:
        raise MappingError(f"{mapping.path}: key 'columns.t.time_of' is for recordings with time tracks (TDMS, MDF, "
                           f"CAN logs); name the time {what} with from = \"...\".")


def require_finite(path: Path, columns: dict[str, np.ndarray], locate: Callable[[int], str]) -> None:
    """Every mapped value a finite number, else the first that is not, located."""
    for name, values in columns.items():
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            raise MappingError(f"{path}, {locate(int(bad[0]))}, channel for {name}: {values[bad[0]]} is not a "
                               f"finite number.")
