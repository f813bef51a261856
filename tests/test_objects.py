"""Object sets of the environments (bh8_gym.envs.objects): sizes, split, user files, shape cache.

Graspable sizes and masses follow the BH8-262's geometry and payload (manual App. A; SPEC.md §1:
inner link 70 mm, outer 50 mm, 2 kg per fingertip).
"""
from __future__ import annotations

import numpy as np
import pybullet
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bh8_gym.envs.objects import (
    ObjectLoader,
    ObjectSet,
    ObjectSpec,
    PrimitiveRanges,
    parse_object_file,
    RandomUrdfRanges,
    random_urdf_names,
    random_urdf_spec,
    sample_primitive,
)


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


def test_random_urdf_split_is_fixed_and_disjoint():
    """Held-out test split = folders whose names end in 0; train = the rest; no overlap."""
    train, test = random_urdf_names("train"), random_urdf_names("test")
    assert len(test) == 100 and len(train) == 899  # 900 minus the broken 168
    assert all(name.endswith("0") for name in test)
    assert not any(name.endswith("0") for name in train)
    assert not set(train) & set(test)
    with pytest.raises(ValueError, match="split"):
        random_urdf_names("validation")


def test_named_sets_sample_from_their_split():
    rng = np.random.default_rng(0)
    test_set = ObjectSet.named("test")
    for _ in range(20):
        spec = test_set.sample(rng)
        assert spec.kind == "mesh" and spec.name.startswith("random_urdf/") and spec.name.endswith("0")
    train_set = ObjectSet.named("train")
    assert not any(train_set.sample(rng).name.endswith("0") for _ in range(20))
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
    assert "168" not in random_urdf_names("train") + random_urdf_names("test")
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
    ],
)
def test_invalid_specs_raise(kwargs, message):
    with pytest.raises(ValueError, match=message):
        ObjectSpec(**kwargs)
