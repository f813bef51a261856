"""Objects lie at rest before the hand comes (bh8_gym/envs/resting.py): a pick pipeline plans the
approach from the pose the object lies in, so the scene must not set a mesh down in a pose it then
falls out of."""
from __future__ import annotations

import os

import numpy as np
import pybullet
import pytest

from bh8_gym.envs.objects import random_urdf_spec
from bh8_gym.envs.resting import IDENTITY, resting_orientation, resting_pose
from bh8_gym.objects import ObjectLoader, ObjectSpec

# random_urdfs models that tip over when set down as loaded (a plate on its edge, a blob on a point)
TIPPING = ("015", "025", "135", "165", "195", "215")


def _tilt_after_a_second(spec, orientation) -> float:
    """Degrees the object tilts in 1 s after being set down on a plane in `orientation`."""
    client = pybullet.connect(pybullet.DIRECT)
    try:
        pybullet.setGravity(0, 0, -9.81, physicsClientId=client)
        pybullet.createMultiBody(0, pybullet.createCollisionShape(pybullet.GEOM_PLANE, physicsClientId=client),
                                 physicsClientId=client)
        body = ObjectLoader(client, visuals=False).create(spec, (0, 0, 1), orientation)
        low, _ = pybullet.getAABB(body, -1, physicsClientId=client)
        pybullet.resetBasePositionAndOrientation(body, (0, 0, 1 - low[2] + 1e-4), orientation, physicsClientId=client)
        for _ in range(240):
            pybullet.stepSimulation(physicsClientId=client)
        turned = pybullet.getBasePositionAndOrientation(body, physicsClientId=client)[1]
        # the tilt: how far the body's own "up" moved (a turn about the vertical is no tilt)
        before, after = (np.reshape(pybullet.getMatrixFromQuaternion(q), (3, 3))[2] for q in (orientation, turned))
        return float(np.degrees(np.arccos(np.clip(np.dot(before, after), -1.0, 1.0))))
    finally:
        pybullet.disconnect(client)


@pytest.mark.parametrize("name", TIPPING)
def test_a_mesh_set_down_in_its_resting_pose_stays_there(name):
    spec = random_urdf_spec(name, np.random.default_rng(0))
    assert _tilt_after_a_second(spec, IDENTITY) > 10.0, "the model should tip over as loaded"
    assert _tilt_after_a_second(spec, resting_orientation(spec)) < 3.0


def test_the_resting_pose_is_the_meshes_and_primitives_keep_theirs():
    spec = random_urdf_spec("015", np.random.default_rng(0))
    bigger = ObjectSpec(kind="mesh", path=spec.path, scale=spec.scale * 1.5, mass=0.2)
    assert resting_pose(bigger) == resting_pose(spec)  # cached per file: the pose does not depend on scale
    assert resting_pose(spec).extents[2] < resting_pose(spec).extents.max()  # it lies on its side
    for kind, size in (("box", (0.05, 0.04, 0.03)), ("cylinder", (0.05, 0.08)), ("sphere", (0.05,))):
        assert resting_orientation(ObjectSpec(kind, size, mass=0.1)) == IDENTITY


def test_a_flat_lying_model_is_scaled_to_the_reachable_height():
    """RandomUrdfRanges.min_height applies to the height at rest: model 015 lies 1.4 cm high
    at its drawn size, so it is scaled up (within max_extent)."""
    spec = random_urdf_spec("015", np.random.default_rng(0))
    height = resting_pose(spec).extents[2] * spec.scale
    assert height > 0.03



def _box_obj(low, high) -> str:
    """A box from corner `low` to corner `high` (its mass centre is the file's origin)."""
    corners = [(x, y, z) for x in (low[0], high[0]) for y in (low[1], high[1]) for z in (low[2], high[2])]
    faces = ["1 2 4 3", "5 7 8 6", "1 5 6 2", "3 4 8 7", "1 3 7 5", "2 6 8 4"]
    return "".join(f"v {x} {y} {z}\n" for x, y, z in corners) + "".join(f"f {face}\n" for face in faces)


def test_the_resting_pose_follows_the_files_content_not_its_path(tmp_path):
    """Issue 32 item 12: the cache was keyed by path, so a mesh file rewritten in place kept the
    pose and extents of what it used to hold. Keyed by content, the new content is settled. A tall
    box centred on its origin stands; the same box beside its origin (its mass centre outside its
    footprint) falls on its side. Both are settled at the same size, so a shape cached by path and
    scale would be stale as well; the old content is still remembered."""
    standing = _box_obj((-0.01, -0.015, 0.0), (0.01, 0.015, 0.08))
    falling = _box_obj((0.01, -0.015, 0.0), (0.03, 0.015, 0.08))
    reference = tmp_path / "falling.obj"
    reference.write_text(falling)
    expected = resting_pose(ObjectSpec(kind="mesh", path=str(reference), scale=1.0, mass=0.1))
    part = tmp_path / "part.obj"
    part.write_text(standing)
    spec = ObjectSpec(kind="mesh", path=str(part), scale=1.0, mass=0.1)
    stands = resting_pose(spec)
    assert stands.extents[2] > 0.08 and expected.extents[2] < 0.05  # the two rest differently
    stat = part.stat()
    part.write_text(falling.replace("\nf", "\n# rewritten\nf", 1))  # new bytes, the falling box's shape
    os.utime(part, ns=(stat.st_atime_ns, stat.st_mtime_ns))  # the same time, too
    assert resting_pose(spec).orientation == expected.orientation
    np.testing.assert_allclose(resting_pose(spec).extents, expected.extents)
    part.write_text(standing)
    assert resting_pose(spec) is stands
