"""Wrappers and helpers around the BH8 environments.

`ContinuousActions` is what training uses: Gaussian policies (PPO, SAC) emit floats, the hand
takes bytes. The mapping is the host's (`bh8_gym.action_bytes`): `bh8 deploy` applies the same
one to a policy's output, so a trained policy drives a real hand with exactly the bytes it
produced in simulation.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Callable

import gymnasium as gym
import numpy as np

from bh8_gym.action_bytes import bytes_to_unit, centres_and_halves, unit_to_byte_list


class ContinuousActions(gym.ActionWrapper, gym.utils.RecordConstructorArgs):
    """Actions are float32 in [-1, 1], one per control datum; mapped to the LOOP bytes as
    `action_bytes.unit_to_bytes` maps them.

    Out-of-range floats are clipped (Gaussian policies overshoot); NaN/inf or a wrong shape raise
    ValueError naming the value.
    """

    def __init__(self, env: gym.Env):
        gym.utils.RecordConstructorArgs.__init__(self)  # so gym.make(wrapped.spec) rebuilds it
        gym.ActionWrapper.__init__(self, env)
        space = env.action_space
        if not isinstance(space, gym.spaces.Box) or not np.issubdtype(space.dtype, np.integer):
            raise ValueError(f"ContinuousActions wraps an integer Box action space, got {space!r}")
        self._low = space.low.astype(np.float64)
        self._high = space.high.astype(np.float64)
        self._dtype = space.dtype
        self._centres, self._halves = centres_and_halves(self._low, self._high)
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=space.shape, dtype=np.float32)

    def action(self, action) -> np.ndarray:
        unit = np.asarray(action, dtype=np.float64)
        if unit.shape != self._low.shape:
            raise ValueError(f"action must have shape {self._low.shape}, got {unit.shape}: {action!r}")
        units = unit.tolist()
        if not all(math.isfinite(u) for u in units):
            raise ValueError(f"action must be finite, got {action!r}")
        # A fresh array: the env may keep the action (previous-action observation, info).
        return np.array(unit_to_byte_list(units, self._centres, self._halves), dtype=self._dtype)

    def reverse_action(self, action) -> np.ndarray:
        return bytes_to_unit(action, self._low, self._high)


def record_episode(
    env: gym.Env,
    policy: Callable[[np.ndarray], np.ndarray],
    path: str | Path,
    seed: int | None = None,
    fps: float | None = None,
    every: int | None = None,
) -> dict:
    """Run one episode with `policy(obs) -> action`, render every `every`-th step, write a GIF/MP4.

    `env` must have render_mode "rgb_array". `every` defaults to `rendering.steps_per_frame` (frames
    of at least 20 ms: browsers show shorter GIF frames at 100 ms); fps defaults to real time (the
    env's control rate divided by `every`). Returns {"steps", "return", "is_success", "path"}.
    """
    from bh8_gym.rendering import steps_per_frame, write_animation

    if env.render_mode != "rgb_array":
        raise ValueError(f"record_episode needs render_mode='rgb_array', got {env.render_mode!r}")
    cycle_seconds = env.unwrapped.cycle_seconds
    if every is None:
        every = steps_per_frame(cycle_seconds)
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every!r}")
    obs, info = env.reset(seed=seed)
    frames = [env.render()]
    total, steps, done = 0.0, 0, False
    while not done:
        obs, reward, terminated, truncated, info = env.step(policy(obs))
        total += float(reward)
        steps += 1
        done = terminated or truncated
        if steps % every == 0 or done:
            frames.append(env.render())
    if fps is None:
        fps = 1.0 / (cycle_seconds * every)
    write_animation(frames, str(path), fps=fps)
    return {"steps": steps, "return": total, "is_success": bool(info.get("is_success", False)), "path": str(path)}
