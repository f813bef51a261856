"""What calibration buys a grasp tuned in simulation (issue 40's last target), with the scripted
squeeze grasp standing in for a trained policy (training one per hand costs hours; the script's
settings are "trained" by picking the best of a grid on the simulator instead).

Three hands, all on BH8Grasp-v0 without randomisation, the same episodes (seeds) for each: the
nominal simulator (the defaults), the calibrated one (`--calibrated hand.toml`, from `bh8 calibrate
fit`), and the "real" hand (`--hidden hidden.toml`, the drawn hand the log was recorded on). For each
setting of the grid (SqueezeBaseline's strain target and close gain) the success rate on each hand.
"Trained on the nominal hand": the grid's best setting on the nominal simulator; its loss X is its
success there minus its success on the real hand. "Trained on the calibrated hand": the best on the
calibrated simulator; its loss is its success there minus on the real hand.

Run: python benchmarks/bench_calibrated_grasp.py --hidden hidden.toml --calibrated hand.toml
     [--episodes 100] [--objects primitives-validation] [--jobs 2]
"""
from __future__ import annotations

import argparse
import itertools
from concurrent.futures import ProcessPoolExecutor

import numpy as np

TARGETS = (175, 205, 235)
CLOSE_GAINS = (40, 60, 90)


def success_rate(job) -> float:
    hand, targets_gains, objects, episodes, first_seed = job
    from bh8_gym.agents.env_factory import make_env
    from bh8_gym.agents.grasps import make_loop_script, run_script

    env = make_env("BH8Grasp-v0", {"object_set": objects, "randomize": False,
                                   **({"hand_parameters": hand} if hand else {})})
    try:
        out = []
        for target, gain in targets_gains:
            script = make_loop_script("squeeze", env, strain_target=target, close_gain=gain)
            out.append(np.mean([run_script(env, script, first_seed + k) for k in range(episodes)]))
        return out
    finally:
        env.close()


def comparison_parser(description: str) -> argparse.ArgumentParser:
    """The arguments of both benchmarks that set a calibrated simulator beside the drawn hand (this one
    and bench_calibrated_squeeze.py): the drawn hand, its fit, and the episodes each hand runs."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--hidden", required=True, help="the drawn hand's file (the 'real' hand)")
    parser.add_argument("--calibrated", required=True, help="bh8 calibrate fit's hand file for it")
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--objects", default="primitives-validation")
    parser.add_argument("--first-seed", type=int, default=20000)
    parser.add_argument("--jobs", type=int, default=2)
    return parser


def three_hands(args: argparse.Namespace) -> dict:
    """The hand file of each simulator compared (None: the defaults)."""
    return {"nominal": None, "calibrated": args.calibrated, "real": args.hidden}


def main() -> None:
    args = comparison_parser(__doc__.splitlines()[0]).parse_args()
    grid = list(itertools.product(TARGETS, CLOSE_GAINS))
    hands = three_hands(args)
    jobs = [(hand, grid, args.objects, args.episodes, args.first_seed) for hand in hands.values()]
    with ProcessPoolExecutor(args.jobs) as pool:
        rates = dict(zip(hands, pool.map(success_rate, jobs)))
    print(f"{'strain target, close gain':28s} " + " ".join(f"{name:>11s}" for name in hands))
    for index, (target, gain) in enumerate(grid):
        print(f"{target:>14d}, {gain:<12d} " + " ".join(f"{100 * rates[name][index]:10.1f}%" for name in hands))
    for trained in ("nominal", "calibrated"):
        best = int(np.argmax(rates[trained]))
        loss = rates[trained][best] - rates["real"][best]
        print(f"trained on the {trained} hand: {grid[best]}, {100 * rates[trained][best]:.1f} % there, "
              f"{100 * rates['real'][best]:.1f} % on the real hand: loses {100 * loss:.1f} points")
    best_real = max(rates["real"])
    print(f"the grid's best on the real hand: {100 * best_real:.1f} % ({args.episodes} episodes of {args.objects} "
          f"from seed {args.first_seed}, randomisation off)")


if __name__ == "__main__":
    main()
