"""The files of a training run directory that `bh8 train` writes and `bh8 eval` reads: the training
curve (evaluations.csv), the best model, and the atomic writes they and the checkpoints use
(the whole directory layout is in agents/train.py's docstring)."""
from __future__ import annotations

import csv
import io
import json
import shutil
from pathlib import Path
from typing import Any

from bh8_gym.agents.policy_file import atomic_write

EVALUATIONS_FILE = "evaluations.csv"
EVALUATION_COLUMNS = ("timesteps", "success_rate", "success_ci_low", "success_ci_high", "mean_return",
                      "std_return", "mean_length", "episodes")
BEST_MODEL_FILE = "best_model.zip"


def write_text_atomic(path: Path, text: str) -> None:
    """Write `text` (UTF-8) so a crash leaves either the old file or the complete new one."""
    atomic_write(path, lambda handle: handle.write(text.encode()))


def write_json_atomic(path: Path, data: Any) -> None:
    """Write JSON so a crash leaves either the old file or the complete new one."""
    write_text_atomic(path, json.dumps(data, indent=2, sort_keys=True))


def copy_atomic(source: Path, destination: Path) -> None:
    """Copy a file (`atomic_write`)."""
    with open(source, "rb") as handle:
        atomic_write(destination, lambda out: shutil.copyfileobj(handle, out))


def save_model_atomic(model, path: Path) -> None:
    """`model.save`, atomically (`atomic_write`: SB3 saves to a file object as to a path)."""
    atomic_write(path, model.save)


def append_evaluation(out_dir: Path, row: dict) -> None:
    """One row of `evaluations.csv` (EVALUATION_COLUMNS), the header first in a new file."""
    path = Path(out_dir) / EVALUATIONS_FILE
    new_file = not path.exists()
    with path.open("a", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=EVALUATION_COLUMNS)
        if new_file:
            writer.writeheader()
        writer.writerow(row)


def read_evaluations(out_dir: Path) -> list[dict[str, float]]:
    """The rows of `evaluations.csv` (the training curve) as floats."""
    path = Path(out_dir) / EVALUATIONS_FILE
    with path.open(newline="") as handle:
        return [{key: float(value) for key, value in row.items()} for row in csv.DictReader(handle)]


def drop_evaluations_after(out_dir: Path, timesteps: int) -> None:
    """Remove the `evaluations.csv` rows past `timesteps` (atomically): a run killed after its last
    checkpoint made them, and the resumed run makes them again."""
    path = Path(out_dir) / EVALUATIONS_FILE
    if not path.exists():
        return
    with path.open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    kept = [row for row in rows if float(row["timesteps"]) <= timesteps]
    if len(kept) < len(rows):
        text = io.StringIO(newline="")
        writer = csv.DictWriter(text, fieldnames=EVALUATION_COLUMNS)
        writer.writeheader()
        writer.writerows(kept)
        write_text_atomic(path, text.getvalue())
