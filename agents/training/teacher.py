"""Teacher and student: a teacher that knows which scripted grasp holds each training episode,
distilled into the deployable student on the student's own states (DAgger).

The teacher is privileged: for each training episode (a seed of the training env, which is
deterministic per seed) it runs every script of its list (`agents/evaluation/ceiling.py`'s family) and grasps
with one that holds the object, the one that holds most objects of that family where several do
(`choose_scripts`). No host knows that: it is what
the outcome of the episode tells. But it acts only through a script that reads the feedback blocks
as they come, so at any state of any trajectory its action is defined: what its script does after
that feedback history. That makes it a DAgger expert.

The student is the policy: an MLP on the host's observation, which should carry the haptic
history (`history = true` in env_kwargs: bh8_gym/haptic_history.py), or it cannot tell which
grasp the teacher chose. DAgger (Ross et al., 2011): iteration 0 runs the teacher alone;
iteration k runs teacher and student together, the teacher's action executed with probability
beta**k each step and the student's otherwise, the teacher's script reading every block; every
step of every iteration is labelled with the teacher's action, and the student is fitted to all
of them after each iteration (`pretrain.clone`: the actor's mean to the labels, the critic to the
discounted returns of the executed steps).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bh8_gym.agents.grasps import make_script, run_script
from bh8_gym.agents.env_factory import make_env
from bh8_gym.agents.training.pretrain import Demonstrations, clone, discounted_returns, progress_bar


def choose_scripts(env, scripts: list[str], seeds, progress: bool = False) -> list[tuple[str, bool]]:
    """Per seed, the script of `scripts` the teacher grasps that episode of `env` with, and whether
    it holds the object: of those that hold it, the one that holds most episodes of its object
    family (objects alike are taught alike where the outcomes allow); if none does, the family's
    best. Every script runs every seed."""
    from bh8_gym.envs.objects import object_family
    from bh8_gym.envs.scenes import episode_object

    seeds = list(seeds)
    held: dict[str, list[bool]] = {}
    families: list[str] = []
    bar = progress_bar(None, progress, total=len(scripts) * len(seeds), desc="teacher: trying its grasps", unit="ep")
    for name in scripts:
        script = make_script(name, env)
        held[name] = []
        for seed in seeds:
            held[name].append(run_script(env, script, seed))
            if len(families) < len(seeds):
                families.append(object_family(episode_object(env)))
            bar.update()
    bar.close()
    rate = {(family, name): sum(h for h, f in zip(held[name], families) if f == family)
            for family in set(families) for name in scripts}
    chosen = []
    for i, family in enumerate(families):
        holding = [name for name in scripts if held[name][i]] or scripts
        chosen.append((max(holding, key=lambda name: (rate[family, name], -scripts.index(name))),
                       any(held[name][i] for name in scripts)))
    return chosen




@dataclass
class Rollouts:
    """What one DAgger iteration ran: per step the observation, the teacher's label and the
    discounted return of the executed trajectory; per episode its outcome."""

    observations: list
    labels: list
    returns: list
    successes: int
    episodes: int


def rollout(env, policy, teacher, seed: int, beta: float, rng: np.random.Generator, gamma: float,
            out: Rollouts) -> None:
    """One episode: each step the teacher's action (probability `beta`) or the student's
    (`policy.predict`, deterministic); every step labelled with the teacher's action."""
    observation, info = env.reset(seed=seed)
    teacher.reset(env)
    rewards, done = [], False
    while not done:
        label = teacher.act(observation, info)
        out.observations.append(observation)
        out.labels.append(label)
        if beta >= 1.0 or rng.random() < beta:
            action = label
        else:
            action, _ = policy.predict(observation, deterministic=True)
        observation, reward, terminated, truncated, info = env.step(np.asarray(action, dtype=np.float32))
        rewards.append(float(reward))
        done = terminated or truncated
    out.returns.extend(discounted_returns(rewards, gamma))
    out.successes += bool(info.get("is_success"))
    out.episodes += 1


def distill(model, env_id: str, env_kwargs: dict, settings, seed: int, progress: bool = False,
            report=print) -> tuple[Demonstrations, dict]:
    """Choose the teacher's grasp per training episode, then run `settings.dagger_iterations`
    DAgger iterations into `model`'s policy. Returns all labelled steps (for the cloning loss kept
    during RL) and a summary for pretrain.json."""
    scripts = list(settings.teacher)
    seeds = [settings.seed + i for i in range(settings.episodes)]
    env = make_env(env_id, env_kwargs)
    student = model  # on the training env's observations (an asymmetric actor masks the privileged ones)
    try:
        chosen = choose_scripts(env, scripts, seeds, progress)
        teachers = {name: make_script(name, env) for name in scripts}
        counts = {name: sum(1 for c, _ in chosen if c == name) for name in scripts}
        held = sum(h for _, h in chosen)
        report(f"teacher: {held} of {len(seeds)} training episodes held by some script; it teaches "
               f"{', '.join(f'{n} {c}' for n, c in counts.items())}")
        data = Rollouts([], [], [], 0, 0)
        rng = np.random.default_rng(settings.seed)
        history = []
        for iteration in range(settings.dagger_iterations):
            beta = settings.dagger_beta ** iteration
            run = Rollouts([], [], [], 0, 0)
            episodes = progress_bar(zip(seeds, [c for c, _ in chosen]), progress, total=len(seeds), unit="ep",
                                    desc=f"DAgger {iteration + 1}/{settings.dagger_iterations} (beta {beta:.2f})")
            for episode_seed, name in episodes:
                rollout(env, student, teachers[name], episode_seed, beta, rng, float(model.gamma), run)
            for key in ("observations", "labels", "returns"):
                getattr(data, key).extend(getattr(run, key))
            demonstrations = Demonstrations(np.asarray(data.observations, dtype=np.float32),
                                            np.asarray(data.labels, dtype=np.float32),
                                            np.asarray(data.returns, dtype=np.float32), run.successes, run.episodes)
            losses = clone(model, demonstrations, settings, seed=seed + iteration, progress=progress)
            history.append({"iteration": iteration, "beta": beta, "held": run.successes, "episodes": run.episodes,
                            "steps": len(data.labels), **losses})
            report(f"DAgger {iteration + 1}/{settings.dagger_iterations}: beta {beta:.2f}, the executed grasps "
                   f"held {run.successes}/{run.episodes}; {len(data.labels)} labelled steps; actor MSE "
                   f"{losses['actor_mse']:.4f}")
    finally:
        env.close()
    summary = {"teacher": scripts, "chosen": counts, "held_by_some_script": held,
               "episodes": len(seeds), "iterations": history}
    return demonstrations, summary
