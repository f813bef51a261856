"""What reading and writing every policy file shares: `PolicyFileError` (a file that cannot be read,
or a model that cannot be exported), the size bound on a file, atomic writes, and the run.json that
`bh8 train` leaves beside a model. numpy only.
"""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import BinaryIO, Callable

import numpy as np

# Our bounds on a policy file (an exported MLP is KBs to a few MB): past them it is refused unread,
# so a zip bomb cannot exhaust memory.
POLICY_FILE_LIMIT_BYTES = 1 << 30
MAX_LAYERS = 64  # linear layers of a policy's network


class PolicyFileError(ValueError):
    """A policy file that cannot be read, or a model that cannot be exported."""


def atomic_write(path: Path, write: Callable[[BinaryIO], None]) -> None:
    """`write(handle)` into a temp file beside `path`, fsync, then rename it over `path`: a crash leaves
    either the old file or the complete new one. The file gets the umask's mode, as an open() would
    (mkstemp's 0600 would keep the other accounts of a lab, e.g. the one that deploys, out)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())  # on disk before the rename: a power loss leaves old or new, not empty
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Write `arrays` to `path` as .npz, atomically (`atomic_write`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda handle: np.savez(handle, **arrays))

RUN_METADATA_FILE = "run.json"


def find_run_metadata(model_path: Path) -> dict:
    """The `run.json` that `bh8 train` writes into its output directory (searched upwards 2 levels)."""
    for folder in (model_path.parent, model_path.parent.parent):
        candidate = folder / RUN_METADATA_FILE
        if candidate.exists():
            return json.loads(candidate.read_text())
    return {}
