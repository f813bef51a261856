"""Wall time and env steps per second of a short PPO run (bh8 train's code path) of the default config.

    python benchmarks/bench_training.py [--env BH8Grasp-v0] [--timesteps 20480] [--n-envs N]
        [--n-steps N] [--batch-size N] [--vec-env sharded|subproc] [--cpu]

Measures the whole run: env start-up, env stepping and PPO updates (evaluation, checkpoints and
the config's [pretrain] warm start off: the warm start is a fixed cost per run, measured in
docs/benchmarks.md's row for the default config). By default the run is the env's default
config's (agents/configs/ppo_grasp.toml: 8 envs, rollouts of 8 x 256 steps, minibatches of 256);
--n-envs, --n-steps and --batch-size change it (the earlier rows of docs/benchmarks.md name them).
torch runs one thread per process (Trainer sets it). --vec-env subproc runs the envs in SB3's
SubprocVecEnv, one worker process per env, as bh8 train did before ShardedVecEnv
(agents/training/vec_env.py): the same run, for comparison. --cpu also prints where the CPU time of a
vector step goes, per process (Linux /proc): on a machine with a free core per process the
training process's share bounds the step rate.
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from bh8_gym.agents.training.config_check import MAX_TIMESTEPS
from bh8_gym.agents.env_factory import EnvFactory
from bh8_gym.agents.training.train import default_config_path, load_config
from bh8_gym.agents.training.trainer import Trainer


class MeasuredTrainer(Trainer):
    """bh8 train's run; with `subproc`, the envs in SubprocVecEnv workers. Keeps the vector env
    (`vec`) and the CPU seconds its workers used from the first rollout to the end (`worker_cpu`)."""

    subproc = False

    def _vec_env(self):
        from stable_baselines3.common.vec_env import SubprocVecEnv

        if self.subproc and self.n_envs > 1:
            self.vec = SubprocVecEnv([EnvFactory(self.config["env_id"], self._training_env_kwargs, seed=None)
                                      for _ in range(self.n_envs)])
        else:
            self.vec = super()._vec_env()
        close = self.vec.close

        def close_after_reading_cpu():
            self.worker_cpu = workers_cpu_seconds(self.vec) - getattr(self, "worker_cpu_start", 0.0)
            close()

        self.vec.close = close_after_reading_cpu
        return self.vec


def workers_cpu_seconds(vec) -> float:
    """User + system CPU seconds of a vector env's worker processes so far (from /proc)."""
    total = 0.0
    for process in getattr(vec, "processes", []):
        with open(f"/proc/{process.pid}/stat") as stat:
            fields = stat.read().rsplit(")", 1)[1].split()
        total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return total


def timing(trainer: MeasuredTrainer, seconds: dict):
    """Wraps PPO's rollout collection and update to add their CPU time in this thread to `seconds`,
    and the envs' share of the rollouts (ShardedVecEnv's shard in this process)."""
    from stable_baselines3 import PPO

    from bh8_gym.agents.training import vec_env

    def timed(owner, name, key, before=None):
        original = getattr(owner, name)

        def wrapper(*args, **kwargs):
            if before is not None:
                before()
            start = time.thread_time()
            try:
                return original(*args, **kwargs)
            finally:
                seconds[key] += time.thread_time() - start

        setattr(owner, name, wrapper)

    def first_rollout():
        if not hasattr(trainer, "worker_cpu_start"):
            trainer.worker_cpu_start = workers_cpu_seconds(trainer.vec)

    timed(PPO, "collect_rollouts", "rollouts", first_rollout)
    timed(PPO, "train", "update")
    timed(vec_env._Shard, "step", "own envs")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="BH8Grasp-v0", help="environment id (default: %(default)s)")
    parser.add_argument("--timesteps", type=int, default=20_480,
                        help="env steps of the PPO run, all envs together (default: %(default)s)")
    parser.add_argument("--n-envs", type=int, default=None, help="parallel envs (default: the config's train.n_envs)")
    parser.add_argument("--n-steps", type=int, default=None, help="PPO rollout length per env (default: the config's)")
    parser.add_argument("--batch-size", type=int, default=None, help="PPO minibatch size (default: the config's)")
    parser.add_argument("--vec-env", choices=("sharded", "subproc"), default="sharded",
                        help="where the envs run: bh8 train's ShardedVecEnv or SB3's SubprocVecEnv (default: %(default)s)")
    parser.add_argument("--cpu", action="store_true", help="also print the CPU time per vector step, per process")
    args = parser.parse_args()

    config = load_config(default_config_path("PPO", args.env))
    for name in ("n_steps", "batch_size"):
        if getattr(args, name) is not None:
            config["hyperparameters"][name] = getattr(args, name)
    # evaluation and checkpoints out of the way: this measures training throughput
    config["eval"]["freq"] = MAX_TIMESTEPS
    config["train"]["checkpoint_freq"] = MAX_TIMESTEPS
    config.pop("pretrain", None)
    seconds = {"rollouts": 0.0, "update": 0.0, "own envs": 0.0}
    with tempfile.TemporaryDirectory() as out:
        trainer = MeasuredTrainer(config, Path(out), n_envs=args.n_envs, seed=0, progress=False)  # None: the config's
        n_envs = trainer.n_envs
        trainer.subproc = args.vec_env == "subproc"
        if args.cpu:
            timing(trainer, seconds)
        start = time.perf_counter()
        state = trainer.run(args.timesteps)
        wall = time.perf_counter() - start
    steps = state["num_timesteps"]
    hyperparameters = config["hyperparameters"]
    print(f"PPO on {args.env}, {n_envs} envs ({args.vec_env}), n_steps {hyperparameters['n_steps']}, "
          f"batch_size {hyperparameters['batch_size']}, cpu_count={os.cpu_count()}")
    print(f"{steps} env steps in {wall:.1f} s wall (incl. env start-up): {steps / wall:.0f} env steps/s")
    if args.cpu:
        ms = 1e3 * n_envs / steps  # per vector step
        print(f"CPU ms per vector step ({n_envs} env steps): training process {ms * seconds['rollouts']:.2f} "
              f"collecting rollouts (of which stepping its own envs {ms * seconds['own envs']:.2f}) + "
              f"{ms * seconds['update']:.2f} PPO update; worker processes {ms * trainer.worker_cpu:.2f} in all")


if __name__ == "__main__":
    main()
