"""Configs and run records, third round (issue 39, findings 8, 9 and 10): what a config or a run's
own files say is checked before anything trains on it, and a bad one is one line, exit 2.
"""
from __future__ import annotations

import json
import math
import os
import shutil

import pytest

from bh8_gym.agents.training.config_check import ConfigError, check_config, check_env_tables, check_rollout
from test_config_check import GRASP, REACH, _base, _with


def _pretrain(**table) -> dict:
    config = _base("PPO", GRASP)
    config["pretrain"] = {"episodes": 2, "epochs": 1, **table}
    return config


@pytest.mark.parametrize("config, message", [
    (_pretrain(dagger_iterations=2), "give a teacher"),
    (_pretrain(dagger_beta=0.5), "give a teacher"),
    (_pretrain(baseline="loop", teacher=["loop-v70"]), "not both"),
    (_pretrain(teacher=["loop-v70", "loop-v70"]), "names a script twice"),
    (_pretrain(baseline="loop", baseline_kwargs={"close_velocity": 1e9}), "close_velocity must be an integer in 0..127"),
    (_pretrain(baseline="loop", baseline_kwargs={"gain": 0.5}), "gain must be an integer in 0..255"),
    (_with(_base(), None, "env_id", "CartPole-v1"), "not a bh8-gym environment"),
])
def test_configs_bh8_train_accepted_and_then_failed_on_are_refused(config, message):
    """Finding 10 (and 9's CartPole-v1): each was accepted, then failed or misbehaved later."""
    with pytest.raises(ConfigError, match=message):
        check_config(config)


def test_a_batch_larger_than_the_rollout_is_refused():
    config = _with(_base(), "hyperparameters", "batch_size", 128)  # n_steps 32
    with pytest.raises(ConfigError, match="batch_size 128 is larger than the rollout"):
        check_rollout(config, 2)
    check_rollout(config, 4)  # 32 x 4 = 128: fits


def test_a_hold_of_1e7_seconds_in_a_config_is_refused_when_the_config_is_checked():
    """Finding 4: `arm.hold_seconds` 1e7 in a config made LoopInterface.episode_steps loop (about 10^9
    cycles). The arm's schedule is bounded: the env the config builds refuses it, naming the key."""
    config = _base("PPO", GRASP)
    config["env_kwargs"] = {"arm": {"hold_seconds": 1e7}}
    with pytest.raises(ConfigError, match=r"env_kwargs: .*hold_seconds must be a number in \[0, 60\]"):
        check_env_tables(config)


def test_a_history_in_training_but_not_in_evaluation_is_refused_before_any_rollout():
    """Finding 10: a `history` differing between env_kwargs and eval_env_kwargs failed only at the
    first evaluation, after a rollout; the two envs' spaces are compared when the config is checked."""
    config = _base("PPO", GRASP)
    config["env_kwargs"] = {"history": True}
    with pytest.raises(ConfigError, match="history must be the same in both"):
        check_env_tables(config)


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    from test_train_cli import _train, _write_config

    folder = tmp_path_factory.mktemp("run3")
    config = _write_config(folder / "tiny.toml")
    code, _, err = _train("--config", config, "--out", folder / "run")
    assert code == 0, err
    return folder / "run"


@pytest.mark.parametrize("change, message", [
    ({"total_timesteps": 1e308}, "total_timesteps must be an integer"),
    ({"total_timesteps": "64"}, "total_timesteps must be an integer"),
    ({"num_timesteps": -5}, "num_timesteps must be an integer"),
    ({"best_success_rate": "0.5"}, "best_success_rate must be"),
    ({"next_evaluation": 10**30}, "next_evaluation must be an integer"),
])
def test_latest_json_is_checked_before_a_resume_uses_it(finished_run, tmp_path, change, message):
    """Finding 8: latest.json's total_timesteps 1e308 trained past MAX_TIMESTEPS, and strings raised
    TypeErrors mid-run. Each number is range-checked now: exit 2, one line naming the file."""
    from test_train_cli import _train

    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    state = run / "checkpoints" / "latest.json"
    state.write_text(json.dumps({**json.loads(state.read_text()), **change}))
    code, _, err = _train("--resume", "--out", run)
    assert code == 2 and message in err and "latest.json" in err and err.count("\n") == 1, err


def test_nan_weights_in_a_checkpoint_are_refused_naming_it(finished_run, tmp_path):
    """Finding 10: NaN checkpoint weights resumed, then stopped later with "action must be finite"
    without naming the file."""
    import io
    import zipfile

    import torch

    from test_train_cli import _train

    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    model = run / "checkpoints" / "latest.zip"
    with zipfile.ZipFile(model) as archive:
        members = {name: archive.read(name) for name in archive.namelist()}
    weights = torch.load(io.BytesIO(members["policy.pth"]), weights_only=True)
    first = next(name for name, value in weights.items() if value.is_floating_point())
    weights[first] = torch.full_like(weights[first], math.nan)
    buffer = io.BytesIO()
    torch.save(weights, buffer)
    members["policy.pth"] = buffer.getvalue()
    with zipfile.ZipFile(model, "w") as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    code, _, err = _train("--resume", "--out", run, "--timesteps", "128")
    assert code == 2 and "latest.zip" in err and "NaN or infinite" in err, err


def test_a_mesh_path_that_is_a_folder_is_one_line(tmp_path):
    """Finding 9: a mesh path that is a folder was a raw traceback."""
    from bh8_gym.objects import ObjectError, ObjectLoader, ObjectSpec

    folder = tmp_path / "part.obj"
    folder.mkdir()
    with pytest.raises(ObjectError, match="is a folder"):
        ObjectLoader(0).create(ObjectSpec("mesh", path=str(folder), scale=0.05), (0, 0, 1), (0, 0, 0, 1))


def test_a_sweep_folder_1100_levels_deep_is_not_a_recursion_error(tmp_path):
    """Finding 9: a sweep folder 1100 levels deep raised RecursionError (the seal walked it). Resume
    now reads only our records, one level down, and never walks the folder."""
    from bh8_gym.agents.sweep.report import check_folders, started_trials
    from bh8_gym.agents.sweep.settings import resumed_settings
    from test_sweep_hostile import _new_sweep_json, _resume_args

    folder = _new_sweep_json(tmp_path)
    (folder / "ray").mkdir()
    descriptors = [os.open(folder / "ray", os.O_RDONLY)]
    try:
        for _ in range(1100):  # each made relative to the one above: no path walked 1100 deep
            os.mkdir("d", dir_fd=descriptors[-1])
            descriptors.append(os.open("d", os.O_RDONLY, dir_fd=descriptors[-1]))
        settings = resumed_settings(_resume_args(folder))
        check_folders(settings)
        assert started_trials(settings) == []
    finally:
        for parent in reversed(descriptors[:-1]):  # deepest first: rmtree itself recurses
            os.rmdir("d", dir_fd=parent)
        for descriptor in descriptors:
            os.close(descriptor)
