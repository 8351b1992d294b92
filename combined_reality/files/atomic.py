"""Files written whole or not at all: readers see the old file or the complete new one,
also after a crash. Every file the tool writes (runs, JSON results, reports, cylinder
files, points tables, batch results) goes through here."""
from __future__ import annotations

import json
import math
import os
import secrets
from pathlib import Path
from typing import Iterable

__all__ = ["atomic_write", "write_text_atomic", "write_json_atomic", "clean_json", "fsync_dir"]


def atomic_write(path: Path, data: bytes | Iterable[bytes]) -> None:
    """Write via a temporary file, fsync and rename: readers see the old file or the whole new one.
    `data` may come in parts (written as they are made: a long run's CSV is never held whole)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    # os.open with 0o666 lets the umask decide the permissions, as for an ordinary new file
    # (tempfile would leave the result readable by its owner only).
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
    try:
        with os.fdopen(fd, "wb") as f:
            for part in (data,) if isinstance(data, bytes) else data:
                f.write(part)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    fsync_dir(path.parent)


def fsync_dir(directory: Path) -> None:
    """Make a rename in `directory` durable (best effort: not possible on every platform)."""
    # Makes the rename itself durable; not possible on every platform, hence best effort.
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
    """Write UTF-8 text atomically, creating the folder if needed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
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
