"""Running episodes of a policy or a scripted grasp and what each one gives (`EpisodeResult`):
success, return, length, grasp time and peak strain. `bh8 eval` (agents/evaluation/evaluate.py) reports them,
`bh8 train` validates on them and the ceiling (agents/evaluation/ceiling.py) compares scripts with them.

Metrics per episode:
  success     `info["is_success"]` at the episode's last step (the env decides: object lifted
              clear of the table and touching the hand).
  grasp time  simulated seconds from reset until the fingers stop closing: the first cycle at
              which every LOOP finger motor reports a strain rise of at least
              `GRASP_STRAIN_RISE` over its value at reset (contact load); episodes that never
              load all fingers have no grasp time and are left out of the mean.
  peak strain the largest LFS any finger reported during the episode (8-bit, §6.2.2).
Strain comes from decoding each step's `info["feedback_block"]` with the env's LoopLayout, i.e.
the bytes a real hand would send.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from bh8_gym.child_processes import check_alive

from bh8_gym.envs.objects import object_family
from bh8_gym.envs.scenes import episode_object

# LFS counts above the no-load reading that mean a finger is loaded by contact. No-load readings
# are 100-140 with per-finger offsets (SPEC.md §1), so the rise is measured from each finger's own
# reading at reset; 8 counts is well above the gauge's quantisation and below any real grasp load.
GRASP_STRAIN_RISE = 8



@dataclass
class EpisodeResult:
    object_name: str
    success: bool
    episode_return: float
    length: int
    sim_seconds: float
    grasp_time: float | None
    peak_strain: int | None
    object_set: str = ""
    family: str = ""
    safety_stop: bool = False


def object_name(spec) -> str:
    """A readable name for an episode's object (file stem, or primitive kind and size in cm)."""
    if spec is None:
        return "(no object)"
    if getattr(spec, "name", ""):
        return spec.name
    size = "x".join(f"{s * 100:.1f}" for s in spec.size)
    return f"{spec.kind} {size}cm"


class StrainTracker:
    """Follows the finger strain gauges through an episode's feedback blocks."""

    def __init__(self, layout):
        self.layout = layout
        self.indices = [i for i, (motor, name) in enumerate(layout.feedback_fields)
                        if name == "LFS" and motor in (1, 2, 3)]
        self.reset()

    def reset(self) -> None:
        self.baseline = None
        self.peak = None
        self.grasp_cycle = None
        self.cycles = 0

    def observe(self, feedback_block: bytes | None) -> None:
        """One RealTime cycle's feedback block."""
        self.cycles += 1
        if not self.indices or not feedback_block:
            return
        values = self.layout.decode_feedback(feedback_block)
        self.observe_strains(np.array([values[i] for i in self.indices]))

    def observe_strains(self, strains: np.ndarray) -> None:
        """Finger strain readings (from a feedback block, or FGET SG in supervisory mode)."""
        if self.baseline is None:
            self.baseline = strains
        peak = int(strains.max())
        self.peak = peak if self.peak is None else max(self.peak, peak)
        if self.grasp_cycle is None and np.all(strains - self.baseline >= GRASP_STRAIN_RISE):
            self.grasp_cycle = self.cycles


def run_episodes(policy, env, n_episodes: int, seed: int = 0, deterministic: bool = True,
                 baseline=None, progress: bool = False, object_set: str = "") -> list[EpisodeResult]:
    """Run `n_episodes` (seeds seed, seed+1, ...) with `policy.predict` or a scripted `baseline`.

    `env`: a single env (see env_factory.make_env), or for a deterministic policy a list of envs
    built alike: they then run that many episodes at once, one `predict` on the batch of their
    observations per step (`run_policy_batch`). `baseline`: an object with
    `run_episode(env, seed) -> (return, length, info)` for baselines that use supervisory GCL.
    With `deterministic=False` a policy's exploration noise is drawn anew for every episode
    (`reset_noise`; gSDE would otherwise repeat one perturbation in all of them). `progress`
    shows a bar on a terminal (`bh8 eval`). `object_set` labels the results.
    """
    if n_episodes < 1:
        raise ValueError(f"n_episodes must be positive, got {n_episodes!r}")
    if isinstance(env, (list, tuple)):
        if baseline is None and deterministic and len(env) > 1:
            return run_policy_batch(policy, env, n_episodes, seed, progress=progress, object_set=object_set)
        env = env[0]
    episodes = tqdm(range(n_episodes), desc="episodes", unit="ep", disable=None if progress else True, leave=False)
    tracker = StrainTracker(env.unwrapped.layout)
    results = []
    for episode in episodes:
        check_alive()
        tracker.reset()
        if baseline is not None and hasattr(baseline, "run_episode"):
            total, length, info, extra_seconds, grasp_time = baseline.run_episode(env, seed + episode, tracker)
        else:
            obs, info = env.reset(seed=seed + episode)
            if baseline is not None:
                baseline.reset(env)
            elif not deterministic and hasattr(policy, "reset_noise"):
                policy.reset_noise()
            total, length, done, extra_seconds = 0.0, 0, False, 0.0
            while not done:
                check_alive()  # a worker of this command killed meanwhile: stop now, not at the end
                if baseline is not None:
                    action = baseline.act(obs, info)
                else:
                    action, _ = policy.predict(obs, deterministic=deterministic)
                obs, reward, terminated, truncated, info = env.step(action)
                tracker.observe(info.get("feedback_block"))
                total += float(reward)
                length += 1
                done = terminated or truncated
            grasp_time = tracker_grasp_time(env, tracker)
        results.append(_episode_result(env, tracker, info, total, length, extra_seconds, grasp_time, object_set))
    return results


def tracker_grasp_time(env, tracker: StrainTracker) -> float | None:
    """Seconds from reset to the cycle the tracker saw every finger loaded (None: never)."""
    return None if tracker.grasp_cycle is None else tracker.grasp_cycle * float(env.unwrapped.cycle_seconds)


def _episode_result(env, tracker: StrainTracker, info: dict, total: float, length: int, extra_seconds: float,
                    grasp_time: float | None, object_set: str) -> EpisodeResult:
    """The result of the episode `env` has just ended (`info`: its last step's)."""
    cycle_seconds = float(env.unwrapped.cycle_seconds)
    spec = episode_object(env)
    return EpisodeResult(
        object_name=object_name(spec),
        object_set=object_set,
        family=object_family(spec) if spec is not None else "",
        safety_stop="safety_stop" in info,
        success=bool(info.get("is_success", False)),
        episode_return=total,
        length=length,
        sim_seconds=length * cycle_seconds + extra_seconds,
        grasp_time=grasp_time,
        peak_strain=tracker.peak,
    )


class _Slot:
    """One env of `run_policy_batch` and the episode it is running."""

    def __init__(self, env):
        self.env = env
        self.tracker = StrainTracker(env.unwrapped.layout)
        self.episode = None  # None: idle

    def start(self, episode: int, seed: int) -> None:
        self.episode = episode
        self.tracker.reset()
        self.observation, self.info = self.env.reset(seed=seed + episode)
        self.total, self.length = 0.0, 0


def run_policy_batch(policy, envs, n_episodes: int, seed: int = 0, progress: bool = False,
                     object_set: str = "") -> list[EpisodeResult]:
    """`run_episodes` of a deterministic policy on several envs at once: each env runs one episode
    at a time, taking the next seed when its episode ends, and every step is one `predict` on the
    observations of the envs still running.

    Why: a policy's forward pass costs nearly the same for a batch of 4 observations as for one;
    a validation evaluation takes 0.9 of the time with 4 envs (docs/benchmarks.md, "Evaluation").
    The episodes are the ones `run_episodes` runs on one env (an episode is fixed by its seed,
    tests/test_objects.py, and a deterministic policy's action by its observation), returned in
    episode order; a return can differ in its last digits where an env's earlier episodes changed
    the order of PyBullet's contacts (agents/evaluation/eval_worker.py).
    """
    slots = [_Slot(env) for env in envs]
    results: list[EpisodeResult | None] = [None] * n_episodes
    next_episode = 0
    for slot in slots[:n_episodes]:
        slot.start(next_episode, seed)
        next_episode += 1
    with tqdm(total=n_episodes, desc="episodes", unit="ep", disable=None if progress else True, leave=False) as bar:
        running = [slot for slot in slots if slot.episode is not None]
        while running:
            check_alive()
            actions, _ = policy.predict(np.stack([slot.observation for slot in running]), deterministic=True)
            for slot, action in zip(running, actions, strict=True):
                slot.observation, reward, terminated, truncated, slot.info = slot.env.step(action)
                slot.tracker.observe(slot.info.get("feedback_block"))
                slot.total += float(reward)
                slot.length += 1
                if terminated or truncated:
                    results[slot.episode] = _episode_result(slot.env, slot.tracker, slot.info, slot.total,
                                                            slot.length, 0.0,
                                                            tracker_grasp_time(slot.env, slot.tracker), object_set)
                    bar.update()
                    if next_episode < n_episodes:
                        slot.start(next_episode, seed)
                        next_episode += 1
                    else:
                        slot.episode = None
            running = [slot for slot in running if slot.episode is not None]
    return results
