"""Snapshot and branch: what one restore costs against PyBullet's own restoreState, part by part.

    python benchmarks/bench_snapshot.py [--repeats 5] [--restores 2000]

Restores a BH8Grasp-v0 episode's snapshot (taken with the fingers on the object, 50 cycles in) over
and over, each figure the best of `--repeats` rounds (the machine's other work only adds time), and
prints µs per restore for: the env's whole restore (`BH8LoopEnv.restore`), the firmware's (with the
plant's), the plant's (PyBullet's restoreState, the contact pairs renewed, the plant's own state),
the contact-pair renewal alone and PyBullet's restoreState alone, each also as a multiple of it.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import pybullet

import bh8_gym  # noqa: F401
import gymnasium as gym


def best_microseconds(call, restores: int, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(restores):
            call()
        best = min(best, (time.perf_counter() - start) / restores * 1e6)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--restores", type=int, default=2000)
    args = parser.parse_args()
    env = gym.make("BH8Grasp-v0", randomize=True, history=True).unwrapped
    env.reset(seed=3)
    close = np.array([100, 255, 100, 255, 100, 255, 0, 255], dtype=np.int16)
    for _ in range(50):
        env.step(close)
    snapshot = env.snapshot()
    plant, state = env.plant, snapshot.firmware.plant_state
    parts = {
        "env restore (BH8LoopEnv.restore)": lambda: env.restore(snapshot),
        "firmware + plant (Firmware.restore)": lambda: env.firmware.restore(snapshot.firmware),
        "plant (HandPlant.restore_state)": lambda: plant.restore_state(state),
        "contact pairs renewed": plant._renew_contact_pairs,
        "PyBullet restoreState": lambda: pybullet.restoreState(stateId=state, physicsClientId=plant.client),
    }
    figures = {name: best_microseconds(call, args.restores, args.repeats) for name, call in parts.items()}
    reference = figures["PyBullet restoreState"]
    print("| part | µs per restore | × restoreState |\n|---|---:|---:|")
    for name, value in figures.items():
        print(f"| {name} | {value:.1f} | {value / reference:.1f} |")
    env.release(snapshot)
    env.close()


if __name__ == "__main__":
    main()
