"""The ceiling family and its summary (agents/evaluation/ceiling.py) and the teacher's choice (agents/training/teacher.py)."""
from __future__ import annotations

import json

import pytest

from bh8_gym.agents.grasps import FAMILY
from bh8_gym.agents.evaluation.ceiling import CeilingRecord, load_records, save_records, summarize_ceiling


def _record():
    # 6 episodes: boxes 0-2, spheres 3-5
    return CeilingRecord("set", 100, [f"o{i}" for i in range(6)], ["box"] * 3 + ["sphere"] * 3, {
        "a": [True, True, True, False, False, True],
        "b": [False, True, False, True, True, False],
        "c": [False, False, False, False, False, False],
    })


def test_the_summary_counts_best_single_per_family_and_union():
    summary = summarize_ceiling(_record())
    assert summary["scripts"] == {"a": 4, "b": 3, "c": 0}
    assert summary["best_single"] == "a" and summary["best_single_held"] == 4
    # boxes: a holds 3; spheres: b holds 2 -> 5
    assert summary["per_family"]["box"]["best_script"] == "a"
    assert summary["per_family"]["sphere"]["best_script"] == "b"
    assert summary["per_family_best_held"] == 5
    assert summary["union_held"] == 6
    # over a subset of the scripts
    assert summarize_ceiling(_record(), ["b", "c"])["union_held"] == 3


def test_the_summary_splits_the_objects_lower_than_3_cm():
    """Issue 28's target is on the objects lower than 3 cm at rest: the best script on those, the
    overall best single script's count on them, and the union there; none without heights."""
    assert summarize_ceiling(_record())["low_objects"] is None
    record = _record()
    record.heights = [0.01, 0.02, 0.05, 0.025, 0.06, 0.04]  # episodes 0, 1, 3 are low
    low = summarize_ceiling(record)["low_objects"]
    assert low == {"episodes": 3, "best_script": "a", "held": 2, "union": 3, "best_single_held": 2}
    assert summarize_ceiling(record, ["b", "c"])["low_objects"]["held"] == 2
    assert CeilingRecord.from_json(json.loads(json.dumps(record.to_json()))) == record
    bad = record.to_json()
    bad["heights"] = [0.01]
    with pytest.raises(ValueError, match="1 heights"):
        CeilingRecord.from_json(bad)


def test_records_round_trip_and_refuse_other_episodes(tmp_path):
    record = _record()
    save_records([record], tmp_path / "ceiling.json")
    assert load_records(tmp_path / "ceiling.json")[0] == record
    other = CeilingRecord("set", 101, record.objects, record.families, {"d": [True] * 6})
    with pytest.raises(ValueError, match="different episodes"):
        record.merge(other)
    bad = record.to_json()
    bad["success"]["a"] = [True]
    with pytest.raises(ValueError, match="1 episodes"):
        CeilingRecord.from_json(json.loads(json.dumps(bad)))


def test_the_family_has_a_dozen_object_blind_scripts():
    """Issue 27: at least 12 scripts; every one builds on the grasp env (a wrong setting would be a
    ValueError naming it) and acts from the feedback blocks only."""
    from bh8_gym.agents.grasps import make_script
    from bh8_gym.agents.env_factory import make_env

    assert len(FAMILY) >= 12
    env = make_env("BH8Grasp-v0", {"randomize": False})
    try:
        observation, info = env.reset(seed=0)
        for name in FAMILY:
            script = make_script(name, env)
            action = script.act(observation, info)
            assert env.action_space.contains(action), name
        with pytest.raises(ValueError, match="unknown script"):
            make_script("nope", env)
    finally:
        env.close()


def test_run_scripts_records_what_bh8_eval_measures():
    """The ceiling runs a script exactly as `bh8 eval --baseline` does: same episodes, same outcomes."""
    from bh8_gym.agents.evaluation.baselines import make_baseline
    from bh8_gym.agents.evaluation.ceiling import run_scripts
    from bh8_gym.agents.env_factory import make_env
    from bh8_gym.agents.evaluation.episodes import run_episodes

    record = run_scripts(["loop"], "primitives-validation", 2, 20000)
    env = make_env("BH8Grasp-v0", {"object_set": "primitives-validation", "randomize": False})
    try:
        results = run_episodes(None, env, 2, seed=20000, baseline=make_baseline("loop", env))
    finally:
        env.close()
    assert record.objects == [r.object_name for r in results]
    assert record.success["loop"] == [r.success for r in results]


def test_the_teacher_teaches_objects_alike_alike(monkeypatch):
    """agents/training/teacher.choose_scripts: of the scripts that hold an episode, the one that holds most
    of that object family; the family's best where none holds it."""
    from bh8_gym.agents.training import teacher

    outcomes = {"a": [True, True, False, True, False], "b": [True, False, True, True, False]}
    families = ["box", "box", "box", "sphere", "sphere"]
    calls = {"a": iter(outcomes["a"]), "b": iter(outcomes["b"])}
    current = {}

    monkeypatch.setattr(teacher, "make_script", lambda name, env: name)
    monkeypatch.setattr(teacher, "run_script", lambda env, script, seed: (current.update(seed=seed), next(calls[script]))[1])
    monkeypatch.setattr("bh8_gym.envs.scenes.episode_object", lambda env: families[current["seed"]])
    monkeypatch.setattr("bh8_gym.envs.objects.object_family", lambda spec: spec)
    chosen = teacher.choose_scripts(None, ["a", "b"], range(5))
    # boxes: a holds 2, b holds 2 -> a (listed first) where both hold; spheres: b holds 1, a 1
    assert chosen == [("a", True), ("a", True), ("b", True), ("a", True), ("a", False)]
