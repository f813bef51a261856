"""What calibration buys a grasp, measured smoothly (issue 40's last target).

bench_calibrated_grasp.py compares success rates, which cannot judge it: a 0.1 % change of one
parameter flips a fifth of the episodes. Here the same scripted grasp (agents.grasps'
SqueezeBaseline at one setting, standing in for a policy trained on a simulator) runs on the same
episodes (seeds) of BH8Grasp-v0 without randomisation on three hands: the nominal simulator (the
defaults), the calibrated one (`--calibrated hand.toml`, from `bh8 calibrate fit`) and the "real"
hand (`--hidden hidden.toml`, the drawn hand the log was recorded on). Per episode, quantities that
move smoothly with the hand's parameters:

- `squeeze`: the mean torque about the outer joints (N·m, the fingers' mean) over the episode's last
  half: how hard the script, regulating the gauges' reading to its strain target, really squeezes
  (the gauges' gain and offsets turn the same reading into another torque);
- `closed`: cycles until every finger is in contact (how fast a weak close drive closes);
- `reading`: the mean gauge reading (counts) over the last half.

Printed: each quantity's mean over the episodes on each hand with its standard error, X = |nominal
- real| and the calibrated loss |calibrated - real|, and their ratio.

Run: python benchmarks/bench_calibrated_squeeze.py --hidden hidden.toml --calibrated hand.toml
     [--episodes 100] [--objects primitives-validation] [--jobs 2]
"""
from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor

import numpy as np

from bench_calibrated_grasp import comparison_parser, three_hands

QUANTITIES = ("squeeze", "closed", "reading")


def episodes(job) -> dict:
    hand, objects, count, first_seed, close_gain = job
    from bh8_gym.agents.env_factory import make_env
    from bh8_gym.agents.grasps import make_loop_script

    env = make_env("BH8Grasp-v0", {"object_set": objects, "randomize": False,
                                   **({"hand_parameters": hand} if hand else {})})
    try:
        script = make_loop_script("squeeze", env, close_gain=close_gain)
        out = {name: [] for name in QUANTITIES}
        for k in range(count):
            observation, info = env.reset(seed=first_seed + k)
            script.reset(env)
            plant = env.unwrapped.plant
            loads, readings, closed, cycle, done = [], [], None, 0, False
            while not done:
                observation, _, terminated, truncated, info = env.step(script.act(observation, info))
                done = terminated or truncated
                cycle += 1
                loads.append(float(np.mean(plant.outer_joint_torques())))
                readings.append(float(np.mean(plant.strain_gauges()[:3])))
                if closed is None and all(script.contact.values()):
                    closed = cycle
            half = len(loads) // 2
            out["squeeze"].append(float(np.mean(loads[half:])))
            out["reading"].append(float(np.mean(readings[half:])))
            out["closed"].append(float(closed if closed is not None else cycle))
        return out
    finally:
        env.close()


def main() -> None:
    parser = comparison_parser(__doc__.splitlines()[0])
    parser.add_argument("--close-gain", type=int, default=40)
    args = parser.parse_args()
    hands = three_hands(args)
    # Each hand's episodes split over the jobs (the same seeds on every hand).
    chunks = np.array_split(np.arange(args.episodes), max(1, args.jobs))
    jobs = [(hand, args.objects, len(chunk), args.first_seed + int(chunk[0]), args.close_gain)
            for hand in hands.values() for chunk in chunks if len(chunk)]
    with ProcessPoolExecutor(args.jobs) as pool:
        results = list(pool.map(episodes, jobs))
    per_hand = {}
    for index, name in enumerate(hands):
        parts = results[index * len(chunks):(index + 1) * len(chunks)]
        per_hand[name] = {q: np.concatenate([part[q] for part in parts]) for q in QUANTITIES}
    print(f"{args.episodes} episodes of {args.objects} from seed {args.first_seed}, squeeze script, close gain "
          f"{args.close_gain}")
    for q in QUANTITIES:
        means = {name: float(np.mean(values[q])) for name, values in per_hand.items()}
        errors = {name: float(np.std(values[q]) / np.sqrt(len(values[q]))) for name, values in per_hand.items()}
        # paired differences (the same episodes): their standard error
        paired = {name: float(np.std(per_hand[name][q] - per_hand["real"][q]) / np.sqrt(args.episodes))
                  for name in ("nominal", "calibrated")}
        x, loss = abs(means["nominal"] - means["real"]), abs(means["calibrated"] - means["real"])
        print(f"{q:8s} " + "  ".join(f"{name} {means[name]:.4g} ± {errors[name]:.2g}" for name in hands)
              + f";  X {x:.3g} (± {paired['nominal']:.2g}), calibrated {loss:.3g} (± {paired['calibrated']:.2g}), "
              f"ratio {loss / x if x else float('nan'):.2f}")


if __name__ == "__main__":
    main()
