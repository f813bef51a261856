"""Reading a file this package did not write: `read_bounded`, the one way every user file is read.

A size check by `stat` bounds nothing: a symlink to /dev/zero reports 0 bytes and reads without end,
a sparse file of 1 GB reports its size honestly but is read whole, and a FIFO blocks its `open`
until a writer comes. So a user file is opened with O_NONBLOCK (a FIFO's open returns at once),
checked with `fstat` on the open descriptor (what is read, not what the name pointed to a moment
before), refused unless it is a regular file (no FIFO, device, socket or folder), and read for at
most `limit + 1` bytes: a longer file is refused having read no more than that.

Every refusal is a `FileError` (a ValueError), or the caller's subclass of ValueError, naming the
file, so a command prints one line and exits 2.
"""
from __future__ import annotations

import json
import os
import stat
from typing import Any

# Our bounds on a JSON or TOML file of ours (run.json, latest.json, sweep.json, a config, a report):
# they are a few KB; a policy's metadata or an evaluation report some tens of KB.
SMALL_FILE_LIMIT_BYTES = 1 << 20


class FileError(ValueError):
    """A user file that cannot be read safely: missing, not a regular file, too large, not text."""


def read_bounded(path: str | os.PathLike, limit: int, what: str = "file",
                 error: type[ValueError] = FileError) -> bytes:
    """The bytes of `path`, a regular file of at most `limit` bytes, or an `error` naming it as `what`
    ("mesh", "URDF", "config", ...). Never blocks on a FIFO and never reads more than limit + 1 bytes."""
    shown = os.fspath(path) if isinstance(path, (str, os.PathLike)) else repr(path)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except (OSError, ValueError, TypeError) as exc:  # ValueError: a NUL in the name
        reason = getattr(exc, "strerror", None) or exc
        raise error(f"{what} {shown!r} cannot be read: {reason}") from None
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            kind = "a folder" if stat.S_ISDIR(mode) else "not a regular file"
            raise error(f"{what} {shown!r} is {kind}")
        chunks, remaining = [], limit + 1
        while remaining > 0:
            try:
                chunk = os.read(fd, min(remaining, 1 << 20))
            except OSError as exc:  # EIO, EISDIR on odd file systems
                raise error(f"{what} {shown!r} cannot be read: {exc.strerror or exc}") from None
            if not chunk:
                break
            chunks.append(chunk)
            remaining -= len(chunk)
    finally:
        os.close(fd)
    data = b"".join(chunks)
    if len(data) > limit:
        raise error(f"{what} {shown!r} is larger than {_size(limit)}")
    return data


def open_regular(path: str | os.PathLike, what: str = "file", error: type[ValueError] = FileError):
    """A binary file object on `path` for a reader that seeks (a zip of gigabytes, SAC's replay
    buffer), opened as `read_bounded` opens (O_NONBLOCK, fstat on the descriptor) and refused unless
    it is a regular file, whose size is then what the reader can read."""
    shown = os.fspath(path) if isinstance(path, (str, os.PathLike)) else repr(path)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except (OSError, ValueError, TypeError) as exc:
        raise error(f"{what} {shown!r} cannot be read: {getattr(exc, 'strerror', None) or exc}") from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise error(f"{what} {shown!r} is not a regular file")
    return os.fdopen(fd, "rb")


def read_text_bounded(path: str | os.PathLike, limit: int = SMALL_FILE_LIMIT_BYTES, what: str = "file",
                      error: type[ValueError] = FileError) -> str:
    """`read_bounded`, decoded as UTF-8 (an `error` naming the byte that is not)."""
    data = read_bounded(path, limit, what, error)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"{what} {os.fspath(path)!r} is not UTF-8 text (byte {exc.start})") from None


def read_json_bounded(path: str | os.PathLike, limit: int = SMALL_FILE_LIMIT_BYTES, what: str = "file",
                      error: type[ValueError] = FileError, constants: bool = False) -> Any:
    """A JSON file read by `read_text_bounded`; NaN and Infinity (not JSON) refused unless
    `constants`. The caller checks the shape (`bh8_gym.record_schema`, a schema per file kind)."""
    text = read_text_bounded(path, limit, what, error)
    return parse_json(text, f"{what} {os.fspath(path)!r}", error, constants)


def parse_json(text: str | bytes, what: str, error: type[ValueError] = FileError, constants: bool = False) -> Any:
    """`json.loads` with NaN/Infinity refused (unless `constants`), and a RecursionError (nesting
    past the interpreter's limit) or any other ValueError (an integer of more than 4300 digits is
    one) an `error`, not a traceback."""

    def refuse(constant: str):
        raise error(f"{what} holds {constant}, which is not JSON")

    try:
        return json.loads(text, parse_constant=None if constants else refuse)
    except error:
        raise
    except (ValueError, RecursionError) as exc:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        raise error(f"{what} is not valid JSON ({str(exc)[:200]})") from None


def _size(limit: int) -> str:
    for unit, shift in (("GB", 30), ("MB", 20), ("KB", 10)):
        if limit >= 1 << shift:
            return f"{limit / (1 << shift):g} {unit}"
    return f"{limit} bytes"
