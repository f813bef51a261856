"""Wall time of N seeds trained one after another with `bh8 train` against the same N seeds as one
`bh8 sweep` on a local Ray with this machine's cores (one env and one CPU per trial), same steps.

    python benchmarks/bench_sweep.py [--env BH8Grasp-v0] [--timesteps 20480] [--seeds 4]

Both run the env's default PPO config with one validation evaluation at the end (5 episodes) and
one checkpoint, as whole commands (start-up included); the sweep's time also includes starting Ray
and its test evaluation of the chosen model (1 episode per object set). Prints a Markdown table
row and the load average seen (the sweep's gain is the cores it keeps busy: on a shared machine it
shrinks).
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

from bh8_gym.agents.training.train import default_config_path


def _config(env_id: str, timesteps: int, folder: Path) -> Path:
    text = default_config_path("PPO", env_id).read_text()
    config = tomllib.loads(text)
    config["train"].update(total_timesteps=timesteps, checkpoint_freq=timesteps, n_envs=1)
    config["eval"].update(freq=timesteps, episodes=5)
    config.pop("pretrain", None)  # the training loop is what the sweep parallelises; a warm start would dwarf it
    lines = []
    for key, value in config.items():
        if not isinstance(value, dict):
            lines.append(f"{key} = {_toml(value)}")
    for key, value in config.items():
        if isinstance(value, dict):
            lines.append(f"[{key}]")
            lines += [f"{name} = {_toml(item)}" for name, item in value.items()]
    path = folder / "bench.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def _toml(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return repr(value)


def _timed(command: list[str], log: Path) -> float:
    start = time.perf_counter()
    with log.open("w") as handle:
        code = subprocess.call(command, stdout=handle, stderr=subprocess.STDOUT)
    if code != 0:
        sys.exit(f"{' '.join(command)} failed ({code}); see {log}:\n{log.read_text()[-2000:]}")
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="BH8Grasp-v0", help="environment id (default: %(default)s)")
    parser.add_argument("--timesteps", type=int, default=20_480, help="env steps per seed (default: %(default)s)")
    parser.add_argument("--seeds", type=int, default=4, help="seeds (default: %(default)s)")
    args = parser.parse_args()

    bh8 = [sys.executable, "-m", "bh8_gym.cli"]
    loads = [os.getloadavg()[0]]
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        config = _config(args.env, args.timesteps, folder)
        sequential = 0.0
        for seed in range(args.seeds):
            sequential += _timed([*bh8, "train", "--config", str(config), "--seed", str(seed), "--n-envs", "1",
                                  "--no-progress", "--out", str(folder / f"train{seed}")], folder / f"train{seed}.log")
            loads.append(os.getloadavg()[0])
        sweep = _timed([*bh8, "sweep", "--config", str(config), "--seeds", f"0-{args.seeds - 1}",
                        "--out", str(folder / "sweep"), "--test-episodes", "1"], folder / "sweep.log")
        loads.append(os.getloadavg()[0])
    steps = args.seeds * args.timesteps
    print(f"PPO on {args.env}, {args.seeds} seeds x {args.timesteps} env steps, 1 env per run, cpu_count={os.cpu_count()}")
    print(f"load average (1 min) seen: {min(loads):.1f}-{max(loads):.1f}")
    print("| what | sequential `bh8 train` | `bh8 sweep` (local Ray) | speed-up | command | machine |")
    print("|---|---:|---:|---:|---|---|")
    print(f"| {args.seeds} seeds x {args.timesteps:,} steps, PPO on `{args.env}`, 1 env per run | {sequential:.0f} s "
          f"({steps / sequential:.0f} env steps/s) | {sweep:.0f} s ({steps / sweep:.0f} env steps/s) | "
          f"{sequential / sweep:.2f}x | `python benchmarks/bench_sweep.py` | 2-core AMD EPYC, no GPU |")


if __name__ == "__main__":
    main()
