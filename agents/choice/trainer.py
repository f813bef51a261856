"""`bh8 train` of the grasp choice (`algorithm = "GraspChoice"`, agents/configs/choice_grasp.toml):
counterfactual labels on the training objects, the selector fitted to them, the failure predictor
when the settings retry, every candidate model scored on the validation objects and the best one
kept, and a report of what each step gave.

Output in the run directory: `grasp_choice.npz` (the policy file `bh8 eval` and `bh8 deploy` run),
`labels.npz` (the labels, reused by a run with the same settings and contexts), `choice.json`
(labels' summary, each model's validation figures against the probe's own grasp, the one kept) and
`run.json` (the config and seed, as every `bh8 train` run).
"""
from __future__ import annotations

import hashlib
import json
import os
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path
from typing import Callable

import numpy as np

from bh8_gym.agents.choice.labels import Labels, collect_labels
from bh8_gym.agents.choice.model import SuccessModel
from bh8_gym.agents.choice.policy import ChoiceSettings, GraspChoicePolicy
from bh8_gym.agents.env_factory import make_env
from bh8_gym.agents.grasps import run_script

POLICY_FILE = "grasp_choice.npz"
LABELS_FILE = "labels.npz"
REPORT_FILE = "choice.json"
# Each run's training contexts are seeds from its own block, so two seeds never share a context; the
# validation episodes are the same for every run (seed 10000 on, as PPO's evaluations).
CONTEXT_SEED_BLOCK = 1_000_000


def run_episodes(env_id: str, env_kwargs: dict, policy_arrays: dict, seeds: list[int]) -> list[bool]:
    """Each seed's episode with the policy file's arrays (built afresh in this process): held or not."""
    env = make_env(env_id, env_kwargs)
    policy = GraspChoicePolicy.from_arrays(policy_arrays)
    try:
        return [run_script(env, policy, seed) for seed in seeds]
    finally:
        env.close()


def validate(env_id: str, env_kwargs: dict, policies: list[dict], seeds: list[int], processes: int) -> list[list[bool]]:
    """Every policy (its arrays) on the same episodes, the episodes split over `processes` workers."""
    if processes <= 1:
        return [run_episodes(env_id, env_kwargs, arrays, seeds) for arrays in policies]
    halves = [seeds[i::processes] for i in range(processes)]
    with ProcessPoolExecutor(processes, mp_context=get_context("forkserver")) as pool:
        futures = [[pool.submit(run_episodes, env_id, env_kwargs, arrays, part) for part in halves] for arrays in policies]
        results = []
        for parts in futures:
            by_seed = {}
            for part, future in zip(halves, parts):
                by_seed.update(zip(part, future.result()))
            results.append([by_seed[s] for s in seeds])
    return results


class ChoiceTrainer:
    """One run of the grasp choice's training (module docstring)."""

    def __init__(self, config: dict, out: Path, seed: int = 0, processes: int | None = None, progress: bool = True,
                 log: Callable[[str], None] = print):
        self.config, self.out, self.seed = config, Path(out), int(seed)
        self.processes = processes or os.cpu_count() or 1
        self.progress, self.log = progress, log
        table = config["choice"]
        self.settings = ChoiceSettings(**table.get("settings", {}))
        self.contexts = int(table.get("contexts", 800))
        self.validation_episodes = int(config["eval"].get("episodes", 200))
        self.validation_seed = int(config["eval"].get("seed", 10_000))
        self.models = [dict(m) for m in table.get("models", [{}])]
        self.rl_episodes = int(table.get("rl_episodes", 0))
        self.env_id = config["env_id"]
        self.env_kwargs = dict(config.get("env_kwargs", {}))
        self.eval_env_kwargs = {**self.env_kwargs, **config.get("eval_env_kwargs", {})}

    def _labels_key(self) -> str:
        text = json.dumps([self.env_id, self.env_kwargs, self.settings.__dict__, self.contexts, self.seed], sort_keys=True,
                          default=list)
        return hashlib.sha256(text.encode()).hexdigest()

    def labels(self) -> Labels:
        """The run's labels: read back when labels.npz holds this run's, else collected and saved."""
        from bh8_gym.atomic_files import atomic_write_npz

        path, key = self.out / LABELS_FILE, self._labels_key()
        if path.is_file():
            try:
                with np.load(path, allow_pickle=False) as data:
                    if str(data["key"]) == key:
                        arrays = {name: data[name] for name in data.files}
                        return Labels(tuple(str(g) for g in arrays["grasps"]), arrays["seeds"], arrays["features"],
                                      arrays["success"], arrays["safety_stop"], arrays["check_features"],
                                      [str(f) for f in arrays["families"]])
            except (OSError, ValueError, KeyError):
                pass  # damaged or another run's: labelled again
        start = self.seed * CONTEXT_SEED_BLOCK
        labels = collect_labels(self.env_id, self.env_kwargs, self.settings, range(start, start + self.contexts),
                                processes=self.processes, progress=self.progress)
        atomic_write_npz(path, {**labels.arrays(), "key": np.array(key)})
        return labels

    def fit(self, labels: Labels, model: dict) -> GraspChoicePolicy:
        hidden = tuple(model.get("hidden", (64, 64)))
        weight_decay = float(model.get("weight_decay", 1e-3))
        selector = SuccessModel.fit(labels.features, labels.success, hidden=hidden, weight_decay=weight_decay,
                                    seed=self.seed)
        predictor = None
        if self.settings.retries:
            k = len(labels.grasps)
            rows, cols = np.nonzero(~np.isnan(labels.check_features[:, :, 0]))
            mask = np.zeros((len(rows), k))
            mask[np.arange(len(rows)), cols] = 1.0
            targets = np.zeros((len(rows), k))
            targets[np.arange(len(rows)), cols] = labels.success[rows, cols]
            predictor = SuccessModel.fit(labels.check_features[rows, cols], targets, mask=mask, hidden=hidden,
                                         weight_decay=weight_decay, seed=self.seed)
        metadata = {"env_id": self.env_id, "env_kwargs": self.env_kwargs, "algorithm": "GraspChoice",
                    "seed": self.seed, "model": {"hidden": list(hidden), "weight_decay": weight_decay}}
        return GraspChoicePolicy(self.settings, selector, predictor, metadata)

    def fine_tune(self, policy: GraspChoicePolicy, n_features: int, rate: float, seeds: list[int]):
        """RL over the discrete choice: PPO on `DecisionEnv` from the selector, `rl_episodes` decisions
        on the training objects; the fine-tuned actor is kept only if it does better on validation."""
        from stable_baselines3.common.env_util import make_vec_env
        from stable_baselines3.common.vec_env import SubprocVecEnv

        from bh8_gym.agents.choice.decision_env import DecisionEnv, selector_of, warm_started_ppo

        kwargs = {"env_kwargs": self.env_kwargs, "settings": self.settings}
        envs = make_vec_env(DecisionEnv, n_envs=self.processes, seed=self.seed, env_kwargs=kwargs,
                            vec_env_cls=SubprocVecEnv if self.processes > 1 else None,
                            vec_env_kwargs={"start_method": "forkserver"} if self.processes > 1 else None)
        try:
            model = warm_started_ppo(policy.selector, envs, seed=self.seed, n_steps=max(8, 128 // self.processes),
                                     batch_size=64, n_epochs=4, learning_rate=1e-4, ent_coef=0.0)
            model.learn(self.rl_episodes)
        finally:
            envs.close()
        tuned = GraspChoicePolicy(self.settings, selector_of(model, n_features), policy.predictor,
                                  {**policy.metadata, "rl_episodes": self.rl_episodes})
        tuned_rate = float(np.mean(validate(self.env_id, self.eval_env_kwargs, [tuned.arrays()], seeds,
                                            self.processes)[0]))
        keep = tuned_rate > rate
        self.log(f"RL over the choice ({self.rl_episodes} decisions of PPO from the selector): validation "
                 f"{tuned_rate * 100:.1f} % against {rate * 100:.1f} % before" + (" <- kept" if keep else " (not kept)"))
        return (tuned if keep else policy), {"episodes": self.rl_episodes, "rate": tuned_rate, "before": rate,
                                             "kept": keep, "kept_rate": max(tuned_rate, rate)}

    def run(self) -> dict:
        self.out.mkdir(parents=True, exist_ok=True)
        started = time.monotonic()
        labels = self.labels()
        summary = labels.summary()
        self.log(f"labels: {summary['contexts']} contexts; each grasp holds "
                 + ", ".join(f"{name} {rate * 100:.1f} %" for name, rate in summary["hold"].items())
                 + f"; some grasp holds {summary['union'] * 100:.1f} % ({time.monotonic() - started:.0f} s)")
        candidates = [self.fit(labels, model) for model in self.models]
        from bh8_gym.agents.choice.policy import probe_policy

        reference = probe_policy(self.settings, labels.features.shape[1])
        seeds = list(range(self.validation_seed, self.validation_seed + self.validation_episodes))
        held = validate(self.env_id, self.eval_env_kwargs, [p.arrays() for p in (reference, *candidates)], seeds,
                        self.processes)
        rates = [float(np.mean(h)) for h in held]
        best = int(np.argmax(rates[1:]))
        for index, (model, rate) in enumerate(zip(self.models, rates[1:])):
            self.log(f"validation: model {model or 'default'} holds {rate * 100:.1f} % of {len(seeds)} episodes "
                     f"(the probe's grasp {self.settings.probe} alone {rates[0] * 100:.1f} %)"
                     + (" <- kept" if index == best else ""))
        chosen = candidates[best]
        rl = None
        if self.rl_episodes:
            chosen, rl = self.fine_tune(chosen, labels.features.shape[1], rates[best + 1], seeds)
            best_rate = rl["kept_rate"]
        else:
            best_rate = rates[best + 1]
        chosen.metadata["validation"] = {"success_rate": best_rate, "probe_success_rate": rates[0],
                                         "episodes": len(seeds), "seed": self.validation_seed}
        chosen.save(self.out / POLICY_FILE)
        report = {"labels": summary, "settings": self.settings.__dict__, "models": self.models,
                  "validation": {"episodes": len(seeds), "seed": self.validation_seed, "probe": rates[0],
                                 "models": rates[1:], "kept": best, "rl": rl},
                  "seconds": time.monotonic() - started}
        from bh8_gym.atomic_files import atomic_write

        atomic_write(self.out / REPORT_FILE, lambda h: h.write(json.dumps(report, indent=2, default=list).encode()))
        return report
