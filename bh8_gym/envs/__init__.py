"""Gymnasium environments; `register_envs` runs on `import bh8_gym`.

- ``BH8Grasp-v0`` (`grasp.BH8GraspEnv`): grasp an object on a table, then the arm lifts it.
- ``BH8FingerReach-v0`` (`finger_reach.BH8FingerReachEnv`): drive each motor to a target.

Both step one RealTime (LOOP) cycle of the emulated firmware per `step` (base.py). Actions are the
LOOP control bytes (an int16 Box); `wrappers.ContinuousActions` maps [-1, 1] floats onto them for
Gaussian policies. The heavy modules (PyBullet, the firmware) load only when an env is made.
"""
from __future__ import annotations

from gymnasium.envs.registration import register, registry

# Safety nets: the environments end episodes themselves on their simulated clock (grasp: the arm
# schedule, 2.0 s; reach: episode_seconds, 1.0 s), which at 38400 baud is 309 and 215 steps.
# These limits only bind if a user makes episodes longer than their defaults allow.
GRASP_MAX_EPISODE_STEPS = 1000
REACH_MAX_EPISODE_STEPS = 1000

ENV_IDS = ("BH8Grasp-v0", "BH8FingerReach-v0")


def register_envs() -> None:
    """Register the bh8-gym environments with Gymnasium (idempotent)."""
    if "BH8Grasp-v0" not in registry:
        register(
            id="BH8Grasp-v0",
            entry_point="bh8_gym.envs.grasp:BH8GraspEnv",
            max_episode_steps=GRASP_MAX_EPISODE_STEPS,
            kwargs={"object_set": "primitives", "baud": 38400},
        )
    if "BH8FingerReach-v0" not in registry:
        register(
            id="BH8FingerReach-v0",
            entry_point="bh8_gym.envs.finger_reach:BH8FingerReachEnv",
            max_episode_steps=REACH_MAX_EPISODE_STEPS,
            kwargs={"baud": 38400},
        )
