"""The arm's table-contact grasp (envs/scenes.py, envs/arm.py `ArmSchedule.press_rise`): an object lower
than `PlacementRanges.table_contact_below` at rest is approached with the open fingertips just over the
table, and through the grasp the arm is compliant in z, holding `press_force` down on what the hand
touches; a taller object keeps the rigid approach whose fingers' sweep clears the table.
"""
from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from bh8_gym.agents.grasps import make_script
from bh8_gym.agents.env_factory import make_env
from bh8_gym.envs.arm import ArmSchedule
from bh8_gym.envs.scenes import PlacementRanges
from bh8_gym.hand_urdf import FINGER_SWEEP_DEPTH, KNUCKLE_HEIGHT
from bh8_gym.objects import ObjectSpec

LOW_BOX = ObjectSpec("box", (0.06, 0.04, 0.015), mass=0.1)
TALL_BOX = ObjectSpec("box", (0.06, 0.04, 0.06), mass=0.1)
ON = {"table_contact_below": 0.03}  # the measured setting (docs/envs.md); the default, 0, is off


def test_the_table_contact_grasp_is_off_by_default():
    """Off unless asked for: the default env approaches a low object as before, rigidly, its
    fingers' sweep clear of the table."""
    assert PlacementRanges().table_contact_below == 0.0
    env = make_env("BH8Grasp-v0", {"object_files": [LOW_BOX], "randomize": False})
    try:
        env.reset(seed=0)
        scene = env.unwrapped.scene
        assert not scene.table_contact and scene.plant.step_hook is None
        assert scene.palm_height - scene.table_top >= FINGER_SWEEP_DEPTH
    finally:
        env.close()


def _grasp_phase(env, act, each=None) -> int:
    """Steps `env` with `act(obs, info)` until the arm's lift begins (or the episode ends); returns
    the steps taken."""
    obs, info = env.reset(seed=0)
    base = env.unwrapped
    steps = 0
    while base.arm.phase(info.get("time", 0.0))[0] == 0:
        obs, _, terminated, truncated, info = env.step(act(obs, info))
        steps += 1
        if each is not None:
            each()
        if terminated or truncated:  # a safety stop (a strain over the envelope's limit)
            break
    return steps


@pytest.mark.parametrize("kwargs, message", [({"press_force": -1.0}, "press_force"),
                                             ({"press_admittance": 0.0}, "press_admittance"),
                                             ({"press_speed": 5.0}, "press_speed")])
def test_bad_press_settings_are_a_clear_error(kwargs, message):
    with pytest.raises(ValueError, match=message):
        ArmSchedule(**kwargs)
    with pytest.raises(ValueError, match="must be >= 0"):
        PlacementRanges(table_contact_below=-0.01)


def test_the_press_rises_with_the_force_at_a_bounded_speed_and_never_below_its_floor():
    arm = ArmSchedule(press_force=5.0, press_admittance=0.02, press_speed=0.25)
    assert arm.press_rise(0.0, 5.0, 0.002, -0.01) == 0.0  # holding press_force: stays
    assert arm.press_rise(0.0, 10.0, 0.002, -0.01) == pytest.approx(0.1 * 0.002)  # 5 N over: 0.1 m/s up
    assert arm.press_rise(0.0, 1000.0, 0.002, -0.01) == pytest.approx(0.25 * 0.002)  # capped at press_speed
    assert arm.press_rise(0.0, 0.0, 0.002, -0.01) == pytest.approx(-0.1 * 0.002)  # nothing touched: comes down
    assert arm.press_rise(-0.0099, 0.0, 0.002, -0.01) == -0.01  # never below the floor


def test_a_low_object_gets_the_table_contact_grasp_and_the_fingertips_lift_the_hand():
    """The palm starts under the rigid approach's floor (the open hand just over the table); LOOP closes
    at full speed; the fingertips pressed on the table lift the hand instead of stalling on it
    (with the arm rigid at that height they stop before 4,000 counts, tests/test_table_contact.py), no
    clutch breaks away before the fingers pass the bottom of their sweep, and the hand presses down with
    about press_force on average."""
    env = make_env("BH8Grasp-v0", {"object_files": [LOW_BOX], "randomize": False, "placement": ON})
    base = env.unwrapped
    scene, plant = base.scene, base.plant
    try:
        script = make_script("loop-g80", env)  # gain 255 on a box this low passes the strain limit
        forces, rises = [], []

        def watch():
            rises.append(scene.press_rise)
            forces.append(plant.contact_lift())

        env.reset(seed=0)
        assert scene.table_contact
        palm_above_table = scene.palm_height - scene.table_top
        assert palm_above_table < 0.06  # far under the rigid approach's floor (FINGER_SWEEP_DEPTH, 10 cm)
        assert palm_above_table >= LOW_BOX.size[2] + KNUCKLE_HEIGHT  # the knuckles clear of the box
        _grasp_phase(env, lambda obs, info: script.act(obs, info), watch)
        assert max(rises) > 0.02 and min(rises) >= scene._lowest_rise
        fingers = plant.motor_positions()[:3]
        assert np.all(fingers > 6000.0), fingers  # past the bottom of their sweep (about 6,000 counts)
        assert np.mean(forces) < base.arm.press_force + 15.0
        # The lift starts from where the press left the hand, the arm rigid again.
        wrist_z = plant.wrist_pose()[0][2]
        assert wrist_z == pytest.approx(scene.wrist_start[2] + scene.press_rise, abs=2e-3)
        env.step(script.act(None, None))
        assert plant.step_hook is None
    finally:
        env.close()


def test_the_arm_comes_down_until_the_hand_touches_the_table_and_holds_its_press_force():
    """A guarded move: with the fingers not driven, the arm lowers the open hand the start margin onto
    the table and stops there, pressing press_force (averaged over the last 0.2 s)."""
    env = gym.make("BH8Grasp-v0", object_files=[LOW_BOX], randomize=False, placement=ON)
    base = env.unwrapped
    scene, plant = base.scene, base.plant
    try:
        forces, rises = [], []

        def watch():
            forces.append(plant.contact_lift())
            rises.append(scene.press_rise)

        _grasp_phase(env, lambda obs, info: np.zeros(env.action_space.shape, dtype=env.action_space.dtype), watch)
        # Down by the margin (the AABB the start height is read from is a little larger than the
        # links, and the unpowered fingers give a little), then still on the table.
        margin = base.placement.table_contact_margin
        assert -margin - 0.004 < rises[-1] < -margin
        assert np.ptp(rises[-30:]) < 1e-3  # resting: it chatters by a few tenths of a millimetre
        assert np.mean(forces[-30:]) == pytest.approx(base.arm.press_force, abs=2.0)
    finally:
        env.close()


def test_a_tall_object_keeps_the_rigid_approach():
    """A 6 cm box: the palm stops with the knuckles over its top and the fingers' sweep clear of the
    table, and the arm holds the wrist still through the grasp."""
    env = make_env("BH8Grasp-v0", {"object_files": [TALL_BOX], "randomize": False, "placement": ON})
    base = env.unwrapped
    scene, plant = base.scene, base.plant
    try:
        script = make_script("loop", env)
        env.reset(seed=0)
        assert not scene.table_contact
        start = plant.wrist_pose()[0][2]
        heights = []
        _grasp_phase(env, lambda obs, info: script.act(obs, info),
                     lambda: heights.append(plant.wrist_pose()[0][2]))
        assert scene.palm_height - scene.table_top >= FINGER_SWEEP_DEPTH
        assert plant.step_hook is None and scene.press_rise == 0.0
        assert np.max(np.abs(np.array(heights) - start)) < 5e-4
    finally:
        env.close()


def test_an_episode_cut_short_in_the_press_leaves_no_trace_in_the_next():
    """Determinism (docs/envs.md's contract): a safety stop during the press ends the episode with the
    arm's press still set; the next reset starts the arm afresh, so a seed's trajectory is the same
    after it as in a new env."""
    def first_steps(env, steps=40):
        script = make_script("loop", env)
        obs, info = env.reset(seed=0)
        heights = []
        for _ in range(steps):
            obs, *_, info = env.step(script.act(obs, info))
            heights.append(env.unwrapped.plant.wrist_pose()[0][2])
        return heights

    fresh = make_env("BH8Grasp-v0", {"object_files": [LOW_BOX], "randomize": False, "placement": ON})
    used = make_env("BH8Grasp-v0", {"object_files": [LOW_BOX], "randomize": False, "placement": ON})
    try:
        script = make_script("loop", used)  # full gain on a box this low: a safety stop in the grasp
        obs, info = used.reset(seed=0)
        terminated = False
        while not terminated:
            obs, _, terminated, _, info = used.step(script.act(obs, info))
        assert "safety_stop" in info and used.unwrapped.plant.step_hook is not None
        assert first_steps(used) == first_steps(fresh)
    finally:
        fresh.close()
        used.close()
