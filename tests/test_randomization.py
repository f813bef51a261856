"""Domain randomisation of the environments, including the RealTime cycle latency.

SPEC.md §6: a cycle costs the block bytes at BAUD plus the firmware's processing time; SPEC.md §8
lists that processing time as an open point to keep configurable, so with randomize=True each
reset draws it (RandomizationRanges.processing_time) after the plant parameters, and without
randomisation it is the firmware's documented default (REALTIME_PROCESSING_S).
"""
from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import bh8_gym  # noqa: F401  (registers the environments)
from bh8_gym.envs.randomization import PlantRandomizer, RandomizationRanges
from bh8_gym.firmware import REALTIME_PROCESSING_S

ENV_ID = "BH8FingerReach-v0"  # no objects: the cheapest env; the latency wiring is in the base class
STEPS = 5


def _step_times(env, seed: int) -> tuple[list[float], list[float]]:
    """Per-step (host clock, firmware clock) increments of one short episode."""
    env.reset(seed=seed)
    action = np.zeros(env.action_space.shape, dtype=np.int16)
    host, firmware = [], []
    for _ in range(STEPS):
        before_host, before_firmware = env.elapsed(), env.firmware.time
        _, _, _, _, info = env.step(action)
        host.append(info["time"] - before_host)
        firmware.append(env.firmware.time - before_firmware)
    return host, firmware


def test_randomised_latency_changes_the_simulated_time_per_step():
    """SPEC.md §6 + §8: with randomize=True the per-step simulated time is bytes at BAUD plus a
    processing time drawn per reset inside the range, different for two seeds, constant within an
    episode, and the observation's host clock (info["time"]) follows it."""
    env = gym.make(ENV_ID, randomize=True).unwrapped
    try:
        low, high = RandomizationRanges().processing_time
        transfer = env.cycle_seconds - REALTIME_PROCESSING_S
        per_seed = {}
        for seed in (1, 2):
            host, firmware = _step_times(env, seed)
            drawn = env.firmware.processing_time
            assert low <= drawn <= high and drawn != REALTIME_PROCESSING_S
            assert host == pytest.approx([transfer + drawn] * STEPS, abs=1e-12)
            assert firmware == pytest.approx(host, abs=1e-12)
            per_seed[seed] = host[0]
        assert abs(per_seed[1] - per_seed[2]) > 1e-6
    finally:
        env.close()


def test_without_randomisation_each_step_costs_the_nominal_cycle_time():
    """SPEC.md §6: randomize=False charges exactly `cycle_seconds` per step (the firmware's default
    processing time), also right after a randomised episode (the reset's restore puts it back)."""
    env = gym.make(ENV_ID, randomize=True).unwrapped
    try:
        env.reset(seed=3)
        assert env.firmware.processing_time != REALTIME_PROCESSING_S
        env.randomize = False
        for seed in (1, 2):
            host, firmware = _step_times(env, seed)
            assert env.firmware.processing_time == REALTIME_PROCESSING_S
            # float: each step's clock is a sum of three terms, so equal up to one rounding
            assert host == pytest.approx([env.cycle_seconds] * STEPS, rel=1e-14)
            assert firmware == pytest.approx([env.cycle_seconds] * STEPS, rel=1e-12)
    finally:
        env.close()


def test_host_clock_is_the_sum_of_cycle_times_from_the_a_block():
    """SPEC.md §6: elapsed() after n steps is the "A" block's cycle plus n control cycles, summed
    with `next_elapsed` in the firmware's order, so a host recomputes it bit for bit."""
    env = gym.make(ENV_ID, randomize=False).unwrapped
    try:
        env.reset(seed=0)
        expected = env.next_elapsed(0.0, 1, REALTIME_PROCESSING_S)
        assert env.elapsed() == expected
        for _ in range(STEPS):
            _, _, _, _, info = env.step(np.zeros(env.action_space.shape, dtype=np.int16))
            expected = env.next_elapsed(expected, len(info["control_block"]), REALTIME_PROCESSING_S)
            assert env.elapsed() == expected == info["time"]
    finally:
        env.close()


def test_nominal_episode_steps_matches_the_env_truncation():
    """The step count `bh8 deploy` runs by default is where the env truncates without randomisation."""
    env = gym.make(ENV_ID, randomize=False, episode_seconds=0.1).unwrapped
    try:
        env.reset(seed=0)
        steps, truncated = 0, False
        while not truncated:
            _, _, terminated, truncated, _ = env.step(np.zeros(env.action_space.shape, dtype=np.int16))
            steps += 1
            assert not terminated
        assert steps == env.nominal_episode_steps()
    finally:
        env.close()


def test_scene_for_seed_draws_the_env_reset_including_the_latency(tmp_path):
    """scenes.scene_for_seed makes reset(seed)'s draws from reset's generators: plant parameters and
    the processing time (SPEC.md §8) from the physics generator, the episode from np_random."""
    from bh8_gym.envs.scenes import scene_for_seed
    from bh8_gym.firmware import Firmware
    from bh8_gym.plant import HandPlant

    env = gym.make("BH8Grasp-v0").unwrapped
    plant = HandPlant()
    try:
        firmware = Firmware(plant=plant, store_dir=tmp_path / "store")
        env.reset(seed=42)
        scene = scene_for_seed("BH8Grasp-v0", plant, 42, firmware=firmware)
        assert scene.episode == env.scene.episode
        assert plant.params == env.plant.params
        assert firmware.processing_time == env.firmware.processing_time != REALTIME_PROCESSING_S
    finally:
        plant.close()
        env.close()


def test_bad_latency_settings_name_the_value():
    """Bad arguments raise ValueError naming the value."""
    with pytest.raises(ValueError, match="processing_time"):
        RandomizationRanges(processing_time=(2e-3, 1e-3))

    class Plant:
        def set_parameters(self, params):
            pass

    with pytest.raises(ValueError, match="needs PlantRandomizer"):
        PlantRandomizer(Plant()).apply(None, 1e-3)

    class Firmware:
        processing_time = REALTIME_PROCESSING_S

    with pytest.raises(ValueError, match="-0.5"):
        PlantRandomizer(Plant(), Firmware()).apply(None, -0.5)


def test_a_seed_gives_the_same_scenes_with_or_without_randomisation():
    """The plant and latency draws come from a generator of their own: episode after episode of one
    seed, the objects and placements are the same whether the physics is randomised or not, so a
    nominal evaluation and a randomised one see the same scenes."""
    episodes = {}
    for randomize in (True, False):
        env = gym.make("BH8Grasp-v0", randomize=randomize).unwrapped
        try:
            env.reset(seed=7)
            seen = [env.scene.episode]
            for _ in range(2):
                env.reset()
                seen.append(env.scene.episode)
            episodes[randomize] = seen
            processing = env.firmware.processing_time
        finally:
            env.close()
        assert (processing != REALTIME_PROCESSING_S) == randomize
    assert episodes[True] == episodes[False]
    assert len({episode.spec for episode in episodes[True]}) == 3
