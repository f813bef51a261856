"""A SHA-256 of whole episodes: every observation, reward and feedback block, and the plant's joint
states and temperature, for BH8Grasp-v0 (randomised and not) and BH8FingerReach-v0.

Two runs of the same code on the same CPU print the same digest; a change that should not alter
behaviour (a refactoring) must not change it. Floating-point paths differ between CPUs, so compare
digests on one machine only.

Run: python benchmarks/trajectory_digest.py [--episodes 2]
"""
from __future__ import annotations

import argparse
import hashlib

import gymnasium as gym
import numpy as np

import bh8_gym  # noqa: F401  (registers the environments)


def digest(episodes: int) -> str:
    sha = hashlib.sha256()
    for env_id, kwargs in (("BH8Grasp-v0", {}), ("BH8Grasp-v0", {"randomize": False}), ("BH8FingerReach-v0", {})):
        env = gym.make(env_id, **kwargs)
        rng = np.random.default_rng(7)
        for episode in range(episodes):
            obs, info = env.reset(seed=100 + episode)
            sha.update(obs.tobytes() + info["feedback_block"])
            done = False
            while not done:
                action = rng.integers(env.action_space.low, env.action_space.high, endpoint=True)
                obs, reward, terminated, truncated, info = env.step(action)
                done = terminated or truncated
                state = env.unwrapped.plant._state
                sha.update(obs.tobytes() + np.float64(reward).tobytes() + info["feedback_block"])
                sha.update(np.array(state.positions + state.velocities + state.torques + (state.temperature,)).tobytes())
        env.close()
    return sha.hexdigest()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=2, help="episodes per env (default: %(default)s)")
    print(digest(parser.parse_args().episodes))


if __name__ == "__main__":
    main()
