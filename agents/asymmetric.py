"""PPO with an asymmetric critic: the value function sees privileged simulator state, the actor
sees only what a host has on real hardware.

Why: the grasp policy cannot see the object (a real host has only the feedback blocks), so from
its own observation the return is very uncertain; a critic that also sees the object's pose,
rise and contacts (the env's `privileged=True` entries) gives PPO far less noisy advantages.
Nothing privileged reaches the actor, so the trained actor still deploys to a real hand.

Training envs run with `privileged=True` (observation = host entries, then privileged entries,
envs/base.py). `AsymmetricActorCriticPolicy` multiplies the privileged entries by zero before
the actor's network; everywhere else (evaluation, export, deploy) the actor gets host
observations padded with zeros (`HostObservationModel`), which give it the same input.
"""
from __future__ import annotations

import numpy as np
import torch as th
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, FlattenExtractor


class HostObservations(BaseFeaturesExtractor):
    """The observation with its privileged entries zeroed. Same size as the input, so actor and
    critic keep one network input size (SB3's MlpExtractor takes one)."""

    def __init__(self, observation_space, host_observations: int):
        size = int(observation_space.shape[0])
        super().__init__(observation_space, features_dim=size)
        mask = th.zeros(size)
        mask[:host_observations] = 1.0
        self.register_buffer("mask", mask)

    def forward(self, observations: th.Tensor) -> th.Tensor:
        return observations * self.mask


class AsymmetricActorCriticPolicy(ActorCriticPolicy):
    """An MLP actor-critic whose actor reads the first `host_observations` entries only."""

    def __init__(self, observation_space, action_space, lr_schedule, *, host_observations: int, **kwargs):
        size = int(observation_space.shape[0])
        if not (isinstance(host_observations, (int, np.integer)) and 0 < host_observations < size):
            raise ValueError(f"host_observations must be an integer in 1..{size - 1} (the observation has "
                             f"{size} entries, the privileged ones last), got {host_observations!r}")
        for key in ("features_extractor_class", "features_extractor_kwargs", "share_features_extractor"):
            if key in kwargs:
                raise ValueError(f"AsymmetricActorCriticPolicy sets {key} itself")
        self.host_observations = int(host_observations)
        super().__init__(observation_space, action_space, lr_schedule, features_extractor_class=HostObservations,
                         features_extractor_kwargs={"host_observations": self.host_observations},
                         share_features_extractor=False, **kwargs)
        # The critic sees everything (neither extractor has parameters, so the optimiser is unaffected).
        self.vf_features_extractor = FlattenExtractor(observation_space)

    def _get_constructor_parameters(self) -> dict:
        data = super()._get_constructor_parameters()
        for key in ("features_extractor_class", "features_extractor_kwargs", "share_features_extractor"):
            data.pop(key, None)
        data["host_observations"] = self.host_observations
        return data


def host_observation_count(model) -> int | None:
    """The actor's observation size of an asymmetric model, None for an ordinary one."""
    policy = getattr(model, "policy", None)
    return policy.host_observations if isinstance(policy, AsymmetricActorCriticPolicy) else None


class HostObservationModel:
    """`predict` on host observations for an asymmetric model (pads the privileged entries with
    zeros, which the actor ignores); what evaluation and export use."""

    def __init__(self, model):
        self.model = model
        self.host_observations = host_observation_count(model)
        if self.host_observations is None:
            raise ValueError("HostObservationModel needs a model with an AsymmetricActorCriticPolicy")
        self._full = int(model.observation_space.shape[0])

    def predict(self, observation, state=None, episode_start=None, deterministic: bool = True):
        obs = np.asarray(observation, dtype=np.float32)
        if obs.shape[-1] != self.host_observations:
            raise ValueError(f"observation must have {self.host_observations} host entries, got shape {obs.shape}")
        padded = np.zeros((*obs.shape[:-1], self._full), dtype=np.float32)
        padded[..., :self.host_observations] = obs
        return self.model.predict(padded, deterministic=deterministic)
