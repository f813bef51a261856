"""What reading and writing every policy file shares: `PolicyFileError` (a file that cannot be read,
or a model that cannot be exported), the size bound on a file, the atomic writes (`bh8_gym.atomic_files`), and the run.json that
`bh8 train` leaves beside a model. numpy only.
"""
from __future__ import annotations

import json
from pathlib import Path

from bh8_gym.atomic_files import atomic_write, atomic_write_npz  # noqa: F401  (policy files' writers)

# Our bounds on a policy file (an exported MLP is KBs to a few MB): past them it is refused unread,
# so a zip bomb cannot exhaust memory.
POLICY_FILE_LIMIT_BYTES = 1 << 30
MAX_LAYERS = 64  # linear layers of a policy's network


class PolicyFileError(ValueError):
    """A policy file that cannot be read, or a model that cannot be exported."""


RUN_METADATA_FILE = "run.json"


def find_run_metadata(model_path: Path) -> dict:
    """The `run.json` that `bh8 train` writes into its output directory (searched upwards 2 levels)."""
    for folder in (model_path.parent, model_path.parent.parent):
        candidate = folder / RUN_METADATA_FILE
        if candidate.exists():
            return json.loads(candidate.read_text())
    return {}
