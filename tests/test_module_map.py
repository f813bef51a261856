"""The layering docs/architecture.md draws (benchmarks/draw_module_map.py reads it from the import
statements): no rooms import each other in a circle, agents/' verbs import one way (sweep ->
training -> evaluation -> deployment), and the host's side imports nothing of the simulation.
"""
from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

MAP = Path(__file__).resolve().parents[1] / "benchmarks" / "draw_module_map.py"
VERBS = ("agents/sweep/", "agents/training/", "agents/evaluation/", "agents/deployment/")
SIMULATION = {"plant/", "simulator", "firmware/", "objects", "rendering", "urdfs", "meshes", "hand_urdf"}


@pytest.fixture(scope="module")
def rooms():
    spec = importlib.util.spec_from_file_location("draw_module_map", MAP)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    lines, imports = module.read_rooms()
    return module, imports


def reaches(imports: dict[str, set[str]], room: str) -> set[str]:
    seen: set[str] = set()
    todo = [room]
    while todo:
        for used in imports[todo.pop()] - seen:
            seen.add(used)
            todo.append(used)
    return seen


def test_every_room_has_a_floor_so_no_circle(rooms):
    module, imports = rooms
    floors = module.floors_of(imports)
    assert set(floors) == set(imports) and all(floors[used] < floors[room] for room in imports for used in imports[room])


def test_a_circle_is_found_and_named(rooms):
    module, _ = rooms
    with pytest.raises(SystemExit, match="a -> b -> a"):
        module.floors_of({"a": {"b"}, "b": {"a"}})


def test_the_verbs_import_one_way(rooms):
    _, imports = rooms
    for index, verb in enumerate(VERBS):
        assert not reaches(imports, verb) & set(VERBS[:index + 1]), f"{verb} reaches a verb above it"


def test_the_host_side_reaches_no_simulation(rooms):
    """What bh8 deploy runs on a computer with only the hand: no PyBullet behind any of it (the
    client reaches the simulator only for a bh8sim:// URL, by a lazy import)."""
    _, imports = rooms
    for room in ("action_bytes", "loop_interface", "haptic_history", "realtime_codec", "safety"):
        assert not reaches(imports, room) & SIMULATION, room
