"""Every user file is read bounded by reading, not by stat (issue 39, findings 4, 5 and 9's class).

Size checks used `st_size`, so a symbolic link to /dev/zero (size 0) was read without end: a policy
.npz or .zip, the run.json beside a policy, latest.zip, sweep.json. A FIFO as mtllib, latest.zip, a
policy .npz or a config blocked for ever, and sparse 1.2 GB run.json, latest.json and
evaluations.csv had no limit. Every reader now goes through `bh8_gym.safe_files` (O_NONBLOCK open,
fstat on the descriptor, a regular file only, at most limit + 1 bytes read): each of those files
is refused with an error naming it, at once, having read no more than its limit.
"""
from __future__ import annotations

import os
import resource

import pytest

HOSTILE = ("fifo", "link to /dev/zero", "folder", "sparse 2 GB")


def _plant(path, kind: str) -> None:
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "link to /dev/zero":
        os.symlink("/dev/zero", path)
    elif kind == "folder":
        os.mkdir(path)
    else:
        with open(path, "wb") as handle:
            handle.truncate(2 << 30)


def _readers(tmp_path):
    """(file name, a call that reads it) for each kind of user file."""
    from bh8_gym.agents.deployment.policy_file import load_policy
    from bh8_gym.agents.policy_io import find_run_metadata
    from bh8_gym.agents.evaluation.run_files import read_evaluations
    from bh8_gym.agents.training.checkpoint_file import _limited_archive
    from bh8_gym.agents.training.train import load_config
    from bh8_gym.agents.training.trainer import CHECKPOINT_STATE, read_run_json
    from bh8_gym.meshes import read_mesh
    from bh8_gym.safe_files import read_json_bounded
    from bh8_gym.urdfs import read_urdf

    return {
        "mesh.obj": read_mesh, "object.urdf": read_urdf, "policy.npz": load_policy, "policy.zip": load_policy,
        "run.json": lambda path: find_run_metadata(path.parent / "model.zip"),
        "latest.zip": _limited_archive, "latest.json": lambda path: read_run_json(path, CHECKPOINT_STATE),
        "config.toml": load_config, "evaluations.csv": lambda path: read_evaluations(path.parent),
        "sweep.json": lambda path: read_json_bounded(path),
    }


@pytest.mark.timeout(30)  # a FIFO blocked the open for ever
@pytest.mark.parametrize("kind", HOSTILE)
def test_every_user_file_is_refused_unless_a_regular_file_within_its_limit(tmp_path, kind):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    for name, read in _readers(tmp_path).items():
        if kind == "sparse 2 GB" and name in ("policy.npz", "policy.zip", "latest.zip"):
            continue  # limits of 256 MB: reading that much proves nothing /dev/zero does not
        folder = tmp_path / name.replace(".", "_")
        folder.mkdir()
        path = folder / name
        _plant(path, kind)
        with pytest.raises((ValueError, RuntimeError)) as refused:
            read(path)
        assert name in str(refused.value) or str(folder) in str(refused.value), (name, refused.value)
    grown = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before
    assert grown < 600_000, grown  # KB: a limit's worth at most (the sparse file is 2 GB)


def test_the_bounded_reader_reads_a_regular_file_and_no_more_than_its_limit(tmp_path):
    from bh8_gym.safe_files import FileError, read_bounded

    path = tmp_path / "data"
    path.write_bytes(b"x" * 100)
    assert read_bounded(path, 100) == b"x" * 100
    with pytest.raises(FileError, match="larger than 99 bytes"):
        read_bounded(path, 99)
    with pytest.raises(FileError, match="cannot be read"):
        read_bounded(tmp_path / "missing", 10)


def test_json_that_python_cannot_read_is_the_callers_error_not_a_traceback(tmp_path):
    """An integer of more than 4300 digits is a ValueError of json.loads, not a JSONDecodeError."""
    from bh8_gym.agents.policy_io import PolicyFileError, find_run_metadata
    from bh8_gym.safe_files import FileError, parse_json

    for text in ('{"seed": ' + "9" * 5000 + "}", '{"seed": NaN}', "[" * 100_000, "{"):
        with pytest.raises(FileError, match="sweep.json"):
            parse_json(text, "sweep.json")
    (tmp_path / "run.json").write_text('{"seed": ' + "9" * 5000 + "}")
    with pytest.raises(PolicyFileError, match="not valid JSON"):
        find_run_metadata(tmp_path / "model.zip")
