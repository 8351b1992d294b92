"""Reading an input file without trusting it: only regular files are opened (a device, a FIFO
or a socket is refused from its status, before any open, so that /dev/zero cannot fill the
memory and a FIFO without a writer cannot block), no more than a stated number of bytes is
read, and TOML is parsed with its lines and nesting bounded.

Every reader of the tool goes through here (cylinder files here in sim; runs, mappings,
recordings, manifests, points tables and command files in the application). The caller keeps
its own words for a missing file or bad text; what is refused here raises InputFileError
with the path and the reason, which the caller turns into its own error class. Text is decoded
here too (decode_text: a UTF-8 byte order mark dropped, the line of a byte that is not text)."""
from __future__ import annotations

import codecs
import os
import stat
import tomllib
from typing import Callable

from .errors import InputError

__all__ = ["InputFileError", "QUOTE_LIMIT", "shorten", "is_utf8", "TOML_MAX_BYTES", "TOML_MAX_LINE", "file_kind",
           "regular_file_size", "checked_size", "read_checked", "read_bounded", "decode_text", "line_breaks",
           "parse_toml"]

TOML_MAX_BYTES = 1 << 20  # a cylinder file or a mapping is a few kB; 1 MiB is far beyond any
TOML_MAX_LINE = 1 << 16  # characters per line of a TOML file
QUOTE_LIMIT = 80  # characters of a file's content that a message quotes at most


class InputFileError(InputError):
    """An input that is not a regular file, or larger than its limit: one sentence with the path
    (exit status 2)."""


def file_kind(mode: int) -> str | None:
    """What a file that is not a regular file is, in words ("a folder", "a device", ...), from
    its st_mode; None for a regular file."""
    if stat.S_ISREG(mode):
        return None
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def regular_file_size(path: str | os.PathLike[str], what: str, limit: int | None = None,
                      limit_hint: str = "") -> int:
    """The size of `path` if it is a regular file no larger than `limit` bytes; else
    InputFileError ("a device", "a FIFO", too large). Missing files and folders raise the
    OSError of os.stat / IsADirectoryError, for the caller's own words."""
    st = os.stat(path)  # follows links: a link to /dev/zero is /dev/zero
    if stat.S_ISDIR(st.st_mode):
        raise IsADirectoryError(21, "Is a directory", str(path))
    kind = file_kind(st.st_mode)
    if kind is not None:
        raise InputFileError(f"{path} is {kind}, not {what}; give a regular file.")
    if limit is not None and st.st_size > limit:
        raise InputFileError(f"{path}: {st.st_size / 2**20:.4g} MiB is more than {what} may hold "
                             f"({limit / 2**20:.4g} MiB){limit_hint}.")
    return st.st_size


def checked_size(path: str | os.PathLike[str], what: str, error: type[Exception], limit: int | None = None,
                 limit_hint: str = "") -> int:
    """regular_file_size with every refusal (missing, a folder, special, too large, unreadable)
    raised as `error`, one sentence naming the path; `what` is the file's kind ("a run file")."""
    kind = what.removeprefix("an ").removeprefix("a ")
    try:
        return regular_file_size(path, what, limit, limit_hint)
    except InputFileError as e:
        raise error(str(e)) from None
    except FileNotFoundError:
        raise error(f"{path}: {kind} not found.") from None
    except IsADirectoryError:
        raise error(f"{path}: is a directory, not {what}.") from None
    except OSError as e:
        raise error(f"{path}: cannot read {kind} ({e.strerror or e}).") from None


def read_checked(path: str | os.PathLike[str], what: str, error: type[Exception], limit: int | None) -> bytes:
    """read_bounded with every refusal raised as `error` (checked_size); `limit` None: a file
    whose size the caller has bounded already."""
    checked_size(path, what, error, limit)
    try:
        return _read_at_most(path, what, limit)
    except InputFileError as e:
        raise error(str(e)) from None
    except OSError as e:
        raise error(f"{path}: cannot read it ({e.strerror or e}).") from None


def read_bounded(path: str | os.PathLike[str], what: str, limit: int | None, limit_hint: str = "") -> bytes:
    """The bytes of the regular file `path`, at most `limit` of them (a file that grows while it
    is read past the limit is refused too)."""
    regular_file_size(path, what, limit, limit_hint)
    return _read_at_most(path, what, limit, limit_hint)


def _read_at_most(path: str | os.PathLike[str], what: str, limit: int | None, limit_hint: str = "") -> bytes:
    """The bytes of `path`, checked already to be a regular file (one status a read)."""
    with open(path, "rb") as f:
        data = f.read() if limit is None else f.read(limit + 1)
    if limit is not None and len(data) > limit:
        raise InputFileError(f"{path}: more than {limit / 2**20:.4g} MiB, more than {what} may hold"
                             f"{limit_hint}.")
    return data


def is_utf8(encoding: str) -> bool:
    """Whether `encoding` names UTF-8 (whose byte order mark opening a file is dropped)."""
    return encoding.lower().replace("_", "-") in ("utf-8", "utf8")


def decode_text(data: bytes, not_text: Callable[[int, int], Exception] | None = None, encoding: str = "utf-8",
                line0: int = 1, cr_ends_lines: bool = False) -> str:
    """`data`, the bytes of a file from its line `line0` on, as text in `encoding`; a UTF-8
    byte order mark that opens the file (line0 1) is dropped (spreadsheet programs and Windows
    editors like to write one). Bytes that are not such text raise not_text(line, byte): the
    line of the first bad one (lines end at \n; with `cr_ends_lines` at \r and \r\n too, as in
    a CSV) and its offset after the mark; without `not_text`, the UnicodeDecodeError."""
    if line0 == 1 and is_utf8(encoding) and data.startswith(codecs.BOM_UTF8):
        data = data[len(codecs.BOM_UTF8):]
    try:
        return data.decode(encoding)
    except UnicodeDecodeError as e:
        if not_text is None:
            raise
        raise not_text(line0 + line_breaks(data[:e.start], cr_ends_lines), e.start) from None


def line_breaks(data: bytes, cr_ends_lines: bool = True) -> int:
    """The line breaks in `data`: each \n, and with `cr_ends_lines` (a CSV) each \r\n and each
    bare \r too."""
    n = data.count(b"\n")
    return n + data.count(b"\r") - data.count(b"\r\n") if cr_ends_lines and b"\r" in data else n


def parse_toml(text: str, max_line: int = TOML_MAX_LINE) -> dict:
    """tomllib.loads with bounded lines and nesting: an overlong line or arrays and tables
    nested too deeply for the parser raise tomllib.TOMLDecodeError like any other syntax
    error, with the line."""
    for lineno, line in enumerate(text.split("\n"), 1):
        if len(line) > max_line:
            raise tomllib.TOMLDecodeError(f"line {lineno} is longer than {max_line} characters")
    try:
        return tomllib.loads(text)
    except RecursionError:
        raise tomllib.TOMLDecodeError("arrays or inline tables nested too deeply") from None



def shorten(text: object, limit: int = QUOTE_LIMIT) -> str:
    """`text` as a message quotes it: at most `limit` characters, an ellipsis marking a cut."""
    text = str(text)
    return text if len(text) <= limit else text[:limit - 1] + "…"
