"""Files written whole or not at all: readers see the old file or the complete new one,
also after a crash. Every file the tool writes (runs, JSON results, reports, cylinder
files, points tables, batch results) goes through here; the command line checks the paths
first (files.outputs.check_outputs). A device or a folder is never replaced, no folder is
created, and an OS error is one sentence naming the path and the reason (files.outputs)."""
from __future__ import annotations

import contextlib
import json
import math
import os
import secrets
from pathlib import Path
from typing import BinaryIO, Iterable, Iterator

from .outputs import os_error, refuse_special, write_target

__all__ = ["atomic_write", "atomic_writer", "write_text_atomic", "write_json_atomic", "clean_json", "fsync_dir"]


@contextlib.contextmanager
def atomic_writer(path: str | os.PathLike[str]) -> Iterator[BinaryIO]:
    """A binary file to write `path` through in pieces: a temporary file beside it, fsynced and
    renamed over `path` when the block ends without an error, removed otherwise."""
    path = Path(path)
    refuse_special(path)
    target = write_target(path)
    tmp = target.with_name(f".{target.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    try:
        # os.open with 0o666 lets the umask decide the permissions, as for an ordinary new file
        # (tempfile would leave the result readable by its owner only).
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
    except OSError as e:
        raise os_error(e, path) from None
    try:
        with os.fdopen(fd, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException as e:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(e, OSError):
            raise os_error(e, path) from None
        raise
    fsync_dir(target.parent)


def atomic_write(path: str | os.PathLike[str], data: bytes | Iterable[bytes]) -> None:
    """Write via a temporary file, fsync and rename: readers see the old file or the whole new one.
    `data` may come in parts (written as they are made: a long run's CSV is never held whole)."""
    with atomic_writer(path) as f:
        for part in (data,) if isinstance(data, bytes) else data:
            f.write(part)


def fsync_dir(directory: Path) -> None:
    """Make a rename in `directory` durable (best effort: not possible on every platform)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def write_text_atomic(path: str | os.PathLike[str], text: str) -> None:
    """Write UTF-8 text atomically (the folder must exist: no folder is created unasked)."""
    atomic_write(path, text.encode("utf-8"))


def write_json_atomic(path: str | os.PathLike[str], data: dict) -> None:
    """Write JSON atomically; NaN and infinity, which JSON lacks, must be cleaned first (clean_json)."""
    write_text_atomic(path, json.dumps(data, indent=2, allow_nan=False, default=_json_default) + "\n")


def _json_default(o):
    try:
        return float(o)
    except (TypeError, ValueError):
        return str(o)


def clean_json(obj):
    """NaN/inf are not JSON: report them as null."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: clean_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [clean_json(v) for v in obj]
    return obj
