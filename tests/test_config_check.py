"""`bh8 train`'s config checks (agents/training/config_check.py, issue 32 item 11): every key of every table
is checked for its type and range before anything is built, and a bad one is named in one line;
the shipped configs pass; a fuzzed value is either accepted or refused naming its key, never a
crash; `bh8 train` refuses a bad config with exit 2 and writes nothing; values at the edges of the
ranges build a model that trains.
"""
from __future__ import annotations

import contextlib
import copy
import io
import math
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bh8_gym.agents.training import config_check
from bh8_gym.agents.training.config_check import ConfigError, check_config
from bh8_gym.cli import main

REACH, GRASP = "BH8FingerReach-v0", "BH8Grasp-v0"
NAN, INF = float("nan"), float("inf")


def _base(algorithm: str = "PPO", env_id: str = REACH) -> dict:
    """A tiny config of the shape load_config returns."""
    hyperparameters = ({"n_steps": 32, "batch_size": 32, "n_epochs": 1} if algorithm == "PPO"
                       else {"learning_starts": 16, "buffer_size": 256, "batch_size": 16})
    return {"algorithm": algorithm, "env_id": env_id, "env_kwargs": {}, "eval_env_kwargs": {"randomize": False},
            "train": {"total_timesteps": 64, "checkpoint_freq": 10_000}, "eval": {"freq": 10_000, "episodes": 1},
            "hyperparameters": hyperparameters, "policy_kwargs": {"net_arch": [8]}}


def _with(config: dict, table: str | None, key: str, value) -> dict:
    config = copy.deepcopy(config)
    if table is None:
        config[key] = value
    else:
        config.setdefault(table, {})[key] = value
    return config


# (algorithm, env, table, key, value): each a config bh8 train used to crash on, run with a NaN or
# infinity, or accept silently (issue 32 item 11), or of the same kind.
BAD = [
    *[("PPO", REACH, "hyperparameters", key, value) for key, value in [
        ("n_steps", 0), ("n_steps", -1), ("n_steps", 1.5), ("n_steps", "64"), ("n_steps", True),
        ("n_steps", 10**7), ("batch_size", 0), ("batch_size", 1), ("n_epochs", 0), ("n_epochs", 10**6),
        ("gamma", 2.0), ("gamma", -1), ("gamma", 0), ("gamma", NAN), ("gamma", INF), ("gae_lambda", 1.5),
        ("gae_lambda", -0.1), ("clip_range", NAN), ("clip_range", 0), ("clip_range", -0.2), ("clip_range", 1.5),
        ("clip_range", "lin_nan"), ("clip_range", "cos_0.2"), ("learning_rate", INF), ("learning_rate", 0),
        ("learning_rate", -1e-3), ("learning_rate", NAN), ("learning_rate", "lin_0"), ("learning_rate", "lin_inf"),
        ("ent_coef", -0.1), ("ent_coef", NAN), ("vf_coef", INF), ("max_grad_norm", 0), ("target_kl", 0),
        ("use_sde", "yes"), ("sde_sample_freq", -2), ("stats_window_size", 0), ("n_stepz", 64), ("seed", 3),
        ("policy_kwargs", {}), ("rollout_buffer_class", "RolloutBuffer"), ("clip_range_vf", -1),
        ("normalize_advantage", 0)]],
    *[("SAC", REACH, "hyperparameters", key, value) for key, value in [
        ("buffer_size", 0), ("buffer_size", 10**12), ("tau", 0), ("tau", 1.5), ("train_freq", 0),
        ("train_freq", [1, "hour"]), ("gradient_steps", 0), ("ent_coef", "automatic"), ("ent_coef", "auto_-1"),
        ("ent_coef", -1), ("target_entropy", "x"), ("action_noise", "normal"), ("optimize_memory_usage", True),
        ("learning_starts", -1), ("batch_size", 0), ("gamma", 2.0), ("n_epochs", 10)]],
    *[("PPO", REACH, "policy_kwargs", key, value) for key, value in [
        ("net_arch", [0]), ("net_arch", [-1]), ("net_arch", [64.5]), ("net_arch", [10**6]), ("net_arch", [8] * 17),
        ("net_arch", {"pi": [8], "qf": [8]}), ("net_arch", "64"), ("log_std_init", NAN), ("log_std_init", INF),
        ("log_std_init", 3), ("activation", "sigmoid"), ("activation_fn", "tanh"), ("ortho_init", 1),
        ("optimizer_kwargs", {"eps": 0}), ("optimizer_kwargs", {"lr": 1}), ("features_extractor_class", "x"),
        ("n_critics", 2)]],
    *[("SAC", REACH, "policy_kwargs", key, value) for key, value in [
        ("n_critics", 0), ("clip_mean", 0), ("net_arch", {"vf": [8]})]],
    *[("PPO", REACH, "train", key, value) for key, value in [
        ("total_timesteps", 0), ("total_timesteps", -1), ("total_timesteps", 1.5), ("total_timesteps", 10**400),
        ("checkpoint_freq", 0), ("n_envs", 0), ("n_envs", 1000), ("total_timestep", 64)]],
    *[("PPO", REACH, "eval", key, value) for key, value in [
        ("freq", 0), ("episodes", 0), ("episodes", 10**19), ("seed", -1), ("seed", 2**32), ("episode", 3)]],
    *[("PPO", env, table, key, value) for env, table, key, value in [
        (REACH, "env_kwargs", "randomize", "yes"), (GRASP, "env_kwargs", "object_set", 5),
        (REACH, "env_kwargs", "success_bonus", NAN), (REACH, "eval_env_kwargs", "success_bonus", INF),
        (REACH, "env_kwargs", "episode_seconds", INF), (REACH, "env_kwargs", "episode_seconds", 0),
        (REACH, "env_kwargs", "max_episode_steps", 0), (REACH, "env_kwargs", "max_episode_steps", 10**30),
        (REACH, "env_kwargs", "render_mode", "human"), (GRASP, "env_kwargs", "success_height", NAN),
        (GRASP, "eval_env_kwargs", "object_files", "my.obj"), (REACH, "env_kwargs", "plant_parameters", {"x": NAN})]],
    *[("PPO", GRASP, "pretrain", key, value) for key, value in [
        ("episodes", INF), ("episodes", 0), ("baseline", "supervisory"), ("baseline_kwargs", {"bogus": 1}),
        ("keep_decay", 0), ("action_noise", 2), ("episodez", 3)]],
    *[("PPO", REACH, None, key, value) for key, value in [
        ("asymmetric_critic", "yes"), ("hyperparameter", {"gamma": 0.9}), ("algorithm", "DQN"),
        ("env_id", "Nope-v0")]],
]


@pytest.mark.parametrize("algorithm, env_id, table, key, value", BAD,
                         ids=[f"{a}-{t}-{k}={str(v)[:20]}" for a, _, t, k, v in BAD])
def test_a_bad_value_is_refused_naming_its_table_and_key(algorithm, env_id, table, key, value):
    config = _with(_base(algorithm, env_id), table, key, value)
    with pytest.raises(ConfigError) as error:
        check_config(config)
    message = str(error.value)
    assert "\n" not in message and len(message) < 600, message
    named = f"[{table}] {key}" if table else key
    assert named in message or f"[{table}] has no key {key!r}" in message, message


def test_the_message_says_the_range():
    config = _with(_base(), "hyperparameters", "gamma", 2.0)
    with pytest.raises(ConfigError, match=r"^\[hyperparameters\] gamma must be in \(0, 1\], got 2\.0$"):
        check_config(config)


def test_pretrain_needs_the_grasp_env_and_ppo():
    with pytest.raises(ConfigError, match="needs BH8Grasp-v0"):
        check_config(_with(_base(), None, "pretrain", {}))
    with pytest.raises(ConfigError, match="needs PPO"):
        check_config(_with(_base("SAC", GRASP), None, "pretrain", {}))


def test_a_teacher_names_scripts_of_the_ceiling_family():
    """[pretrain] teacher (agents/training/teacher.py): a list of the family's scripts, named in the message."""
    grasp = _base("PPO", GRASP)
    check_config(_with(grasp, None, "pretrain", {"teacher": ["squeeze-g255", "loop"], "dagger_iterations": 2}))
    with pytest.raises(ConfigError, match=r"^\[pretrain\] teacher must be a list of 1\.\.16 items, each one of "):
        check_config(_with(grasp, None, "pretrain", {"teacher": ["squeeze", "no-such-script"]}))
    with pytest.raises(ConfigError, match=r"^\[pretrain\] dagger_beta must be in \[0, 1\], got 1\.5$"):
        check_config(_with(grasp, None, "pretrain", {"teacher": ["loop"], "dagger_beta": 1.5}))


def test_nesting_is_bounded_without_recursion_errors():
    deep: dict = {}
    node = deep
    for _ in range(5000):
        node["t"] = {}
        node = node["t"]
    with pytest.raises(ConfigError, match="nested more than"):
        check_config(_with(_base(), "env_kwargs", "plant_parameters", deep))


def test_every_shipped_config_passes():
    from bh8_gym.agents.evaluation.baselines import LOOP_BASELINES
    from bh8_gym.agents.training.train import load_config

    folder = Path(config_check.__file__).parents[1] / "configs"
    shipped = sorted(folder.glob("*.toml"))
    assert [path.name for path in shipped] == ["graspchoice_grasp.toml", "ppo_grasp.toml", "ppo_reach.toml",
                                               "sac_grasp.toml", "sac_reach.toml"]
    for path in shipped:
        check_config(load_config(path))
    assert config_check.PRETRAIN_KEYS["baseline"].choices == LOOP_BASELINES


def test_every_sb3_keyword_has_a_row():
    """The tables name every constructor keyword of SB3's PPO and SAC and of their policies (checked
    or refused with a reason), so a new SB3 keyword does not slip through unchecked."""
    import inspect

    from stable_baselines3 import PPO, SAC
    from stable_baselines3.common.policies import ActorCriticPolicy
    from stable_baselines3.sac.policies import SACPolicy

    for name, algorithm, policy in (("PPO", PPO, ActorCriticPolicy), ("SAC", SAC, SACPolicy)):
        assert set(inspect.signature(algorithm).parameters) <= set(config_check.HYPERPARAMETERS[name])
        policy_keys = set(inspect.signature(policy).parameters) - {"observation_space", "action_space", "lr_schedule"}
        assert policy_keys <= set(config_check.POLICY_KWARGS[name])


# Any value JSON or TOML can carry, and a few Python ones run.json cannot.
VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(min_value=-(2**70), max_value=2**70) | st.floats() | st.text(max_size=12)
    | st.sampled_from(["auto", "auto_0.1", "lin_3e-4", "lin_x", "step", "episode", "tanh", "relu"]),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=6), children, max_size=3),
    max_leaves=8)
KEYS = [(a, t, k) for a in ("PPO", "SAC") for t, keys in (("hyperparameters", config_check.HYPERPARAMETERS[a]),
                                                           ("policy_kwargs", config_check.POLICY_KWARGS[a]),
                                                           ("train", config_check.TRAIN_KEYS),
                                                           ("eval", config_check.EVAL_KEYS),
                                                           ("env_kwargs", config_check.ENV_KEYWORDS))
        for k in keys]


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(key=st.sampled_from(KEYS), value=VALUES)
def test_any_value_is_accepted_or_refused_naming_its_key(key, value):
    algorithm, table, name = key
    config = _with(_base(algorithm), table, name, value)
    try:
        check_config(config)
    except ConfigError as error:
        assert f"[{table}] {name}" in str(error) and "\n" not in str(error), str(error)
        return
    # accepted: a finite value of the key's kind
    assert config_check.HYPERPARAMETERS.get(algorithm, {}).get(name) is not None or table != "hyperparameters"
    assert not (isinstance(value, float) and not math.isfinite(value))


def test_a_hand_file_is_read_through_its_schema(tmp_path):
    """[env_kwargs] hand_parameters (issue 40): a hand file `bh8 calibrate fit` wrote, or a table of
    hand parameters, checked by the hand file's schema; a bad one named in one line."""
    hand = tmp_path / "hand.toml"
    hand.write_text("[hand]\nfinger_drive_efficiency = 0.45\nstrain_offsets = [111, 122, 133]\n")
    check_config(_with(_base(), "env_kwargs", "hand_parameters", str(hand)))
    check_config(_with(_base(), "env_kwargs", "hand_parameters", {"strain_gain": 110.0}))
    hand.write_text("[hand]\nfinger_drive_efficiency = 4.5\n")
    for value, message in ((str(hand), "finger_drive_efficiency must be a number in 0.02..1"),
                           (str(tmp_path / "missing.toml"), "hand-parameters file .* cannot be read"),
                           ({"time_step": 0.001}, "not a property of the hand"), (3, "the path of a hand file")):
        with pytest.raises(ConfigError, match=message) as error:
            check_config(_with(_base(), "env_kwargs", "hand_parameters", value))
        assert str(error.value).startswith("[env_kwargs] hand_parameters") and "\n" not in str(error.value)


def test_a_nested_key_with_a_line_break_is_quoted_in_a_one_line_message():
    """A key nested in a value is named as TOML would quote it: a line break in it (which the
    property test above found once) does not break the message in two."""
    config = _with(_base("PPO"), "hyperparameters", "use_sde", {"nx\n": [0, 2**70], "ok_key": {"k y": float("nan")}})
    with pytest.raises(ConfigError) as error:
        check_config(config)
    assert str(error.value) == "[hyperparameters] use_sde.'nx\\n'[1] must be a 64-bit integer, got 1180591620717411303424"
    del config["hyperparameters"]["use_sde"]["nx\n"]
    with pytest.raises(ConfigError, match=r"use_sde\.ok_key\.'k y' must be a finite number"):
        check_config(config)


# -- the command ---------------------------------------------------------------------------------


CLI_CASES = [("hyperparameters", "n_steps", "0"), ("hyperparameters", "batch_size", "0"),
             ("hyperparameters", "n_epochs", "0"), ("hyperparameters", "learning_rate", "inf"),
             ("hyperparameters", "gamma", "nan"), ("hyperparameters", "gamma", "2.0"),
             ("hyperparameters", "gamma", "-1"), ("hyperparameters", "clip_range", "nan"),
             ("hyperparameters", "clip_range", "0"), ("policy_kwargs", "log_std_init", "nan"),
             ("policy_kwargs", "net_arch", "[0]"), ("train", "total_timesteps", "0"),
             ("hyperparameters", "max_grad_norm", "inf"), ("eval", "episodes", "-inf")]


@pytest.mark.parametrize("table, key, value", CLI_CASES, ids=[f"{t}.{k}={v}" for t, k, v in CLI_CASES])
def test_bh8_train_refuses_a_bad_config_in_one_line_before_writing_anything(tmp_path, table, key, value):
    tables = {"hyperparameters": {"n_steps": "32", "batch_size": "32", "n_epochs": "1"},
              "policy_kwargs": {"net_arch": "[8]"}, "train": {"total_timesteps": "64"}, "eval": {"freq": "10000"}}
    tables[table][key] = value
    text = 'algorithm = "PPO"\nenv_id = "BH8FingerReach-v0"\n' + "".join(
        f"[{name}]\n" + "".join(f"{k} = {v}\n" for k, v in values.items()) for name, values in tables.items())
    (tmp_path / "bad.toml").write_text(text)
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["train", "--no-progress", "--n-envs", "1", "--config", str(tmp_path / "bad.toml"),
                     "--out", str(tmp_path / "run")])
    assert code == 2, err.getvalue()
    assert err.getvalue().startswith("bh8 train: ") and err.getvalue().count("\n") == 1, err.getvalue()
    assert f"[{table}] {key}" in err.getvalue()
    assert not (tmp_path / "run").exists()


def test_values_at_the_edges_of_the_ranges_build_and_train(tmp_path):
    """What the checks accept trains: PPO with the ranges' ends (gamma 1, gae_lambda 0, clip_range 1,
    a one-layer net of width 1, log std -20 and 2) runs its rollouts and updates without an error."""
    from bh8_gym.agents.training.trainer import Trainer

    for log_std_init in (-20.0, 2.0):
        config = _base()
        config["hyperparameters"].update(gamma=1.0, gae_lambda=0.0, clip_range=1.0, ent_coef=1.0, n_epochs=2,
                                         learning_rate="lin_1", max_grad_norm=1e6, target_kl=100.0)
        config["policy_kwargs"].update(net_arch=[1], log_std_init=log_std_init, activation="silu")
        check_config(config)
        state = Trainer(config, tmp_path / f"run{log_std_init}", n_envs=1, progress=False).run(64)
        assert state["num_timesteps"] == 64
