"""LabVIEW TDMS files through npTDMS (the `tdms` extra). A channel is "Group/Channel"; the
time comes from a channel (from = "Group/Time") or from a waveform channel's own time track
(time_of = "Group/Channel": its wf_start_offset and wf_increment). Channels of other lengths
are aligned on their time tracks (docs/formats.md)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .mapping import ImportMapping, MappingError
from .raw import RawTable, Signal, align_signals, optional_reader, require_file, require_finite

__all__ = ["read_tdms"]


def read_tdms(path: Path, mapping: ImportMapping) -> RawTable:
    nptdms = optional_reader("nptdms", "tdms", "TDMS files")
    require_file(path)
    try:
        f = nptdms.TdmsFile.read(path)
    except Exception as e:  # npTDMS raises ValueError, KeyError, struct.error ... on a damaged file
        raise MappingError(f"{path}: not a readable TDMS file ({type(e).__name__}: {e}).") from None

    def channel(name: str):
        group, _, chan = name.partition("/")
        try:
            return f[group][chan]
        except KeyError:
            known = [f"{g.name}/{c.name}" for g in f.groups() for c in g.channels()]
            raise MappingError(f"{path}: no channel '{name}' (channels are 'Group/Channel': "
                               f"{', '.join(repr(k) for k in known[:10])}{' ...' if len(known) > 10 else ''}).") \
                from None

    def values(name: str) -> np.ndarray:
        try:
            return np.asarray(channel(name)[:], dtype=float)
        except (TypeError, ValueError):
            raise MappingError(f"{path}: channel '{name}' does not hold numbers.") from None

    def track(name: str) -> np.ndarray:
        try:
            return np.asarray(channel(name).time_track(), dtype=float)
        except (KeyError, ValueError):
            raise MappingError(f"{path}: channel '{name}' has no time track (no wf_increment property); give the "
                               f"time as a channel with from = \"Group/Time\".") from None

    t = mapping.channel("t")
    raw = {c.name: values(c.source) for c in mapping.channels if c.source is not None}
    if t.time_of is not None:
        raw["t"] = track(t.time_of)
    n = raw["t"].size
    describe = f"TDMS, {n} samples"
    notes: tuple[str, ...] = ()
    if any(v.size != n for v in raw.values()):  # other rates: align on the time tracks
        base = raw["t"] if t.time_of is not None else track(t.source)
        signals = {c.name: Signal(raw[c.name], track(c.source)) for c in mapping.channels
                   if c.source is not None and c.name != "t"}
        aligned, kept, note = align_signals(mapping, signals, base)
        raw = {"t": raw["t"][kept], **aligned}
        describe += ", channels of other rates aligned on the time tracks"
        notes = (note,) if note else ()
    locate = (lambda i: f"sample {i + 1}")  # noqa: E731
    require_finite(path, raw, locate)
    if raw["t"].size < 2:
        raise MappingError(f"{path}: {raw['t'].size} sample(s); a run needs at least 2.")
    return RawTable(columns=raw, locate=locate, describe=describe, notes=notes)
