"""CAN logs (any format python-can's LogReader reads: .asc, .blf, .log, .trc, ...) decoded
with a DBC through cantools. A channel is "Message.Signal" (or a signal name used by one
message only). Rows are the frames of the time channel's message; every other signal is
taken from its message's frame nearest in time (the frames of one sample arrive a fraction
of a period apart; docs/formats.md)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .mapping import ImportMapping, MappingError
from .raw import RawTable, Signal, align_signals, require_file

__all__ = ["read_can_log"]


def read_can_log(path: Path, mapping: ImportMapping) -> RawTable:
    db = _database(mapping)
    dbc_path = mapping.source.dbc
    require_file(path)
    t = mapping.channel("t")
    where = {c.name: _message_and_signal(db, mapping, c.source if c.source is not None else c.time_of)
             for c in mapping.channels}
    if t.time_of is None and where["t"][1] is None:
        raise MappingError(f"{mapping.path}: key 'columns.t.from' names the message {where['t'][0]}; use "
                           f"time_of = \"{where['t'][0]}\" for its frames' time stamps, or a signal for a clock.")
    frames = _decoded_frames(path, db, dbc_path, {db.get_message_by_name(m).frame_id: m for m, _ in where.values()})

    def signal(channel: str) -> Signal:
        msg, sig = where[channel]
        times = np.array([ts for ts, _ in frames[msg]])
        if sig is None:
            return Signal(times, times)
        return Signal(np.array([float(d[sig]) for _, d in frames[msg]]), times)

    base = signal("t")
    signals = {c.name: signal(c.name) for c in mapping.channels if c.name != "t"}
    aligned, kept, note = align_signals(mapping, signals, base.times, method="nearest")
    columns = {"t": base.values[kept], **aligned}
    if columns["t"].size < 2:
        raise MappingError(f"{path}: {columns['t'].size} sample(s); a run needs at least 2.")
    msg_t = where["t"][0]
    return RawTable(columns=columns, locate=lambda i: f"frame {int(kept[i]) + 1} of message {msg_t}",
                    describe=f"CAN log decoded with {dbc_path.name}, rows at the frames of {msg_t}",
                    notes=(note,) if note else ())


def _database(mapping: ImportMapping):
    """The mapping's DBC, loaded by cantools."""
    import cantools

    dbc_path = mapping.source.dbc
    if dbc_path is None:
        raise MappingError(f"{mapping.path}: a CAN log needs [source] dbc = \"...\" (the database that decodes its "
                           f"frames).")
    try:
        return cantools.database.load_file(dbc_path)
    except FileNotFoundError:
        raise MappingError(f"{mapping.path}: key 'source.dbc': {dbc_path} not found.") from None
    except Exception as e:  # cantools raises its own parse errors, UnsupportedDatabaseFormatError ...
        raise MappingError(f"{mapping.path}: key 'source.dbc': {dbc_path} is not a readable DBC "
                           f"({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}).") from None


def _message_and_signal(db, mapping: ImportMapping, name: str) -> tuple[str, str | None]:
    """A channel's source: "Message.Signal", a signal one message holds, or a message alone
    (its frames' time stamps: time_of)."""
    dbc_name = mapping.source.dbc.name
    msg_name, dot, sig_name = name.partition(".")
    names = {m.name for m in db.messages}
    if dot and msg_name in names:
        msg = db.get_message_by_name(msg_name)
        if sig_name not in [s.name for s in msg.signals]:
            raise MappingError(f"{mapping.path}: message {msg_name} of {dbc_name} has no signal '{sig_name}' "
                               f"(it has {', '.join(s.name for s in msg.signals)}).")
        return msg_name, sig_name
    if not dot and name in names:
        return name, None
    owners = [m.name for m in db.messages if name in [s.name for s in m.signals]]
    if len(owners) == 1:
        return owners[0], name
    if owners:
        raise MappingError(f"{mapping.path}: signal '{name}' is in several messages ({', '.join(owners)}); "
                           f"write it as Message.Signal.")
    raise MappingError(f"{mapping.path}: '{name}' is no message or signal of {dbc_name}.")


def _decoded_frames(path: Path, db, dbc_path: Path, ids: dict[int, str]) -> dict[str, list[tuple[float, dict]]]:
    """(time stamp, decoded signals) of every frame of the messages `ids` (frame id -> name)."""
    import can

    frames: dict[str, list[tuple[float, dict]]] = {m: [] for m in ids.values()}
    try:
        reader = can.LogReader(path)
    except (ValueError, OSError) as e:
        raise MappingError(f"{path}: python-can cannot read this log ({e}).") from None
    try:
        for k, msg in enumerate(reader):
            name = ids.get(msg.arbitration_id)
            if name is None or msg.is_error_frame or msg.is_remote_frame:
                continue
            try:
                frames[name].append((float(msg.timestamp), db.decode_message(msg.arbitration_id, msg.data,
                                                                             decode_choices=False)))
            except Exception as e:  # a frame the DBC cannot decode (too short, bad multiplexer)
                raise MappingError(f"{path}, frame {k + 1}: message {name} does not decode with {dbc_path.name} "
                                   f"({e}).") from None
    except MappingError:
        raise
    except Exception as e:  # a damaged log: python-can's readers raise ValueError, struct.error ...
        raise MappingError(f"{path}: python-can cannot read this log ({type(e).__name__}: {e}).") from None
    finally:
        stop = getattr(reader, "stop", None)
        if stop is not None:
            stop()
    for name, got in frames.items():
        if not got:
            raise MappingError(f"{path}: no frame of message {name} (id 0x{db.get_message_by_name(name).frame_id:x}).")
    return frames
