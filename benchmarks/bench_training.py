"""Wall time and env steps per second of a short PPO run (bh8 train's code path) on all cores.

    python benchmarks/bench_training.py [--env BH8FingerReach-v0] [--timesteps 4096] [--n-envs N]

Measures the whole run: env start-up, env stepping and PPO updates (evaluation, checkpoints and
the config's [pretrain] warm start off: the warm start is a fixed cost per run, measured in
docs/benchmarks.md's row for the default config). torch runs one thread per process (Trainer sets it); envs run in SubprocVecEnv workers.
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from bh8_gym.agents.train import Trainer, default_config_path, load_config


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="BH8FingerReach-v0", help="environment id (default: %(default)s)")
    parser.add_argument("--timesteps", type=int, default=4096,
                        help="env steps of the PPO run, all envs together (default: %(default)s)")
    parser.add_argument("--n-envs", type=int, default=os.cpu_count(),
                        help="parallel envs (default: the CPU count, here %(default)s)")
    parser.add_argument("--n-steps", type=int, default=256, help="PPO rollout length per env (default: %(default)s)")
    args = parser.parse_args()

    config = load_config(default_config_path("PPO", args.env))
    config["hyperparameters"].update(n_steps=args.n_steps, batch_size=64)
    # evaluation and checkpoints out of the way: this measures training throughput
    config["eval"]["freq"] = 10 ** 12
    config["train"]["checkpoint_freq"] = 10 ** 12
    config.pop("pretrain", None)
    with tempfile.TemporaryDirectory() as out:
        trainer = Trainer(config, Path(out), n_envs=args.n_envs, seed=0, progress=False)
        start = time.perf_counter()
        state = trainer.run(args.timesteps)
        wall = time.perf_counter() - start
    steps = state["num_timesteps"]
    print(f"PPO on {args.env}, {args.n_envs} envs (SubprocVecEnv), cpu_count={os.cpu_count()}")
    print(f"{steps} env steps in {wall:.1f} s wall (incl. env start-up): {steps / wall:.0f} env steps/s")


if __name__ == "__main__":
    main()
