"""Building the environments agents train, evaluate and deploy on (no torch here).

Policies act on the `ContinuousActions` view of an environment (floats in [-1, 1] mapped to LOOP
bytes by the env's wrapper), because PPO's and SAC's Gaussians need a float Box; the env's own
integer byte space is what the firmware sees.
"""
from __future__ import annotations

import copy
from typing import Any, Mapping

import gymnasium as gym

from bh8_gym.envs.wrappers import ContinuousActions


def make_env(env_id: str, env_kwargs: Mapping[str, Any] | None = None, seed: int | None = None,
             continuous: bool = True, render_mode: str | None = None) -> gym.Env:
    """`gym.make(env_id, **env_kwargs)` (bh8_gym registered), wrapped in `ContinuousActions`, with a
    TimeLimit no shorter than the env's longest episode."""
    kwargs = copy.deepcopy(dict(env_kwargs or {}))
    if render_mode is not None:
        kwargs["render_mode"] = render_mode
    try:
        env = gym.make(env_id, **kwargs)
        # The registry's max_episode_steps is a backstop; a longer arm schedule or episode_seconds
        # would be cut short of its end (success bonus lost, bootstrapped as truncated).
        limit = env.unwrapped.longest_episode_steps() + 1  # the env's own end comes first
        if env.spec.max_episode_steps is not None and env.spec.max_episode_steps < limit:
            env.close()
            env = gym.make(env_id, **{**kwargs, "max_episode_steps": limit})
    except (gym.error.NameNotFound, gym.error.VersionNotFound, gym.error.NamespaceNotFound,
            gym.error.DeprecatedEnv) as error:
        raise ValueError(f"unknown environment {env_id!r} ({error}); bh8-gym has BH8Grasp-v0 and "
                         "BH8FingerReach-v0") from None
    except TypeError as error:
        if "unexpected keyword argument" not in str(error):
            raise
        raise ValueError(f"{env_id}: {error}") from None  # a typo in a config or --env-kwargs
    if continuous and not _is_float_box(env.action_space):
        env = ContinuousActions(env)
    if seed is not None:
        env.reset(seed=seed)
        env.action_space.seed(seed)
    return env


def _is_float_box(space: gym.Space) -> bool:
    return isinstance(space, gym.spaces.Box) and space.dtype.kind == "f"


class EnvFactory:
    """A picklable env constructor for SubprocVecEnv workers (forkserver pickles it)."""

    def __init__(self, env_id: str, env_kwargs: Mapping[str, Any], seed: int, monitor: bool = True):
        self.env_id = env_id
        self.env_kwargs = dict(env_kwargs)
        self.seed = seed
        self.monitor = monitor

    def __call__(self) -> gym.Env:
        env = make_env(self.env_id, self.env_kwargs, seed=self.seed)
        if self.monitor:
            from stable_baselines3.common.monitor import Monitor

            env = Monitor(env)
        return env
