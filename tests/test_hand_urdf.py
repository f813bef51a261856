"""The generated BH8-262 URDF (manual §9.5 Tables 8-9, §9.6, App. A; SPEC.md §1)."""
from __future__ import annotations

import xml.etree.ElementTree as ET
from math import radians

import numpy as np
import pybullet as p
import pytest

from bh8_gym import hand_urdf, pybullet_files
from bh8_gym import kinematics as kin


@pytest.fixture(scope="module")
def robot():
    return ET.fromstring(hand_urdf.generate_urdf())


@pytest.fixture(scope="module")
def loaded():
    client = p.connect(p.DIRECT)
    flags = p.URDF_USE_INERTIA_FROM_FILE | p.URDF_USE_IMPLICIT_CYLINDER  # as the plant loads it
    with pybullet_files.written([(hand_urdf.urdf_bytes(), ".urdf")]) as (path,):
        body = p.loadURDF(path, useFixedBase=False, flags=flags, physicsClientId=client)
    yield client, body
    p.disconnect(client)


def test_committed_urdf_equals_generator_output():
    """assets/bh8_262.urdf is the generator's output (one source of truth: bh8_gym.kinematics)."""
    assert hand_urdf.default_output_path().read_text() == hand_urdf.generate_urdf()


def test_generator_cli_writes_the_text(tmp_path):
    """`python -m bh8_gym.hand_urdf --output PATH` writes exactly generate_urdf()."""
    target = tmp_path / "hand.urdf"
    assert hand_urdf.main(["--output", str(target)]) == 0
    assert target.read_text() == hand_urdf.generate_urdf()


def test_eight_revolute_joints_with_manual_limits(robot):
    """§9.6 / App. A: 8 joints; inner 0-140°, outer 0-48°, spread 0-180°; F3 does not spread (SPEC §1)."""
    revolute = [j for j in robot.findall("joint") if j.get("type") == "revolute"]
    assert [j.get("name") for j in revolute] == list(hand_urdf.JOINT_NAMES)
    expected = {"spread": 180.0, "inner": 140.0, "outer": 48.0}
    for joint in revolute:
        kind = joint.get("name").split("_")[1]
        limit = joint.find("limit")
        assert float(limit.get("lower")) == 0.0
        assert float(limit.get("upper")) == pytest.approx(radians(expected[kind]), abs=1e-8)
    assert not any(j.get("name").startswith("f3_spread") for j in robot.findall("joint"))


def test_total_mass_is_app_a(robot):
    """App. A: the BarrettHand weighs 1.18 kg."""
    total = sum(float(link.find("inertial/mass").get("value")) for link in robot.findall("link"))
    assert total == pytest.approx(1.18, abs=0.005)


def test_inertias_are_physical(robot):
    """Every inertia is positive and satisfies the triangle inequality (a real rigid body)."""
    for link in robot.findall("link"):
        inertia = link.find("inertial/inertia")
        ixx, iyy, izz = (float(inertia.get(k)) for k in ("ixx", "iyy", "izz"))
        assert min(ixx, iyy, izz) > 0
        assert ixx + iyy >= izz and iyy + izz >= ixx and ixx + izz >= iyy


def _link_indices(client, body):
    return {p.getJointInfo(body, i, physicsClientId=client)[12].decode(): i for i in range(p.getNumJoints(body, physicsClientId=client))}


def test_pybullet_link_frames_match_forward_kinematics(loaded):
    """PyBullet's link frames equal kinematics.link_frames (Equations 1-2, Table 9) within 1 mm."""
    client, body = loaded
    joints = {p.getJointInfo(body, i, physicsClientId=client)[1].decode(): i for i in range(p.getNumJoints(body, physicsClientId=client))}
    links = _link_indices(client, body)
    base_position, base_orientation = p.getBasePositionAndOrientation(body, physicsClientId=client)
    com = p.getDynamicsInfo(body, -1, physicsClientId=client)[3]
    inverse = p.invertTransform(com, (0, 0, 0, 1))
    wrist = p.multiplyTransforms(base_position, base_orientation, *inverse)
    to_wrist = p.invertTransform(*wrist)
    rng = np.random.default_rng(7)
    for _ in range(25):
        spread = rng.uniform(0, np.pi)
        angles = {f: (spread, rng.uniform(0, radians(140)), rng.uniform(0, radians(48))) for f in kin.FINGERS}
        for f, (t1, t2, t3) in angles.items():
            if f != 3:
                p.resetJointState(body, joints[f"f{f}_spread_joint"], t1, physicsClientId=client)
            p.resetJointState(body, joints[f"f{f}_inner_joint"], t2, physicsClientId=client)
            p.resetJointState(body, joints[f"f{f}_outer_joint"], t3, physicsClientId=client)
        for f, (t1, t2, t3) in angles.items():
            expected = kin.link_frames(f, t1, t2, t3)
            for frame, name in zip(expected, ("knuckle", "inner", "outer", "tip")):
                state = p.getLinkState(body, links[f"f{f}_{name}"], computeForwardKinematics=True, physicsClientId=client)
                position, orientation = p.multiplyTransforms(*to_wrist, state[4], state[5])
                rotation = np.array(p.getMatrixFromQuaternion(orientation)).reshape(3, 3)
                assert np.allclose(position, frame[:3, 3], atol=1e-3), (f, name)
                assert np.allclose(rotation, frame[:3, :3], atol=1e-3), (f, name)


def test_fingers_at_full_spread_are_side_by_side_with_gaps(loaded):
    """SPEC §1: at full spread F1 (x=-25 mm), F3 (x=0) and F2 (x=+25 mm) lie side by side, not touching
    (links 21 mm wide, 4 mm apart)."""
    client, body = loaded
    joints = {p.getJointInfo(body, i, physicsClientId=client)[1].decode(): i for i in range(p.getNumJoints(body, physicsClientId=client))}
    links = _link_indices(client, body)
    for f in (1, 2):
        p.resetJointState(body, joints[f"f{f}_spread_joint"], np.pi, physicsClientId=client)
    for f in kin.FINGERS:
        p.resetJointState(body, joints[f"f{f}_inner_joint"], radians(70), physicsClientId=client)
        p.resetJointState(body, joints[f"f{f}_outer_joint"], radians(30), physicsClientId=client)
    p.performCollisionDetection(physicsClientId=client)
    for a, b in ((1, 3), (2, 3)):
        for part_a in ("knuckle", "inner", "outer"):
            for part_b in ("knuckle", "inner", "outer"):
                close = p.getClosestPoints(body, body, 0.01, links[f"f{a}_{part_a}"], links[f"f{b}_{part_b}"], physicsClientId=client)
                # The knuckle housings are 0.4 mm apart (CAD; their contact is off: NO_CONTACT_PAIRS).
                gap = 0.0 if part_a == part_b == "knuckle" else 0.002
                assert all(point[8] > gap for point in close), (a, part_a, b, part_b)


def test_finger_sweep_depth_is_how_deep_a_closing_finger_reaches():
    """FINGER_SWEEP_DEPTH (the grasp scene keeps fingertips off the table with it): the deepest point
    any finger's collision shapes reach below the palm face along the closing path (3:1 coupling,
    manual §9.5 Eq. 4-5), measured against a floor with PyBullet's closest-point query, within 0.5 mm."""
    from bh8_gym.plant import HandPlant, PlantParameters

    plant = HandPlant(params=PlantParameters(table=False))
    try:
        hand, cid = plant.hand_id, plant.client
        wrist, _ = plant.wrist_pose()
        palm_face = wrist[2] - hand_urdf.PALM_TOP
        floor_shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=[1, 1, 0.05], physicsClientId=cid)
        floor = p.createMultiBody(0, floor_shape, -1, [0, 0, palm_face - 0.25], physicsClientId=cid)
        joints = {p.getJointInfo(hand, j, physicsClientId=cid)[1].decode(): j
                  for j in range(p.getNumJoints(hand, physicsClientId=cid))}
        deepest = 0.0
        for counts in range(0, 17_000, 50):
            inner, outer = kin.finger_angles(counts)
            for finger in (1, 2, 3):
                p.resetJointState(hand, joints[f"f{finger}_inner_joint"], inner, physicsClientId=cid)
                p.resetJointState(hand, joints[f"f{finger}_outer_joint"], outer, physicsClientId=cid)
            gap = min(c[8] for c in p.getClosestPoints(hand, floor, 0.5, physicsClientId=cid))
            deepest = max(deepest, 0.2 - gap)
        assert deepest == pytest.approx(hand_urdf.FINGER_SWEEP_DEPTH, abs=5e-4)
    finally:
        plant.close()
