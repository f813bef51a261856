"""Agents: training with checkpoints and resume, numpy export, evaluation statistics, baselines,
and deployment over a serial port to the in-process simulated hand (bh8sim://).

Kept fast: a few hundred env steps of training on BH8FingerReach-v0, a few episodes of evaluation.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bh8_gym.agents.evaluation.episodes import EpisodeResult
from bh8_gym.agents.evaluation.evaluate import (
    per_object_table,
    summarize,
    wilson_interval,
)
from bh8_gym.agents.deployment.numpy_policy import NumpyPolicy
from bh8_gym.agents.policy_io import PolicyFileError, atomic_write_npz

REACH = "BH8FingerReach-v0"


# -- Wilson interval -------------------------------------------------------------------------


@pytest.mark.parametrize(
    "successes, trials, low, high",
    [
        # reference values computed from the closed form (Wilson 1927; Newcombe 1998, method 3)
        (0, 10, 0.0, 0.2775328),
        (10, 10, 0.7224672, 1.0),
        (5, 10, 0.2365931, 0.7634069),
        (81, 263, 0.2553, 0.3662),  # Newcombe 1998 Table I example (81/263)
    ],
)
def test_wilson_interval_reference_values(successes, trials, low, high):
    got_low, got_high = wilson_interval(successes, trials)
    assert got_low == pytest.approx(low, abs=1e-4)
    assert got_high == pytest.approx(high, abs=1e-4)


@given(trials=st.integers(1, 2000), data=st.data())
@settings(max_examples=200, deadline=None)
def test_wilson_bounds_solve_the_score_equation(trials, data):
    """Each bound p satisfies (p_hat - p)^2 = z^2 p (1 - p) / n, the definition of the score interval."""
    successes = data.draw(st.integers(0, trials))
    low, high = wilson_interval(successes, trials)
    p_hat = successes / trials
    z = 1.959963984540054
    assert 0.0 <= low <= p_hat <= high <= 1.0
    for bound in (low, high):
        if bound in (0.0, 1.0) and bound == p_hat:
            continue  # degenerate end: the interval touches p_hat exactly
        assert (p_hat - bound) ** 2 == pytest.approx(z * z * bound * (1 - bound) / trials, rel=1e-6, abs=1e-12)


@pytest.mark.parametrize("successes, trials", [(1, 0), (-1, 5), (6, 5), (1.5, 5), (True, 5), (2, "10")])
def test_wilson_rejects_bad_counts(successes, trials):
    with pytest.raises(ValueError, match="must be"):
        wilson_interval(successes, trials)


def test_summary_and_per_object_table():
    results = [
        EpisodeResult("mug", True, 10.0, 300, 2.1, 0.5, 180),
        EpisodeResult("mug", False, 2.0, 300, 2.1, None, 130),
        EpisodeResult("box 5.0x5.0x5.0cm", True, 8.0, 300, 2.1, 0.7, 200),
    ]
    summary = summarize(results)
    assert summary["successes"] == 2 and summary["episodes"] == 3
    assert (summary["success_ci_low"], summary["success_ci_high"]) == pytest.approx(wilson_interval(2, 3))
    assert summary["mean_grasp_time"] == pytest.approx(0.6)
    assert summary["grasped_episodes"] == 2
    assert summary["max_peak_strain"] == 200
    table = per_object_table(results).splitlines()
    assert table[0].startswith("| object |")
    assert [line.split("|")[1].strip() for line in table[2:]] == ["box 5.0x5.0x5.0cm", "mug", "**all**"]
    assert "1/2 (50.0 %)" in table[3] and "2/3 (66.7 %)" in table[4]


def test_both_tables_print_the_same_rate_for_the_same_episodes():
    """The group table and the per-object table round a rate the same way (85/200 was 42.5 % in one
    and 42 % in the other)."""
    from bh8_gym.agents.evaluation.evaluate import group_table, percent

    results = [EpisodeResult("mug", i < 85, 1.0, 300, 2.1, None, 150, object_set="test", family="random_urdf")
               for i in range(200)]
    for table in (group_table(results), per_object_table(results)):
        assert "| 85/200 (42.5 %) |" in table, table
    assert percent(0.425) == "42.5 %" and percent(0.0, 1.0) == "0.0-100.0 %"


def test_paired_comparison_counts_and_exact_mcnemar_reference_values():
    from bh8_gym.agents.evaluation.evaluate import paired_comparison

    ours = [True] * 10 + [False] * 5 + [True] * 3
    theirs = [False] * 10 + [False] * 5 + [True] * 3
    result = paired_comparison(ours, theirs)
    assert (result["only_ours"], result["only_theirs"], result["both"], result["neither"]) == (10, 0, 3, 5)
    assert result["mcnemar_p"] == pytest.approx(2 / 1024)  # 10 discordant pairs all one way
    assert paired_comparison([True, False], [False, True])["mcnemar_p"] == 1.0
    assert paired_comparison([True, True], [True, True])["mcnemar_p"] == 1.0  # no discordant pair
    with pytest.raises(ValueError, match="equally long"):
        paired_comparison([True], [True, False])


@given(st.lists(st.tuples(st.booleans(), st.booleans()), min_size=1, max_size=400))
def test_paired_comparison_is_symmetric_and_a_probability(pairs):
    from bh8_gym.agents.evaluation.evaluate import paired_comparison

    ours, theirs = [a for a, _ in pairs], [b for _, b in pairs]
    forward, backward = paired_comparison(ours, theirs), paired_comparison(theirs, ours)
    assert forward["mcnemar_p"] == backward["mcnemar_p"]
    assert 0.0 < forward["mcnemar_p"] <= 1.0
    assert forward["only_ours"] + forward["only_theirs"] + forward["both"] + forward["neither"] == len(pairs)
    # one more episode only we win moves the evidence our way: p never rises when we were ahead
    if forward["only_ours"] >= forward["only_theirs"]:
        assert paired_comparison(ours + [True], theirs + [False])["mcnemar_p"] <= forward["mcnemar_p"]


# -- numpy policy files ----------------------------------------------------------------------


def test_policy_file_rejects_pickles_and_foreign_files(tmp_path):
    np.save(tmp_path / "objects.npy", np.array([{"a": 1}], dtype=object))
    atomic_write_npz(tmp_path / "foreign.npz", {"x": np.zeros(3)})
    np.savez(tmp_path / "pickled.npz", format=np.array(["bh8-numpy-policy/1"], dtype=object))
    for name in ("foreign.npz", "pickled.npz"):
        with pytest.raises(PolicyFileError):
            NumpyPolicy(tmp_path / name)
    with pytest.raises(PolicyFileError, match="cannot be read"):
        NumpyPolicy(tmp_path / "missing.npz")


# -- training, resume, export (BH8FingerReach-v0) ---------------------------------------------


def _tiny_reach_config(algorithm: str = "PPO") -> dict:
    from bh8_gym.agents.training.train import default_config_path, load_config

    config = load_config(default_config_path(algorithm, REACH))
    if algorithm == "PPO":
        config["hyperparameters"].update(n_steps=64, batch_size=64, n_epochs=2)
    else:
        config["hyperparameters"].update(learning_starts=32, buffer_size=2_000, batch_size=32)
    config["policy_kwargs"]["net_arch"] = [16, 16]
    config["eval"].update(freq=128, episodes=1)
    config["train"]["checkpoint_freq"] = 128
    return config


def test_train_writes_checkpoints_and_resume_continues_the_step_count(tmp_path):
    """PPO on 2 SubprocVecEnv workers: a checkpoint, a best model and an evaluation row; --resume
    continues from the checkpoint's step counter instead of starting again."""
    from bh8_gym.agents.evaluation.run_files import read_evaluations
    from bh8_gym.agents.training.trainer import Trainer, TrainingError

    config = _tiny_reach_config("PPO")
    out = tmp_path / "run"
    state = Trainer(config, out, n_envs=2, seed=0, progress=False).run(256)
    assert state["num_timesteps"] == 256  # 2 rollouts of 64 steps x 2 envs
    checkpoint = json.loads((out / "checkpoints" / "latest.json").read_text())
    assert checkpoint["num_timesteps"] == 256
    for name in ("checkpoints/latest.zip", "best_model.zip", "final_model.zip", "run.json"):
        assert (out / name).is_file(), name
    assert [row["timesteps"] for row in read_evaluations(out)] == [128.0, 256.0]
    assert not list(out.rglob("*.tmp*")), "temporary checkpoint files left behind"
    assert any((out / "tb").rglob("events.out.tfevents*"))

    with pytest.raises(TrainingError, match="--resume"):
        Trainer(config, out, n_envs=2, progress=False).run(512)
    resumed = Trainer(config, out, n_envs=2, seed=0, progress=False).run(512, resume=True)
    assert resumed["num_timesteps"] == 512
    assert [row["timesteps"] for row in read_evaluations(out)] == [128.0, 256.0, 384.0, 512.0]


def test_linear_learning_rate_schedule_decays_to_zero_over_the_run(tmp_path):
    """learning_rate = "lin_1e-3" (rl-zoo's notation) falls linearly to 0 at the last update;
    any other string is refused naming the value."""
    from stable_baselines3 import PPO

    from bh8_gym.agents.training.trainer import Trainer, TrainingError

    config = _tiny_reach_config("PPO")
    config["hyperparameters"]["learning_rate"] = "lin_1e-3"
    out = tmp_path / "lin"
    Trainer(config, out, n_envs=1, seed=0, progress=False).run(256)
    model = PPO.load(out / "final_model.zip", device="cpu")
    assert model.lr_schedule(1.0) == pytest.approx(1e-3)
    assert model.lr_schedule(0.25) == pytest.approx(2.5e-4)
    assert model.policy.optimizer.param_groups[0]["lr"] == pytest.approx(0.0)  # the last update's

    config["hyperparameters"]["learning_rate"] = "cos_1e-3"
    with pytest.raises(TrainingError, match="cos_1e-3"):
        Trainer(config, tmp_path / "bad", n_envs=1, progress=False).run(64)


def test_sac_checkpoint_keeps_the_replay_buffer_and_resumes(tmp_path):
    from stable_baselines3 import SAC

    from bh8_gym.agents.training.trainer import Trainer

    config = _tiny_reach_config("SAC")
    out = tmp_path / "sac"
    Trainer(config, out, n_envs=1, seed=0, progress=False).run(128)
    assert (out / "checkpoints" / "latest_replay_buffer.npz").is_file()
    trainer = Trainer(config, out, n_envs=1, seed=0, progress=False)
    env = trainer._vec_env()
    try:
        model = trainer._resume_model(env)
        assert model.num_timesteps == 128
        assert isinstance(model, SAC) and model.replay_buffer.size() == 128
    finally:
        env.close()


def test_cli_train_rejects_contradicting_arguments(tmp_path, capsys):
    from bh8_gym.cli import main

    code = main(["train", "--algo", "SAC", "--config", str(_config_file("ppo_reach.toml")), "--out", str(tmp_path)])
    assert code == 2
    assert "contradicts" in capsys.readouterr().err


def test_cli_export_writes_a_checked_numpy_policy_that_names_its_env(tmp_path, capsys):
    """`bh8 export RUN/final_model.zip`: an .npz beside the model that reproduces SB3's actions and
    carries the run's env id (what `bh8 deploy` needs); a wrong suffix or a missing model exits 2."""
    from bh8_gym.agents.deployment.numpy_policy import NumpyPolicy
    from bh8_gym.agents.training.trainer import Trainer
    from bh8_gym.cli import main

    out = tmp_path / "run"
    Trainer(_tiny_reach_config("PPO"), out, n_envs=1, seed=0, progress=False).run(64)
    assert main(["export", str(out / "final_model.zip"), "--check", "64"]) == 0
    printed = capsys.readouterr().out
    assert "max |SB3 - numpy| action difference over 64 random observations" in printed
    policy = NumpyPolicy(out / "final_model.npz")
    assert policy.metadata["env_id"] == REACH and not policy.privileged

    assert main(["export", str(out / "final_model.zip"), "-o", str(tmp_path / "policy.txt")]) == 2
    assert "must end in .npz" in capsys.readouterr().err
    assert main(["export", str(tmp_path / "missing.zip")]) == 2
    assert "does not exist" in capsys.readouterr().err
    mode = (out / "final_model.npz").stat().st_mode & 0o777
    assert mode == 0o666 & ~_umask()  # readable by the account that deploys it (mkstemp gave 0600)

    lonely = tmp_path / "lonely" / "model.zip"  # no run.json beside it: the export could not name its env
    lonely.parent.mkdir()
    lonely.write_bytes((out / "final_model.zip").read_bytes())
    assert main(["export", str(lonely)]) == 2
    assert "no run.json" in capsys.readouterr().err
    (lonely.parent / "run.json").write_text(json.dumps({"env_id": "BH8Grasp-v0", "env_kwargs": {}, "algorithm": "PPO"}))
    assert main(["export", str(lonely)]) == 2  # a foreign run.json: a grasp layout for a reach model
    assert "belongs to another run" in capsys.readouterr().err
    not_sb3 = tmp_path / "not_sb3.zip"
    with zipfile.ZipFile(not_sb3, "w") as archive:
        archive.writestr("readme.txt", "hello")
    assert main(["export", str(not_sb3)]) == 2
    assert "cannot load SB3 model" in capsys.readouterr().err


def _umask() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return umask


def test_damaged_npz_is_a_policy_file_error(tmp_path):
    from bh8_gym.agents.deployment.numpy_policy import NumpyPolicy
    from bh8_gym.agents.policy_io import PolicyFileError

    path = _export_untrained_reach_policy(tmp_path)
    with np.load(path) as data:
        arrays = {name: data[name] for name in data.files if name != "layer1_bias"}
    np.savez(tmp_path / "damaged.npz", **arrays)
    with pytest.raises(PolicyFileError, match="damaged.*layer1_bias"):
        NumpyPolicy(tmp_path / "damaged.npz")


@pytest.mark.parametrize("damage", ["truncated", "empty", "garbage", "zeros", "flipped"])
def test_a_truncated_or_garbled_npz_is_a_policy_file_error(tmp_path, capsys, damage):
    """A half-copied or garbled .npz (zip errors, EOFError, or numpy's "allow_pickle" hint for a
    file that is not a zip at all) is a PolicyFileError, and `bh8 eval` a one-line error, exit 2
    (tracebacks before)."""
    from bh8_gym.agents.deployment.numpy_policy import NumpyPolicy
    from bh8_gym.agents.policy_io import PolicyFileError
    from bh8_gym.cli import main

    data = _export_untrained_reach_policy(tmp_path).read_bytes()
    middle = len(data) // 2
    damaged = {"truncated": data[:middle], "empty": b"", "garbage": bytes(range(256)) * 8, "zeros": bytes(2048),
               "flipped": data[:middle] + bytes([data[middle] ^ 0xFF]) + data[middle + 1:]}[damage]
    path = tmp_path / "damaged.npz"
    path.write_bytes(damaged)
    with pytest.raises(PolicyFileError, match="damaged.npz"):
        NumpyPolicy(path)
    assert main(["eval", str(path), "--episodes", "1"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "damaged.npz" in err


def test_cli_eval_refuses_bad_env_ids_object_files_and_out_paths_before_running(tmp_path, capsys):
    """Clear one-line errors (exit 2) instead of tracebacks; --out is checked before the episodes."""
    from bh8_gym.cli import main

    assert main(["eval", "--baseline", "loop", "--env", "NoSuch-v0", "--episodes", "1"]) == 2
    assert "unknown environment 'NoSuch-v0'" in capsys.readouterr().err
    not_a_urdf = tmp_path / "bad.urdf"
    not_a_urdf.write_text("this is not xml")
    assert main(["eval", "--baseline", "loop", "--episodes", "1", "--object-files", str(not_a_urdf)]) == 2
    assert "is not well-formed XML" in capsys.readouterr().err  # refused before PyBullet reads it (bh8_gym.urdfs)
    a_file = tmp_path / "report"
    a_file.write_text("")
    started = time.monotonic()
    assert main(["eval", "--baseline", "loop", "--episodes", "50", "--out", str(a_file)]) == 2
    assert "cannot be a report directory" in capsys.readouterr().err
    assert time.monotonic() - started < 10  # refused before 50 episodes ran


def test_cli_train_refuses_a_config_typo_before_starting_workers(tmp_path, capsys):
    """A misspelt env keyword or plant field in a config is a clear error naming it, with no run
    directory left behind (it used to kill the SubprocVecEnv workers with a broken pipe)."""
    from bh8_gym.cli import main

    text = _config_file("ppo_reach.toml").read_text()
    assert "[env_kwargs]\n" in text
    typos = [(text.replace("[env_kwargs]\n", "[env_kwargs]\nrandomise = true\n", 1), "unexpected keyword argument 'randomise'"),
             (text + "\n[eval_env_kwargs.plant_parameters]\nsolver_iterations = 0\n",
              "eval_env_kwargs: solver_iterations must be at least 1, got 0")]
    for config_text, message in typos:
        config = tmp_path / "typo.toml"
        config.write_text(config_text)
        out = tmp_path / "run"
        assert main(["train", "--config", str(config), "--out", str(out), "--timesteps", "64"]) == 2
        assert message in capsys.readouterr().err
        assert not out.exists()


def _config_file(name: str) -> Path:
    from bh8_gym.agents.training.train import default_config_path

    return default_config_path("PPO", REACH).with_name(name)


@pytest.mark.parametrize("algorithm,use_sde", [("PPO", False), ("SAC", False), ("PPO", True)])
def test_exported_policy_matches_sb3_actions(tmp_path, algorithm, use_sde):
    """The .npz runs with numpy alone and gives SB3's deterministic actions on random observations
    (also for gSDE policies, whose deterministic action is the same mean)."""
    from stable_baselines3 import PPO, SAC

    from bh8_gym.agents.env_factory import make_env
    from bh8_gym.agents.deployment.export import max_action_difference
    from bh8_gym.agents.deployment.numpy_policy import export_sb3_policy
    from bh8_gym.agents.deployment.sb3_file import SB3Policy

    env = make_env(REACH, {})
    try:
        model = {"PPO": PPO, "SAC": SAC}[algorithm]("MlpPolicy", env, seed=1, device="cpu", use_sde=use_sde,
                                                    policy_kwargs={"net_arch": [32, 24]})
        # move the weights away from their init so a wrong layer order or activation shows
        for parameter in model.policy.parameters():
            parameter.data.add_(0.3 * torch_randn_like(parameter))
        model.save(tmp_path / "model.zip")
    finally:
        env.close()
    path = export_sb3_policy(model, tmp_path / "policy.npz", metadata={"env_id": REACH})
    policy = NumpyPolicy(path)
    assert policy.metadata["algorithm"] == algorithm and policy.metadata["env_id"] == REACH
    with np.load(path, allow_pickle=False) as data:
        assert "metadata" in data.files
    assert max_action_difference(SB3Policy(tmp_path / "model.zip"), policy, 512) < 1e-5
    single, _ = policy.predict(np.zeros(policy.observation_dim, dtype=np.float32))
    assert single.shape == (policy.action_dim,)
    with pytest.raises(ValueError, match="observation must have"):
        policy.predict(np.zeros(policy.observation_dim + 1))
    with pytest.raises(ValueError, match="deterministic=False"):  # an export has no noise to sample
        policy.predict(np.zeros(policy.observation_dim), deterministic=False)


def test_stochastic_evaluation_draws_new_gsde_noise_every_episode(tmp_path):
    """gSDE's exploration is a matrix SB3 draws only in `reset_noise`: with one draw, every stochastic
    episode from the same start repeats the same actions (the trained grasp policy: 0/40 held-out
    successes that way, 11/40 with a draw per episode, as in its training rollouts)."""
    from stable_baselines3 import PPO

    from bh8_gym.agents.env_factory import make_env
    from bh8_gym.agents.evaluation.episodes import run_episodes
    from bh8_gym.agents.deployment.policy_file import load_policy

    env = make_env(REACH, {"randomize": False})
    try:
        PPO("MlpPolicy", env, seed=1, device="cpu", use_sde=True, policy_kwargs={"net_arch": [16]}).save(
            tmp_path / "model.zip")
        policy = load_policy(tmp_path / "model.zip")
        returns = [run_episodes(policy, env, 1, seed=0, deterministic=deterministic)[0].episode_return
                   for deterministic in (True, True, False, False)]
    finally:
        env.close()
    assert returns[0] == returns[1]  # the same start, the mean action: the same episode
    assert returns[2] != returns[3]  # the same start, new noise: another episode


def test_sac_with_gsde_is_refused_by_name(tmp_path):
    from stable_baselines3 import SAC

    from bh8_gym.agents.env_factory import make_env
    from bh8_gym.agents.deployment.numpy_policy import export_sb3_policy
    from bh8_gym.agents.policy_io import PolicyFileError

    env = make_env(REACH, {})
    try:
        model = SAC("MlpPolicy", env, seed=1, device="cpu", use_sde=True, policy_kwargs={"net_arch": [8]})
        with pytest.raises(PolicyFileError, match="gSDE"):
            export_sb3_policy(model, tmp_path / "policy.npz")
    finally:
        env.close()


def torch_randn_like(parameter):
    import torch

    generator = torch.Generator().manual_seed(parameter.numel())
    return torch.randn(parameter.shape, generator=generator)


def test_export_bakes_in_vecnormalize_statistics(tmp_path):
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    from bh8_gym.agents.env_factory import make_env
    from bh8_gym.agents.deployment.numpy_policy import export_sb3_policy

    venv = VecNormalize(DummyVecEnv([lambda: make_env(REACH, {})]), norm_reward=False)
    try:
        rng = np.random.default_rng(0)
        venv.obs_rms.mean = rng.normal(size=venv.observation_space.shape)
        venv.obs_rms.var = rng.uniform(0.1, 4.0, size=venv.observation_space.shape)
        model = PPO("MlpPolicy", venv, seed=0, device="cpu", policy_kwargs={"net_arch": [16]})
        policy = NumpyPolicy(export_sb3_policy(model, tmp_path / "p.npz", vec_normalize=venv))
        raw = rng.normal(scale=3.0, size=(64, *venv.observation_space.shape)).astype(np.float32)
        expected, _ = model.predict(venv.normalize_obs(raw), deterministic=True)
        np.testing.assert_allclose(policy.predict(raw)[0], expected, atol=1e-5)
    finally:
        venv.close()


# -- evaluation and baselines ----------------------------------------------------------------


def _export_untrained_reach_policy(tmp_path, **metadata) -> Path:
    from stable_baselines3 import PPO

    from bh8_gym.agents.env_factory import make_env
    from bh8_gym.agents.deployment.numpy_policy import export_sb3_policy

    env = make_env(REACH, metadata.get("env_kwargs", {}))
    try:
        model = PPO("MlpPolicy", env, seed=0, device="cpu", policy_kwargs={"net_arch": [16]})
    finally:
        env.close()
    return export_sb3_policy(model, tmp_path / "reach.npz", metadata={"env_id": REACH, "env_kwargs": {}, **metadata})


def test_eval_cli_writes_table_and_report(tmp_path, capsys):
    from bh8_gym.cli import main

    policy = _export_untrained_reach_policy(tmp_path)
    out = tmp_path / "report"
    assert main(["eval", str(policy), "--episodes", "3", "--out", str(out), "--gif-episodes", "1"]) == 0
    printed = capsys.readouterr().out
    assert "95% Wilson CI" in printed and "| object set |" in printed
    assert "| object |" not in printed  # the per-object rows go to table.md only
    assert "| object |" in (out / "table.md").read_text() and f"per-object table: {out / 'table.md'}" in printed
    report = json.loads((out / "results.json").read_text())
    assert report["summary"]["episodes"] == 3 and len(report["episodes"]) == 3
    low, high = wilson_interval(report["summary"]["successes"], 3)
    assert report["summary"]["success_ci_low"] == pytest.approx(low)
    assert (out / "table.md").read_text().splitlines()[-1].startswith("| **all** | 3 |")
    assert (out / "episodes.gif").read_bytes()[:6] == b"GIF89a"  # the README's main job writes one too
    # Real time in frames browsers honour: every 3rd step of the reach env's 4.65 ms made 14 ms frames,
    # stored partly as 10 ms, which browsers play at 100 ms (5x slow).
    from PIL import Image, ImageSequence

    with Image.open(out / "episodes.gif") as gif:
        durations = [frame.info["duration"] for frame in ImageSequence.Iterator(gif)]
    assert min(durations) >= 20
    assert sum(durations) / 1000 == pytest.approx(report["episodes"][0]["sim_seconds"], rel=0.1)  # the same episode


def test_eval_cli_env_kwargs_reach_the_env_and_bad_ones_exit_2(tmp_path, capsys):
    """--env-kwargs (JSON) goes on top of the policy's env keywords and is recorded in the report;
    a typo in a keyword or a field, or text that is not a JSON object, exits 2 naming it."""
    from bh8_gym.cli import main

    policy = _export_untrained_reach_policy(tmp_path)
    out = tmp_path / "report"
    assert main(["eval", str(policy), "--episodes", "1", "--gif-episodes", "0", "--out", str(out),
                 "--env-kwargs", '{"plant_parameters": {"solver_iterations": 120}}']) == 0
    report = json.loads((out / "results.json").read_text())
    assert report["env_kwargs"]["plant_parameters"] == {"solver_iterations": 120}
    capsys.readouterr()
    arguments = ["eval", str(policy), "--episodes", "1", "--gif-episodes", "0", "--env-kwargs"]
    for text, message in (('{"plant_parameters": {"solver_iteration": 1}}', "no field 'solver_iteration'"),
                          ('{"object_sett": "test"}', "object_sett")):
        assert main([*arguments, text]) == 2
        assert message in capsys.readouterr().err
    for text, message in (("[1]", "expected a JSON object"), ("{", "not valid JSON")):  # refused by argparse
        with pytest.raises(SystemExit) as exit_info:
            main([*arguments, text])
        assert exit_info.value.code == 2 and message in capsys.readouterr().err


def test_eval_compare_pairs_two_reports_on_the_same_episodes(tmp_path, capsys):
    from bh8_gym.cli import main

    policy = _export_untrained_reach_policy(tmp_path)
    first, second = tmp_path / "first", tmp_path / "second"
    common = ["--episodes", "3", "--seed", "7", "--gif-episodes", "0"]
    assert main(["eval", str(policy), *common, "--out", str(first)]) == 0
    assert main(["eval", str(policy), *common, "--out", str(second), "--compare", str(first)]) == 0
    assert "exact McNemar p = 1" in capsys.readouterr().out  # the same policy: no discordant episode
    paired = json.loads((second / "results.json").read_text())["paired"]
    assert paired["only_ours"] == paired["only_theirs"] == 0 and paired["episodes"] == 3

    assert main(["eval", str(policy), "--episodes", "3", "--seed", "8", "--gif-episodes", "0",
                 "--compare", str(first)]) == 2
    assert "from seed 7" in capsys.readouterr().err


def test_eval_in_two_processes_gives_the_one_process_report(tmp_path):
    """bh8 eval runs half of each object set's episodes in a worker process (--processes 2, the
    default on a machine with 2 cores), a policy's in batches of envs: the same episodes in the
    same order as in one process, for a policy file and for a script, on each object set. The reach
    env's figures are the same to the last bit; a grasp episode's may differ in the last digits,
    because the env's earlier episodes (a different history in the worker) leave PyBullet's
    contact order changed (docs/benchmarks.md, "Evaluation")."""
    from bh8_gym.cli import main

    policy = _export_untrained_reach_policy(tmp_path)
    runs = {
        "policy": [str(policy), "--episodes", "5", "--seed", "3"],
        "script": ["--baseline", "loop", "--objects", "primitives-test,test", "--episodes", "3"],
    }
    episodes = {}
    for name, arguments in runs.items():
        for processes in ("1", "2"):
            out = tmp_path / f"{name}-{processes}"
            assert main(["eval", *arguments, "--gif-episodes", "0", "--no-progress", "--processes", processes,
                         "--out", str(out)]) == 0
            episodes[name, processes] = json.loads((out / "results.json").read_text())["episodes"]
    assert episodes["policy", "1"] == episodes["policy", "2"] and len(episodes["policy", "1"]) == 5
    one, two = ([(e["object_set"], e["object_name"]) for e in episodes["script", processes]] for processes in "12")
    assert one == two and [name for name, _ in one] == ["primitives-test"] * 3 + ["test"] * 3
    assert len(set(one)) > 2  # different episodes, not one repeated


def test_bh8_eval_imports_no_torch_until_an_sb3_file_needs_it():
    """An exported .npz policy and the scripts evaluate without torch or SB3 (an install without
    the train extras; agents/deployment/numpy_policy.py): importing bh8 eval and its worker loads
    neither."""
    import subprocess
    import sys

    code = ("import sys, bh8_gym.agents.evaluation.evaluate, bh8_gym.agents.evaluation.eval_worker, "
            "bh8_gym.agents.evaluation.episodes; "
            "print(sorted(m for m in ('torch', 'stable_baselines3') if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"


def test_eval_prints_set_and_family_rows_and_pairs_each_set(tmp_path, capsys):
    """On several object sets the console gets each set's summary, its family rows and a paired
    line per set before the overall one; the per-object rows only table.md."""
    from bh8_gym.cli import main

    common = ["eval", "--baseline", "loop", "--objects", "primitives-test,test", "--episodes", "2",
              "--gif-episodes", "0"]
    first, second = tmp_path / "first", tmp_path / "second"
    assert main([*common, "--out", str(first)]) == 0
    assert main([*common, "--out", str(second), "--compare", str(first)]) == 0
    printed = capsys.readouterr().out.split("\n")
    group_rows, object_table = (second / "table.md").read_text().split("\n\n")
    assert all(row in printed for row in group_rows.splitlines())
    assert "| primitives-test | " in group_rows  # the primitives' families have rows of their own
    objects = [row for row in object_table.splitlines()[2:] if "**all**" not in row]
    assert objects and not any(row in printed for row in objects)
    paired = [line for line in printed if "on the same" in line]
    assert [line.split(" on the same")[0] for line in paired] == [
        "primitives-test: paired", "test: paired", f"paired with {first}"]
    assert all(line.endswith("exact McNemar p = 1") for line in paired)  # the same grasp: no discordance


def test_training_and_evaluating_a_model_warns_nothing_deprecated(tmp_path):
    """No SB3 schedule deprecation (get_schedule_fn, constant_fn) and no Gymnasium "Box precision
    lowered" while training with a linear schedule and evaluating the saved model from its file."""
    import warnings

    from bh8_gym.agents.training.trainer import Trainer
    from bh8_gym.cli import main

    config = _tiny_reach_config("PPO")
    config["hyperparameters"].update(learning_rate="lin_3e-4", clip_range="lin_0.2")
    config["eval"]["freq"] = 64
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        Trainer(config, tmp_path / "run", n_envs=1, seed=0, progress=False).run(64)
        assert main(["eval", str(tmp_path / "run" / "best_model.zip"), "--episodes", "1", "--gif-episodes", "0",
                     "--no-progress"]) == 0
    messages = [str(w.message) for w in caught]
    assert not [m for m in messages if "deprecated" in m or "precision lowered" in m], messages


def test_training_curve_plot(tmp_path):
    from bh8_gym.agents.evaluation.evaluate import plot_training_curve

    rows = [{"timesteps": t, "success_rate": s, "success_ci_low": max(s - 0.2, 0), "success_ci_high": min(s + 0.2, 1),
             "mean_return": r} for t, s, r in [(1000, 0.0, -5.0), (2000, 0.4, 1.0), (3000, 0.7, 4.0)]]
    path = plot_training_curve(rows, tmp_path / "curve.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="no evaluation rows"):
        plot_training_curve([], tmp_path / "empty.png")


@pytest.mark.slow
@pytest.mark.parametrize("name", ["loop", "supervisory"])
def test_baselines_run_on_the_grasp_env(name):
    """Both scripted grasps close the fingers on the object: strain rises, and an episode holds the
    object or loads all three gauges (which sense the outer joints only: a finger pressing with its
    inner link may not)."""
    from bh8_gym.agents.evaluation.baselines import make_baseline
    from bh8_gym.agents.env_factory import make_env
    from bh8_gym.agents.evaluation.episodes import run_episodes
    from bh8_gym.agents.evaluation.evaluate import summarize

    env = make_env("BH8Grasp-v0", {"object_set": "primitives", "randomize": False})
    try:
        results = run_episodes(None, env, 2, seed=3, baseline=make_baseline(name, env))
    finally:
        env.close()
    summary = summarize(results)
    assert summary["episodes"] == 2
    assert all(r.length > 0 and r.peak_strain is not None for r in results)
    assert summary["grasped_episodes"] >= 1 or summary["successes"] >= 1, results


def test_the_supervisory_baseline_episode_ends_with_the_arm_schedule():
    """Its arm starts lifting when GTC returns; its episode must end when that schedule does (as the
    LOOP policies' do), not after the env's 2 s of cycles, which held the object 0.8 s longer."""
    from bh8_gym.agents.evaluation.baselines import SupervisoryBaseline
    from bh8_gym.agents.env_factory import make_env

    env = make_env("BH8Grasp-v0", {"object_set": "primitives", "randomize": False})
    try:
        SupervisoryBaseline(env).run_episode(env, seed=3, tracker=None)
        base = env.unwrapped
        on_schedule = base.firmware.time - base.scene.start_time
        assert base.arm.total_seconds <= on_schedule < base.arm.total_seconds + base.cycle_seconds
    finally:
        env.close()


# -- deploy ----------------------------------------------------------------------------------


def test_deploy_runs_cycles_on_bh8sim_and_logs_decodable_blocks(tmp_path, capsys):
    from bh8_gym.agents.env_factory import make_env
    from bh8_gym.cli import main

    policy = _export_untrained_reach_policy(tmp_path)
    log = tmp_path / "deploy.jsonl"
    code = main(["deploy", "--port", "bh8sim://?seed=0", "--policy", str(policy), "--cycles", "20",
                 "--log", str(log), "--clock", "cycles"])
    assert code == 0, capsys.readouterr()
    records = [json.loads(line) for line in log.read_text().splitlines()]
    blocks = [r for r in records if "cycle" in r]
    assert len(blocks) == 1 + 20 + 1  # the "A" block, 20 policy cycles, the stop block
    env = make_env(REACH, {})
    try:
        layout = env.unwrapped.layout
        assert [r["line"] for r in records if r.get("event") == "command"][:-1] == [
            *env.unwrapped.setup_commands]
    finally:
        env.close()
    assert bytes.fromhex(blocks[0]["control"]) == b"A"
    for record in blocks:
        layout.decode_feedback(bytes.fromhex(record["feedback"]))
        control = bytes.fromhex(record["control"])
        if control[:1] == b"C":
            values = layout.decode_control(control[1:])
            velocities = [v for v, (_, name) in zip(values, layout.control_fields) if name == "LCV"]
            assert max(abs(v) for v in velocities) <= 100  # the default velocity clamp
    assert bytes.fromhex(blocks[-1]["control"]) == layout.encode_control([0] * len(layout.control_fields))
    assert records[-1]["event"] == "stop" and records[-1]["reason"] == "done"


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP], ids=["SIGINT", "SIGTERM", "SIGHUP"])
def test_deploy_stops_safely_on_a_termination_signal(tmp_path, signum):
    """Ctrl-C, `kill` or a closed terminal mid-run is a safe stop at the next cycle boundary, not a
    hand left in LOOP with its last velocities: the zero-velocity block, ^C, the exit action, a
    logged reason, exit code 3. (Ctrl-C as a KeyboardInterrupt mid-exchange skipped the zero block.)"""
    policy = _export_untrained_reach_policy(tmp_path)
    log = tmp_path / "deploy.jsonl"
    process = subprocess.Popen(
        [sys.executable, "-m", "bh8_gym.cli", "deploy", "--port", "bh8sim://?seed=0", "--policy", str(policy),
         "--cycles", "10000000", "--log", str(log), "--clock", "cycles"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        deadline = time.monotonic() + 60.0
        while not (log.exists() and log.read_text().count('"cycle"') > 5):  # running policy cycles
            assert process.poll() is None and time.monotonic() < deadline, process.communicate()
            time.sleep(0.05)
        process.send_signal(signum)
        out, err = process.communicate(timeout=60)
    finally:
        process.kill()
    assert process.returncode == 3, err
    reason = "interrupted (Ctrl-C)" if signum == signal.SIGINT else f"terminated ({signal.Signals(signum).name})"
    assert f"stopped: {reason}" in out
    records = [json.loads(line) for line in log.read_text().splitlines()]
    assert records[-1]["event"] == "stop" and records[-1]["reason"] == reason
    assert records[-3] == {**records[-3], "event": "command", "line": "GT"}  # the default exit action
    assert records[-2] == {**records[-2], "event": "baud", "rate": 9600}  # back to the rate it was found at
    last_block = [r for r in records if "cycle" in r][-1]
    control = bytes.fromhex(last_block["control"])
    assert control[0:1] == b"C" and set(control[1:]) == {0}  # LCV 0, LCPG 0: no motion, no torque


def test_deploy_stops_safely_when_the_policy_outputs_nan(tmp_path):
    """A policy that outputs NaN (a diverged network) is a safety stop with the reason logged and
    the zero block sent, not an exception about an out-of-range byte."""
    from bh8_gym.agents.deployment.deploy import Deployment
    from bh8_gym.agents.env_factory import make_env
    from bh8_gym.agents.deployment.policy_file import load_policy
    from bh8_gym.client import BarrettHand

    exported = load_policy(_export_untrained_reach_policy(tmp_path))

    class DivergingPolicy:
        privileged, observation_dim, action_dim, path = (exported.privileged, exported.observation_dim,
                                                         exported.action_dim, exported.path)

        def __init__(self):
            self.calls = 0

        def predict(self, observation, deterministic=True):
            if np.ndim(observation) == 2:  # deploy's test of the policy before it runs, not a cycle
                return exported.predict(observation, deterministic=deterministic)
            self.calls += 1
            action, state = exported.predict(observation, deterministic=deterministic)
            if self.calls > 3:
                action = np.full_like(action, np.nan)
            return action, state

    env = make_env(REACH, {})
    log = tmp_path / "deploy.jsonl"
    try:
        with log.open("w") as log_file, BarrettHand("bh8sim://?seed=0") as hand:
            deployment = Deployment(hand, DivergingPolicy(), env.unwrapped.interface, log_file, clock="cycles")
            deployment.setup(env.unwrapped.baud)
            reason = deployment.run(20)
    finally:
        env.close()
    assert reason.startswith("safety stop: the policy's action") and "nan" in reason
    records = [json.loads(line) for line in log.read_text().splitlines()]
    blocks = [r for r in records if "cycle" in r]
    assert len(blocks) == 1 + 3 + 1  # the "A" block, 3 good cycles, the zero block
    control = bytes.fromhex(blocks[-1]["control"])
    assert control[0:1] == b"C" and set(control[1:]) == {0}


def test_deploy_refuses_privileged_policy(tmp_path, capsys):
    from bh8_gym.cli import main

    policy = _export_untrained_reach_policy(tmp_path, privileged=True)
    log = tmp_path / "never.jsonl"
    code = main(["deploy", "--port", "bh8sim://?seed=0", "--policy", str(policy), "--log", str(log)])
    assert code != 0
    assert "privileged" in capsys.readouterr().err
    assert not log.exists() or "cycle" not in log.read_text()


# -- asymmetric critic -------------------------------------------------------------------------


def test_asymmetric_critic_trains_and_its_actor_uses_host_observations_only(tmp_path):
    """PPO with `asymmetric_critic`: the critic reads the env's privileged entries, the actor does
    not (issue 5: privileged state only for analysis and asymmetric critics). The run is marked
    deployable, evaluation feeds host observations, and the export keeps only the host inputs."""
    import torch

    from bh8_gym.agents.env_factory import make_env
    from bh8_gym.agents.deployment.export import max_action_difference
    from bh8_gym.agents.deployment.numpy_policy import export_sb3_policy
    from bh8_gym.agents.deployment.sb3_file import SB3Policy
    from bh8_gym.agents.training.train import default_config_path, load_config
    from bh8_gym.agents.training.trainer import Trainer

    config = load_config(default_config_path("PPO", "BH8Grasp-v0"))
    config["asymmetric_critic"] = True
    config["env_kwargs"] = {"object_set": "primitives", "randomize": True}
    config["eval_env_kwargs"] = {"object_set": "primitives", "randomize": False}
    config["hyperparameters"].update(n_steps=64, batch_size=64, n_epochs=1)
    config["policy_kwargs"]["net_arch"] = [16, 16]
    config["eval"].update(freq=64, episodes=1)
    config["train"]["checkpoint_freq"] = 64
    config["pretrain"].update(episodes=1, epochs=1)  # the default's warm start, kept short
    out = tmp_path / "run"
    Trainer(config, out, n_envs=1, seed=0, progress=False).run(64)
    run = json.loads((out / "run.json").read_text())
    assert run["asymmetric_critic"] is True and run["privileged"] is False

    sb3 = SB3Policy(out / "final_model.zip")
    host_env = make_env("BH8Grasp-v0", {"object_set": "primitives", "randomize": False})
    full_env = make_env("BH8Grasp-v0", {"object_set": "primitives", "randomize": False, "privileged": True})
    try:
        host_size = host_env.observation_space.shape[0]
        assert sb3.observation_dim == host_size < full_env.observation_space.shape[0]
        full, _ = full_env.reset(seed=3)
        model = sb3.model
        altered = full.copy()
        altered[host_size:] += 5.0  # different object pose and contacts
        with torch.no_grad():
            obs = torch.as_tensor(np.stack([full, altered]))
            actions = model.policy.get_distribution(obs).distribution.mean.numpy()
            values = model.policy.predict_values(obs).numpy()
        assert np.allclose(actions[0], actions[1])  # the actor never sees privileged entries
        assert not np.isclose(values[0, 0], values[1, 0])  # the critic does
        assert np.allclose(sb3.predict(full[:host_size])[0], model.predict(full, deterministic=True)[0])
    finally:
        host_env.close()
        full_env.close()

    path = export_sb3_policy(sb3.model, tmp_path / "policy.npz", metadata={"privileged": False})
    exported = NumpyPolicy(path)
    assert exported.observation_dim == host_size and not exported.privileged
    assert max_action_difference(sb3, exported, 256) < 1e-5
    with pytest.raises(ValueError, match="host entries"):
        sb3.predict(np.zeros(host_size + 1, dtype=np.float32))
    # `bh8 export` of the run's model: the default grasp config trains this way (it refused it,
    # comparing the critic's observation size with the env's)
    from bh8_gym.cli import main

    assert main(["export", str(out / "final_model.zip"), "-o", str(tmp_path / "cli.npz")]) == 0
    assert NumpyPolicy(tmp_path / "cli.npz").observation_dim == host_size


def test_asymmetric_critic_needs_ppo_and_no_privileged_actor():
    from bh8_gym.agents.training.train import default_config_path, load_config
    from bh8_gym.agents.training.trainer import Trainer, TrainingError

    config = load_config(default_config_path("SAC", "BH8Grasp-v0"))
    config["asymmetric_critic"] = True
    with pytest.raises(TrainingError, match="needs PPO"):
        Trainer(config, Path("unused"))
    config = load_config(default_config_path("PPO", "BH8Grasp-v0"))
    config["asymmetric_critic"] = True
    config["env_kwargs"]["privileged"] = True
    with pytest.raises(TrainingError, match="remove privileged"):
        Trainer(config, Path("unused"))


def test_eval_no_progress_hides_the_episode_bar_on_a_terminal(tmp_path, monkeypatch):
    """`bh8 eval --no-progress`, as `bh8 train --no-progress`: the bar drawn on a terminal is not drawn."""
    import contextlib
    import io

    from bh8_gym.cli import main

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    policy = _export_untrained_reach_policy(tmp_path)
    drawn = {}
    for flag in ([], ["--no-progress"]):
        err = Terminal()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            assert main(["eval", str(policy), "--episodes", "2", "--gif-episodes", "0", *flag]) == 0
        drawn[bool(flag)] = "episodes:" in err.getvalue()
    assert drawn == {False: True, True: False}


def test_eval_reports_each_object_set_and_family(tmp_path, capsys):
    """`bh8 eval --objects A,B`: --episodes per set, each set and each family in it summarised
    (results.json by_object_set, by_family; the table), the episodes labelled with both."""
    from bh8_gym.cli import main

    out = tmp_path / "report"
    assert main(["eval", "--baseline", "loop", "--objects", "validation,primitives-validation", "--episodes", "2",
                 "--gif-episodes", "0", "--no-progress", "--out", str(out)]) == 0
    report = json.loads((out / "results.json").read_text())
    assert report["object_sets"] == ["validation", "primitives-validation"]
    assert [e["object_set"] for e in report["episodes"]] == ["validation"] * 2 + ["primitives-validation"] * 2
    assert {e["family"] for e in report["episodes"][:2]} == {"random_urdf"}
    assert {e["family"] for e in report["episodes"][2:]} <= {"box", "cylinder", "sphere", "capsule"}
    for name in ("validation", "primitives-validation"):
        part = report["by_object_set"][name]
        assert part["episodes"] == 2 and part["successes"] == sum(
            e["success"] for e in report["episodes"] if e["object_set"] == name)
    assert report["by_family"]["random_urdf"]["episodes"] == 2
    printed = capsys.readouterr().out
    assert "| **validation** | all | 2 |" in printed and "| **primitives-validation** | all | 2 |" in printed
    assert main(["eval", "--baseline", "loop", "--objects", " , ", "--episodes", "1"]) == 2


def test_stalled_fingers_follow_the_firmwares_stall_rule_and_stay_stalled():
    """§5.5 case 1 at the default TSTOP, as a host sees it in LFAP: a finger that has closed 1000
    counts and then moved under 10 counts in 30 ms has stalled (and stays so: its worm holds it,
    §9.3.1); one still moving, or standing before it has closed 1000 counts, has not."""
    from bh8_gym.agents.grasps import StalledFingers

    watch = StalledFingers()
    dt = 0.004  # a cycle
    positions = {1: 0, 2: 0, 3: 0}
    for k in range(40):  # F1 closes on and stops at 5000; F2 keeps closing; F3 stands at 500
        positions = {1: min(5000, 400 * k), 2: 300 * k, 3: 500}
        stalled = watch.update(k * dt, positions)
        if 400 * k < 5000:
            assert not stalled[1]
    assert stalled == {1: True, 2: False, 3: False}
    for k in range(40, 60):  # F1 moves again (a reading after a stall does not unlock it)
        assert watch.update(k * dt, {1: 5000 + 50 * k, 2: 300 * k, 3: 500})[1]
    watch.reset()
    assert not any(watch.stalled.values())
