"""Wrappers and helpers around the BH8 environments.

`ContinuousActions` is what training uses: Gaussian policies (PPO, SAC) emit floats, the hand
takes bytes. The same mapping (`unit_to_bytes`) is what `bh8 deploy` applies to a policy's output,
so a trained policy drives a real hand with exactly the bytes it produced in simulation.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Callable

import gymnasium as gym
import numpy as np


def unit_to_bytes(unit: np.ndarray, low: np.ndarray, high: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Map floats in [-1, 1] (clipped) linearly onto the integer range low..high, rounding to nearest.

    LCV (-128..127): -1 -> -128, 0 -> 0, +1 -> 127. LCPG (0..255): -1 -> 0, +1 -> 255.
    """
    units, centres, halves = np.broadcast_arrays(np.asarray(unit, dtype=np.float64), (low + high) / 2.0, (high - low) / 2.0)
    values = np.array(unit_to_byte_list(units.ravel().tolist(), centres.ravel().tolist(), halves.ravel().tolist()),
                      dtype=np.int64).reshape(units.shape)
    if out is None:
        return values.astype(np.int16)
    out[...] = values
    return out


def unit_to_byte_list(units: list[float], centres: list[float], halves: list[float]) -> list[int]:
    """`unit_to_bytes` on plain floats, element by element: round(centre + half x clip(u, -1, 1)),
    halves to even as np.rint. The per-step path: on a handful of values numpy's call costs dominate."""
    return [round(centre + half * (-1.0 if u < -1.0 else (1.0 if u > 1.0 else u)))
            for u, centre, half in zip(units, centres, halves)]


def bytes_to_unit(values: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """Inverse of `unit_to_bytes` (up to rounding): integer control values -> floats in [-1, 1]."""
    centre = (low + high) / 2.0
    half = (high - low) / 2.0
    return ((np.asarray(values, dtype=np.float64) - centre) / half).astype(np.float32)


class ContinuousActions(gym.ActionWrapper, gym.utils.RecordConstructorArgs):
    """Actions are float32 in [-1, 1], one per control datum; mapped to the LOOP bytes by `unit_to_bytes`.

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
        # unit_to_bytes' centre and half-range, once, as plain floats
        self._centres = ((self._low + self._high) / 2.0).tolist()
        self._halves = ((self._high - self._low) / 2.0).tolist()
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
