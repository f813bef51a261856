"""Object sets of the environments (bh8_gym.envs.objects): sizes, split, user files, shape cache.

Graspable sizes and masses follow the BH8-262's geometry and payload (manual App. A; SPEC.md §1:
inner link 70 mm, outer 50 mm, 2 kg per fingertip).
"""
from __future__ import annotations

import math

import numpy as np
import pybullet
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bh8_gym.envs.objects import (
    ObjectSet,
    PrimitiveRanges,
    object_family,
    primitive_size_cells,
    primitive_split,
    RandomUrdfRanges,
    random_urdf_names,
    random_urdf_spec,
    sample_primitive,
)
from bh8_gym.objects import ObjectLoader, ObjectSpec, parse_object_file


@pytest.fixture
def client():
    cid = pybullet.connect(pybullet.DIRECT)
    yield cid
    pybullet.disconnect(cid)


@given(seed=st.integers(0, 2**32 - 1))
@settings(max_examples=200, deadline=None)
def test_primitives_are_graspable(seed):
    """Every procedural primitive is 3-9 cm in each extent, 50-400 g, friction 0.4-1.2."""
    spec = sample_primitive(np.random.default_rng(seed))
    ranges = PrimitiveRanges()
    assert spec.kind in ("box", "cylinder", "sphere", "capsule")
    assert all(ranges.extent[0] <= s <= ranges.extent[1] for s in spec.size)
    assert ranges.mass[0] <= spec.mass <= ranges.mass[1]
    assert ranges.friction[0] <= spec.friction <= ranges.friction[1]


def test_primitive_sampling_covers_every_kind_and_is_seeded():
    kinds = {sample_primitive(np.random.default_rng(s)).kind for s in range(60)}
    assert kinds == {"box", "cylinder", "sphere", "capsule"}
    assert sample_primitive(np.random.default_rng(7)) == sample_primitive(np.random.default_rng(7))


def test_random_urdf_splits_are_fixed_and_disjoint():
    """Test = folders whose names end in 0, validation = in 5, train = the rest; no overlap, and
    every model (but the broken 168) in exactly one."""
    train, validation, test = (random_urdf_names(split) for split in ("train", "validation", "test"))
    assert (len(train), len(validation), len(test)) == (799, 100, 100)  # 1000 minus the broken 168
    assert all(name.endswith("0") for name in test) and all(name.endswith("5") for name in validation)
    assert not any(name[-1] in "05" for name in train)
    assert len(set(train) | set(validation) | set(test)) == 999
    with pytest.raises(ValueError, match="split"):
        random_urdf_names("holdout")


@pytest.mark.parametrize("kind", ["box", "cylinder", "sphere", "capsule"])
def test_primitive_size_cells_split_each_kind(kind):
    """Each kind's 5 mm size cells fall in exactly one split; test and validation hold about 10 %
    each and at least one cell; the split is fixed (hash of the cell), not drawn with a seed."""
    every = set(primitive_size_cells(kind, None))
    splits = {split: set(primitive_size_cells(kind, split)) for split in ("train", "validation", "test")}
    assert set().union(*splits.values()) == every
    assert sum(len(cells) for cells in splits.values()) == len(every)
    for held_out in ("validation", "test"):
        assert 1 <= len(splits[held_out]) <= max(1, round(0.1 * len(every)))
    assert primitive_size_cells(kind, "test") == primitive_size_cells(kind, "test")


@given(seed=st.integers(0, 2**32 - 1), split=st.sampled_from(["train", "validation", "test"]))
@settings(max_examples=150, deadline=None)
def test_a_primitive_drawn_from_a_split_belongs_to_it(seed, split):
    spec = sample_primitive(np.random.default_rng(seed), split=split)
    assert primitive_split(spec) == split
    if spec.kind == "capsule":
        assert spec.size[1] >= spec.size[0]


def test_named_sets_sample_from_their_split():
    rng = np.random.default_rng(0)
    for name, ending in (("test", "0"), ("validation", "5")):
        objects = ObjectSet.named(name)
        for _ in range(20):
            spec = objects.sample(rng)
            assert spec.kind == "mesh" and spec.name.startswith("random_urdf/") and spec.name.endswith(ending)
            assert object_family(spec) == "random_urdf"
    assert not any(ObjectSet.named("train").sample(rng).name[-1] in "05" for _ in range(20))
    for split in ("train", "validation", "test"):
        primitives = [ObjectSet.named(f"primitives-{split}").sample(rng) for _ in range(20)]
        assert all(primitive_split(spec) == split and object_family(spec) == spec.kind for spec in primitives)
    mixed = [ObjectSet.named("mixed-test").sample(rng) for _ in range(60)]
    families = {object_family(spec) for spec in mixed}
    assert "random_urdf" in families and families - {"random_urdf"}
    assert all(spec.name.endswith("0") if object_family(spec) == "random_urdf" else primitive_split(spec) == "test"
               for spec in mixed)
    assert all(ObjectSet.named("primitives").sample(rng).kind != "mesh" for _ in range(20))
    with pytest.raises(ValueError, match="object_set"):
        ObjectSet.named("kitchen")


def test_random_urdf_models_are_scaled_into_a_graspable_size(client):
    """Loaded random URDFs: largest extent 5-8 cm, or up to 10 cm where a flat model was scaled up
    to 4 cm high; none lower than 4 cm unless the 10 cm cap stopped it."""
    loader = ObjectLoader(client, visuals=False)
    rng = np.random.default_rng(1)
    ranges = RandomUrdfRanges()
    for name in ("000", "123", "456", "990", "001", "010", "100"):
        spec = random_urdf_spec(name, rng)
        body = loader.create(spec, (0, 0, 1), (0, 0, 0, 1))
        low, high = pybullet.getAABB(body, -1, physicsClientId=client)
        extents = [h - l for l, h in zip(low, high)]
        # PyBullet pads AABBs by its contact margin (about 1 mm per side).
        assert ranges.extent[0] - 0.001 <= max(extents) <= ranges.max_extent + 0.004, (name, extents)
        assert extents[2] >= ranges.min_height - 0.001 or max(extents) >= ranges.max_extent - 0.001, (name, extents)
        assert pybullet.getDynamicsInfo(body, -1, physicsClientId=client)[0] == pytest.approx(spec.mass)


def test_models_with_broken_meshes_are_left_out_of_the_splits():
    """pybullet_data's random_urdfs/168 has NaN vertices: it is in no split, and asking for it by
    name raises a ValueError naming it instead of loading a NaN-scaled body."""
    assert all("168" not in random_urdf_names(split) for split in ("train", "validation", "test"))
    with pytest.raises(ValueError, match="168"):
        random_urdf_spec("168", np.random.default_rng(0))


def test_loader_caches_shapes_and_applies_mass_and_friction(client):
    loader = ObjectLoader(client, visuals=False)
    spec = ObjectSpec("box", (0.05, 0.06, 0.07), mass=0.2, friction=0.9)
    first = loader.create(spec, (0, 0, 1), (0, 0, 0, 1))
    shape = pybullet.getCollisionShapeData(first, -1, physicsClientId=client)[0]
    assert np.allclose(shape[3], (0.05, 0.06, 0.07))  # box dimensions (full extents)
    info = pybullet.getDynamicsInfo(first, -1, physicsClientId=client)
    assert info[0] == pytest.approx(0.2) and info[1] == pytest.approx(0.9)
    loader.remove(first)
    assert len(loader._shapes) == 1
    again = loader.create(ObjectSpec("box", (0.05, 0.06, 0.07), mass=0.3, friction=0.5), (0, 0, 1), (0, 0, 0, 1))
    assert len(loader._shapes) == 1  # same shape, new mass and friction: cache hit
    assert pybullet.getDynamicsInfo(again, -1, physicsClientId=client)[0] == pytest.approx(0.3)


@pytest.mark.parametrize(
    "spec",
    [
        ObjectSpec("sphere", (0.05,)),
        ObjectSpec("cylinder", (0.04, 0.08)),
        ObjectSpec("capsule", (0.03, 0.08)),
    ],
)
def test_primitive_bodies_have_the_specified_size(client, spec):
    body = ObjectLoader(client, visuals=True).create(spec, (0, 0, 1), (0, 0, 0, 1))
    low, high = pybullet.getAABB(body, -1, physicsClientId=client)
    height = high[2] - low[2]
    expected = spec.size[-1] if spec.kind != "sphere" else spec.size[0]
    assert height == pytest.approx(expected, abs=0.003)


def test_user_object_files(tmp_path, client):
    """URDF with a scale, and a mesh with scale and mass; bad specs raise naming the problem."""
    import pybullet_data

    urdf = f"{pybullet_data.getDataPath()}/cube_small.urdf"
    spec = parse_object_file(f"{urdf}:1.5")
    assert spec.kind == "urdf" and spec.scale == 1.5 and spec.mass is None
    body = ObjectLoader(client).create(spec, (0, 0, 1), (0, 0, 0, 1))
    low, high = pybullet.getAABB(body, -1, physicsClientId=client)
    assert high[0] - low[0] == pytest.approx(0.05 * 1.5, abs=0.004)

    mesh = tmp_path / "tetra.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n")
    spec = parse_object_file(f"{mesh}:0.05:0.12")
    assert (spec.kind, spec.scale, spec.mass) == ("mesh", 0.05, 0.12)
    body = ObjectLoader(client).create(spec, (0, 0, 1), (0, 0, 0, 1))
    assert pybullet.getDynamicsInfo(body, -1, physicsClientId=client)[0] == pytest.approx(0.12)

    with pytest.raises(ValueError, match="MASS"):
        parse_object_file(f"{mesh}:0.05")
    with pytest.raises(ValueError, match="does not exist"):
        parse_object_file(str(tmp_path / "missing.urdf"))
    with pytest.raises(ValueError, match="numbers"):
        parse_object_file(f"{urdf}:big")
    files = ObjectSet.from_files([f"{urdf}:1.5", spec])
    assert {files.sample(np.random.default_rng(s)).kind for s in range(20)} == {"urdf", "mesh"}


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(kind="cone", size=(0.05,)), "kind"),
        (dict(kind="box", size=(0.05, 0.05)), "3 positive"),
        (dict(kind="sphere", size=(-0.05,)), "positive"),
        (dict(kind="box", size=(0.05, 0.05, 0.05), mass=0.0), "mass"),
        (dict(kind="box", size=(0.05, 0.05, 0.05), friction=float("nan")), "friction"),
        (dict(kind="capsule", size=(0.06, 0.04)), "length"),
        (dict(kind="mesh", path="x.obj", mass=None), "mass"),
        (dict(kind="sphere", size=(0.05,), mass=None), "mass"),  # found by the fuzz: createMultiBody(None) raised TypeError
    ],
)
def test_invalid_specs_raise(kwargs, message):
    with pytest.raises(ValueError, match=message):
        ObjectSpec(**kwargs)


# -- hostile objects and meshes (issue 19) ------------------------------------------------------

TETRA = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"
# Each crashed PyBullet's OBJ reader (SIGSEGV: the whole process died) or loaded NaN vertices when
# PyBullet read the user's file; bh8_gym.meshes refuses them naming the line.
BAD_OBJ = {
    "face index past the vertices": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 999999\n", "line 4: face vertex 999999"),
    "face before any vertex": ("f 1 2 3\n" + TETRA, "line 1: face vertex 1"),
    "face index past a C int": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99999999999999\n", "not a face vertex"),
    "negative index past the start": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf -1 -2 -9\n", "face vertex -9"),
    "index 0": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", "face vertex 0"),
    "face of one vertex": ("v 0 0 0\nf 1\n", "has no faces"),
    "empty face": ("v 0 0 0\nf\n", "has no faces"),
    "NaN vertex": ("v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "3 decimal numbers"),
    "vertex past float32": ("v 1e39 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "beyond float32"),
    "no faces": ("v 0 0 0\nv 1 0 0\nv 0 1 0\n", "has no faces"),
    "empty file": ("", "has no faces"),
    "a NUL byte": (TETRA.replace("f 1 2 3", "f 1 2 3\0 junk"), "NUL byte"),
}


@pytest.mark.parametrize("case", sorted(BAD_OBJ))
def test_a_bad_obj_is_refused_before_pybullet_reads_it(tmp_path, client, case):
    """`f 1 2 999999` as an object file made PyBullet segfault (exit 139): meshes are read by a
    validating reader first, and a bad one is a ValueError naming the file and the line."""
    text, message = BAD_OBJ[case]
    mesh = tmp_path / "bad.obj"
    mesh.write_text(text)
    with pytest.raises(ValueError, match=message):
        parse_object_file(f"{mesh}:0.05:0.1")
    with pytest.raises(ValueError, match=message):  # the loader checks as well (specs made in code)
        ObjectLoader(client, visuals=False).create(ObjectSpec("mesh", path=str(mesh), scale=0.05), (0, 0, 1), (0, 0, 0, 1))


def test_an_env_with_a_crashing_obj_is_a_clear_error_not_a_dead_process(tmp_path):
    """The issue's attack end to end, in a child process (before the fix it died of SIGSEGV): the
    env refuses the file at make with a ValueError naming the face."""
    import subprocess
    import sys

    mesh = tmp_path / "bad.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 999999\n")
    script = ("import gymnasium as gym, bh8_gym, sys\n"
              "try:\n"
              f"    env = gym.make('BH8Grasp-v0', object_files=[{str(mesh) + ':0.05:0.1'!r}]); env.reset(seed=0)\n"
              "except ValueError as error:\n"
              "    print(error); sys.exit(2)\n")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2, (result.returncode, result.stderr[-500:])
    assert "face vertex 999999 is not one of the 3 vertices" in result.stdout


def test_binary_stl_is_checked_and_ascii_stl_refused(tmp_path, client):
    """PyBullet reads binary STL only (84 + 50 n bytes): an ASCII or truncated STL, or NaN
    vertices, is refused; a good one loads."""
    import struct

    def stl(triangles, count=None):
        body = b"".join(struct.pack("<12fH", 0, 0, 1, *[c for v in t for c in v], 0) for t in triangles)
        return b"\0" * 80 + struct.pack("<I", len(triangles) if count is None else count) + body

    triangle = ((0, 0, 0), (1, 0, 0), (0, 1, 0))
    good = tmp_path / "good.stl"
    good.write_bytes(stl([triangle, ((0, 0, 0), (0, 0, 1), (1, 0, 0))]))
    spec = parse_object_file(f"{good}:0.05:0.1")
    assert ObjectLoader(client, visuals=False).create(spec, (0, 0, 1), (0, 0, 0, 1)) >= 0
    for name, data in (("ascii.stl", b"solid x\nfacet normal 0 0 1\nendsolid x\n"),
                       ("short.stl", stl([triangle], count=5)), ("none.stl", stl([])),
                       ("nan.stl", stl([((math.nan, 0, 0), (1, 0, 0), (0, 1, 0))]))):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(ValueError, match=name):
            parse_object_file(f"{tmp_path / name}:0.05:0.1")


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(kind="sphere", size=(1e300,)), "each extent must be 0.001 to 2 m"),
        (dict(kind="box", size=(1e300, 1e300, 1e300)), "each extent must be"),
        (dict(kind="cylinder", size=(0.04, 1e-5)), "each extent must be"),
        (dict(kind="box", size=(0.05, 0.05, 0.05), mass=1e300), "mass must be 0.001 to 10 kg"),
        (dict(kind="box", size=(0.05, 0.05, 0.05), mass=1e-300), "mass must be"),
        (dict(kind="box", size=(0.05, 0.05, 0.05), friction=1e300), "friction must be 0 to 10"),
    ],
)
def test_object_specs_outside_the_physical_bounds_raise(kwargs, message):
    """Sizes 1 mm to 2 m, masses 1 g to 10 kg, friction 0 to 10 (bh8_gym.plant's bounds): far
    outside them PyBullet's solver turns the world to NaN."""
    with pytest.raises(ValueError, match=message):
        ObjectSpec(**kwargs)


def test_an_object_scaled_by_1e300_is_refused_at_make_not_a_nan_reward(tmp_path):
    """A mesh or URDF scaled by 1e300 ran an episode returning reward nan with no error: its size
    at that scale is checked when the env is made (meshes from their vertices, URDFs loaded in a
    scratch world)."""
    import gymnasium as gym
    import pybullet_data

    import bh8_gym  # noqa: F401

    mesh = tmp_path / "tetra.obj"
    mesh.write_text(TETRA)
    with pytest.raises(ValueError, match=r"tetra.obj' at scale 1e\+300 measures .* each extent must be"):
        gym.make("BH8Grasp-v0", object_files=[f"{mesh}:1e300:0.1"])
    urdf = f"{pybullet_data.getDataPath()}/cube_small.urdf"
    with pytest.raises(ValueError, match=r"cube_small.urdf' at scale 1e\+300 measures"):
        gym.make("BH8Grasp-v0", object_files=[f"{urdf}:1e300"])
    with pytest.raises(ValueError, match="at scale 1e-05 measures"):
        gym.make("BH8Grasp-v0", object_files=[f"{mesh}:0.00001:0.1"])  # a 10 µm speck


def _rss_mb() -> float:
    with open("/proc/self/statm") as handle:
        return int(handle.read().split()[1]) * 4096 / 1e6


def test_primitive_episodes_keep_the_shapes_and_the_memory_bounded(monkeypatch):
    """PyBullet never frees a collision shape, and a random primitive's never repeats: 2,000
    primitive episodes added ~2.7 KB each for good. Past WORLD_SHAPE_LIMIT shapes the env builds a
    fresh world at reset, so the shapes and the memory stay bounded."""
    import gymnasium as gym

    import bh8_gym  # noqa: F401
    from bh8_gym.envs import base

    monkeypatch.setattr(base, "WORLD_SHAPE_LIMIT", 64, raising=False)
    env = gym.make("BH8Grasp-v0", object_set="primitives").unwrapped
    try:
        for _ in range(200):  # the allocator's steady state
            env.reset()
        before = _rss_mb()
        for _ in range(2000):
            env.reset()
            assert env.scene.shapes_created <= 64
        assert _rss_mb() - before < 2.0  # 2000 episodes kept ~5.4 MB before
    finally:
        env.close()


def test_a_renewed_world_replays_a_seed_exactly(monkeypatch):
    """Contract: a seed replays exactly whatever the env ran before, across a world renewal too
    (the feedback bytes of a fresh env's episode)."""
    import gymnasium as gym

    import bh8_gym  # noqa: F401
    from bh8_gym.envs import base

    def episode_bytes(env, seed):
        _, info = env.reset(seed=seed)
        blocks = [info["feedback_block"]]
        for step in range(40):
            _, _, _, _, info = env.step(np.array([60, 200] * 3 + [0, 0], dtype=np.int16)[: env.action_space.shape[0]])
            blocks.append(info["feedback_block"])
        return blocks

    fresh = gym.make("BH8Grasp-v0", object_set="primitives").unwrapped
    used = gym.make("BH8Grasp-v0", object_set="primitives").unwrapped
    try:
        reference = episode_bytes(fresh, 7)
        monkeypatch.setattr(base, "WORLD_SHAPE_LIMIT", 4, raising=False)
        plant = used.plant
        for seed in range(6):
            used.reset(seed=100 + seed)
        assert used.plant is not plant  # the world was renewed on the way
        assert episode_bytes(used, 7) == reference
    finally:
        fresh.close()
        used.close()
