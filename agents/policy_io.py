"""What reading and writing every policy file shares: `PolicyFileError` (a file that cannot be read,
or a model that cannot be exported), the size bound on a file, the atomic writes (`bh8_gym.atomic_files`), and the run.json that
`bh8 train` leaves beside a model. numpy only.
"""
from __future__ import annotations

import os
from pathlib import Path

from bh8_gym.atomic_files import atomic_write, atomic_write_npz  # noqa: F401  (policy files' writers)
from bh8_gym.record_schema import Flag, Int, Schema, Table, Text
from bh8_gym.safe_files import SMALL_FILE_LIMIT_BYTES, read_bounded, read_json_bounded

# Our bounds on a policy file (an exported MLP is KBs to a few MB; bh8 train's SB3 models about 1 MB):
# past them it is refused having read no more, so a zip bomb or a link to /dev/zero cannot exhaust memory.
POLICY_FILE_LIMIT_BYTES = 256 << 20
MAX_LAYERS = 64  # linear layers of a policy's network
# What a policy's metadata (an export's, or the run.json beside a model) may hold, before anything
# uses it: the env it names is built from env_kwargs, whose own checks follow.
POLICY_METADATA = Schema("policy metadata", required={}, optional={
    "algorithm": Text(64), "env_id": Text(200), "env_kwargs": Table(), "privileged": Flag(),
    "n_layers": Int(1, MAX_LAYERS), "activation": Text(32), "output_transform": Text(32),
    "num_timesteps": Int(0, 10**13), "seed": Int(0, 2**32), "config": Table()})


class PolicyFileError(ValueError):
    """A policy file that cannot be read, or a model that cannot be exported."""


RUN_METADATA_FILE = "run.json"


def read_policy_bytes(path: Path) -> bytes:
    """A policy file's bytes, read bounded (`bh8_gym.safe_files`): a FIFO, a folder or a link to a
    device is refused, and no more than POLICY_FILE_LIMIT_BYTES + 1 bytes are read."""
    return read_bounded(path, POLICY_FILE_LIMIT_BYTES, "policy file", PolicyFileError)


def check_metadata(metadata, where: str) -> dict:
    """`metadata` if it is a table whose known keys hold what they should (POLICY_METADATA)."""
    return POLICY_METADATA.check(metadata, where, PolicyFileError)


def find_run_metadata(model_path: Path) -> dict:
    """The `run.json` that `bh8 train` writes into its output directory (searched upwards 2 levels),
    read bounded and checked (a list, a folder or a FIFO there is a PolicyFileError naming it)."""
    for folder in (model_path.parent, model_path.parent.parent):
        candidate = folder / RUN_METADATA_FILE
        if os.path.lexists(candidate):
            return check_metadata(read_json_bounded(candidate, SMALL_FILE_LIMIT_BYTES, "run.json", PolicyFileError),
                                  str(candidate))
    return {}
