"""`ShardedVecEnv` (agents/training/vec_env.py): the same envs, steps, resets and infos as SB3's
`SubprocVecEnv`, with the first shard of envs in this process and one worker process per further
shard; a failing or vanished worker is a clear error, never a hang; a training run is the same run.
"""
from __future__ import annotations

import functools
import os
import signal
import time

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces

from bh8_gym.agents.training.vec_env import ShardedVecEnv, WorkerError, shard_sizes


class TinyEnv(gym.Env):
    """Seeded observations; an episode ends by termination (action > 0.8) or truncation (5 steps).
    `pid` is the process the env lives in; `fail_on_step` raises in that step."""

    observation_space = spaces.Box(-np.inf, np.inf, (2,), np.float32)
    action_space = spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self, fail_on_step: int | None = None, fail_to_build: bool = False):
        if fail_to_build:
            raise ValueError("TinyEnv cannot be built")
        self.pid = os.getpid()
        self.fail_on_step = fail_on_step
        self.steps = 0

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return self._obs(), {"seed": seed, "options": options, "draw": float(self.np_random.uniform())}

    def step(self, action):
        self.t += 1
        self.steps += 1
        if self.steps == self.fail_on_step:
            raise RuntimeError(f"step {self.steps} failed")
        return self._obs(), float(action[0]) + self.t, bool(action[0] > 0.8), self.t >= 5, {"t": self.t}

    def _obs(self):
        return np.array([self.np_random.uniform(), self.t], dtype=np.float32)

    def double(self, x):
        return 2 * x


def tiny_factories(n: int, **kwargs):
    return [functools.partial(TinyEnv, **kwargs) for _ in range(n)]


@pytest.fixture
def sharded():
    """A factory for ShardedVecEnvs, each closed after the test."""
    made = []

    def make(*args, **kwargs):
        made.append(ShardedVecEnv(*args, **kwargs))
        return made[-1]

    yield make
    for vec in made:
        vec.close()


@pytest.mark.parametrize("n_envs, n_processes, sizes", [(1, 2, [1]), (2, 2, [1, 1]), (3, 2, [2, 1]), (8, 2, [4, 4]),
                                                         (5, 3, [2, 2, 1])])
def test_shard_sizes_are_even_and_cover_every_env(n_envs, n_processes, sizes):
    assert shard_sizes(n_envs, n_processes) == sizes


def test_the_first_shard_lives_in_this_process_and_each_other_shard_in_one_worker(sharded):
    vec = sharded(tiny_factories(4), n_processes=2)
    pids = vec.get_attr("pid")
    assert pids[:2] == [os.getpid()] * 2
    assert pids[2] == pids[3] != os.getpid()
    assert [process.pid for process in vec.processes] == [pids[2]]


def test_steps_resets_and_infos_match_subproc_vec_env(sharded):
    """Every observation, reward, done, info (terminal observation, TimeLimit.truncated) and reset
    info of SB3's SubprocVecEnv, step by step, with seeds and reset options, uneven shards."""
    from stable_baselines3.common.vec_env import SubprocVecEnv

    reference = SubprocVecEnv(tiny_factories(3))
    try:
        ours = sharded(tiny_factories(3), n_processes=2)
        for vec in (reference, ours):
            vec.seed(7)
            vec.set_options([{"a": 1}, {}, {"c": 3}])
        assert_same(reference.reset(), ours.reset())
        assert_same(reference.reset_infos, ours.reset_infos)
        rng = np.random.default_rng(0)
        endings = set()
        for _ in range(40):
            actions = rng.uniform(-1, 1, (3, 1)).astype(np.float32)
            expected, got = reference.step(actions), ours.step(actions)
            assert_same(expected, got)
            assert_same(reference.reset_infos, ours.reset_infos)
            endings |= {info["TimeLimit.truncated"] for info, done in zip(got[3], got[2]) if done}
        assert endings == {True, False}, "both terminated and truncated episodes were stepped"
        assert_same(reference.reset(), ours.reset())  # unseeded now: each env's own generator
    finally:
        reference.close()


def assert_same(expected, got):
    assert type(expected) is type(got) or {type(expected), type(got)} <= {list, tuple}
    if isinstance(expected, np.ndarray):
        assert expected.dtype == got.dtype and expected.shape == got.shape
        np.testing.assert_array_equal(expected, got)
    elif isinstance(expected, (list, tuple)):
        assert len(expected) == len(got)
        for a, b in zip(expected, got):
            assert_same(a, b)
    elif isinstance(expected, dict):
        assert expected.keys() == got.keys()
        for key in expected:
            assert_same(expected[key], got[key])
    else:
        assert expected == got


def test_attributes_and_methods_reach_the_envs_named_in_env_order(sharded):
    vec = sharded(tiny_factories(5), n_processes=3)
    vec.set_attr("fail_on_step", 99, indices=[4, 0, 2])
    assert vec.get_attr("fail_on_step") == [99, None, 99, None, 99]
    assert vec.get_attr("fail_on_step", indices=[4, 1]) == [99, None]
    assert vec.env_method("double", 21, indices=[3, 0]) == [42, 42]
    assert vec.env_method("double", x=1) == [2] * 5
    assert vec.has_attr("double") and not vec.has_attr("no_such_attribute")
    assert vec.env_is_wrapped(gym.Wrapper) == [False] * 5


def test_an_env_failing_in_a_worker_is_an_error_with_its_traceback_and_close_returns(sharded):
    vec = sharded(tiny_factories(2, fail_on_step=3), n_processes=2)
    vec.set_attr("fail_on_step", None, indices=[0])  # only the worker's env fails
    vec.reset()
    vec.step(np.zeros((2, 1), np.float32))
    vec.step(np.zeros((2, 1), np.float32))
    with pytest.raises(WorkerError, match="(?s)env worker 1 failed.*RuntimeError: step 3 failed"):
        vec.step(np.zeros((2, 1), np.float32))
    start = time.monotonic()
    vec.close()
    assert time.monotonic() - start < 15 and not vec.processes[0].is_alive()


def test_a_worker_that_cannot_build_its_envs_is_an_error_naming_why():
    with pytest.raises(WorkerError, match="ValueError: TinyEnv cannot be built"):
        ShardedVecEnv([TinyEnv] + tiny_factories(1, fail_to_build=True), n_processes=2)


def test_a_vanished_worker_is_an_error_not_a_hang(sharded):
    vec = sharded(tiny_factories(2), n_processes=2)
    vec.reset()
    os.kill(vec.processes[0].pid, signal.SIGKILL)
    vec.processes[0].join(timeout=10)
    with pytest.raises(WorkerError, match="env worker 1 .* exited"):
        vec.step(np.zeros((2, 1), np.float32))
    vec.close()


def test_workers_ignore_the_signals_they_are_told_to(sharded):
    """bh8 train's workers ignore Ctrl-C sent to the process group: training stops through the
    training process, which still needs its workers for the checkpoint."""
    vec = sharded(tiny_factories(2), n_processes=2, ignore_signals=(signal.SIGINT,))
    vec.reset()
    os.kill(vec.processes[0].pid, signal.SIGINT)
    time.sleep(0.2)
    vec.step(np.zeros((2, 1), np.float32))
    assert vec.processes[0].is_alive()


def test_training_on_sharded_envs_is_the_run_subproc_vec_env_gives(tmp_path):
    """The same seed gives the same policy, bit for bit, whether the envs live in SubprocVecEnv's
    one-env workers or in ShardedVecEnv's shards (2 envs: one here, one in a worker)."""
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import SubprocVecEnv

    from bh8_gym.agents.env_factory import EnvFactory
    from bh8_gym.agents.training.train import default_config_path, load_config
    from bh8_gym.agents.training.trainer import Trainer

    class SubprocTrainer(Trainer):
        def _vec_env(self):
            return SubprocVecEnv([EnvFactory(self.config["env_id"], self._training_env_kwargs, seed=None)
                                  for _ in range(self.n_envs)])

    config = load_config(default_config_path("PPO", "BH8FingerReach-v0"))
    config["hyperparameters"].update(n_steps=64, batch_size=64, n_epochs=2)
    config["policy_kwargs"]["net_arch"] = [16, 16]
    config["eval"]["freq"] = config["train"]["checkpoint_freq"] = 10 ** 9
    parameters = []
    for trainer_class, out in ((Trainer, tmp_path / "sharded"), (SubprocTrainer, tmp_path / "subproc")):
        trainer_class(config, out, n_envs=2, seed=3, progress=False).run(256)
        policy = PPO.load(out / "final_model.zip", device="cpu").policy
        parameters.append({name: value.clone() for name, value in policy.state_dict().items()})
    vec = Trainer(config, tmp_path / "layout", n_envs=2, progress=False)._vec_env()
    try:  # one env here, one in a worker (SubprocVecEnv: a worker per env)
        assert len(vec.processes) == min(2, os.cpu_count()) - 1
    finally:
        vec.close()
    assert parameters[0].keys() == parameters[1].keys()
    for name in parameters[0]:
        assert torch.equal(parameters[0][name], parameters[1][name]), name
