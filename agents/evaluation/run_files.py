"""The files of a training run directory that `bh8 train` writes and `bh8 eval` reads: the training
curve (evaluations.csv), the best model, and the atomic writes they and the checkpoints use
(the whole directory layout is in agents/training/trainer.py's docstring)."""
from __future__ import annotations

import csv
import io
import json
import math
import os
import shutil
from pathlib import Path
from typing import Any

from bh8_gym.agents.policy_io import atomic_write
from bh8_gym.safe_files import open_regular, read_text_bounded

EVALUATIONS_FILE = "evaluations.csv"
EVALUATION_COLUMNS = ("timesteps", "success_rate", "success_ci_low", "success_ci_high", "mean_return",
                      "std_return", "mean_length", "episodes")
BEST_MODEL_FILE = "best_model.zip"
EVALUATIONS_LIMIT_BYTES = 16 << 20  # a row per evaluation, about 100 bytes each


def write_text_atomic(path: Path, text: str) -> None:
    """Write `text` (UTF-8) so a crash leaves either the old file or the complete new one."""
    atomic_write(path, lambda handle: handle.write(text.encode()))


def write_json_atomic(path: Path, data: Any) -> None:
    """Write JSON so a crash leaves either the old file or the complete new one."""
    write_text_atomic(path, json.dumps(data, indent=2, sort_keys=True))


def copy_atomic(source: Path, destination: Path) -> None:
    """Copy a file (`atomic_write`)."""
    with open_regular(source, "file") as handle:  # a FIFO planted there is refused, not waited on
        atomic_write(destination, lambda out: shutil.copyfileobj(handle, out))


def save_model_atomic(model, path: Path) -> None:
    """`model.save`, atomically (`atomic_write`: SB3 saves to a file object as to a path)."""
    atomic_write(path, model.save)


def append_evaluation(out_dir: Path, row: dict) -> None:
    """One row of `evaluations.csv` (EVALUATION_COLUMNS), the header first in a new file, on a line
    of its own: after a row cut short (a kill or a full disk mid-append) it starts a new line, so
    the two are not read as one."""
    path = Path(out_dir) / EVALUATIONS_FILE
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, fieldnames=EVALUATION_COLUMNS)
    last = b""
    if os.path.lexists(path):
        with open_regular(path, EVALUATIONS_FILE) as handle:  # a FIFO planted there is refused
            size = os.fstat(handle.fileno()).st_size
            if size:
                handle.seek(size - 1)
                last = handle.read(1)
    if not last:
        writer.writeheader()
    elif last != b"\n":
        text.write("\r\n")  # the csv module's line break
    writer.writerow(row)
    with path.open("a", newline="") as handle:
        handle.write(text.getvalue())


def read_evaluations(out_dir: Path, skipped: list[int] | None = None) -> list[dict[str, float]]:
    """The complete rows of `evaluations.csv` (the training curve) as floats. A row cut short (the
    file's last line without its line break, or a row with a field missing or not a number) is
    left out, and its line number added to `skipped` when given, for the caller to report."""
    rows, bad = _evaluation_rows(Path(out_dir) / EVALUATIONS_FILE)
    if skipped is not None:
        skipped += bad
    return [{key: float(value) for key, value in row.items()} for row in rows]


def _evaluation_rows(path: Path) -> tuple[list[dict[str, str]], list[int]]:
    """The complete rows of the evaluations.csv `path` (as text) and the line numbers of the others."""
    # bounded (a sparse 1 GB file, a FIFO or a link to /dev/zero is refused); the line breaks as
    # written: a cut row has none
    text = read_text_bounded(path, EVALUATIONS_LIMIT_BYTES, EVALUATIONS_FILE)
    lines = text.splitlines()
    cut_last = bool(text) and not text.endswith("\n")
    if not lines or next(csv.reader([lines[0]])) != list(EVALUATION_COLUMNS) or (cut_last and len(lines) == 1):
        return [], list(range(1, len(lines) + 1))  # no header: nothing can be read as a row
    rows, bad = [], []
    for number, line in enumerate(lines[1:], start=2):
        fields = next(csv.reader([line]), [])
        if _numbers(fields) and not (cut_last and number == len(lines)):
            rows.append(dict(zip(EVALUATION_COLUMNS, fields)))
        else:
            bad.append(number)
    return rows, bad


def _numbers(fields: list[str]) -> bool:
    """Whether `fields` are a row's worth of numbers."""
    if len(fields) != len(EVALUATION_COLUMNS):
        return False
    try:
        return all(math.isfinite(float(value)) for value in fields)
    except ValueError:
        return False


def drop_evaluations_after(out_dir: Path, timesteps: int) -> list[int]:
    """Remove the `evaluations.csv` rows past `timesteps` (atomically): a run killed after its last
    checkpoint made them, and the resumed run makes them again. Rows cut short go too; their line
    numbers are returned, for the caller to report."""
    path = Path(out_dir) / EVALUATIONS_FILE
    if not path.exists():
        return []
    rows, bad = _evaluation_rows(path)
    kept = [row for row in rows if float(row["timesteps"]) <= timesteps]
    if len(kept) < len(rows) or bad:
        text = io.StringIO(newline="")
        writer = csv.DictWriter(text, fieldnames=EVALUATION_COLUMNS)
        writer.writeheader()
        writer.writerows(kept)
        write_text_atomic(path, text.getvalue())
    return bad
