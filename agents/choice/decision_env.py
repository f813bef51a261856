"""The grasp choice as a Gymnasium environment of one decision, for RL over the discrete choice (SB3's
PPO with a `Discrete` action) and the optional fine-tuning stage of `bh8 train` (`[choice] rl_episodes`).

## Action Space
``Discrete(K)``: the candidate grasp (`ChoiceSettings.grasps`) that drives the fingers from the
decision point to the episode's end.

## Observation Space
``Box(float32)``: the features at the decision point (`features.ChoiceFeatures`, the grasp env's
feedback blocks only), after the probe has closed the fingers for `decision_seconds`.

## Rewards
1 if the grasp holds the object at the episode's end (the grasp env's success), else 0.

## Episode End
Every episode is one decision: `step` runs the chosen grasp to the grasp env's end and terminates.

## Starting State
`reset(seed)` draws a grasp-env episode seed from the env's generator, resets the grasp env with it
and runs the probe to the decision point.
"""
from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from bh8_gym.agents.choice.features import ChoiceFeatures
from bh8_gym.agents.choice.model import SuccessModel
from bh8_gym.agents.choice.policy import ChoiceSettings, probe_policy
from bh8_gym.agents.env_factory import make_env


class DecisionEnv(gym.Env):
    """One grasp decision per episode (module docstring)."""

    metadata = {"render_modes": []}

    def __init__(self, env_id: str = "BH8Grasp-v0", env_kwargs: dict | None = None,
                 settings: ChoiceSettings | dict | None = None):
        self.settings = settings if isinstance(settings, ChoiceSettings) else ChoiceSettings(**(settings or {}))
        self.grasp_env = make_env(env_id, env_kwargs or {})
        base = self.grasp_env.unwrapped
        self.n_features = len(ChoiceFeatures(base.layout.feedback_fields, base.episode_seconds).names)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (self.n_features,), dtype=np.float32)
        self.action_space = gym.spaces.Discrete(len(self.settings.grasps))
        self._policy = probe_policy(self.settings, self.n_features)
        self._pending = None

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        episode_seed = int(self.np_random.integers(2**31))
        env, base, policy = self.grasp_env, self.grasp_env.unwrapped, self._policy
        obs, info = env.reset(seed=episode_seed)
        policy.reset(env)
        while True:
            action = policy.act(obs, info)
            if policy.phase != "probe":
                break
            obs, _, terminated, truncated, info = base.step(env.action(action))
            if terminated or truncated:  # over before the decision: whatever is chosen, this is the outcome
                self._pending = bool(info["is_success"])
                return policy.decision_features().astype(np.float32), {"episode_seed": episode_seed}
        self._pending = None
        self._obs, self._info = obs, info
        return policy.decided_features.astype(np.float32), {"episode_seed": episode_seed}

    def step(self, action):
        if not self.action_space.contains(action):
            raise ValueError(f"action must be a grasp index 0..{self.action_space.n - 1}, got {action!r}")
        env, base, policy = self.grasp_env, self.grasp_env.unwrapped, self._policy
        if self._pending is not None:
            held = self._pending
        else:
            policy.chosen = int(action)
            obs, info, step_action = self._obs, self._info, policy.last_actions[int(action)]
            while True:
                obs, _, terminated, truncated, info = base.step(env.action(step_action))
                if terminated or truncated:
                    break
                step_action = policy.act(obs, info)
            held = bool(info["is_success"])
        observation = np.zeros(self.n_features, dtype=np.float32)
        return observation, float(held), True, False, {"is_success": held, "grasp": self.settings.grasps[int(action)]}

    def close(self):
        self.grasp_env.close()


def warm_started_ppo(selector: SuccessModel, env, seed: int = 0, **hyperparameters):
    """SB3 PPO on a `DecisionEnv` whose actor starts as `selector`: the same tanh layers, the input
    scaling folded into the first layer, the selector's logits the categorical's (its argmax is the
    selector's choice). The critic starts fresh; a small learning rate and clipping keep the actor
    near where it started."""
    import torch
    from stable_baselines3 import PPO

    hidden = [w.shape[1] for w in selector.weights[:-1]]
    model = PPO("MlpPolicy", env, seed=seed, device="cpu",
                policy_kwargs={"net_arch": {"pi": hidden, "vf": hidden}, "activation_fn": torch.nn.Tanh}, **hyperparameters)
    weights = [w.copy() for w in selector.weights]
    biases = [b.copy() for b in selector.biases]
    biases[0] = biases[0] - (selector.mean / selector.std) @ weights[0]
    weights[0] = weights[0] / selector.std[:, None]
    linears = [m for m in model.policy.mlp_extractor.policy_net if isinstance(m, torch.nn.Linear)]
    linears.append(model.policy.action_net)
    with torch.no_grad():
        for layer, weight, bias in zip(linears, weights, biases):
            layer.weight.copy_(torch.tensor(weight.T))
            layer.bias.copy_(torch.tensor(bias))
    return model


def selector_of(model, n_features: int) -> SuccessModel:
    """A PPO actor's logits as a `SuccessModel` (argmax = the actor's deterministic choice)."""
    import torch

    linears = [m for m in model.policy.mlp_extractor.policy_net if isinstance(m, torch.nn.Linear)]
    linears.append(model.policy.action_net)
    return SuccessModel(np.zeros(n_features), np.ones(n_features),
                        [layer.weight.detach().double().numpy().T.copy() for layer in linears],
                        [layer.bias.detach().double().numpy().copy() for layer in linears])
