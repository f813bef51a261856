"""The ceiling: how much room a per-object choice of grasp leaves over the best fixed script.

A family of scripted grasps (`agents/grasps.FAMILY`: the LOOP and squeeze scripts at settings
that span closing velocity, gain, spread, strain target and softness) runs on the same episodes. Per object set it gives

- the best single script (what a lab gets by picking one script on these objects),
- the best script per object family (an oracle told the family: "balls like this, boxes like that"),
- the union: episodes some script of the family holds (an oracle told the episode);
- each of them again on the episodes whose object is lower than LOW_OBJECT_HEIGHT at rest (the
  ones the arm's table-contact grasp is for, envs/scenes.py), when the record has the heights.

The union minus the best single script is the room a policy that picks its grasp per object can
win; `benchmarks/bench_ceiling.py` measures it and docs/agents.md's Results report it beside the
policy. The same record of which script holds which episode labels the teacher of
`agents/training/teacher.py` on the training objects.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

from tqdm import tqdm

from bh8_gym.safe_files import read_json_bounded
from bh8_gym.agents.grasps import make_script
from bh8_gym.agents.env_factory import make_env
from bh8_gym.agents.evaluation.episodes import object_name, run_episodes
from bh8_gym.agents.evaluation.run_files import write_json_atomic
from bh8_gym.envs.objects import object_family
from bh8_gym.envs.scenes import episode_object

#: Metres: the summary's split of low objects (issue 28's target: the best script holds half of them).
LOW_OBJECT_HEIGHT = 0.03


@dataclass
class CeilingRecord:
    """Which script held which episode of one object set (episodes from `seed` on)."""

    object_set: str
    seed: int
    objects: list[str]
    families: list[str]
    success: dict[str, list[bool]] = field(default_factory=dict)
    #: Each episode's object height at rest, metres (empty in records made before it was kept).
    heights: list[float] = field(default_factory=list)

    @property
    def episodes(self) -> int:
        return len(self.objects)

    def merge(self, other: "CeilingRecord") -> None:
        """Add another record's scripts, run on the same episodes."""
        if (other.object_set, other.seed, other.objects) != (self.object_set, self.seed, self.objects):
            raise ValueError(f"records of different episodes: {other.object_set} from {other.seed} "
                             f"against {self.object_set} from {self.seed}")
        self.success.update(other.success)

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, data: dict) -> "CeilingRecord":
        record = cls(str(data["object_set"]), int(data["seed"]), [str(o) for o in data["objects"]],
                     [str(f) for f in data["families"]],
                     {str(k): [bool(s) for s in v] for k, v in data["success"].items()},
                     [float(h) for h in data.get("heights", [])])
        for name, row in record.success.items():
            if len(row) != record.episodes:
                raise ValueError(f"ceiling record: script {name!r} has {len(row)} episodes, not {record.episodes}")
        if record.heights and len(record.heights) != record.episodes:
            raise ValueError(f"ceiling record: {len(record.heights)} heights for {record.episodes} episodes")
        return record


def run_scripts(names: Iterable[str], object_set: str, episodes: int, seed: int,
                env_kwargs: dict | None = None, progress: bool = False) -> CeilingRecord:
    """Run each script of `names` on `episodes` episodes of `object_set` from `seed` (physics not
    randomised unless `env_kwargs` says so)."""
    kwargs = {"object_set": object_set, "randomize": False, **(env_kwargs or {})}
    env = make_env("BH8Grasp-v0", kwargs)
    record = None
    try:
        for name in tqdm(list(names), desc=object_set, unit="script", disable=None if progress else True):
            results = run_episodes(None, env, episodes, seed=seed, baseline=make_script(name, env),
                                   object_set=object_set)
            if record is None:
                record = CeilingRecord(object_set, seed, [r.object_name for r in results],
                                       [r.family for r in results])
            record.success[name] = [r.success for r in results]
        if record is not None:  # after the scripts: each reset places the episode's object again
            record.heights = episode_heights(env, episodes, seed)
    finally:
        env.close()
    if record is None:
        raise ValueError("no script to run")
    return record


def episode_heights(env, episodes: int, seed: int) -> list[float]:
    """The height at rest (metres) of each episode's object in `env` (reset, not run)."""
    heights = []
    for episode in range(episodes):
        env.reset(seed=seed + episode)
        heights.append(float(env.unwrapped.scene.object_extents[2]))
    return heights


def episode_objects(object_set: str, episodes: int, seed: int) -> tuple[list[str], list[str]]:
    """The object name and family of each episode (without running any)."""
    env = make_env("BH8Grasp-v0", {"object_set": object_set, "randomize": False})
    names, families = [], []
    try:
        for episode in range(episodes):
            env.reset(seed=seed + episode)
            spec = episode_object(env)
            names.append(object_name(spec))
            families.append(object_family(spec))
    finally:
        env.close()
    return names, families


def summarize_ceiling(record: CeilingRecord, scripts: Sequence[str] | None = None) -> dict:
    """Best single script, best script per family and the union, over `scripts` (default: all)."""
    names = list(scripts or record.success)
    if not names:
        raise ValueError("no scripts in the ceiling record")
    counts = {name: sum(record.success[name]) for name in names}
    best = max(names, key=lambda name: (counts[name], -names.index(name)))
    union = [any(record.success[name][i] for name in names) for i in range(record.episodes)]

    def subset(rows: list[int]) -> dict:
        """The best script on the episodes `rows`, what it and the best single script hold there, and the union."""
        held = {name: sum(record.success[name][i] for i in rows) for name in names}
        top = max(names, key=lambda name: (held[name], -names.index(name)))
        return {"episodes": len(rows), "best_script": top, "held": held[top],
                "union": sum(union[i] for i in rows), "best_single_held": held[best]}

    per_family = {family: subset([i for i, f in enumerate(record.families) if f == family])
                  for family in sorted(set(record.families))}
    low = (subset([i for i, height in enumerate(record.heights) if height < LOW_OBJECT_HEIGHT])
           if record.heights else None)
    return {"object_set": record.object_set, "seed": record.seed, "episodes": record.episodes,
            "scripts": counts, "best_single": best, "best_single_held": counts[best],
            "per_family_best_held": sum(f["held"] for f in per_family.values()),
            "union_held": sum(union), "per_family": per_family, "low_objects": low}


def teacher_choice(record: CeilingRecord, preference: Sequence[str]) -> list[str | None]:
    """Per episode, the first script of `preference` that holds it (None: none does)."""
    return [next((name for name in preference if record.success[name][i]), None) for i in range(record.episodes)]


def save_records(records: Sequence[CeilingRecord], path: Path) -> None:
    write_json_atomic(Path(path), [r.to_json() for r in records])


def load_records(path: Path) -> list[CeilingRecord]:
    data = read_json_bounded(path, 256 << 20, "ceiling records")
    if not isinstance(data, list):
        raise ValueError(f"{path}: not a list of ceiling records")
    return [CeilingRecord.from_json(item) for item in data]
