"""Counterfactual labels: which candidate grasps hold, from the very state the choice decides in.

For each training context (an episode's seed) the probe runs to the decision point; there the whole
simulation is snapshotted (`BH8LoopEnv.snapshot`: plant, firmware, scene, the host's clock and
history) and every candidate grasp is rolled out from it to the episode's end, the policy copied
with it. Every branch starts from the same state whatever the others did, so a context labels every
candidate at once, and since everything before the decision is the fixed probe, the labels do not
depend on the selector being trained (no DAgger needed). Each branch also records the features at
`check_seconds`, from which the failure predictor of the second chance learns.

Contexts run in parallel in worker processes (`concurrent.futures`), each with its own env.
"""
from __future__ import annotations

import copy
import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from multiprocessing import get_context

import numpy as np
from tqdm import tqdm

from bh8_gym.agents.choice.features import ChoiceFeatures
from bh8_gym.agents.choice.policy import ChoiceSettings, GraspChoicePolicy, probe_policy
from bh8_gym.agents.env_factory import make_env
from bh8_gym.envs.objects import object_family
from bh8_gym.envs.scenes import episode_object

CHUNK = 8  # contexts per task sent to a worker


@dataclass
class Labels:
    """Per context: the features at the decision, which grasp held (1/0), which stopped on strain,
    and each branch's features at the check (NaN where the branch ended before it)."""

    grasps: tuple[str, ...]
    seeds: np.ndarray
    features: np.ndarray  # (n, d)
    success: np.ndarray  # (n, k)
    safety_stop: np.ndarray  # (n, k)
    check_features: np.ndarray  # (n, k, d)
    families: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.seeds)

    @classmethod
    def concatenate(cls, parts: list["Labels"]) -> "Labels":
        parts = [p for p in parts if len(p)]
        order = np.argsort(np.concatenate([p.seeds for p in parts]), kind="stable")
        families = sum((p.families for p in parts), [])
        return cls(parts[0].grasps, np.concatenate([p.seeds for p in parts])[order],
                   np.concatenate([p.features for p in parts])[order], np.concatenate([p.success for p in parts])[order],
                   np.concatenate([p.safety_stop for p in parts])[order],
                   np.concatenate([p.check_features for p in parts])[order], [families[i] for i in order])

    def summary(self) -> dict:
        """Per grasp the share of contexts it holds, and the share some grasp holds (the union)."""
        rates = {name: float(self.success[:, k].mean()) for k, name in enumerate(self.grasps)}
        return {"contexts": len(self), "hold": rates, "union": float(self.success.max(1).mean())}

    def arrays(self) -> dict[str, np.ndarray]:
        return {"grasps": np.array(self.grasps), "seeds": self.seeds, "features": self.features,
                "success": self.success, "safety_stop": self.safety_stop, "check_features": self.check_features,
                "families": np.array(self.families)}


def _finish(env, policy, obs, info, first_action, check_seconds: float, n_features: int):
    """Step `policy` from a branch's first action to the episode's end: (success, stop, check features)."""
    base = env.unwrapped
    check = np.full(n_features, np.nan)
    action = first_action
    while True:
        obs, _, terminated, truncated, info = base.step(env.action(action))
        if terminated or truncated:
            return bool(info["is_success"]), "safety_stop" in info, check
        action = policy.act(obs, info)
        if np.isnan(check[0]) and policy.attempt_cycles * policy.cycle_seconds >= check_seconds:
            check = policy.decision_features()


def label_context(env, settings: ChoiceSettings, seed: int):
    """One context: (features, success (k,), stops (k,), check features (k, d), family)."""
    base = env.unwrapped
    n_features = len(ChoiceFeatures(base.layout.feedback_fields, base.episode_seconds).names)
    policy = probe_policy(settings, n_features)
    obs, info = env.reset(seed=seed)
    policy.reset(env)
    family = object_family(episode_object(env))
    k = len(settings.grasps)
    while True:
        action = policy.act(obs, info)
        if policy.phase != "probe":
            break
        obs, _, terminated, truncated, info = base.step(env.action(action))
        if terminated or truncated:  # the episode ended before the decision: every grasp shares its fate
            outcome = float(info["is_success"])
            return (policy.decision_features(), np.full(k, outcome), np.full(k, float("safety_stop" in info)),
                    np.full((k, n_features), np.nan), family)
    features = policy.decision_features()
    first_actions = policy.last_actions
    memo = {id(base): base, id(env): env, id(base.layout): base.layout, id(policy.selector): policy.selector}
    snapshot = base.snapshot()
    success, stops, checks = np.zeros(k), np.zeros(k), np.full((k, n_features), np.nan)
    try:
        for index in range(k):
            base.restore(snapshot)
            branch: GraspChoicePolicy = copy.deepcopy(policy, memo)
            branch.chosen = index
            success[index], stops[index], checks[index] = _finish(env, branch, obs, info, first_actions[index],
                                                                  settings.check_seconds, n_features)
    finally:
        base.release(snapshot)
    return features, success, stops, checks, family


def _label_chunk(env_id: str, env_kwargs: dict, settings: ChoiceSettings, seeds: list[int]) -> Labels:
    env = _worker_env(env_id, env_kwargs)
    rows = [label_context(env, settings, seed) for seed in seeds]
    return Labels(settings.grasps, np.array(seeds), np.array([r[0] for r in rows]), np.array([r[1] for r in rows]),
                  np.array([r[2] for r in rows]), np.array([r[3] for r in rows]), [r[4] for r in rows])


_ENVS: dict = {}


def _worker_env(env_id: str, env_kwargs: dict):
    """One env per process and kwargs, built once (a world costs ~50 ms, an env's first reset more)."""
    key = (env_id, repr(sorted(env_kwargs.items())))
    if key not in _ENVS:
        _ENVS[key] = make_env(env_id, env_kwargs)
    return _ENVS[key]


def collect_labels(env_id: str, env_kwargs: dict, settings: ChoiceSettings, seeds, processes: int | None = None,
                   progress: bool = False) -> Labels:
    """Label every seed of `seeds` (`label_context`), in `processes` worker processes (default: one per
    core; 1: in this process). The result is the same whatever the split: each context is its own
    reset(seed) on a fresh or restored world."""
    seeds = [int(s) for s in seeds]
    processes = max(1, min(processes or os.cpu_count() or 1, max(1, len(seeds) // CHUNK)))
    chunks = [seeds[i:i + CHUNK] for i in range(0, len(seeds), CHUNK)]
    bar = tqdm(total=len(seeds), desc="labels", unit="ctx", disable=None if progress else True, leave=False)
    parts = []
    if processes == 1:
        for chunk in chunks:
            parts.append(_label_chunk(env_id, env_kwargs, settings, chunk))
            bar.update(len(chunk))
    else:
        with ProcessPoolExecutor(processes, mp_context=get_context("forkserver")) as pool:
            futures = [pool.submit(_label_chunk, env_id, env_kwargs, settings, chunk) for chunk in chunks]
            for future in as_completed(futures):
                parts.append(future.result())
                bar.update(len(parts[-1]))
    bar.close()
    return Labels.concatenate(parts)
