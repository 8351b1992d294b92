"""Output paths, checked before the work: a command that will write a file says at once, in
one sentence, why it cannot, instead of failing after minutes of fitting.

A file output must be a regular file or not exist yet, in a folder that exists (no command
creates folders the user did not ask for) and accepts new files (tried by creating and
removing a file there, which also finds read-only and special file systems that permission
bits do not show); it must not be a device or FIFO (the atomic replace would turn it into a
regular file), nor one of the command's inputs (compared by inode, so that another name of
the same file is caught), nor the target of another output option. A folder output (batch
--out, demo --out) may be created, in a folder that exists. A disk with no space left is a
failure of the machine (exit status 1), everything else a bad request (exit status 2).

The writers (files.atomic, files.RunRecorder) say the same sentences when the disk fills or
a write fails midway (`os_error`), never naming their temporary files."""
from __future__ import annotations

import errno
import os
import secrets
from pathlib import Path
from typing import Iterable, Mapping

from sim.inputs import file_kind

from ..errors import InputError, ToolFailure

__all__ = ["OutputError", "WriteError", "check_outputs", "os_error", "refuse_special", "write_target"]

PathLike = str | os.PathLike[str]


class OutputError(InputError):
    """An output path the tool cannot write (exit status 2): one sentence naming it and why."""


class WriteError(ToolFailure):
    """Writing a valid output failed (the disk is full, an I/O error): exit status 1."""


# errno -> (why, whose fault: True = the request's)
_REASONS = {
    errno.ENOSPC: ("the disk is full", False),
    errno.EDQUOT: ("the disk quota is used up", False),
    errno.EFBIG: ("the file is larger than the file system allows", False),
    errno.EIO: ("an input/output error of the disk", False),
    errno.EROFS: ("the file system is read-only", True),
    errno.EACCES: ("permission denied", True),
    errno.EPERM: ("the operation is not permitted (an immutable file or folder?)", True),
    errno.ENOENT: ("the folder does not exist or takes no files", True),
    errno.ENOTDIR: ("a part of the path is not a folder", True),
    errno.EISDIR: ("it is a folder", True),
    errno.ENAMETOOLONG: ("the name is too long", True),
    errno.ELOOP: ("too many symbolic links", True),
}


def os_error(e: OSError, path: PathLike, flag: str | None = None,
             doing: str = "cannot write") -> InputError | ToolFailure:
    """The one sentence for an OS error on output `path` (never the name of a temporary file):
    an OutputError where the request is at fault, else a WriteError."""
    why, theirs = _REASONS.get(e.errno or 0, (e.strerror or str(e), False))
    who = f"{flag} {path}" if flag else str(path)
    msg = f"{who}: {doing} it: {why}."
    return OutputError(msg) if theirs else WriteError(msg)


def write_target(path: PathLike) -> Path:
    """Where writing `path` lands: a symbolic link is written through (the file it points to is
    replaced, the link kept), like a shell's redirection."""
    p = Path(path)
    return Path(os.path.realpath(p)) if p.is_symlink() else p


def refuse_special(path: PathLike, flag: str | None = None) -> None:
    """Refuse an existing target that is not a regular file: the tool never replaces a device,
    a FIFO or a folder."""
    try:
        st = os.stat(path)
    except OSError:
        return
    kind = file_kind(st.st_mode)
    if kind is not None:
        who = f"{flag} {path}" if flag else str(path)
        hint = "; give a file name inside it" if kind == "a folder" else "; the tool writes only regular files"
        raise OutputError(f"{who} is {kind}, not a file it may replace{hint}.")


def _identity(path: PathLike) -> tuple[int, int] | None:
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return st.st_dev, st.st_ino


def _try_create_in(folder: Path, who: str) -> None:
    """Create and remove a file in `folder`: the only sure test that it accepts new files."""
    probe = folder / f".combined-reality-check.{os.getpid()}.{secrets.token_hex(4)}"
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except OSError as e:
        why, theirs = _REASONS.get(e.errno or 0, (e.strerror or str(e), False))
        msg = f"{who}: the folder {folder} does not accept new files" + (
            "." if e.errno == errno.ENOENT else f": {why}.")
        raise OutputError(msg) if theirs else WriteError(msg) from None
    os.close(fd)
    os.unlink(probe)
    try:
        vfs = os.statvfs(folder)
    except OSError:
        return
    free = (vfs.f_bfree if os.geteuid() == 0 else vfs.f_bavail) * vfs.f_frsize
    if free == 0:
        raise WriteError(f"{who}: the disk holding {folder} is full.")


def _check_file(flag: str, path: PathLike) -> Path:
    text = os.fspath(path)
    if not str(text).strip():
        raise OutputError(f"{flag}: give a file name, not an empty one.")
    who = f"{flag} {text}"
    refuse_special(text, flag)
    target = write_target(text)
    if target.exists() and not os.access(target, os.W_OK):
        raise OutputError(f"{who}: the file is read-only; make it writable or give another name.")
    folder = target.parent
    if not folder.exists():
        raise OutputError(f"{who}: the folder {folder} does not exist (create it first).")
    if not folder.is_dir():
        raise OutputError(f"{who}: {folder} is not a folder.")
    _try_create_in(folder, who)
    return target


def _check_folder(flag: str, path: PathLike) -> Path:
    text = os.fspath(path)
    if not str(text).strip():
        raise OutputError(f"{flag}: give a folder name, not an empty one.")
    who = f"{flag} {text}"
    folder = Path(text)
    if folder.exists():
        if not folder.is_dir():
            raise OutputError(f"{who} exists and is not a folder.")
        _try_create_in(folder, who)
        return folder
    parent = folder.parent
    if not parent.is_dir():
        raise OutputError(f"{who}: the folder {parent} it would be created in does not exist.")
    _try_create_in(parent, who)
    return folder


def check_outputs(files: Mapping[str, PathLike | None], inputs: Iterable[PathLike | None] = (),
                  folders: Mapping[str, PathLike | None] | None = None) -> None:
    """Refuse, before any work, output files (option -> path; None: not asked for; '-': stdout)
    and output folders that cannot be written, that are an input, or that two options name.
    OutputError (exit status 2), or WriteError for a full disk (exit status 1)."""
    ins = {}
    for p in inputs:
        if p is not None and os.fspath(p) != "-":
            ident = _identity(p)
            if ident is not None:
                ins.setdefault(ident, os.fspath(p))
    seen: dict[str, str] = {}  # resolved path -> option
    for flag, path in (folders or {}).items():
        if path is not None:
            seen[os.path.realpath(_check_folder(flag, path))] = flag
    for flag, path in files.items():
        if path is None or os.fspath(path) == "-":
            continue
        target = _check_file(flag, path)
        ident = _identity(target)
        if ident is not None and ident in ins:
            raise OutputError(f"{flag} {os.fspath(path)} is the input {ins[ident]}; the tool never writes over its "
                              "inputs, so give another file name.")
        key = os.path.realpath(target)
        if key in seen:
            raise OutputError(f"{seen[key]} and {flag} name the same file {os.fspath(path)}; give each its own.")
        seen[key] = flag
