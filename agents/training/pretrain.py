"""Warm start from a scripted grasp: behaviour cloning of the actor and a fitted critic before RL.

From scratch, PPO on BH8Grasp-v0 spends its first 100 k+ steps dropping objects (0 % on the
validation objects at 50 k and 100 k steps with the default config): the success bonus is rare
until the fingers close, stop at contact and keep a squeeze inside the strain limit in one
episode. A scripted grasp (agents/grasps.py) already does that on about half of the objects.
So the `[pretrain]` table of a config records that grasp on the training objects (the training
env itself: same observations, randomisation and safety envelope), fits the actor's mean action to
its actions and the critic to the discounted returns it earned, and RL starts from there. The
policy stays an MLP on the host's observations: nothing of the script is needed to deploy it.

    [pretrain]
    baseline = "squeeze"                             # agents.evaluation.baselines.BASELINES (LOOP ones)
    baseline_kwargs = {close_gain = 40, hold_gain = 80}
    episodes = 200                                   # demonstrations, seeds from `seed`
    epochs = 30
    learning_rate = 1e-3
    batch_size = 256
    seed = 30000
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from bh8_gym.agents.evaluation.baselines import LOOP_BASELINES, make_baseline
from bh8_gym.agents.env_factory import make_env
from bh8_gym.agents.policy_io import atomic_write_npz


@dataclass(frozen=True)
class PretrainSettings:
    """The `[pretrain]` table of a training config."""

    baseline: str = "squeeze"
    baseline_kwargs: dict = field(default_factory=dict)
    episodes: int = 200
    epochs: int = 30
    learning_rate: float = 1e-3
    batch_size: int = 256
    seed: int = 30_000
    value_weight: float = 0.5
    #: Gaussian noise (float action units) added to the actions the script's episodes execute, not
    #: to the recorded ones: the script recovers from the disturbance, so the clone learns to
    #: recover too instead of failing as soon as RL's exploration moves it off the script's path.
    action_noise: float = 0.0
    #: While RL runs, every rollout ends with `keep_batches` minibatches of the cloning loss, weighted
    #: `keep_weight` × `keep_decay` ** rollouts: RL improves on the script without forgetting it early.
    keep_weight: float = 0.0
    keep_decay: float = 0.95
    keep_batches: int = 8
    #: The weight never decays below this: without it, the default config held 52-62 % on the
    #: validation objects to 700 k steps and then fell to 0 % once the weight had decayed to nothing.
    keep_floor: float = 0.0
    #: A teacher instead of `baseline` (agents/training/teacher.py): scripts of the ceiling family
    #: (agents/evaluation/ceiling.py), in order of preference; each training episode is taught by the first
    #: that holds it, distilled in `dagger_iterations` DAgger iterations (the teacher's action
    #: executed with probability dagger_beta ** iteration).
    teacher: tuple = ()
    dagger_iterations: int = 1
    dagger_beta: float = 0.5

    @classmethod
    def from_table(cls, table: dict[str, Any]) -> PretrainSettings:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(table) - known)
        if unknown:
            raise ValueError(f"[pretrain] has no {', '.join(unknown)} (known: {', '.join(sorted(known))})")
        if "teacher" in table:
            table = {**table, "teacher": tuple(table["teacher"]) if isinstance(table["teacher"], (list, tuple))
                     else table["teacher"]}
        settings = cls(**table)
        if settings.teacher:
            from bh8_gym.agents.grasps import FAMILY

            if not (isinstance(settings.teacher, tuple) and all(name in FAMILY for name in settings.teacher)):
                raise ValueError(f"[pretrain] teacher must be a list of the ceiling family's scripts "
                                 f"({', '.join(FAMILY)}), got {settings.teacher!r}")
            if not 1 <= settings.dagger_iterations <= 20 or not 0 <= settings.dagger_beta <= 1:
                raise ValueError("[pretrain] dagger_iterations must be 1-20 and dagger_beta in [0, 1]")
        if settings.baseline not in LOOP_BASELINES:
            raise ValueError(f"[pretrain] baseline must be one of {LOOP_BASELINES} (a LOOP policy), "
                             f"got {settings.baseline!r}")
        for name in ("episodes", "epochs", "batch_size"):
            if int(getattr(settings, name)) < 1:
                raise ValueError(f"[pretrain] {name} must be at least 1, got {getattr(settings, name)}")
        if not 0 <= settings.action_noise <= 1:
            raise ValueError(f"[pretrain] action_noise must be in [0, 1], got {settings.action_noise}")
        if settings.keep_weight < 0 or not 0 < settings.keep_decay <= 1 or settings.keep_batches < 1:
            raise ValueError("[pretrain] keep_weight must be >= 0, keep_decay in (0, 1], keep_batches >= 1")
        if not 0 <= settings.keep_floor <= settings.keep_weight:
            raise ValueError(f"[pretrain] keep_floor must be in [0, keep_weight], got {settings.keep_floor}")
        if not settings.learning_rate > 0:
            raise ValueError(f"[pretrain] learning_rate must be positive, got {settings.learning_rate}")
        return settings


def keep_weight_after(settings: PretrainSettings, rollouts: int) -> float:
    """The cloning loss's weight after `rollouts` rollouts of RL: decaying, never under the floor."""
    return max(settings.keep_weight * settings.keep_decay ** rollouts, settings.keep_floor)


@dataclass
class Demonstrations:
    """Per step: observation, the script's action (the float action space), discounted return."""

    observations: np.ndarray
    actions: np.ndarray
    returns: np.ndarray
    successes: int
    episodes: int


DEMONSTRATIONS_FILE = "demonstrations.npz"  # in the run directory: a resumed run keeps cloning them


def save_demonstrations(path, demonstrations: Demonstrations) -> None:
    atomic_write_npz(path, {"observations": demonstrations.observations, "actions": demonstrations.actions,
                            "returns": demonstrations.returns,
                            "counts": np.array([demonstrations.successes, demonstrations.episodes])})


def load_demonstrations(path) -> Demonstrations:
    with np.load(path, allow_pickle=False) as data:
        successes, episodes = (int(v) for v in data["counts"])
        return Demonstrations(data["observations"], data["actions"], data["returns"], successes, episodes)


def progress_bar(iterable, progress: bool, **kwargs):
    """`iterable` with a tqdm bar when `progress` and stderr is a terminal (disable=None): a log
    file gets no bar updates."""
    return tqdm(iterable, disable=None if progress else True, leave=False, dynamic_ncols=True, **kwargs)


def record(env_id: str, env_kwargs: dict, settings: PretrainSettings, gamma: float,
           progress: bool = False) -> Demonstrations:
    """Run the scripted grasp for `settings.episodes` episodes on the training env (`progress`: a
    bar on a terminal)."""
    env = make_env(env_id, env_kwargs)
    rng = np.random.default_rng(settings.seed)
    try:
        script = make_baseline(settings.baseline, env, **settings.baseline_kwargs)
        observations, actions, returns, successes = [], [], [], 0
        episodes = progress_bar(range(settings.episodes), progress, desc=f"demonstrations ({settings.baseline})",
                                unit="ep")
        for episode in episodes:
            observation, info = env.reset(seed=settings.seed + episode)
            script.reset(env)
            rewards, done = [], False
            while not done:
                action = script.act(observation, info)
                observations.append(observation)
                actions.append(action)
                if settings.action_noise:
                    action = np.clip(action + rng.normal(0.0, settings.action_noise, action.shape), -1.0, 1.0)
                observation, reward, terminated, truncated, info = env.step(action.astype(np.float32))
                rewards.append(float(reward))
                done = terminated or truncated
            successes += bool(info.get("is_success"))
            episodes.set_postfix(held=successes, refresh=False)
            returns.append(discounted_returns(rewards, gamma))
    finally:
        env.close()
    return Demonstrations(np.asarray(observations, dtype=np.float32), np.asarray(actions, dtype=np.float32),
                          np.concatenate(returns).astype(np.float32), successes, settings.episodes)


def discounted_returns(rewards, gamma: float) -> np.ndarray:
    """Each step's discounted return; the env's end is terminal (no bootstrap past it)."""
    discounted, running = np.empty(len(rewards)), 0.0
    for step in range(len(rewards) - 1, -1, -1):
        running = rewards[step] + gamma * running
        discounted[step] = running
    return discounted


def actor_cloning_loss(policy, observations, actions):
    """MSE of the policy's mean action (its deterministic action, Gaussian and gSDE alike) to the
    script's actions, on one batch."""
    import torch

    return torch.nn.functional.mse_loss(policy.get_distribution(observations).distribution.mean, actions)


def value_fit_loss(policy, observations, returns):
    """MSE of the critic's values to the script's discounted returns, on one batch."""
    import torch

    return torch.nn.functional.mse_loss(policy.predict_values(observations).flatten(), returns)


def clone(model, demonstrations: Demonstrations, settings: PretrainSettings, seed: int,
          progress: bool = False) -> dict[str, float]:
    """Fit the policy's mean action (MSE) and its value (MSE to the discounted return); returns the
    last epoch's losses (`progress`: a bar on a terminal)."""
    import torch

    policy = model.policy
    policy.set_training_mode(True)
    optimizer = torch.optim.Adam(policy.parameters(), lr=settings.learning_rate)
    observations = torch.as_tensor(demonstrations.observations)
    actions = torch.as_tensor(demonstrations.actions)
    returns = torch.as_tensor(demonstrations.returns)
    generator = torch.Generator().manual_seed(seed)
    count = len(observations)
    losses = {}
    epochs = progress_bar(range(settings.epochs), progress, desc="cloning", unit="epoch")
    for _ in epochs:
        order = torch.randperm(count, generator=generator)
        actor_sum = value_sum = 0.0
        for start in range(0, count, settings.batch_size):
            batch = order[start:start + settings.batch_size]
            actor_loss = actor_cloning_loss(policy, observations[batch], actions[batch])
            value_loss = value_fit_loss(policy, observations[batch], returns[batch])
            loss = actor_loss + settings.value_weight * value_loss
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            actor_sum += float(actor_loss.detach()) * len(batch)
            value_sum += float(value_loss.detach()) * len(batch)
        losses = {"actor_mse": actor_sum / count, "value_mse": value_sum / count}
        epochs.set_postfix({name: f"{value:.4g}" for name, value in losses.items()}, refresh=False)
    policy.set_training_mode(False)
    return losses
