"""How well the grasp choice's labels (most of `bh8 train`'s default run) use the cores.

Labels the same training contexts (the default config's settings and env) in 1 process and in
`--processes` worker processes (`agents/choice/labels.collect_labels`, as `bh8 train` runs it, the
pool's start-up included), in interleaved rounds, and prints contexts per second (and in 1 process
the CPU seconds per context), and the speed-up over 1 process: on a machine with N free cores it is at most N.
The labels must be equal whatever the split (they are: each context is its own reset(seed)); the
benchmark checks that too.

    python benchmarks/bench_labels.py [--contexts 96] [--processes 2] [--rounds 2]
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np

from bh8_gym.agents.choice.labels import collect_labels
from bh8_gym.agents.choice.policy import ChoiceSettings
from bh8_gym.agents.training.train import default_config_path, load_config


def one_run(config: dict, seeds: range, processes: int):
    """(wall seconds, CPU seconds of this process (the workers' are not counted), labels)."""
    settings = ChoiceSettings(**config["choice"].get("settings", {}))
    wall, cpu = time.perf_counter(), time.process_time()
    labels = collect_labels(config["env_id"], config["env_kwargs"], settings, seeds, processes=processes)
    return time.perf_counter() - wall, time.process_time() - cpu, labels


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--contexts", type=int, default=96, help="contexts per run (default: %(default)s)")
    parser.add_argument("--processes", type=int, default=2, help="worker processes to compare with 1 (default: %(default)s)")
    parser.add_argument("--rounds", type=int, default=2, help="interleaved rounds (default: %(default)s)")
    args = parser.parse_args()
    config = load_config(default_config_path("GraspChoice", "BH8Grasp-v0"))
    seeds = range(1_000_000, 1_000_000 + args.contexts)  # away from the training contexts' blocks
    one_run(config, range(1), 1)  # this process's env built and warm, as in a run's second chunk
    rows: dict[int, list[tuple[float, float]]] = {1: [], args.processes: []}
    reference = None
    for _ in range(args.rounds):
        for processes in rows:
            wall, cpu, labels = one_run(config, seeds, processes)
            rows[processes].append((wall, cpu))
            if reference is None:
                reference = labels
            elif not (np.array_equal(labels.success, reference.success)
                      and np.array_equal(labels.features, reference.features, equal_nan=True)):
                raise SystemExit(f"labels differ with {processes} processes: they must not depend on the split")
    print(f"{args.contexts} contexts per run, {args.rounds} rounds, cpu_count={os.cpu_count()}")
    walls = {processes: np.array([wall for wall, _ in runs]) for processes, runs in rows.items()}
    for processes, runs in rows.items():
        cpu = f", {np.median([c for _, c in runs]) / args.contexts:.2f} CPU s per context" if processes == 1 else ""
        print(f"{processes} process(es): {np.median(walls[processes]):.1f} s wall (range {walls[processes].min():.1f}-"
              f"{walls[processes].max():.1f}), {args.contexts / np.median(walls[processes]):.2f} contexts/s{cpu}")
    ratios = walls[1] / walls[args.processes]
    print(f"speed-up with {args.processes} processes, round by round: median {np.median(ratios):.2f} "
          f"(range {ratios.min():.2f}-{ratios.max():.2f})")


if __name__ == "__main__":
    main()
