"""The only files PyBullet parses: written by this package, into a folder of this process's own.

PyBullet's file readers (OBJ, MTL, STL, textures, URDF) trust their input, so no byte of a user's
file reaches them (`bh8_gym.meshes`, `bh8_gym.urdfs` rewrite what they read). What PyBullet loads
is written here: `written(files)` puts each text in a private folder (made by `mkdtemp`, mode 0700,
once per process) under the SHA-256 of its bytes, yields the paths, and removes the files once
PyBullet has read them; the folder goes when the process exits.

Named by content, a path always holds the same bytes, so PyBullet's own cache of OBJ files by name
(it keeps every OBJ it read for the process's life) is right and does not grow with repeated loads.
"""
from __future__ import annotations

import atexit
import hashlib
import os
import shutil
import tempfile
import threading
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager

_lock = threading.Lock()
_folder: dict[str, object] = {}  # "path" and "pid": a forked child makes its own
_in_use: Counter[str] = Counter()


def private_folder() -> str:
    """This process's folder for PyBullet's files (made on first use)."""
    with _lock:
        if _folder.get("pid") != os.getpid() or not os.path.isdir(str(_folder.get("path"))):
            _in_use.clear()
            _folder.update(path=tempfile.mkdtemp(prefix="bh8-gym-pybullet-"), pid=os.getpid())
        return str(_folder["path"])


def path_for(data: bytes, suffix: str) -> str:
    """The path `written` gives `data` (its name: the SHA-256 of the bytes and `suffix`)."""
    return os.path.join(private_folder(), hashlib.sha256(data).hexdigest() + suffix)


@contextmanager
def written(files: list[tuple[bytes, str]]) -> Iterator[list[str]]:
    """The paths of files holding each (bytes, suffix) of `files`, for PyBullet to read inside the
    `with` block; removed after it (unless another block of this process still uses one)."""
    paths = [path_for(data, suffix) for data, suffix in files]
    with _lock:
        for path, (data, _) in zip(paths, files):
            if _in_use[path] == 0:
                _write_atomically(path, data)
            _in_use[path] += 1
    try:
        yield paths
    finally:
        with _lock:
            for path in paths:
                _in_use[path] -= 1
                if _in_use[path] <= 0:
                    del _in_use[path]
                    try:
                        os.unlink(path)
                    except OSError:
                        pass


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


def _remove_folder() -> None:
    if _folder.get("pid") == os.getpid():
        shutil.rmtree(str(_folder["path"]), ignore_errors=True)


atexit.register(_remove_folder)
