"""The only files PyBullet parses: written by this package, into a folder only this account can write.

PyBullet's file readers (OBJ, MTL, STL, textures, URDF) trust their input, so no byte of a user's
file reaches them (`bh8_gym.meshes`, `bh8_gym.urdfs` rewrite what they read). What PyBullet loads
is written here: `written(files)` puts each text under the SHA-256 of its bytes in `private_folder()`
and yields the paths for PyBullet to read.

The folder is this account's cache, `$XDG_CACHE_HOME/bh8-gym/pybullet` (default ~/.cache/...):
made with mode 0700 and used only while it is a real folder (not a link) that this account owns
and no one else may enter, else a folder `mkdtemp` makes for this process (removed at exit). Named
by content, a file is written once and always holds the same bytes: every process of the account
shares it (a deploy under a file-size limit does not write the hand's URDF again), and PyBullet's
own cache of OBJ files by name (it keeps every OBJ it read for the process's life) stays right. A
file is read back and compared before each use, and written again unless it holds those bytes.
"""
from __future__ import annotations

import atexit
import hashlib
import os
import shutil
import stat
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from bh8_gym.safe_files import FileError, read_bounded

_lock = threading.Lock()
_folder: dict[str, object] = {}  # "path", "pid", and "temporary" (a folder of this process's own)


def cache_folder() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "bh8-gym" / "pybullet"


def _private(path: Path) -> bool:
    """Whether `path` is a folder (not a link) of this account that no other may write or enter."""
    try:
        info = os.lstat(path)
    except OSError:
        return False
    return stat.S_ISDIR(info.st_mode) and info.st_uid == os.getuid() and not info.st_mode & 0o077


def private_folder() -> str:
    """The folder PyBullet's files are written to (module docstring)."""
    with _lock:
        if _folder.get("pid") != os.getpid() or not _private(Path(str(_folder.get("path")))):
            folder = cache_folder()
            try:
                folder.mkdir(mode=0o700, parents=True, exist_ok=True)
            except OSError:
                pass
            temporary = not _private(folder)
            if temporary:
                folder = Path(tempfile.mkdtemp(prefix="bh8-gym-pybullet-"))
            _folder.update(path=str(folder), pid=os.getpid(), temporary=temporary)
        return str(_folder["path"])


def path_for(data: bytes, suffix: str) -> str:
    """The path `written` gives `data` (its name: the SHA-256 of the bytes and `suffix`)."""
    return os.path.join(private_folder(), hashlib.sha256(data).hexdigest() + suffix)


@contextmanager
def written(files: list[tuple[bytes, str]]) -> Iterator[list[str]]:
    """The paths of files holding each (bytes, suffix) of `files`, for PyBullet to read inside the
    `with` block (each written once, atomically, if it is not there yet)."""
    paths = [path_for(data, suffix) for data, suffix in files]
    for path, (data, _) in zip(paths, files):
        if not _holds(path, data):
            _write_atomically(path, data)
    yield paths


def _holds(path: str, data: bytes) -> bool:
    """Whether the file `path` is there and holds exactly `data` (a cheap read: KBs)."""
    try:
        return read_bounded(path, len(data)) == data
    except FileError:
        return False


def _write_atomically(path: str, data: bytes) -> None:
    handle, temporary = tempfile.mkstemp(dir=os.path.dirname(path))
    try:
        with os.fdopen(handle, "wb") as stream:
            stream.write(data)
        os.replace(temporary, path)
    except BaseException:
        try:
            os.unlink(temporary)
        except OSError:
            pass
        raise


def _remove_temporary_folder() -> None:
    if _folder.get("pid") == os.getpid() and _folder.get("temporary"):
        shutil.rmtree(str(_folder["path"]), ignore_errors=True)


atexit.register(_remove_temporary_folder)
