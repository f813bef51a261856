"""Snapshot and branch (`BH8LoopEnv.snapshot`/`restore`): the counterfactual labels of the grasp
choice roll every candidate grasp out from one snapshot, so each branch must start from exactly the
same state whatever the branches before it did."""
import gymnasium as gym
import numpy as np
import pytest

import bh8_gym  # noqa: F401  (registers the envs)

CLOSE = np.array([100, 255, 100, 255, 100, 255, 0, 255], dtype=np.int16)
OPEN = np.array([-60, 255, -60, 255, -60, 255, 0, 255], dtype=np.int16)


def _roll(env, action, steps):
    out = []
    for _ in range(steps):
        obs, reward, terminated, truncated, info = env.step(action)
        out.append((obs.tobytes(), reward, info["is_success"], info["feedback_block"]))
        if terminated or truncated:
            break
    return out


@pytest.fixture(scope="module")
def grasp_env():
    env = gym.make("BH8Grasp-v0", object_set="primitives", randomize=True, history=True).unwrapped
    yield env
    env.close()


def test_a_branch_replays_exactly_whatever_ran_before_it(grasp_env):
    env = grasp_env
    env.reset(seed=3)
    _roll(env, CLOSE, 50)  # the fingers reach the object
    snapshot = env.snapshot()
    first = _roll(env, CLOSE, 60)
    env.restore(snapshot)
    other = _roll(env, OPEN, 60)
    env.restore(snapshot)
    again = _roll(env, CLOSE, 60)
    env.release(snapshot)
    assert other != first  # the branches differ...
    assert again == first  # ...and the first replays to the bit after the other ran
    assert len(first) == 60


def test_restore_puts_back_the_hosts_clock_and_history(grasp_env):
    env = grasp_env
    env.reset(seed=5)
    _roll(env, CLOSE, 20)
    snapshot = env.snapshot()
    elapsed, history = env.elapsed(), env._history.values()
    _roll(env, CLOSE, 30)
    env.restore(snapshot)
    assert env.elapsed() == elapsed
    assert env._history.values() == history
    env.release(snapshot)


def test_snapshot_needs_an_episode_and_restore_an_env_snapshot():
    env = gym.make("BH8FingerReach-v0").unwrapped
    try:
        with pytest.raises(gym.error.ResetNeeded):
            env.snapshot()
        env.reset(seed=0)
        with pytest.raises(TypeError, match="EnvSnapshot"):
            env.restore("state")
        snapshot = env.snapshot()  # the reach scene has no moving parts of its own
        env.step(env.action_space.sample())
        env.restore(snapshot)
        env.release(snapshot)
    finally:
        env.close()
