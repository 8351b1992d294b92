"""ASAM MDF (3 and 4) files through asammdf (the `mdf` extra). A channel is its name; each
carries its own time stamps (its channel group's master). Rows are the samples of the time
channel (from = "...": its values are the time; time_of = "...": its time stamps are);
the other channels are aligned on them (the command held, measurements interpolated)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .mapping import ImportMapping, MappingError
from .raw import RawTable, Signal, align_signals, optional_reader, require_file, require_finite

__all__ = ["read_mdf"]


def read_mdf(path: Path, mapping: ImportMapping) -> RawTable:
    asammdf = optional_reader("asammdf", "mdf", "MDF files")
    require_file(path)
    try:
        mdf = asammdf.MDF(path)
    except Exception as e:  # asammdf raises MdfException, ValueError, struct.error ... on a damaged file
        raise MappingError(f"{path}: not a readable MDF file ({type(e).__name__}: {e}).") from None
    try:
        def signal(name: str) -> Signal:
            try:
                s = mdf.get(name)
            except Exception as e:  # MdfException: unknown or ambiguous name
                raise MappingError(f"{path}: channel '{name}': {e}.") from None
            try:
                return Signal(np.asarray(s.samples, dtype=float), np.asarray(s.timestamps, dtype=float))
            except (TypeError, ValueError):
                raise MappingError(f"{path}: channel '{name}' does not hold numbers.") from None

        t = mapping.channel("t")
        base = signal(t.time_of if t.time_of is not None else t.source)
        signals = {c.name: signal(c.source) for c in mapping.channels if c.source is not None and c.name != "t"}
    finally:
        mdf.close()
    aligned, kept, note = align_signals(mapping, signals, base.times)
    t_values = base.times if t.time_of is not None else base.values
    columns = {"t": t_values[kept], **aligned}
    locate = (lambda i: f"sample {int(kept[i]) + 1}")  # noqa: E731
    require_finite(path, columns, locate)
    if columns["t"].size < 2:
        raise MappingError(f"{path}: {columns['t'].size} sample(s) where every channel was recorded; a run needs at "
                           f"least 2.")
    return RawTable(columns=columns, locate=locate,
                    describe=f"MDF, {columns['t'].size} samples on the time base of the time channel",
                    notes=(note,) if note else ())
