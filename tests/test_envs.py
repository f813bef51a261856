"""The Gymnasium environments (bh8_gym.envs): contract checks, byte-level determinism, timing, spaces.

One env step is one RealTime cycle through the emulated firmware (manual §6; SPEC.md §5 block
layout, §6 time per cycle), so several tests check the raw blocks in `info`.
"""
from __future__ import annotations

import pickle
import shutil
import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pybullet
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import bh8_gym  # noqa: F401  (registers the environments)
from bh8_gym.envs import ENV_IDS
from bh8_gym.envs.randomization import RandomizationRanges, sample_plant_parameters
from bh8_gym.action_bytes import bytes_to_unit, unit_to_bytes
from bh8_gym.envs.wrappers import ContinuousActions
from bh8_gym.firmware import REALTIME_PROCESSING_S
from bh8_gym.plant import PlantParameters
from bh8_gym.realtime_codec import MotorFlags


@pytest.fixture(scope="module")
def grasp():
    env = gym.make("BH8Grasp-v0").unwrapped
    yield env
    env.close()


@pytest.fixture(scope="module")
def reach():
    env = gym.make("BH8FingerReach-v0").unwrapped
    yield env
    env.close()


def run_bytes(env, seed, actions):
    """Feedback blocks of an episode start with `seed` under a fixed action sequence."""
    _, info = env.reset(seed=seed)
    blocks = [info["feedback_block"]]
    for action in actions:
        _, _, terminated, truncated, info = env.step(action)
        blocks.append(info["feedback_block"])
        if terminated or truncated:
            break
    return blocks


def test_both_envs_are_registered():
    from gymnasium.envs.registration import registry

    for env_id in ENV_IDS:
        assert env_id in registry


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_gymnasium_and_sb3_env_checkers_pass(env_id):
    from gymnasium.utils.env_checker import check_env as gym_check
    from stable_baselines3.common.env_checker import check_env as sb3_check

    env = gym.make(env_id).unwrapped
    try:
        gym_check(env, skip_render_check=True)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # SB3 only recommends a symmetric float Box
            sb3_check(env, warn=True)
        wrapped = ContinuousActions(env)
        sb3_check(wrapped, warn=True)
    finally:
        env.close()


def test_setup_script_configures_the_firmware_as_the_layout_says(grasp):
    """The setup script (HI, FSET of the LOOP flags, PSET LFT/LFDPD/BAUD, LOOP) runs without ERR on a
    fresh firmware and leaves it in LOOP with the env's layout (§6.2, SPEC.md §5)."""
    from bh8_gym.firmware import Firmware

    firmware = Firmware(seed=0)
    try:
        for line in (*grasp.setup_commands, grasp.baud_command):
            reply = firmware.transact(line.encode() + b"\r")
            assert b"ERR" not in reply and reply.endswith(b"=> "), (line, reply)
        assert firmware.transact(grasp.loop_command.encode() + b"\r").endswith(b"*")
        assert firmware.in_loop and firmware.loop_layout == grasp.layout
        assert firmware.baud == 38400
    finally:
        firmware.shutdown()
    assert grasp.setup_commands[0] == "HI" and grasp.loop_command == "1234LOOP"
    assert [name for _, name in grasp.layout.control_fields] == ["LCV", "LCPG"] * 4
    # The spread has no strain gauge (§5.3.2: its LFS reads 255): the env asks for the fingers' only.
    assert grasp.layout.feedback_fields == ((1, "LFS"), (1, "LFAP"), (2, "LFS"), (2, "LFAP"),
                                            (3, "LFS"), (3, "LFAP"), (4, "LFAP"))
    assert "4FSET LFS 0" in grasp.setup_commands
    assert "LFS4" not in grasp.observation_fields


def test_the_spread_strain_byte_is_left_out_only_when_the_spread_loops():
    """LFS is requested for every finger in the LOOP; a LOOP without the spread needs no extra line."""
    env = gym.make("BH8Grasp-v0", motors=(1, 2, 3), randomize=False).unwrapped
    try:
        assert [m for m, name in env.layout.feedback_fields if name == "LFS"] == [1, 2, 3]
        assert not any(line.startswith("4FSET") for line in env.setup_commands)
    finally:
        env.close()


@pytest.mark.parametrize("baud", [38400, 9600])
def test_a_step_costs_the_spec_cycle_time(baud):
    """SPEC.md §6: (control + feedback bytes) × 10 / BAUD + processing per RealTime cycle."""
    env = gym.make("BH8Grasp-v0", baud=baud, randomize=False).unwrapped
    try:
        env.reset(seed=0)
        t0 = env.firmware.time
        _, _, _, _, info = env.step(np.zeros(8, dtype=np.int16))
        expected = (len(info["control_block"]) + len(info["feedback_block"])) * 10 / baud + REALTIME_PROCESSING_S
        assert len(info["control_block"]) == 9 and len(info["feedback_block"]) == 12
        assert env.firmware.time - t0 == pytest.approx(expected, abs=1e-9)
        assert env.cycle_seconds == pytest.approx(expected)
    finally:
        env.close()


def test_grasp_episode_runs_the_arm_schedule_and_ends_on_time(grasp):
    """The episode lasts the arm schedule (2.0 s: 309 steps at 38400 baud); the wrist rises 10 cm.
    Its end is terminal, not a truncation: the schedule is the task and the clock is observed."""
    obs, _ = grasp.reset(seed=3)
    start = grasp.plant.wrist_pose()[0].copy()
    phase_index = grasp.observation_fields.index("phase_grasp")
    assert obs[phase_index] == 1.0
    steps, done, phases = 0, False, set()
    while not done:
        obs, reward, terminated, truncated, info = grasp.step(np.zeros(8, dtype=np.int16))
        phases.add(int(np.argmax(obs[phase_index:phase_index + 3])))
        assert set(info["reward_terms"]) == {"reach", "contact", "lift", "success"}
        assert reward == pytest.approx(sum(info["reward_terms"].values()))
        steps += 1
        done = terminated or truncated
    # Ends at the first step whose feedback arrives at or after 2.0 s on the host's clock.
    assert terminated and not truncated and 2.0 <= info["time"] < 2.0 + grasp.cycle_seconds
    assert steps == int(np.ceil((2.0 - (info["time"] - steps * grasp.cycle_seconds)) / grasp.cycle_seconds - 1e-9))
    # 309 steps on the nominal 1 ms processing time, 287-324 over its randomised 0.7-1.5 ms.
    assert grasp.nominal_episode_steps() == 309 and 287 <= steps <= 324
    assert phases == {0, 1, 2}
    assert grasp.plant.wrist_pose()[0][2] - start[2] == pytest.approx(0.10, abs=0.005)
    assert info["is_success"] is False  # fingers never moved: nothing was lifted


def test_identical_seeds_give_identical_feedback_bytes():
    """Same seed and actions: byte-identical feedback blocks, across two env instances and after
    reusing one env (snapshot restore); another seed differs (randomised plant and object)."""
    rng = np.random.default_rng(0)
    env_a = gym.make("BH8Grasp-v0").unwrapped
    env_b = gym.make("BH8Grasp-v0").unwrapped
    try:
        actions = [np.array(rng.integers(env_a.action_space.low, env_a.action_space.high + 1), dtype=np.int16)
                   for _ in range(60)]
        first = run_bytes(env_a, 11, actions)
        run_bytes(env_a, 5, actions)  # something else in between
        again = run_bytes(env_a, 11, actions)
        other_env = run_bytes(env_b, 11, actions)
        different = run_bytes(env_b, 12, actions)
        assert first == again == other_env
        assert first != different
    finally:
        env_a.close()
        env_b.close()


def test_a_seed_replays_exactly_whatever_the_env_ran_before():
    """Issue 5 contract 7 (identical trajectories for identical seeds) over whole contact-rich
    episodes: the scripted LOOP grasp on a held-out object gives the same observations in a fresh
    env and in one that grasped another object first. restoreState kept the last episode's contact
    manifolds, and their order changed the solver's; the trajectories parted after ~250 steps."""
    from bh8_gym.agents.grasps import LoopBaseline
    from bh8_gym.agents.env_factory import make_env  # the env as `bh8 eval` wraps it

    def episode(env, seed):
        policy = LoopBaseline(env)
        obs, info = env.reset(seed=seed)
        policy.reset(env)
        observations = [obs]
        while True:
            obs, _, terminated, truncated, info = env.step(policy.act(obs, info))
            observations.append(obs)
            if terminated or truncated:
                return np.array(observations)

    fresh = make_env("BH8Grasp-v0", {"object_set": "test", "randomize": False})
    used = make_env("BH8Grasp-v0", {"object_set": "test", "randomize": False})
    try:
        reference = episode(fresh, 100019)
        episode(used, 100015)
        assert np.array_equal(episode(used, 100019), reference)
    finally:
        fresh.close()
        used.close()


def test_observation_builder_reproduces_the_env_observation(grasp):
    """What deploy computes from a raw feedback block equals the env's observation."""
    obs, info = grasp.reset(seed=1)
    values = grasp.layout.decode_feedback(info["feedback_block"])
    assert np.array_equal(grasp.observation_from_feedback(values, np.zeros(8), grasp.elapsed()), obs)
    action = np.array([50, 200, -20, 10, 100, 255, -100, 0], dtype=np.int16)
    obs, _, _, _, info = grasp.step(action)
    values = grasp.layout.decode_feedback(info["feedback_block"])
    built = grasp.observation_from_feedback(values, action, grasp.elapsed())
    assert np.array_equal(built, obs)
    prev = grasp.observation_fields.index("prev_LCV1")
    assert obs[prev] == pytest.approx(0.5)  # LCV 50 of the envelope's ±100
    lfap1 = grasp.observation_fields.index("LFAP1")
    assert obs[lfap1] == pytest.approx(values[1] / 17500)


@pytest.mark.parametrize(
    "action, message",
    [
        (np.zeros(7, dtype=np.int16), "shape"),
        (np.array([128, 0, 0, 0, 0, 0, 0, 0]), "out of range"),
        (np.array([101, 0, 0, 0, 0, 0, 0, 0]), "out of range"),  # the safety envelope's |LCV| <= 100
        (np.array([0, -1, 0, 0, 0, 0, 0, 0]), "out of range"),
        (np.array([0, 256, 0, 0, 0, 0, 0, 0]), "out of range"),
        (np.array([0.5, 0, 0, 0, 0, 0, 0, 0]), "whole numbers"),
        (np.array([np.nan, 0, 0, 0, 0, 0, 0, 0]), "integers"),
    ],
)
def test_invalid_actions_raise_naming_the_value(grasp, action, message):
    grasp.reset(seed=0)
    with pytest.raises(ValueError, match=message):
        grasp.step(action)


def test_continuous_actions_map_onto_the_loop_bytes(reach):
    """[-1, 1] → LCV -128..127 linearly, clipped; NaN raises. In an env, +1 is the safety
    envelope's largest LCV (100, bh8_gym.safety)."""
    low, high = np.array([-128.0, 0.0]), np.array([127.0, 255.0])
    assert unit_to_bytes(np.array([-1.0, -1.0]), low, high).tolist() == [-128, 0]
    assert unit_to_bytes(np.array([1.0, 1.0]), low, high).tolist() == [127, 255]
    assert unit_to_bytes(np.array([5.0, -3.0]), low, high).tolist() == [127, 0]
    assert unit_to_bytes(np.array([0.0, 0.0]), low, high).tolist() == [0, 128]
    values = np.arange(-128, 128)
    back = unit_to_bytes(bytes_to_unit(values, low[:1], high[:1]).astype(np.float64), low[:1], high[:1])
    assert np.array_equal(back, values)
    env = ContinuousActions(reach)
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.ones(4, dtype=np.float32))
    assert info["control_block"] == b"C" + bytes([100] * 4)
    with pytest.raises(ValueError, match="finite"):
        env.step(np.array([np.nan, 0, 0, 0], dtype=np.float32))


def test_human_rendering_without_a_display_is_a_clear_error(monkeypatch):
    """render_mode="human" on a headless machine raises instead of letting PyBullet's GUI end the
    process; so does gymnasium's check_env with its render check (it makes a "human" env)."""
    from gymnasium.utils.env_checker import check_env

    from bh8_gym.plant import DisplayUnavailableError

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    with pytest.raises(DisplayUnavailableError, match="DISPLAY"):
        gym.make("BH8FingerReach-v0", render_mode="human")
    env = gym.make("BH8FingerReach-v0").unwrapped
    try:
        with pytest.raises(DisplayUnavailableError):
            check_env(env)
    finally:
        env.close()


@pytest.mark.skipif(shutil.which("xvfb-run") is None, reason="needs xvfb-run (Debian package xvfb)")
def test_gymnasium_env_checker_with_its_render_check_passes_on_a_display():
    """With a display, check_env's defaults pass too: they make and render a "human" env (PyBullet's GUI)."""
    script = ("import gymnasium as gym, bh8_gym\n"
              "from gymnasium.utils.env_checker import check_env\n"
              "for env_id in bh8_gym.envs.ENV_IDS:\n"
              "    env = gym.make(env_id).unwrapped\n"
              "    check_env(env)\n"
              "    env.close()\n"
              "print('checked')\n")
    process = subprocess.run(["xvfb-run", "-a", sys.executable, "-c", script], capture_output=True, text=True,
                             timeout=240)
    assert process.returncode == 0 and process.stdout.strip().endswith("checked"), process.stderr[-2000:]


class _ByteActionEnv(gym.Env):
    """Only an action space: LCV and LCPG bytes for four motors, as the grasp env's default layout."""

    action_space = gym.spaces.Box(np.array([-128, 0] * 4), np.array([127, 255] * 4), dtype=np.int16)
    observation_space = gym.spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)


@given(arrays(np.float32, 8, elements=st.floats(-3.0, 3.0, width=32)))
def test_continuous_actions_wrapper_is_unit_to_bytes(unit):
    """The wrapper's per-step plain-float mapping gives exactly `unit_to_bytes`' bytes (which
    `bh8 deploy` applies too), halfway cases and clipping included."""
    wrapper = ContinuousActions(_ByteActionEnv())
    low, high = wrapper.env.action_space.low.astype(np.float64), wrapper.env.action_space.high.astype(np.float64)
    mapped = wrapper.action(unit)
    assert mapped.dtype == np.int16
    assert mapped.tolist() == unit_to_bytes(unit.astype(np.float64), low, high).tolist()
    reference = np.rint((low + high) / 2.0 + (high - low) / 2.0 * np.clip(unit.astype(np.float64), -1.0, 1.0))
    assert mapped.tolist() == reference.astype(np.int64).tolist()  # numpy's rint: halves to even


def test_reach_targets_success_terminates(reach):
    """Targets at the initialised position (HI ends at 0, SPEC.md §4): success and termination."""
    reach.reset(seed=0)
    reach.set_targets([0, 0, 0, 0])
    _, reward, terminated, truncated, info = reach.step(np.zeros(4, dtype=np.int16))
    assert info["is_success"] and terminated and not truncated
    assert info["reward_terms"]["success"] == 1.0
    reach.reset(seed=0)
    reach.set_targets([8000, 8000, 8000, 1500])
    _, reward, terminated, _, info = reach.step(np.zeros(4, dtype=np.int16))
    assert not terminated and reward < -0.3


def test_reach_closing_reduces_the_error(reach):
    """Positive LCV closes the fingers (SPEC.md §1: + closes), so the error to a closed target falls."""
    reach.reset(seed=0)
    reach.set_targets([6000, 6000, 6000, 1000])
    errors = []
    for _ in range(60):
        _, reward, terminated, _, info = reach.step(np.array([100, 100, 100, 40], dtype=np.int16))
        errors.append(-info["reward_terms"]["error"])
    assert errors[-1] < errors[0] - 0.1


def test_privileged_observations_only_on_request():
    env = gym.make("BH8Grasp-v0", privileged=True, randomize=False).unwrapped
    try:
        obs, info = env.reset(seed=0)
        assert "privileged" in info and "object_position" in info["privileged"]
        assert obs.shape[0] == env.observation_space.shape[0] == len(env.observation_fields)
        assert "object_dz" in env.observation_fields
        values = env.layout.decode_feedback(info["feedback_block"])
        host = env.observation_from_feedback(values, np.zeros(8), env.elapsed())
        assert np.array_equal(host, obs[: len(host)]) and len(host) < len(obs)
    finally:
        env.close()


def test_privileged_entries_read_each_cycles_world_once(monkeypatch):
    """The reward, the privileged observation and info["privileged"] share one contact query and one
    object pose per step (GraspTask.new_cycle), each of that step's world."""
    env = gym.make("BH8Grasp-v0", privileged=True, randomize=False).unwrapped
    queries = []
    contact_points = pybullet.getContactPoints
    monkeypatch.setattr(pybullet, "getContactPoints", lambda *a, **k: queries.append(a) or contact_points(*a, **k))
    try:
        env.reset(seed=3)
        close = np.array([80 if name == "LCV" else 200 for _, name in env.layout.control_fields], dtype=np.int16)
        touched = 0.0
        for _ in range(100):
            queries.clear()
            obs, _, _, _, info = env.step(close)
            assert len(queries) == 1
            body, plant = env.scene.object_body, env.plant
            position = np.array(pybullet.getBasePositionAndOrientation(body, physicsClientId=plant.client)[0])
            touching = {link for link in plant.contacts_by_link(body)}
            fingers = [float(any(plant.link_index(f"f{k}_{part}") in touching for part in ("inner", "outer", "tip")))
                       for k in (1, 2, 3)]
            entries = dict(zip(env.observation_fields, obs))
            assert [entries[f"object_d{axis}"] for axis in "xyz"] == list(
                (position - plant.wrist_pose()[0]).astype(np.float32))
            assert [entries[f"contact_f{k}"] for k in (1, 2, 3)] == fingers
            assert np.array_equal(info["privileged"]["object_position"], position)
            touched += sum(fingers)
        assert touched > 0  # the fingers reached the object
    finally:
        env.close()


def test_object_sets_and_user_files():
    import pybullet_data

    env = gym.make("BH8Grasp-v0", object_set="test", randomize=False).unwrapped
    try:
        for seed in range(3):
            env.reset(seed=seed)
            assert env.scene.episode.spec.name.endswith("0")
    finally:
        env.close()
    urdf = f"{pybullet_data.getDataPath()}/cube_small.urdf:1.2"
    env = gym.make("BH8Grasp-v0", object_files=[urdf], randomize=False).unwrapped
    try:
        env.reset(seed=0)
        assert env.scene.episode.spec.kind == "urdf"
        env.step(np.zeros(8, dtype=np.int16))
    finally:
        env.close()


def test_one_object_file_is_taken_whole():
    """object_files="part.urdf" is one file (it was iterated character by character)."""
    import pybullet_data

    env = gym.make("BH8Grasp-v0", object_files=f"{pybullet_data.getDataPath()}/cube_small.urdf:1.2", randomize=False)
    try:
        env.reset(seed=0)
        assert env.unwrapped.scene.episode.spec.name == "cube_small"
    finally:
        env.close()


def test_feedback_coefficients_are_applied_to_lfv_and_lfdp():
    """§6.2.2-§6.2.3: the host multiplies LFV by LFVC and LFDP by LFDPC; the observation is in
    counts whatever the coefficients (the same motion gives about the same entries)."""
    observed = {}
    for coefficient in (1, 4):
        env = gym.make("BH8Grasp-v0", lfv=True, lfdp=True, lfvc=coefficient, lfdpc=coefficient,
                       randomize=False).unwrapped
        try:
            env.reset(seed=0)
            for _ in range(20):
                obs, _, _, _, info = env.step(np.array([40, 255] * 4, dtype=np.int16))
            values = env.layout.decode_feedback(info["feedback_block"])
            fields = env.observation_fields
            for (motor, name), value in zip(env.layout.feedback_fields, values):
                if name == "LFDP":
                    assert obs[fields.index(f"LFDP{motor}")] == pytest.approx(value * coefficient / 128)
            observed[coefficient] = np.array([obs[fields.index(f"{name}1")] for name in ("LFV", "LFDP")])
        finally:
            env.close()
    assert observed[1][1] > 0.2  # F1 closes several counts per cycle
    # equal within one quantum of the coarser data: LFVC / 16 and LFDPC / 128
    assert abs(observed[4][0] - observed[1][0]) <= 4 / 16 and abs(observed[4][1] - observed[1][1]) <= 4 / 128


def test_a_closed_env_says_so():
    env = gym.make("BH8FingerReach-v0").unwrapped
    env.reset(seed=0)
    env.close()
    env.close()
    with pytest.raises(gym.error.ClosedEnvironmentError, match="closed"):
        env.reset(seed=0)
    with pytest.raises(gym.error.ClosedEnvironmentError, match="closed"):
        env.step(np.zeros(4, dtype=np.int16))
    with pytest.raises(gym.error.ClosedEnvironmentError, match="closed"):
        env.render()


def test_step_before_reset_is_a_reset_needed_error():
    """The unwrapped env (no OrderEnforcing) says what to do instead of failing in the reward."""
    env = gym.make("BH8Grasp-v0", render_mode="rgb_array").unwrapped
    try:
        with pytest.raises(gym.error.ResetNeeded, match="reset"):
            env.step(np.zeros(8, dtype=np.int16))
    finally:
        env.close()


def test_agents_make_a_time_limit_no_shorter_than_the_episode():
    """A longer arm schedule than the registry's 1000-step backstop allows would be cut short (the
    success bonus lost, the episode bootstrapped as truncated): what train, eval and deploy make
    lets it end on its own clock."""
    from bh8_gym.agents.env_factory import make_env

    env = make_env("BH8Grasp-v0", {"arm": {"hold_seconds": 5.0}, "randomize": False})
    try:
        longest = env.unwrapped.longest_episode_steps()
        assert longest == env.unwrapped.nominal_episode_steps() > 1000 == gym.spec("BH8Grasp-v0").max_episode_steps
        assert env.spec.max_episode_steps == longest + 1
        env.reset(seed=0)
        steps, terminated, truncated = 0, False, False
        while not (terminated or truncated):
            _, _, terminated, truncated, _ = env.step(np.zeros(8, dtype=np.float32))
            steps += 1
        assert terminated and not truncated and steps == longest
    finally:
        env.close()
    randomized = gym.make("BH8Grasp-v0").unwrapped
    assert randomized.longest_episode_steps() == 324  # 0.7 ms processing, the fastest drawn
    randomized.close()


def test_continuous_actions_wrapper_is_rebuilt_from_its_spec_and_passes_check_env():
    """Gymnasium's wrapper contract (RecordConstructorArgs): gym.make(wrapped.spec) rebuilds it."""
    from gymnasium.utils.env_checker import check_env

    env = ContinuousActions(gym.make("BH8FingerReach-v0"))
    rebuilt = gym.make(env.spec)
    try:
        assert isinstance(rebuilt, ContinuousActions)
        assert env.spec.additional_wrappers[-1].name == "ContinuousActions"
        check_env(env, skip_render_check=True)
    finally:
        env.close()
        rebuilt.close()


def test_randomisation_is_seeded_and_within_its_ranges():
    base = PlantParameters()
    ranges = RandomizationRanges()
    a = sample_plant_parameters(base, np.random.default_rng(3), ranges)
    assert a == sample_plant_parameters(base, np.random.default_rng(3), ranges)
    assert a != sample_plant_parameters(base, np.random.default_rng(4), ranges)
    assert 0.85 * base.motor_peak_torque <= a.motor_peak_torque <= 1.15 * base.motor_peak_torque
    assert all(100 <= v <= 140 for v in a.strain_offsets)
    assert 0.5 <= a.finger_friction <= 1.1
    with pytest.raises(ValueError, match="finger_friction"):
        RandomizationRanges(finger_friction=(1.0, 0.5))


def test_randomisation_reaches_the_physics(grasp):
    """A randomised reset changes the hand's PyBullet friction and the strain offsets."""
    import pybullet

    seen_friction, seen_offsets = set(), set()
    for seed in range(3):
        grasp.reset(seed=seed)
        info = pybullet.getDynamicsInfo(grasp.plant.hand_id, 2, physicsClientId=grasp.plant.client)
        seen_friction.add(round(info[1], 6))
        seen_offsets.add(grasp.plant.strain_offsets)
    assert len(seen_friction) == 3 and len(seen_offsets) == 3


def test_bad_configuration_raises():
    with pytest.raises(ValueError, match="baud"):
        gym.make("BH8Grasp-v0", baud=115200)
    with pytest.raises(ValueError, match="lcvc"):
        gym.make("BH8Grasp-v0", lcvc=0)
    with pytest.raises(ValueError, match="object_set"):
        gym.make("BH8Grasp-v0", object_set="nope")
    with pytest.raises(ValueError, match="no control data"):
        gym.make("BH8Grasp-v0", lcv=False, lcpg=False)


def test_plant_parameters_as_a_dict_of_fields():
    """`plant_parameters` takes PlantParameters or, as a TOML config or JSON gives it, a dict of its
    fields (lists for tuples); a field that does not exist or a value of the wrong kind is refused
    naming it, before any physics runs."""
    env = gym.make("BH8Grasp-v0", plant_parameters={"solver_iterations": 200, "strain_offsets": [110, 120, 130]},
                   randomize=False).unwrapped
    try:
        assert env.plant.params.solver_iterations == 200 and env.plant.params.strain_offsets == (110, 120, 130)
        env.reset(seed=0)
    finally:
        env.close()
    for bad, message in (({"solver_iteration": 5}, "no field 'solver_iteration'"), (5, "got 5"),
                         ({"solver_iterations": 0}, "solver_iterations must be at least 1, got 0"),
                         ({"solver_iterations": "many"}, "solver_iterations must be int, got 'many'"),
                         ({"finger_friction": float("nan")}, "finger_friction must be float, got nan"),
                         ({"table": 1}, "table must be bool, got 1"),
                         ({"wrist_position": [0.0, 0.0]}, r"wrist_position must be tuple\[float, float, float\]")):
        with pytest.raises(ValueError, match=message):
            gym.make("BH8Grasp-v0", plant_parameters=bad)


@pytest.mark.parametrize("env_id, keyword, fields, attribute", [
    ("BH8Grasp-v0", "randomization", {"motor_peak_torque": [0.9, 1.1]}, "randomization"),
    ("BH8Grasp-v0", "placement", {"yaw_error": 0.1}, "placement"),
    ("BH8Grasp-v0", "reward_weights", {"success": 5.0}, "weights"),
    ("BH8Grasp-v0", "arm", {"lift_seconds": 0.5}, "arm"),
    ("BH8FingerReach-v0", "targets", {"finger": [0, 5000]}, "ranges"),
    ("BH8FingerReach-v0", "tolerance", {"finger": 100}, "tolerance"),
])
def test_settings_dataclasses_as_dicts_of_fields(env_id, keyword, fields, attribute):
    """The env's settings dataclasses, like plant_parameters, take a dict of their fields (all a
    TOML config or --env-kwargs JSON can carry); they used to be accepted and then fail with an
    AttributeError at the first reset or step. Bad fields are refused at make, naming them."""
    env = gym.make(env_id, **{keyword: fields}).unwrapped
    try:
        settings = getattr(env, attribute)
        for name, value in fields.items():
            assert getattr(settings, name) == (tuple(value) if isinstance(value, list) else value)
        env.reset(seed=0)
        env.step(env.action_space.sample())
    finally:
        env.close()
    with pytest.raises(ValueError, match="no field 'nope'"):
        gym.make(env_id, **{keyword: {"nope": 1}})
    name = next(iter(fields))
    with pytest.raises(ValueError, match=f"{keyword}: {name} must be"):
        gym.make(env_id, **{keyword: {name: "text"}})


def test_an_env_writes_no_files():
    """The env's firmware keeps its store in memory: a vector-env worker killed without close() used
    to leave a temporary store directory behind."""
    import tempfile
    from pathlib import Path

    before = set(Path(tempfile.gettempdir()).iterdir())
    env = gym.make("BH8FingerReach-v0")
    try:
        env.reset(seed=0)
        assert env.unwrapped.firmware.store.directory is None
        assert set(Path(tempfile.gettempdir()).iterdir()) - before == set()
    finally:
        env.close()


def test_more_configuration_errors_at_make():
    """A bad render_size is refused at make (it failed only at render()); object_files=[] is an
    error (it fell back to the primitives); copying an env says what to do instead."""
    with pytest.raises(ValueError, match="render_size"):
        gym.make("BH8Grasp-v0", render_size=(0, 10))
    with pytest.raises(ValueError, match="object_files is empty"):
        gym.make("BH8Grasp-v0", object_files=[])
    env = gym.make("BH8FingerReach-v0")
    try:
        with pytest.raises(TypeError, match="factory"):
            pickle.dumps(env.unwrapped)
    finally:
        env.close()


@pytest.mark.parametrize("name", ["randomize", "privileged", "lcpg", "lfv", "lft", "shake"])
@pytest.mark.parametrize("value", ["false", 2, None])
def test_on_off_keywords_refuse_non_booleans(name, value):
    """A JSON or CLI string "false" is truthy: it must not silently switch randomisation (or a flag) on."""
    with pytest.raises(ValueError, match=f"{name} must be True or False, got {value!r}"):
        gym.make("BH8Grasp-v0", **{name: value})


def test_other_loop_flags_change_the_layout_and_spaces():
    env = gym.make("BH8Grasp-v0", motors=(1, 2, 3), lcpg=False, lfv=True, lfdp=True, lft=True,
                   randomize=False).unwrapped
    try:
        assert env.action_space.shape == (3,)
        assert env.layout.flags[1] == MotorFlags(LCV=True, LCPG=False, LFV=True, LFS=True, LFAP=True, LFDP=True)
        obs, info = env.reset(seed=0)
        assert len(info["feedback_block"]) == 1 + 3 * 5 + 2
        assert "LFT" in env.observation_fields
        temperature = obs[env.observation_fields.index("LFT")]
        assert 0.3 < temperature < 0.6  # tenths of °C / 1000: the hand idles at 40-50 °C (§2)
    finally:
        env.close()


def test_vector_envs_sb3_subproc_and_gymnasium_async():
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv

    vec = make_vec_env("BH8FingerReach-v0", n_envs=2, seed=0, vec_env_cls=SubprocVecEnv,
                       wrapper_class=ContinuousActions)
    try:
        obs = vec.reset()
        assert obs.shape == (2, vec.observation_space.shape[0])
        for _ in range(5):
            obs, rewards, dones, infos = vec.step(np.zeros((2, 4), dtype=np.float32))
        assert rewards.shape == (2,) and "feedback_block" in infos[0]
    finally:
        vec.close()
    async_env = gym.vector.AsyncVectorEnv([lambda: gym.make("BH8FingerReach-v0") for _ in range(2)])
    try:
        obs, _ = async_env.reset(seed=[0, 1])
        for _ in range(5):
            obs, rewards, terminated, truncated, infos = async_env.step(np.zeros((2, 4), dtype=np.int16))
        assert obs.shape[0] == 2 and not np.array_equal(obs[0], obs[1])
    finally:
        async_env.close()


def test_serve_scene_for_a_seed_matches_the_env_reset():
    """`bh8 serve --env ID --seed N` builds the same object, placement and plant parameters."""
    from bh8_gym.envs.scenes import scene_for_seed
    from bh8_gym.plant import HandPlant

    env = gym.make("BH8Grasp-v0").unwrapped
    plant = HandPlant()
    try:
        env.reset(seed=42)
        scene = scene_for_seed("BH8Grasp-v0", plant, 42)
        assert scene.episode == env.scene.episode
        assert plant.params == env.plant.params
        assert scene.table_top == pytest.approx(env.scene.table_top)
    finally:
        plant.close()
        env.close()


def test_rgb_array_rendering_and_episode_recording(tmp_path):
    """Headless frames of the configured size; record_episode writes an animation file."""
    from bh8_gym.envs.wrappers import record_episode

    env = gym.make("BH8Grasp-v0", render_mode="rgb_array", render_size=(96, 72), randomize=False)
    try:
        env.reset(seed=0)
        frame = env.render()
        assert frame.shape == (72, 96, 3) and frame.dtype == np.uint8 and frame.std() > 5
        result = record_episode(env, lambda obs: np.array([40, 150] * 3 + [0, 100], dtype=np.int16),
                                tmp_path / "episode.gif", seed=0, every=30)
        assert result["steps"] > 250 and (tmp_path / "episode.gif").stat().st_size > 1000
        # by default frames of at least 20 ms: the GIF plays in real time (one frame per 6.7 ms
        # step was stored as 0 cs, which players show at 100 ms: 15x slow)
        from PIL import Image, ImageSequence

        record_episode(env, lambda obs: np.zeros(8, dtype=np.int16), tmp_path / "real_time.gif", seed=0)
        with Image.open(tmp_path / "real_time.gif") as gif:
            durations = [frame.info["duration"] for frame in ImageSequence.Iterator(gif)]
        assert min(durations) >= 20 and sum(durations) / 1000 == pytest.approx(env.unwrapped.arm.total_seconds, rel=0.05)
        assert env.metadata["render_fps"] == round(1 / env.unwrapped.cycle_seconds)
    finally:
        env.close()


def test_a_squeeze_past_the_safety_envelope_ends_the_episode_as_deploy_would():
    """bh8_gym.safety: the env trains inside deploy's envelope. A full squeeze (LCV 100, LCPG 255)
    on this seed's object drives a finger's strain past 230: that step ends the episode
    (terminated, no success, the "safety" penalty, info["safety_stop"] naming the reading, which
    is the message deploy stops a hand with); with the limit raised to 255 the same squeeze runs
    on. LCV past the envelope is out of the action space."""
    from bh8_gym.safety import SafetyEnvelope

    squeeze = np.array([100, 255, 100, 255, 100, 255, 0, 255], dtype=np.int16)

    def run(**kwargs):
        env = gym.make("BH8Grasp-v0", object_set="primitives-train", randomize=False, **kwargs).unwrapped
        try:
            env.reset(seed=0)
            steps = 0
            while True:
                _, reward, terminated, truncated, info = env.step(squeeze)
                steps += 1
                if terminated or truncated:
                    return steps, reward, terminated, info
        finally:
            env.close()

    steps, reward, terminated, info = run()
    assert terminated and steps < 300 and not info["is_success"]
    assert info["safety_stop"].startswith("motor ") and info["safety_stop"].endswith("above the limit 230")
    assert info["reward_terms"]["safety"] == -5.0 and info["reward_terms"]["success"] == 0.0
    assert reward == pytest.approx(sum(info["reward_terms"].values()))
    assert SafetyEnvelope().strain_violation([(2, 231)]) == "motor 2 strain 231 above the limit 230"
    steps, _, _, info = run(safety={"max_strain": 255})
    assert steps == 309 and "safety_stop" not in info
    env = gym.make("BH8Grasp-v0", safety={"max_velocity": 60}).unwrapped
    try:
        assert env.action_space.low[0] == -60 and env.action_space.high[0] == 60
    finally:
        env.close()


@pytest.mark.parametrize("fields, message", [({"max_strain": 256}, "max_strain"), ({"max_velocity": -1}, "max_velocity"),
                                             ({"max_velocity": 1.5}, "max_velocity"),
                                             ({"max_temperature": float("nan")}, "max_temperature"),
                                             ({"max_speed": 3}, "max_speed")])
def test_a_bad_safety_envelope_is_a_clear_error(fields, message):
    with pytest.raises(ValueError, match=message):
        gym.make("BH8Grasp-v0", safety=fields)


def test_the_arm_places_the_hand_as_a_top_down_pick_pipeline():
    """envs.scenes.PlacementRanges: the palm is centred on the object's footprint (within the
    position error), the fingers close across its narrowest width (a box's shorter side along the
    hand's y axis, F3 opposite F1-F2), the knuckles stop `clearance` above the estimated top
    (within top_error), and never lower than the fingers' sweep plus the margin
    (hand_urdf.FINGER_SWEEP_DEPTH): fingertips clear the table. An object lower than
    `table_contact_below` gets the table-contact grasp instead (tests/test_arm_press.py): the palm
    lower, never the knuckles into the object."""
    from bh8_gym.envs.objects import ObjectSet
    from bh8_gym.objects import ObjectSpec
    from bh8_gym.envs.scenes import GraspEpisode, PlacementRanges
    from bh8_gym.hand_urdf import FINGER_SWEEP_DEPTH, KNUCKLE_HEIGHT

    env = gym.make("BH8Grasp-v0", randomize=False, placement={"table_contact_below": 0.03}).unwrapped
    try:
        scene, client = env.scene, env.plant.client
        placement = PlacementRanges(table_contact_below=0.03)
        for size in ((0.08, 0.03, 0.06), (0.03, 0.08, 0.06), (0.05, 0.05, 0.015)):
            spec = ObjectSpec("box", size, mass=0.1)
            episode = GraspEpisode(spec, (0.01, -0.005), 0.0, clearance=0.012, top_error=-0.003)
            scene.begin_episode(episode)
            low, high = pybullet.getAABB(scene.object_body, -1, physicsClientId=client)
            widths = (high[0] - low[0], high[1] - low[1])
            assert widths[1] == pytest.approx(min(size[:2]), abs=2e-3), size  # across the closing axis
            assert ((low[0] + high[0]) / 2, (low[1] + high[1]) / 2) == pytest.approx((0.01, -0.005), abs=1e-6)
            palm_above_table = scene.palm_height - scene.table_top
            wrap = size[2] - 0.003 + KNUCKLE_HEIGHT + 0.012
            assert scene.table_contact == (size[2] - 0.003 < placement.table_contact_below)
            if scene.table_contact:
                assert wrap <= palm_above_table < FINGER_SWEEP_DEPTH
            else:
                expected = max(wrap, FINGER_SWEEP_DEPTH + placement.fingertip_margin)
                assert palm_above_table == pytest.approx(expected, abs=1e-9)
        rng = np.random.default_rng(0)
        draws = [scene.sample_episode(rng) for _ in range(200)]
        assert all(abs(d.top_error) <= placement.top_error for d in draws)
        assert all(placement.clearance[0] <= d.clearance <= placement.clearance[1] for d in draws)
        mesh = ObjectSet.named("train").sample(rng)  # a random_urdf: its grasp yaw measured, then cached
        body = scene.loader.create(mesh, (0, 0, -5), (0, 0, 0, 1))
        yaw = scene.grasp_yaw(mesh, body)
        assert 0.0 <= yaw < np.pi and scene.grasp_yaw(mesh, body) == yaw
        scene.loader.remove(body)
    finally:
        env.close()
    with pytest.raises(ValueError, match="clearance"):
        PlacementRanges(top_error=0.01, clearance=(0.005, 0.02))
