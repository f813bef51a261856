"""The worm windows reach PyBullet only when they can act (`HandPlant._send_windows`), with the same
physics to the bit as sending every change (docs/modelling.md: the worms as joint limits)."""
from __future__ import annotations

import types

import gymnasium as gym
import numpy as np
import pybullet as p

import bh8_gym  # noqa: F401  (registers the environments)
from bh8_gym.plant import WORM_JOINTS, HandPlant


def send_every_change(plant) -> None:
    """The reference: each window sent as soon as it changes (what the plant did before)."""
    state, sent_low, sent_high = plant._state, plant._sent_low, plant._sent_high
    for joint in WORM_JOINTS:
        lower, upper = state.window_low[joint], state.window_high[joint]
        if lower != sent_low[joint] or upper != sent_high[joint]:
            p.changeDynamics(plant.hand_id, plant.joint_indices[joint], jointLowerLimit=lower, jointUpperLimit=upper,
                             physicsClientId=plant.client)
            sent_low[joint], sent_high[joint] = lower, upper


def grasp_run(monkeypatch, reference: bool, steps: int) -> tuple[list[bytes], int]:
    """Each step's feedback block and plant state as bytes, and how many joint windows were sent:
    random LOOP bytes from seed 5: they open fingers against held-back partners, which inverts windows
    (a send of the last valid one skipped earlier shows by step 180)."""
    env = gym.make("BH8Grasp-v0")
    plant = env.unwrapped.plant
    if reference:
        plant._send_windows = types.MethodType(send_every_change, plant)
    sent = []
    change_dynamics = p.changeDynamics

    def counted(*args, **kwargs):
        sent.extend(["window"] if "jointLowerLimit" in kwargs else [])
        return change_dynamics(*args, **kwargs)

    monkeypatch.setattr(p, "changeDynamics", counted)
    rng = np.random.default_rng(5)
    env.reset(seed=5)
    trace = []
    for _ in range(steps):
        action = rng.integers(env.action_space.low, env.action_space.high, endpoint=True)
        _, _, terminated, truncated, info = env.step(action)
        state = plant._state
        trace.append(info["feedback_block"] + np.array(
            state.positions + state.velocities + state.torques + state.outer_loads).tobytes())
        if terminated or truncated:
            env.reset()
    monkeypatch.undo()
    env.close()
    return trace, len(sent)


def test_windows_sent_when_they_can_act_give_the_same_physics(monkeypatch):
    lazy, lazy_sent = grasp_run(monkeypatch, reference=False, steps=250)
    every, every_sent = grasp_run(monkeypatch, reference=True, steps=250)
    assert lazy == every
    assert lazy_sent < every_sent / 2  # closing fingers move their windows every step


def test_pybullet_ignores_an_inverted_window():
    """`_send_windows` relies on it: the last window that was not inverted stays in force."""
    with HandPlant(seed=0) as plant:
        hand, joint, client = plant.hand_id, plant.joint_indices[WORM_JOINTS[0]], plant.client
        p.setJointMotorControl2(hand, joint, p.VELOCITY_CONTROL, force=0.0, physicsClientId=client)
        p.changeDynamics(hand, joint, jointLowerLimit=0.0, jointUpperLimit=0.2, physicsClientId=client)
        p.changeDynamics(hand, joint, jointLowerLimit=0.5, jointUpperLimit=0.4, physicsClientId=client)
        p.resetJointState(hand, joint, 0.3, 0.0, physicsClientId=client)
        p.stepSimulation(physicsClientId=client)
        # Above the window (0, 0.2): pushed back down (no limit would leave it; (0.5, 0.4), pushed up).
        assert p.getJointState(hand, joint, physicsClientId=client)[1] < -1.0
