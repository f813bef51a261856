"""`EvaluationWorker` (agents/evaluation/eval_worker.py): an evaluation split between this process and a
worker gives the results of `run_episodes` in one process, in order; a worker that fails is a
clear error and leaves no stale reply behind.
"""
from __future__ import annotations

import os

import pytest

from bh8_gym.agents.env_factory import make_env
from bh8_gym.agents.evaluation.eval_worker import EvaluationWorker, EvaluationWorkerError, PolicyJob, predictor
from bh8_gym.agents.evaluation.episodes import run_episodes

GRASP = "BH8Grasp-v0"


@pytest.fixture(scope="module")
def asymmetric_model(tmp_path_factory):
    """A briefly trained grasp policy with the default config's asymmetric critic (its actor sees
    host observations only, so the worker must pad them as this process does)."""
    from stable_baselines3 import PPO

    from bh8_gym.agents.training.train import default_config_path, load_config

    from bh8_gym.agents.training.trainer import Trainer

    config = load_config(default_config_path("PPO", GRASP))
    config.pop("pretrain", None)
    config["hyperparameters"].update(n_steps=64, batch_size=64, n_epochs=2)
    config["eval"]["freq"] = config["train"]["checkpoint_freq"] = 10 ** 9
    out = tmp_path_factory.mktemp("run")
    Trainer(config, out, n_envs=1, seed=0, progress=False).run(64)
    return PPO.load(out / "final_model.zip", device="cpu"), config["eval_env_kwargs"]


def test_a_split_evaluation_gives_the_one_process_results_in_order(asymmetric_model):
    model, env_kwargs = asymmetric_model
    expected = run_episodes(predictor(model), make_env(GRASP, env_kwargs), 3, seed=10_000)
    worker = EvaluationWorker(GRASP, env_kwargs)
    try:
        env = make_env(GRASP, env_kwargs)
        assert worker.run(PolicyJob(model.policy), env, 3, 10_000) == expected  # episodes 10000-10001 here, 10002 there
        assert worker.run(PolicyJob(model.policy), env, 3, 10_000) == expected  # and again: the same episodes
        assert worker.process.pid != os.getpid() and worker.process.is_alive()
    finally:
        worker.close()
    assert not worker.process.is_alive()


def test_several_envs_run_a_policys_episodes_at_once_with_the_one_env_results_in_order(asymmetric_model):
    """run_episodes on a list of envs (one forward pass per step for all of them): each env takes
    the next seed when its episode ends, and the results are the one-env ones, in episode order
    (up to the last digits of a return: an env's earlier episodes, a different history here, can
    change PyBullet's contact order; docs/benchmarks.md, "Evaluation")."""
    model, env_kwargs = asymmetric_model
    envs = [make_env(GRASP, env_kwargs) for _ in range(3)]

    def same(got, expected):
        assert [r.object_name for r in got] == [r.object_name for r in expected]
        assert [r.episode_return for r in got] == pytest.approx([r.episode_return for r in expected], rel=0.05, abs=0.1)

    try:
        expected = run_episodes(predictor(model), envs[0], 5, seed=10_000)
        same(run_episodes(predictor(model), envs, 5, seed=10_000), expected)  # 3 at once, then 2 more
        assert len({result.object_name for result in expected}) > 1  # different episodes, not one repeated
        same(run_episodes(predictor(model), envs, 2, seed=10_003), expected[3:])  # fewer episodes than envs
    finally:
        for env in envs:
            env.close()


def test_a_policy_just_trained_with_gradients_is_sent_to_the_worker(asymmetric_model):
    """A forward pass with gradients (behaviour cloning before the first evaluation does one) leaves
    the policy's action distribution holding non-leaf tensors, which torch refuses to pickle; the
    worker still gets the policy and gives the one-process results."""
    import torch

    model, env_kwargs = asymmetric_model
    env = make_env(GRASP, env_kwargs)
    expected = run_episodes(predictor(model), env, 2, seed=10_000)
    observations = torch.zeros((4, *model.observation_space.shape))
    model.policy.evaluate_actions(observations, torch.zeros((4, *model.action_space.shape)))
    assert model.policy.action_dist.distribution.mean.requires_grad
    worker = EvaluationWorker(GRASP, env_kwargs)
    try:
        assert worker.run(PolicyJob(model.policy), env, 2, 10_000) == expected
    finally:
        worker.close()


def test_a_worker_that_cannot_build_its_env_is_an_error_naming_why_and_the_next_run_too(asymmetric_model):
    model, env_kwargs = asymmetric_model
    worker = EvaluationWorker(GRASP, {**env_kwargs, "no_such_keyword": 1})
    try:
        env = make_env(GRASP, env_kwargs)
        for _ in range(2):  # the failed reply was read: the next run gets its own
            with pytest.raises(EvaluationWorkerError, match="(?s)evaluation worker failed.*no_such_keyword"):
                worker.run(PolicyJob(model.policy), env, 2, 10_000)
    finally:
        worker.close()


def test_training_with_several_envs_evaluates_in_two_processes_with_the_one_process_figures(tmp_path, monkeypatch):
    """bh8 train's evaluation row, with half the episodes in the worker, is the one `run_episodes`
    gives for the evaluated model in one process."""
    from stable_baselines3 import PPO

    from bh8_gym.agents.evaluation import eval_worker
    from bh8_gym.agents.evaluation.evaluate import summarize
    from bh8_gym.agents.evaluation.run_files import read_evaluations
    from bh8_gym.agents.training.train import default_config_path, load_config
    from bh8_gym.agents.training.trainer import Trainer

    split_runs = []
    original_run = eval_worker.EvaluationWorker.run
    monkeypatch.setattr(eval_worker.EvaluationWorker, "run",
                        lambda self, *args: split_runs.append(args[2]) or original_run(self, *args))
    config = load_config(default_config_path("PPO", "BH8FingerReach-v0"))
    config["hyperparameters"].update(n_steps=64, batch_size=64, n_epochs=2)
    config["policy_kwargs"]["net_arch"] = [16, 16]
    config["eval"].update(freq=128, episodes=3)
    config["train"]["checkpoint_freq"] = 10 ** 9
    out = tmp_path / "run"
    Trainer(config, out, n_envs=2, seed=0, progress=False).run(128)
    assert split_runs == [3]
    [row] = read_evaluations(out)
    model = PPO.load(out / "best_model.zip", device="cpu")  # the model that evaluation saw
    summary = summarize(run_episodes(predictor(model), make_env(config["env_id"], config["eval_env_kwargs"]), 3,
                                     seed=int(config["eval"]["seed"])))
    assert row["success_rate"] == summary["success_rate"]
    assert row["mean_return"] == pytest.approx(summary["mean_return"], rel=1e-12)


def test_a_trainer_given_one_process_steps_its_envs_and_evaluates_in_this_process_only(tmp_path, monkeypatch):
    """`Trainer(processes=1)` (a `bh8 sweep` trial with cpu=1 and several envs) starts no env worker
    and no evaluation worker: it keeps to the CPUs it was given, and its figures are the same."""
    from bh8_gym.agents.evaluation import eval_worker
    from bh8_gym.agents.evaluation.run_files import read_evaluations
    from bh8_gym.agents.training.train import default_config_path, load_config
    from bh8_gym.agents.training.trainer import Trainer

    split_runs = []
    monkeypatch.setattr(eval_worker.EvaluationWorker, "__init__",
                        lambda self, *args, **kwargs: split_runs.append(args) or pytest.fail("a worker was started"))
    config = load_config(default_config_path("PPO", "BH8FingerReach-v0"))
    config["hyperparameters"].update(n_steps=64, batch_size=64, n_epochs=2)
    config["policy_kwargs"]["net_arch"] = [16, 16]
    config["eval"].update(freq=128, episodes=3)
    config["train"]["checkpoint_freq"] = 10 ** 9
    trainer = Trainer(config, tmp_path / "run", n_envs=4, seed=0, progress=False, processes=1)
    vec = trainer._vec_env()
    try:
        assert vec.num_envs == 4 and vec.processes == []
    finally:
        vec.close()
    trainer.run(128)
    assert split_runs == [] and read_evaluations(tmp_path / "run")  # it evaluated, here
    assert Trainer(config, tmp_path / "other", n_envs=4, progress=False, processes=2).processes == 2
    assert Trainer(config, tmp_path / "third", n_envs=1, progress=False, processes=2).processes == 1
