"""The PyBullet plant's drive train, clutch, sensors and state (SPEC.md §1, §8; manual §9.3-§9.5, §2, App. A).

The plant is driven directly with simple test-local control (no firmware).
"""
from __future__ import annotations

from math import radians

import numpy as np
import pybullet as p
import pytest

from bh8_gym.objects import ObjectError, ObjectPlacement, ObjectSpec, add_object, add_object_from_spec, parse_object_spec
from bh8_gym.plant import HandPlant, PlantError, PlantParameters

MCV_100 = 100 / 16 / 256e-6  # counts/s: 6.25 counts per 256 µs sample (SPEC §4)
MCV_40 = 40 / 16 / 256e-6
IVEL_300_FRACTION = 10 / 4 * (300 / 16) / 127  # HCTL velocity mode at the stop: FPG/4 x error / 127


def run(plant, seconds, each=None):
    for _ in range(int(round(seconds / plant.dt))):
        plant.step()
        if each is not None:
            each()


def init_finger(plant, motor):
    """Like HI: slam the finger open against its stop at IVEL 300 twice (IHIT 2), preloading the clutch,
    then back off IOFF 50 counts (§5.3.4 IOFF)."""
    for _ in range(2):
        plant.set_drive(motor, -54_000.0, IVEL_300_FRACTION)
        run(plant, 0.6)
        plant.set_drive(motor, 3_000.0, IVEL_300_FRACTION)
        run(plant, 0.1)
    plant.set_drive(motor, -54_000.0, IVEL_300_FRACTION)
    run(plant, 0.3)
    plant.back_off_stop(motor, 50.0)


def link_pose(plant, name):
    state = p.getLinkState(plant.hand_id, plant._link_index_by_name[name], computeForwardKinematics=True, physicsClientId=plant.client)
    return state[4], state[5]


def obstacle_on_inner_link(plant, inner_degrees=60.0):
    """A sphere fixed in the world where F3's inner link will be at `inner_degrees`."""
    saved = plant.joint_angles()
    angles = saved.copy()
    angles[6], angles[7] = radians(inner_degrees), radians(inner_degrees / 3)
    plant.set_joint_angles(angles)
    position, orientation = link_pose(plant, "f3_inner")
    centre, _ = p.multiplyTransforms(position, orientation, (0.040, 0.0185, 0.0), (0, 0, 0, 1))
    plant.set_joint_angles(saved)
    return add_object(plant, ObjectSpec("sphere", (0.016,), friction=None), position=centre, fixed=True)


@pytest.fixture
def plant():
    with HandPlant(seed=0) as hand:
        yield hand


def test_free_close_keeps_the_3_to_1_coupling(plant):
    """§9.5 Equation 4, SPEC §1: clutch engaged, inner = M/125°, outer relative = M/375° (3:1); M = 93.75 x outer-to-palm."""
    plant.set_drive(3, MCV_100, 1.0)
    for _ in range(5):
        run(plant, 0.1)
        angles = np.degrees(plant.joint_angles())
        inner, outer = angles[6], angles[7]
        counts = plant.motor_positions()[2]
        assert plant.clutch_engaged(3)
        assert inner > 5.0
        assert outer == pytest.approx(inner / 3.0, abs=0.3)
        assert counts == pytest.approx(125.0 * inner, abs=40.0)
        assert counts == pytest.approx(93.75 * (inner + outer), abs=1.0)
    assert plant.motor_velocities()[2] == pytest.approx(MCV_100, rel=0.03)


def test_finger_speed_allows_app_a_timing(plant):
    """App. A: open to closed in about 1 s at MCV 100; spread 180° in about 0.3 s at 60. Closed is the
    palm: §8 puts the default CT (17,000 counts) at or just beyond the palm surface, where the pad stops."""
    plant.set_drive(1, MCV_100, 1.0)
    plant.set_drive(4, 60 / 16 / 256e-6, 1.0)
    run(plant, 0.3)
    assert plant.motor_positions()[3] == pytest.approx(3150.0, abs=30.0)
    run(plant, 0.3)
    assert plant.motor_positions()[0] == pytest.approx(0.6 * MCV_100, rel=0.03)
    run(plant, 0.4)  # 17,000 counts at 24,414/s: 0.70 s, within App. A's "about 1 s"
    assert 17_000.0 < plant.motor_positions()[0] < 17_200.0  # stopped by the palm, short of the 140° stop
    gap = p.getClosestPoints(plant.hand_id, plant.hand_id, 0.01, -1, plant._link_index_by_name["f1_outer"],
                             physicsClientId=plant.client)
    assert -0.001 < min(c[8] for c in gap) < 0.0005  # on the palm face, not through it


def test_breakaway_on_an_inner_link_obstacle_and_reengagement(plant):
    """§9.3.1 / SPEC §1: an obstacle stops the inner link near 60°, the clutch slips, the inner link stays
    (worm) while the outer keeps closing; opening re-engages the clutch and both links open together."""
    obstacle_on_inner_link(plant)
    init_finger(plant, 3)
    assert plant.clutch_preload(3) > 0.0
    plant.set_drive(3, MCV_100, 1.0)
    run(plant, 0.8)
    assert not plant.clutch_engaged(3)
    breakaway = plant.breakaway_position(3)
    assert breakaway is not None
    inner_at_breakaway = breakaway / 125.0
    assert 50.0 < inner_at_breakaway < 62.0
    inner_track, outer_track = [], []
    run(plant, 0.4, lambda: (inner_track.append(np.degrees(plant.joint_angles()[6])), outer_track.append(np.degrees(plant.joint_angles()[7]))))
    assert max(inner_track) - min(inner_track) < 2.0
    assert abs(inner_track[-1] - inner_at_breakaway) < 2.0
    assert outer_track[-1] == pytest.approx(48.0, abs=0.5)  # the outer link closed to its own stop
    assert plant.motor_positions()[2] > breakaway + 500.0
    assert plant.clutch_preload(3) == 0.0  # manual §8: premature breakaway until fully opened again
    plant.set_drive(3, -MCV_100, 1.0)
    run(plant, 1.5)
    assert plant.clutch_engaged(3)
    angles = np.degrees(plant.joint_angles())
    assert angles[6] < 1.0 and angles[7] < 1.0
    assert abs(plant.motor_positions()[2]) < 20.0
    assert plant.clutch_preload(3) > 0.0  # driven against the open stop again


def test_the_preload_of_an_open_is_its_own_blow_not_an_earlier_opens():
    """§9.3.1 and manual §8 (opening against the stop preloads the clutch; docs/modelling.md): the
    rotor's impact on the open stop is what this open lost there. A finger that slammed open, was
    unwound (back_off_stop, as HI's move to 0) and driven closed for 8 ms, then opened from 0.5° at
    5 % duty preloads less than the same open from 1° with no such history: the earlier open's
    speed is forgotten once the motor turns closed (issue 42; it was remembered for 0.5 s, and gave
    the preload limit)."""
    def preload_after_open(history: bool) -> float:
        with HandPlant(PlantParameters(initial_preload=0.0), seed=0) as plant:
            angles = np.zeros(8)
            inner, outer = plant.joint_names.index("f1_inner_joint"), plant.joint_names.index("f1_outer_joint")
            angles[inner], angles[outer] = radians(8.0 if history else 1.0), radians((8.0 if history else 1.0) / 3)
            plant.set_joint_angles(angles)
            if history:
                plant.set_drive(1, -40000.0, 1.0)
                run(plant, 0.06)
                plant.back_off_stop(1, 500.0)
                plant.set_drive(1, 7000.0, 1.0)
                run(plant, 0.008)
            assert plant.joint_angles()[inner] <= radians(1.0)
            plant.set_drive(1, -40000.0, 0.05)
            run(plant, 0.12)
            return plant.clutch_preload(1)

    fresh, after_a_slam = preload_after_open(False), preload_after_open(True)
    assert 0.5 < after_a_slam <= fresh < PlantParameters().preload_limit


@pytest.mark.parametrize("mcv, breaks_away", [(20, False), (35, False), (40, True), (60, True)])
def test_breakaway_from_mcv_40_up(plant, mcv, breaks_away):
    """Manual §8 troubleshooting ("The TorqueSwitch does not breakaway properly ... The close velocity is
    too slow. Increase the close velocity greater than or equal to 40") and SPEC §8: after a default HI,
    a close at MCV 40 or more breaks away on an obstacle at the inner link; a slower one stalls on it,
    the clutch engaged and the 3:1 coupling kept."""
    obstacle_on_inner_link(plant)
    init_finger(plant, 3)
    plant.set_drive(3, mcv / 16 / 256e-6, 1.0)
    run(plant, 1.6)
    assert plant.clutch_engaged(3) != breaks_away
    inner, outer = np.degrees(plant.joint_angles()[6:8])
    assert 50.0 < inner < 62.0
    if not breaks_away:
        assert outer == pytest.approx(inner / 3.0, abs=1.0)


def test_blocked_outer_link_stalls_the_whole_finger(plant):
    """SPEC §1 / App. B FAQ: if the fingertip makes first contact the finger stalls (no breakaway)."""
    angles = plant.joint_angles()
    angles[6], angles[7] = radians(45.0), radians(15.0)
    plant.set_joint_angles(angles)
    position, orientation = link_pose(plant, "f3_tip")
    centre, _ = p.multiplyTransforms(position, orientation, (0.0, 0.0, 0.013), (0, 0, 0, 1))
    plant.set_joint_angles(plant.joint_angles() * 0.0)
    add_object(plant, ObjectSpec("sphere", (0.024,), friction=None), position=centre, fixed=True)
    init_finger(plant, 3)
    plant.set_drive(3, MCV_100, 1.0)
    run(plant, 1.0)
    inner, outer = np.degrees(plant.joint_angles()[6:8])
    assert plant.clutch_engaged(3)
    assert inner < 47.0 and outer == pytest.approx(inner / 3.0, abs=1.5)


def test_unpowered_finger_is_not_back_drivable_but_the_spread_is(plant):
    """SPEC §1: finger worm drives hold an unpowered finger under load; the spread is back-drivable and
    F1/F2 spread symmetrically (§9.3.2)."""
    angles = np.radians([90.0, 40.0, 40 / 3, 90.0, 40.0, 40 / 3, 40.0, 40 / 3])
    plant.set_joint_angles(angles)
    for motor in (1, 2, 3, 4):
        plant.set_drive_off(motor)
    f3_outer = plant._link_index_by_name["f3_outer"]
    f1_knuckle = plant._link_index_by_name["f1_knuckle"]
    before = plant.joint_angles()

    def push():
        position, orientation = link_pose(plant, "f3_tip")
        rotation = np.array(p.getMatrixFromQuaternion(orientation)).reshape(3, 3)
        # 20 N on the fingertip pad, opening the finger (pad normal is the tip frame's z axis).
        p.applyExternalForce(plant.hand_id, f3_outer, list(-20.0 * rotation[:, 2]), position, p.WORLD_FRAME, physicsClientId=plant.client)
        wrist_z = np.array(p.getMatrixFromQuaternion(plant.wrist_pose()[1])).reshape(3, 3)[:, 2]
        p.applyExternalTorque(plant.hand_id, f1_knuckle, list(0.3 * wrist_z), p.WORLD_FRAME, physicsClientId=plant.client)

    run(plant, 0.5, push)
    after = plant.joint_angles()
    assert np.degrees(abs(after[6] - before[6])) < 0.2 and np.degrees(abs(after[7] - before[7])) < 0.2
    assert np.degrees(abs(after[0] - before[0])) > 5.0  # the spread moved
    assert after[3] == pytest.approx(after[0], abs=radians(1.0))  # and F2 followed F1


def test_powered_finger_pushed_backwards_does_not_move(plant):
    """SPEC §1 (worm drives): a finger closing with little torque, pushed open harder, stalls instead of opening."""
    angles = plant.joint_angles()
    angles[6], angles[7] = radians(40.0), radians(40 / 3)
    plant.set_joint_angles(angles)
    f3_outer = plant._link_index_by_name["f3_outer"]
    plant.set_drive(3, 2_000.0, 0.05)
    start = plant.motor_positions()[2]

    def push():
        position, orientation = link_pose(plant, "f3_tip")
        rotation = np.array(p.getMatrixFromQuaternion(orientation)).reshape(3, 3)
        p.applyExternalForce(plant.hand_id, f3_outer, list(-30.0 * rotation[:, 2]), position, p.WORLD_FRAME, physicsClientId=plant.client)

    run(plant, 0.5, push)
    # The worm gives no more than the drive train's compliance (PlantParameters.worm_slack, twice: 9 counts).
    assert plant.motor_positions()[2] > start - 10.0


def test_strain_gauge_offset_and_fingertip_load(plant):
    """§9.4 / SPEC §1: no-load SG in 100..140 per finger; a closing-direction fingertip load raises it; spread 255."""
    angles = plant.joint_angles()
    angles[6], angles[7] = radians(40.0), radians(40 / 3)  # off the stops: the load goes through the drive
    plant.set_joint_angles(angles)
    for motor in (1, 2, 3, 4):
        plant.set_drive_off(motor)
    run(plant, 0.2)
    unloaded = plant.strain_gauges()
    assert unloaded[3] == 255
    for finger in range(3):
        assert 100 <= plant.strain_offsets[finger] <= 140
        assert abs(int(unloaded[finger]) - plant.strain_offsets[finger]) <= 3
    assert len(set(HandPlant(seed=1).strain_offsets + plant.strain_offsets)) > 3  # seeded, per finger
    f3_outer = plant._link_index_by_name["f3_outer"]
    readings = []
    for newtons in (5.0, 10.0):
        def push(newtons=newtons):
            position, orientation = link_pose(plant, "f3_tip")
            rotation = np.array(p.getMatrixFromQuaternion(orientation)).reshape(3, 3)
            p.applyExternalForce(plant.hand_id, f3_outer, list(-newtons * rotation[:, 2]), position, p.WORLD_FRAME, physicsClientId=plant.client)
        run(plant, 0.1, push)
        readings.append(int(plant.strain_gauges()[2]))
    assert unloaded[2] + 10 < readings[0] < readings[1] <= 255


def test_holding_torque_warms_the_hand():
    """SPEC §1 / §2: idle the hand sits at its 40-60 °C steady state; motor I²R loss (Km, Table 7) heats it."""
    with HandPlant(seed=0) as idle, HandPlant(seed=0) as holding:
        assert 40.0 <= idle.temperature <= 60.0
        holding.set_drive(3, -MCV_100, 1.0)  # pushes against the open stop: stalled at full torque
        run(idle, 2.0)
        run(holding, 2.0)
        assert abs(idle.temperature - idle.params.ambient_temperature - 8.0 * 2.9) < 0.01
        assert holding.motor_torques()[2] == pytest.approx(-0.05)
        expected_rise = 2.0 * (0.05 / 0.0083) ** 2 / holding.params.heat_capacity
        assert holding.temperature - idle.temperature == pytest.approx(expected_rise, rel=0.05)


def test_spread_stalled_at_its_stop_draws_its_torque_and_warms_the_hand():
    """§2: "Idling the spread motor, when possible, will help keep the temperature lower": a spread
    motor pushing into its stop is stalled at its torque limit like a finger's, and heats alike
    (it read ~0 N·m: the stop, not the motor, held the joint)."""
    with HandPlant(seed=0) as idle, HandPlant(seed=0) as holding:
        holding.set_drive(4, -MCV_100, 1.0)  # into the open stop (0 counts)
        run(idle, 2.0)
        run(holding, 2.0)
        assert holding.motor_torques()[3] == pytest.approx(-0.05)
        expected_rise = 2.0 * (0.05 / 0.0083) ** 2 / holding.params.heat_capacity
        assert holding.temperature - idle.temperature == pytest.approx(expected_rise, rel=0.1)


def test_fingers_at_full_spread_close_without_touching(plant):
    """SPEC §1: at full spread the fingers lie beside F3 and close in parallel without touching each other."""
    plant.set_drive(4, 14_648.0, 1.0)
    run(plant, 0.4)
    assert plant.motor_positions()[3] == pytest.approx(3150.0, abs=10.0)
    for motor in (1, 2, 3):
        plant.set_drive(motor, MCV_100, 1.0)
    touches = []
    run(plant, 1.0, lambda: touches.extend(p.getContactPoints(plant.hand_id, plant.hand_id, physicsClientId=plant.client)))
    assert {(c[3], c[4]) for c in touches if c[3] != -1 and c[4] != -1} == set()  # only fingertips on the palm
    assert np.all(plant.motor_positions()[:3] > 17_000.0)


def test_save_restore_reproduces_a_trajectory_exactly(plant):
    """Contract 1: restore_state returns PyBullet and the plant's own state, so a trajectory repeats exactly."""
    add_object(plant, ObjectSpec("box", (0.05, 0.05, 0.05), mass=0.2, friction=None), position=(0.0, 0.0, 0.16))
    obstacle_on_inner_link(plant)
    run(plant, 0.1)
    state = plant.save_state()

    def trajectory():
        rows = []
        plant.set_drives([MCV_100, MCV_100, MCV_100, 5_000.0], [1.0, 1.0, 1.0, 0.5])
        for _ in range(500):
            plant.step()
            rows.append(np.concatenate([plant.motor_positions(), plant.strain_gauges(), [plant.temperature, plant.time]]))
        plant.set_drives([0, 0, 0, 0], [np.nan] * 4)
        return np.array(rows), [plant.clutch_engaged(f) for f in (1, 2, 3)], plant.breakaway_position(3)

    first = trajectory()
    plant.restore_state(state)
    second = trajectory()
    assert np.array_equal(first[0], second[0])
    assert first[1:] == second[1:]


def test_bad_arguments_raise_plant_error(plant):
    """Bad arguments raise PlantError naming the value (common rules)."""
    with pytest.raises(PlantError, match="5"):
        plant.set_drive(5, 0.0, 1.0)
    with pytest.raises(PlantError, match="1.5"):
        plant.set_drive(1, 0.0, 1.5)
    with pytest.raises(PlantError, match="nan"):
        plant.set_drive(1, float("nan"), 1.0)
    with pytest.raises(PlantError):
        plant.set_drives([0.0] * 3, [1.0] * 3)
    with pytest.raises(ObjectError, match="teapot"):
        ObjectSpec("teapot", (0.1,))
    with pytest.raises(ObjectError):
        ObjectSpec("box", (0.1, -0.1, 0.1))
    with pytest.raises(ObjectError, match="missing.urdf"):
        add_object(plant, ObjectSpec("urdf", path="missing.urdf"))
    with pytest.raises(PlantError):
        plant.set_wrist_pose((0, 0, 0.3), (0, 0, 0, 2))
    with pytest.raises(PlantError, match="time_step"):
        HandPlant(PlantParameters(time_step=0.01))
    with pytest.raises(PlantError):
        plant.restore_state(12345)


def test_objects_from_specs_and_urdf_scaling(plant):
    """add_object handles primitives, URDF files with globalScaling, and the command-line spec syntax."""
    import pybullet_data

    assert parse_object_spec("box:0.05x0.05x0.08@0,0,0.12;mass=0.2") == ObjectPlacement(
        ObjectSpec("box", (0.05, 0.05, 0.08), mass=0.2, friction=None), (0.0, 0.0, 0.12)
    )
    sphere = add_object_from_spec(plant, "sphere:d0.06@0.3,0,0.05")
    capsule = add_object(plant, ObjectSpec("capsule", (0.04, 0.10), friction=None), position=(0.3, 0.2, 0.1))
    cube = add_object(plant, ObjectSpec("urdf", path=f"{pybullet_data.getDataPath()}/cube_small.urdf", scale=2.0, mass=None,
                                        friction=None), position=(-0.3, 0, 0.1))
    run(plant, 0.5)
    assert plant.object_pose(sphere)[0][2] == pytest.approx(0.03, abs=0.003)  # resting on the table
    assert plant.object_pose(cube)[0][2] == pytest.approx(0.05, abs=0.005)  # 5 cm cube scaled x2 -> 10 cm
    assert plant.object_pose(capsule)[0][2] < 0.1


def test_a_placed_urdf_takes_the_mass_its_spec_gives(plant):
    """Issue 42: `;mass=M` in an `--object` spec (module docstring of bh8_gym.objects: a URDF keeps
    "its own masses unless `mass` is given") sets the URDF's base mass; without it the file's own
    mass stays (cube_small.urdf: 0.1 kg). add_object used to drop the given mass."""
    import pybullet_data

    urdf = f"{pybullet_data.getDataPath()}/cube_small.urdf"
    heavy = add_object_from_spec(plant, f"{urdf}@0.3,0.3,0.1;mass=0.35")
    own = add_object_from_spec(plant, f"{urdf}@-0.3,0.3,0.1")
    assert parse_object_spec(urdf).spec.mass is None
    assert p.getDynamicsInfo(heavy, -1, physicsClientId=plant.client)[0] == pytest.approx(0.35)
    assert p.getDynamicsInfo(own, -1, physicsClientId=plant.client)[0] == pytest.approx(0.1)


def test_wrist_follows_the_flange_target(plant):
    """Contract 1: set_wrist_pose moves the arm flange; the wrist follows (palm-up here)."""
    plant.set_wrist_pose((0.05, 0.0, 0.35), (0.0, 0.0, 0.0, 1.0))
    run(plant, 0.5)
    position, orientation = plant.wrist_pose()
    assert np.allclose(position, (0.05, 0.0, 0.35), atol=0.002)
    assert abs(abs(orientation[3]) - 1.0) < 1e-3


def test_set_parameters_changes_behaviour_and_restore_state_still_works(plant):
    """Contract 1 / SPEC §8: PlantParameters are the randomisation knobs; set_parameters applies them to a
    live plant (motor speed, strain offsets, friction) and save/restore still repeats a trajectory."""
    from dataclasses import replace as with_fields

    state = plant.save_state()

    def close():
        plant.set_drives([MCV_100, MCV_100, MCV_100, 0.0], [1.0, 1.0, 1.0, np.nan])
        run(plant, 0.3)
        return plant.motor_positions()[:3].copy(), plant.strain_gauges().copy()

    default_positions, _ = close()
    slow = with_fields(plant.params, motor_no_load_speed=5_000.0, strain_offsets=(101, 102, 103), finger_friction=0.3)
    plant.restore_state(state)
    plant.set_parameters(slow)
    assert plant.strain_offsets == (101, 102, 103)
    assert p.getDynamicsInfo(plant.hand_id, plant.joint_indices[2], physicsClientId=plant.client)[1] == pytest.approx(0.3)
    slow_positions, slow_gauges = close()
    assert np.all(slow_positions < 1.05 * 0.3 * 5_000.0) and np.all(default_positions > 0.25 * MCV_100)
    assert abs(int(slow_gauges[0]) - 101) <= 3
    plant.restore_state(state)
    first = close()
    plant.restore_state(state)
    second = close()
    assert np.array_equal(first[0], second[0]) and np.array_equal(first[1], second[1])
    with pytest.raises(PlantError, match="time_step"):
        plant.set_parameters(with_fields(slow, time_step=0.001))
    with pytest.raises(PlantError, match="motor_peak_torque"):
        plant.set_parameters(with_fields(slow, motor_peak_torque=float("nan")))


def test_locked_finger_reads_its_hold_position(plant):
    """SPEC §1: an unpowered finger's worm holds it; the motor encoder of a locked finger does not move."""
    plant.set_drive(3, MCV_100, 1.0)
    run(plant, 0.3)
    plant.set_drive_off(3)
    plant.step()
    held = plant.motor_positions()[2]
    readings = []
    run(plant, 0.5, lambda: readings.append(plant.motor_positions()[2]))
    assert held > 5_000.0 and np.all(np.array(readings) == held)
    assert plant.motor_velocities()[2] == 0.0


def test_finger_pads_resist_a_turn_about_the_contact_normal_as_a_patch_does(plant):
    """A rubber pad pressed on an object is a patch, not a point: a uniform circular patch of radius a
    carries up to (2/3)·mu·N·a about its normal (`finger_pad_radius`, docs/modelling.md). PyBullet
    multiplies a link's torsional friction by the other body's lateral friction, so the finger links
    get (2/3)·a·finger_friction (the palm none), and a randomised finger friction keeps the two in step."""
    from dataclasses import replace as with_fields

    def spinning(link):
        return p.getDynamicsInfo(plant.hand_id, link, physicsClientId=plant.client)[7]

    fingers = [index for name, index in plant._link_index_by_name.items() if name.startswith("f")]
    assert len(fingers) >= 6
    assert all(spinning(link) == 0.0 for link in fingers)  # off by default: point contacts
    plant.set_parameters(with_fields(plant.params, finger_pad_radius=0.004))
    a, mu = plant.params.finger_pad_radius, plant.params.finger_friction
    for link in fingers:
        assert spinning(link) == pytest.approx(2.0 / 3.0 * a * mu)
    assert spinning(-1) == 0.0
    plant.set_parameters(with_fields(plant.params, finger_friction=0.5, finger_pad_radius=0.003))
    assert spinning(fingers[0]) == pytest.approx(2.0 / 3.0 * 0.003 * 0.5)
    with pytest.raises(PlantError, match="finger_pad_radius"):
        plant.set_parameters(with_fields(plant.params, finger_pad_radius=0.02))  # wider than the finger
