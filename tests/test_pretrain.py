"""Warm start from a scripted grasp ([pretrain], agents/training/pretrain.py): the config is checked before
anything runs, the cloned actor acts like the script on its own demonstrations, and a warm-started
run evaluates the cloned policy at step 0 so it can be kept as the best model."""
from __future__ import annotations

import json

import numpy as np
import pytest

GRASP = "BH8Grasp-v0"


def _grasp_config(pretrain: dict) -> dict:
    from bh8_gym.agents.training.train import default_config_path, load_config

    config = load_config(default_config_path("PPO", GRASP))
    config["env_kwargs"] = {"object_set": "primitives-train", "randomize": False}
    config["eval_env_kwargs"] = {"object_set": "primitives-validation", "randomize": False}
    config["hyperparameters"].update(n_steps=128, batch_size=64, n_epochs=1)
    config["policy_kwargs"]["net_arch"] = [32, 32]
    config["eval"].update(freq=10_000, episodes=2)
    config["train"]["checkpoint_freq"] = 10_000
    config["pretrain"] = pretrain
    return config


@pytest.mark.parametrize("table, message", [
    ({"baseline": "squeeze", "episodez": 3}, "has no key 'episodez'"),
    ({"baseline": "supervisory"}, "baseline must be one of 'loop', 'squeeze'"),
    ({"baseline": "nonsense"}, "baseline must be one of 'loop', 'squeeze'"),
    ({"episodes": 0}, r"episodes must be an integer in 1\.\."),
    ({"learning_rate": -1.0}, r"learning_rate must be in \(0, 1\]"),
    ({"keep_weight": 0.5, "keep_floor": 0.6}, "keep_floor must be in"),
    ({"keep_floor": -0.1}, "keep_floor must be in"),
])
def test_a_bad_pretrain_table_is_refused_before_anything_runs(tmp_path, table, message):
    from bh8_gym.agents.training.trainer import Trainer, TrainingError

    with pytest.raises(TrainingError, match=message):
        Trainer(_grasp_config(table), tmp_path / "run", n_envs=1, progress=False)
    assert not (tmp_path / "run").exists()


def test_pretrain_needs_ppo(tmp_path):
    from bh8_gym.agents.training.trainer import Trainer, TrainingError

    config = _grasp_config({})
    config["algorithm"] = "SAC"
    config["asymmetric_critic"] = False
    config["hyperparameters"] = {}
    with pytest.raises(TrainingError, match="needs PPO"):
        Trainer(config, tmp_path / "run", n_envs=1, progress=False)


def test_cloned_actor_acts_like_the_script_on_its_demonstrations():
    """After cloning, the policy's deterministic action is much closer to the squeeze script's than
    before (the script's bytes, in the float action space), and the critic has moved towards the
    demonstrations' returns."""
    import torch
    from stable_baselines3 import PPO

    from bh8_gym.agents.env_factory import make_env
    from bh8_gym.agents.training.pretrain import PretrainSettings, clone, record

    settings = PretrainSettings(baseline="squeeze", episodes=2, epochs=40, seed=5)
    kwargs = {"object_set": "primitives-train", "randomize": False}
    demonstrations = record(GRASP, kwargs, settings, gamma=0.99)
    assert demonstrations.observations.shape[0] == demonstrations.actions.shape[0] == demonstrations.returns.shape[0]
    assert demonstrations.observations.shape[0] > 400  # two whole episodes of ~300 cycles
    assert np.all(np.abs(demonstrations.actions) <= 1.0 + 1e-6)  # the float action space
    env = make_env(GRASP, kwargs)
    try:
        model = PPO("MlpPolicy", env, seed=0, device="cpu", policy_kwargs={"net_arch": [64, 64]})
    finally:
        env.close()

    def errors():
        with torch.no_grad():
            observations = torch.as_tensor(demonstrations.observations)
            mean = model.policy.get_distribution(observations).distribution.mean.numpy()
            values = model.policy.predict_values(observations).numpy().ravel()
        return (float(np.mean((mean - demonstrations.actions) ** 2)),
                float(np.mean((values - demonstrations.returns) ** 2)))

    actor_before, value_before = errors()
    losses = clone(model, demonstrations, settings, seed=0)
    actor_after, value_after = errors()
    assert actor_after < 0.25 * actor_before, (actor_before, actor_after)
    assert value_after < value_before, (value_before, value_after)
    assert losses["actor_mse"] == pytest.approx(actor_after, rel=0.5)


def test_a_warm_started_run_evaluates_the_cloned_policy_at_step_zero(tmp_path):
    from bh8_gym.agents.evaluation.run_files import read_evaluations
    from bh8_gym.agents.training.trainer import Trainer

    config = _grasp_config({"baseline": "squeeze", "episodes": 1, "epochs": 2})
    out = tmp_path / "run"
    Trainer(config, out, n_envs=1, seed=0, progress=False).run(128)
    report = json.loads((out / "pretrain.json").read_text())
    assert report["episodes"] == 1 and report["steps"] > 200 and report["baseline"] == "squeeze"
    assert [row["timesteps"] for row in read_evaluations(out)][0] == 0.0
    assert (out / "best_model.zip").is_file()


def test_keeping_the_demonstrations_during_rl_and_resuming_with_them(tmp_path):
    """keep_weight > 0: the demonstrations are saved in the run directory, RL's rollouts end with
    cloning minibatches (logged weight decays), and a resumed run reads them back."""
    from bh8_gym.agents.training.pretrain import DEMONSTRATIONS_FILE, load_demonstrations
    from bh8_gym.agents.training.trainer import Trainer

    config = _grasp_config({"baseline": "squeeze", "episodes": 1, "epochs": 1, "action_noise": 0.1,
                            "keep_weight": 1.0, "keep_batches": 2})
    out = tmp_path / "run"
    Trainer(config, out, n_envs=1, seed=0, progress=False).run(128)
    demonstrations = load_demonstrations(out / DEMONSTRATIONS_FILE)
    assert demonstrations.episodes == 1 and len(demonstrations.actions) > 200
    state = Trainer(config, out, n_envs=1, seed=0, progress=False).run(256, resume=True)
    assert state["num_timesteps"] == 256
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    weights = []
    for events in sorted(out.glob("tb/*/events.out.tfevents*")):
        accumulator = EventAccumulator(str(events))
        accumulator.Reload()
        if "pretrain/keep_weight" in accumulator.Tags()["scalars"]:
            weights += [event.value for event in accumulator.Scalars("pretrain/keep_weight")]
    # one rollout of 128 steps per run: weight 1 after the first, 0.95 after the resumed second
    assert weights == pytest.approx([1.0, 0.95]), weights


def test_the_cloning_weight_decays_to_its_floor_and_stays_there():
    """keep_floor: the default continued to 1 M steps lost the grasp once the weight had decayed
    to nothing (docs/agents.md); with a floor the weight stops there."""
    from bh8_gym.agents.training.pretrain import PretrainSettings, keep_weight_after

    settings = PretrainSettings(keep_weight=1.0, keep_decay=0.9, keep_floor=0.3)
    weights = [keep_weight_after(settings, n) for n in range(40)]
    assert weights[:3] == pytest.approx([1.0, 0.9, 0.81])
    assert all(a >= b for a, b in zip(weights, weights[1:])) and min(weights) == 0.3 == weights[-1]
    assert keep_weight_after(PretrainSettings(keep_weight=1.0, keep_decay=0.9), 200) < 1e-4


def test_action_noise_disturbs_the_executed_actions_but_records_the_scripts():
    """DART-style demonstrations: with action noise the recorded labels are still the script's
    bytes (a LOOP velocity of exactly 0 while a finger holds appears among them), the episode
    differs from the noiseless one."""
    from bh8_gym.agents.training.pretrain import PretrainSettings, record

    kwargs = {"object_set": "primitives-train", "randomize": False}
    clean = record(GRASP, kwargs, PretrainSettings(episodes=1, seed=7), gamma=0.99)
    noisy = record(GRASP, kwargs, PretrainSettings(episodes=1, seed=7, action_noise=0.2), gamma=0.99)
    assert not np.array_equal(clean.observations[:50], noisy.observations[:50])
    levels = np.unique(np.round(noisy.actions[:, 0], 4))
    assert len(levels) < 40, "labels must be the script's quantised bytes, not noisy floats"


def test_dagger_labels_the_students_own_states_with_the_teachers_actions():
    """agents/training/teacher.py: iteration 0 runs the teacher alone (every executed action is its label);
    a later iteration with beta 0 runs the student alone, and the teacher's script, reading the
    same blocks, still labels every step it visits."""
    from stable_baselines3 import PPO

    from bh8_gym.agents.env_factory import make_env
    from bh8_gym.agents.training.pretrain import PretrainSettings
    from bh8_gym.agents.training.teacher import distill

    kwargs = {"object_set": "primitives-train", "randomize": False, "history": True}
    env = make_env(GRASP, kwargs)
    try:
        model = PPO("MlpPolicy", env, seed=0, device="cpu", n_steps=64, batch_size=64,
                    policy_kwargs={"net_arch": [32], "log_std_init": -3.0})
    finally:
        env.close()
    settings = PretrainSettings(teacher=("squeeze", "loop"), episodes=2, epochs=2, seed=11,
                                dagger_iterations=2, dagger_beta=0.0)
    reports = []
    demonstrations, summary = distill(model, GRASP, kwargs, settings, seed=0, report=reports.append)
    assert summary["episodes"] == 2 and sum(summary["chosen"].values()) == 2
    first, second = summary["iterations"]
    assert first["beta"] == 1.0 and second["beta"] == 0.0
    assert second["steps"] == len(demonstrations.actions) > first["steps"] > 500
    assert demonstrations.observations.shape[1] == model.observation_space.shape[0]
    # the teacher's labels are the float actions its scripts produce: inside [-1, 1]
    assert np.all(np.abs(demonstrations.actions) <= 1.0 + 1e-6)
    assert any("DAgger 2/2" in line for line in reports)


def test_bh8_train_says_what_the_warm_start_does_and_prints_each_validation_evaluation(tmp_path):
    """`bh8 train` reports the warm start (the script's episodes held, the cloning losses) and each
    validation evaluation as it lands (step, success with its CI, mean return, new best or not).
    Off a terminal (here: captured) it draws no progress bar, so a CI log gets lines, not bar spam."""
    import contextlib
    import io
    import re

    from bh8_gym.cli import main

    config = tmp_path / "tiny.toml"
    config.write_text("""algorithm = "PPO"
env_id = "BH8Grasp-v0"
[env_kwargs]
object_set = "primitives-train"
randomize = false
[eval_env_kwargs]
object_set = "primitives-validation"
randomize = false
[train]
checkpoint_freq = 10000
[eval]
freq = 128
episodes = 2
[pretrain]
baseline = "squeeze"
episodes = 2
epochs = 2
[hyperparameters]
n_steps = 128
batch_size = 64
n_epochs = 1
[policy_kwargs]
net_arch = [16]
""")
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["train", "--config", str(config), "--out", str(tmp_path / "run"), "--n-envs", "1",
                     "--timesteps", "128"])
    assert code == 0, err.getvalue()
    lines = out.getvalue().splitlines()
    assert lines[0] == "warm start: recording 2 episodes of the squeeze grasp, then 2 epochs of cloning ([pretrain])"
    assert re.fullmatch(r"warm start: the script held [0-2] of 2 episodes \(\d+ steps recorded\)", lines[1])
    assert re.fullmatch(r"warm start: cloned; actor MSE \S+, value MSE \S+", lines[2])
    evaluation = (r"step {}: validation success \d+\.\d % \(95% Wilson CI \d+\.\d-\d+\.\d %, 2 episodes\), "
                  r"mean return -?\d+\.\d\d; ")
    assert re.fullmatch(evaluation.format(0) + "new best", lines[3]), lines[3]
    assert re.fullmatch(evaluation.format(128) + r"(new best|best so far \d+\.\d % at step 0)", lines[4]), lines[4]
    assert lines[5].startswith("trained to 128 steps; best validation success rate ") and len(lines) == 6
    assert "%|" not in err.getvalue() and "\r" not in err.getvalue()  # no bar drawn into a log
