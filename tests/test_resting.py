"""Objects lie at rest before the hand comes (bh8_gym/envs/resting.py): a pick pipeline plans the
approach from the pose the object lies in, so the scene must not set a mesh down in a pose it then
falls out of."""
from __future__ import annotations

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
