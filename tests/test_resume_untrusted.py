"""`bh8 train --resume` runs nothing from a checkpoint (issue 32 item 2): the model is rebuilt from
run.json's config, the weights and optimiser states are read by torch with weights_only, SAC's
replay buffer is an .npz, and a pickled replay buffer of an earlier version is unpickled only with
--trust-file. Each hostile file is checked to run no code (its payload would create a folder) and
to end in one line and exit 2, or in a resumed run.

Kept fast: PPO and SAC on BH8FingerReach-v0, a few dozen env steps per run.
"""
from __future__ import annotations

import base64
import contextlib
import io
import json
import os
import pickle
import shutil
import zipfile
from pathlib import Path

import pytest

from bh8_gym.cli import main


class Payload:
    """Unpickling this makes a folder: the sign that a loader ran code from a file."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return os.mkdir, (self.marker,)


def _train(*arguments) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["train", "--no-progress", "--n-envs", "1", *map(str, arguments)])
    return code, out.getvalue(), err.getvalue()


def _config(folder: Path, algorithm: str) -> Path:
    hyperparameters = ("n_steps = 32\nbatch_size = 32\nn_epochs = 1\nlearning_rate = \"lin_1e-3\"" if algorithm == "PPO"
                       else "learning_starts = 16\nbuffer_size = 512\nbatch_size = 16")
    path = folder / f"{algorithm}.toml"
    path.write_text(f"""algorithm = "{algorithm}"
env_id = "BH8FingerReach-v0"
[eval_env_kwargs]
randomize = false
[train]
total_timesteps = 64
checkpoint_freq = 32
[eval]
freq = 10000
episodes = 1
[hyperparameters]
{hyperparameters}
[policy_kwargs]
net_arch = [8]
""")
    return path


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """A PPO and a SAC run of 32 steps with a checkpoint, to be copied and tampered with."""
    folder = tmp_path_factory.mktemp("runs")
    made = {}
    for algorithm in ("PPO", "SAC"):
        code, _, err = _train("--config", _config(folder, algorithm), "--out", folder / algorithm, "--timesteps", "32")
        assert code == 0, err
        made[algorithm] = folder / algorithm
    return made


def _copy(run: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(run, tmp_path / run.name))


def _rewrite_member(zip_path: Path, name: str, content: bytes) -> None:
    with zipfile.ZipFile(zip_path) as archive:
        members = {member: archive.read(member) for member in archive.namelist()}
    members[name] = content
    with zipfile.ZipFile(zip_path, "w") as archive:
        for member, data in members.items():
            archive.writestr(member, data)


def _pickled_entry(marker: Path) -> dict:
    """A `data` entry as SB3 writes a pickled setting (base64 of a cloudpickle), carrying Payload."""
    return {":type:": "<class 'function'>", ":serialized:": base64.b64encode(pickle.dumps(Payload(marker))).decode()}


def test_a_pickle_in_the_checkpoints_lr_schedule_is_not_run(runs, tmp_path):
    """The attack of the issue: lr_schedule replaced in checkpoints/latest.zip. The resumed run
    rebuilds its schedules from run.json's config ("lin_1e-3" here) and goes on."""
    run, marker = _copy(runs["PPO"], tmp_path), tmp_path / "ran"
    checkpoint = run / "checkpoints" / "latest.zip"
    with zipfile.ZipFile(checkpoint) as archive:
        data = json.loads(archive.read("data"))
    for key in ("lr_schedule", "learning_rate", "clip_range", "policy_class", "observation_space"):
        data[key] = _pickled_entry(marker)
    _rewrite_member(checkpoint, "data", json.dumps(data).encode())
    code, out, err = _train("--resume", "--out", run, "--timesteps", "64")
    assert not marker.exists(), "the checkpoint's pickle ran"
    assert code == 0, err
    assert out.startswith("trained to 64 steps")


def test_a_pickle_in_the_weights_is_refused_in_one_line(runs, tmp_path):
    import torch

    run, marker = _copy(runs["PPO"], tmp_path), tmp_path / "ran"
    buffer = io.BytesIO()
    torch.save({"weight": Payload(marker)}, buffer)
    _rewrite_member(run / "checkpoints" / "latest.zip", "policy.optimizer.pth", buffer.getvalue())
    code, _, err = _train("--resume", "--out", run, "--timesteps", "64")
    assert not marker.exists(), "the checkpoint's pickle ran"
    assert code == 2 and err.startswith("bh8 train: --resume:") and err.count("\n") == 1, err
    assert "policy.optimizer.pth" in err and "not plain tensors" in err


@pytest.mark.parametrize("damage, message", [
    ("counter", "num_timesteps must be a non-negative integer"),
    ("extra member", "unexpected evil.pth"),
    ("other network", "does not fit the model"),
    ("not a zip", "cannot read"),
])
def test_a_damaged_or_foreign_checkpoint_is_refused_in_one_line(runs, tmp_path, damage, message):
    run = _copy(runs["PPO"], tmp_path)
    checkpoint = run / "checkpoints" / "latest.zip"
    if damage == "counter":
        with zipfile.ZipFile(checkpoint) as archive:
            data = json.loads(archive.read("data"))
        data["num_timesteps"] = -5
        _rewrite_member(checkpoint, "data", json.dumps(data).encode())
    elif damage == "extra member":
        _rewrite_member(checkpoint, "evil.pth", b"")
    elif damage == "other network":  # run.json says [8]; the weights are of a [16] network
        metadata = json.loads((run / "run.json").read_text())
        metadata["config"]["policy_kwargs"]["net_arch"] = [16]
        (run / "run.json").write_text(json.dumps(metadata))
    else:
        checkpoint.write_bytes(b"not a zip at all")
    code, _, err = _train("--resume", "--out", run, "--timesteps", "64")
    assert code == 2 and err.startswith("bh8 train: ") and err.count("\n") == 1, err
    assert message in err and "Traceback" not in err


def test_sac_resumes_its_replay_buffer_from_an_npz(runs, tmp_path):
    from bh8_gym.agents.training.trainer import Trainer, read_run_json

    run = _copy(runs["SAC"], tmp_path)
    checkpoints = run / "checkpoints"
    assert (checkpoints / "latest_replay_buffer.npz").is_file() and not (checkpoints / "latest_replay_buffer.pkl").exists()
    trainer = Trainer(read_run_json(run / "run.json")["config"], run, n_envs=1, progress=False)
    env = trainer._vec_env()
    try:
        model = trainer._resume_model(env)
        assert model.num_timesteps == 32 and model.replay_buffer.size() == 32
        assert model.replay_buffer.observations[:32].any() and not model.replay_buffer.observations[32:].any()
    finally:
        env.close()
    code, out, err = _train("--resume", "--out", run, "--timesteps", "64")
    assert code == 0, err


def test_an_earlier_versions_pickled_replay_buffer_needs_trust_file(runs, tmp_path):
    """latest_replay_buffer.pkl (SB3's pickle, written before the .npz): refused, saying why and how,
    unless --trust-file; a replaced one carrying a payload runs nothing without it."""
    from bh8_gym.agents.training.trainer import Trainer, read_run_json

    run = _copy(runs["SAC"], tmp_path)
    checkpoints = run / "checkpoints"
    trainer = Trainer(read_run_json(run / "run.json")["config"], run, n_envs=1, progress=False)
    env = trainer._vec_env()
    try:
        trainer._resume_model(env).save_replay_buffer(checkpoints / "latest_replay_buffer.pkl")
    finally:
        env.close()
    (checkpoints / "latest_replay_buffer.npz").unlink()
    saved = (checkpoints / "latest_replay_buffer.pkl").read_bytes()

    marker = tmp_path / "ran"
    (checkpoints / "latest_replay_buffer.pkl").write_bytes(pickle.dumps(Payload(marker)))
    code, _, err = _train("--resume", "--out", run, "--timesteps", "64")
    assert not marker.exists(), "the replay buffer's pickle ran"
    assert code == 2 and err.count("\n") == 1 and "--trust-file" in err and "pickle" in err, err

    (checkpoints / "latest_replay_buffer.pkl").write_bytes(saved)
    code, out, err = _train("--resume", "--out", run, "--timesteps", "64", "--trust-file")
    assert code == 0, err
    assert (checkpoints / "latest_replay_buffer.npz").is_file()  # the next checkpoint is pickle-free


def test_a_damaged_npz_replay_buffer_is_refused_in_one_line(runs, tmp_path):
    import numpy as np

    run = _copy(runs["SAC"], tmp_path)
    path = run / "checkpoints" / "latest_replay_buffer.npz"
    with np.load(path) as saved:
        arrays = {name: saved[name] for name in saved.files}
    arrays["observations"] = arrays["observations"][:10]
    with path.open("wb") as handle:
        np.savez(handle, **arrays)
    code, _, err = _train("--resume", "--out", run, "--timesteps", "64")
    assert code == 2 and err.count("\n") == 1 and "observations" in err and "buffer" in err, err


def test_a_run_json_without_a_config_or_seed_is_refused_in_one_line(runs, tmp_path):
    run = _copy(runs["PPO"], tmp_path)
    metadata = json.loads((run / "run.json").read_text())
    for damage in ({"seed": "x"}, {"config": None}, {"config": {**metadata["config"], "hyperparameters": {"gamma": 7}}}):
        (run / "run.json").write_text(json.dumps({**metadata, **damage}))
        code, _, err = _train("--resume", "--out", run)
        assert code == 2 and err.count("\n") == 1 and "run.json" in err and "Traceback" not in err, err
