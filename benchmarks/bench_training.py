"""Wall time and env steps per second of a short PPO run (bh8 train's code path) on all cores.

    python benchmarks/bench_training.py [--env BH8Grasp-v0] [--timesteps 20000] [--n-envs N]
        [--n-steps 256] [--batch-size 64] [--config-hyperparameters] [--vec-env sharded|subproc]

Measures the whole run: env start-up, env stepping and PPO updates (evaluation, checkpoints and
the config's [pretrain] warm start off: the warm start is a fixed cost per run, measured in
docs/benchmarks.md's row for the default config). By default the rollouts are short (--n-steps 256,
--batch-size 64) so that a few thousand steps hold several updates; --config-hyperparameters
keeps the config's own (the default config's throughput). torch runs one thread per process
(Trainer sets it). --vec-env subproc runs the envs in SB3's SubprocVecEnv, one worker process per
env, as bh8 train did before ShardedVecEnv (agents/vec_env.py): the same run, for comparison.
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from bh8_gym.agents.env_factory import EnvFactory
from bh8_gym.agents.train import Trainer, default_config_path, load_config


class SubprocTrainer(Trainer):
    """bh8 train's run with the envs in SubprocVecEnv workers."""

    def _vec_env(self):
        from stable_baselines3.common.vec_env import SubprocVecEnv

        return SubprocVecEnv([EnvFactory(self.config["env_id"], self._training_env_kwargs, seed=None)
                              for _ in range(self.n_envs)])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="BH8FingerReach-v0", help="environment id (default: %(default)s)")
    parser.add_argument("--timesteps", type=int, default=4096,
                        help="env steps of the PPO run, all envs together (default: %(default)s)")
    parser.add_argument("--n-envs", type=int, default=os.cpu_count(),
                        help="parallel envs (default: the CPU count, here %(default)s)")
    parser.add_argument("--n-steps", type=int, default=256, help="PPO rollout length per env (default: %(default)s)")
    parser.add_argument("--batch-size", type=int, default=64, help="PPO minibatch size (default: %(default)s)")
    parser.add_argument("--config-hyperparameters", action="store_true",
                        help="the config's n_steps and batch_size instead of --n-steps and --batch-size")
    parser.add_argument("--vec-env", choices=("sharded", "subproc"), default="sharded",
                        help="where the envs run: bh8 train's ShardedVecEnv or SB3's SubprocVecEnv (default: %(default)s)")
    args = parser.parse_args()

    config = load_config(default_config_path("PPO", args.env))
    if not args.config_hyperparameters:
        config["hyperparameters"].update(n_steps=args.n_steps, batch_size=args.batch_size)
    # evaluation and checkpoints out of the way: this measures training throughput
    config["eval"]["freq"] = 10 ** 12
    config["train"]["checkpoint_freq"] = 10 ** 12
    config.pop("pretrain", None)
    trainer_class = SubprocTrainer if args.vec_env == "subproc" and args.n_envs > 1 else Trainer
    with tempfile.TemporaryDirectory() as out:
        trainer = trainer_class(config, Path(out), n_envs=args.n_envs, seed=0, progress=False)
        start = time.perf_counter()
        state = trainer.run(args.timesteps)
        wall = time.perf_counter() - start
    steps = state["num_timesteps"]
    hyperparameters = config["hyperparameters"]
    print(f"PPO on {args.env}, {args.n_envs} envs ({args.vec_env}), n_steps {hyperparameters['n_steps']}, "
          f"batch_size {hyperparameters['batch_size']}, cpu_count={os.cpu_count()}")
    print(f"{steps} env steps in {wall:.1f} s wall (incl. env start-up): {steps / wall:.0f} env steps/s")


if __name__ == "__main__":
    main()
