"""How an object lies on a table before the hand comes: the pose it settles into under gravity.

A pick pipeline sees the object at rest and plans the approach (grasp yaw, palm height) from that
pose. pybullet_data's random_urdfs come in arbitrary orientations: placed as loaded, 56 of the 100
validation models tip over by more than 10° within a second (a plate on its edge, a blob on a
point), so a palm height planned from the loaded pose met an object that had fallen away from the
fingers. `resting_pose(spec)` drops the mesh once (at a fixed size: the pose it settles into
does not depend on its scale) on a plane in a private PyBullet world and returns the orientation it
comes to rest in and its extents lying so (cached by the mesh's content, a SHA-256 of the clean OBJ
PyBullet is given: the same mesh always rests the same way on one machine, and a file rewritten in
place is settled again; the scale it is settled at follows from those bytes). Set down so, 4 of the 100
validation models still tilt more than 10° in a second (a marginal facet at their own size and
friction), against 56 as loaded. Primitives are made lying still (a box on a face, a cylinder on its end, a capsule on its side), so they keep
their orientation.
"""
from __future__ import annotations

import hashlib
from dataclasses import replace
from typing import NamedTuple

import numpy as np
import pybullet

from bh8_gym.meshes import read_mesh
from bh8_gym.objects import ObjectLoader, ObjectSpec

IDENTITY = (0.0, 0.0, 0.0, 1.0)
SETTLED_SIZE = 0.06  # metres: the largest extent of a mesh as it is dropped
SETTLE_STEP = 1.0 / 240.0  # seconds (PyBullet's default step)
SETTLE_SECONDS = 2.0  # at most; a blob that is still rocking after this is taken as it is
STILL_SPEED = 1e-3  # m/s and rad/s: at rest once both stay under this ...
STILL_STEPS = 24  # ... for this many steps (0.1 s)
SETTLE_FRICTION = 0.8  # the middle of the objects' friction range (envs.objects)
WORLD_SHAPES = 256  # a fresh private world after this many shapes (PyBullet keeps each shape)


class RestingPose(NamedTuple):
    orientation: tuple[float, float, float, float]  # (x, y, z, w) from the file's frame
    extents: np.ndarray | None  # the axis-aligned extents lying so, in the file's units (meshes)


_poses: dict[bytes, RestingPose] = {}  # by the SHA-256 of the mesh file's bytes
_world: dict[str, object] = {}


def resting_pose(spec: ObjectSpec) -> RestingPose:
    """How `spec` lies on a table once set down from its loaded orientation (primitives: as made)."""
    if spec.kind != "mesh":
        return RestingPose(IDENTITY, None)
    mesh = read_mesh(spec.path)
    key = hashlib.sha256(mesh.obj_bytes).digest()  # the geometry PyBullet is given
    if key not in _poses:
        low, high = mesh.bounds
        scale = SETTLED_SIZE / float(np.max(high - low))
        orientation, extents = _settle(replace(spec, scale=scale, mass=0.1))
        _poses[key] = RestingPose(orientation, extents / scale)
    return _poses[key]


def resting_orientation(spec: ObjectSpec) -> tuple[float, float, float, float]:
    """The orientation (x, y, z, w) in which `spec` lies at rest on a table."""
    return resting_pose(spec).orientation


def _private_world() -> int:
    if _world.get("client") is None or _world["shapes"] >= WORLD_SHAPES:
        if _world.get("client") is not None:
            pybullet.disconnect(physicsClientId=_world["client"])
        client = pybullet.connect(pybullet.DIRECT)
        pybullet.setGravity(0.0, 0.0, -9.81, physicsClientId=client)
        pybullet.setTimeStep(SETTLE_STEP, physicsClientId=client)
        plane = pybullet.createCollisionShape(pybullet.GEOM_PLANE, physicsClientId=client)
        pybullet.createMultiBody(0.0, plane, physicsClientId=client)
        _world.update(client=client, shapes=0)
    return _world["client"]


def _settle(spec: ObjectSpec) -> tuple[tuple[float, float, float, float], np.ndarray]:
    client = _private_world()
    # A loader of its own each time: a loader's shape cache is keyed by path, and a file rewritten
    # in place must be read again (PyBullet reads our clean copy, named by its content).
    loader = ObjectLoader(client, visuals=False)
    body = loader.create(spec, (0.0, 0.0, 1.0), IDENTITY)
    _world["shapes"] += loader.shapes_created
    try:
        low, _ = pybullet.getAABB(body, -1, physicsClientId=client)
        pybullet.resetBasePositionAndOrientation(body, (0.0, 0.0, 1.0 - low[2] + 1e-4), IDENTITY,
                                                 physicsClientId=client)
        pybullet.changeDynamics(body, -1, lateralFriction=SETTLE_FRICTION, physicsClientId=client)
        still = 0
        for _ in range(int(SETTLE_SECONDS / SETTLE_STEP)):
            pybullet.stepSimulation(physicsClientId=client)
            linear, angular = pybullet.getBaseVelocity(body, physicsClientId=client)
            speed = max(sum(v * v for v in linear), sum(w * w for w in angular)) ** 0.5
            still = still + 1 if speed < STILL_SPEED else 0
            if still >= STILL_STEPS:
                break
        orientation = tuple(float(q) for q in pybullet.getBasePositionAndOrientation(body, physicsClientId=client)[1])
        pybullet.resetBasePositionAndOrientation(body, (0.0, 0.0, 1.0), orientation, physicsClientId=client)
        low, high = pybullet.getAABB(body, -1, physicsClientId=client)
        return orientation, np.subtract(high, low)
    finally:
        loader.remove(body)
