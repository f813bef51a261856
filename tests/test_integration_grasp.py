"""The plant driven through the real firmware: squeeze kept by locked worms, no gravity overrun,
TorqueSwitch breakaway with GC, locked fingers that do not drift, per-instance processing time.

Sources: manual §9.3.1 (TorqueSwitch, worm drives), App. B FAQ A1 (motor current removed, the
grasp stays), §5.2.1 (C, TC, HI, GO), §5.5 (termination, HOLD); SPEC.md §1, §3.1 (breakaway
parameters), §4, §6, §8.
"""
from __future__ import annotations

from math import radians

import numpy as np
import pybullet as p
import pytest

from bh8_gym import hand_urdf
from bh8_gym.envs.interfaces import grasp_interface
from bh8_gym.firmware import REALTIME_PROCESSING_S, Firmware
from bh8_gym.objects import ObjectSpec, add_object, remove_object
from bh8_gym.plant import HandPlant
from bh8_gym.simulator import build_firmware, shutdown_firmware

PALM_DOWN = (1.0, 0.0, 0.0, 0.0)
PALM_UP = (0.0, 0.0, 0.0, 1.0)
WRIST_OVER_CYLINDER = 0.13 + 0.010 + hand_urdf.SPREAD_KNUCKLE[2] + hand_urdf.PALM_TOP  # m, over a 13 cm cylinder
MCV_20_COUNTS_PER_S = 20 / 16 / 256e-6  # SPEC §4: 1/16 count per 256 µs sample = 4,883 counts/s


def command(fw: Firmware, line: str) -> bytes:
    reply = fw.transact(line.encode() + b"\r")
    assert reply.endswith(b"=> ") and b"ERR" not in reply, reply
    return reply


def run_sampling(fw: Firmware, line: str, sample):
    """Run a motion command 2 ms at a time, calling sample() after each step; returns the samples."""
    fw.write(line.encode() + b"\r")
    samples = []
    while not fw.idle:
        fw.run_for(fw.plant.dt)
        samples.append(sample())
    fw.read()
    return samples


@pytest.fixture
def grasp_fw(tmp_path):
    plant = HandPlant(seed=0)
    # The knuckle housings stand 15 mm proud of the palm face (hand_urdf): 10 mm above the cylinder.
    plant.set_wrist_pose((0.0, 0.0, WRIST_OVER_CYLINDER), PALM_DOWN, teleport=True)
    cylinder = add_object(plant, ObjectSpec("cylinder", (0.06, 0.13), mass=0.15, friction=None), position=(0.0, 0.0, 0.065))
    fw = Firmware(plant=plant, store_dir=tmp_path, seed=0)
    command(fw, "HI")
    yield fw, cylinder
    fw.shutdown()
    plant.close()


def finger_forces(plant, body) -> np.ndarray:
    """Total normal force (N) each finger's links press on `body` with."""
    forces = np.zeros(3)
    fingers = {plant._link_index_by_name[f"f{f}_{part}"]: f - 1 for f in (1, 2, 3) for part in ("inner", "outer")}
    for contact in plant.contacts(plant.hand_id, body):
        if contact[3] in fingers:
            forces[fingers[contact[3]]] += contact[9]
    return forces


def test_locked_fingers_keep_their_squeeze_and_the_grasp_survives_a_lift(grasp_fw):
    """§9.3.1 / FAQ A1: with HOLD 0 a C that stalls on an object switches the motors off, the worms
    lock and the grasp stays: the fingers keep pressing and a 150 g cylinder is lifted. F3 opposes F1
    and F2, which stand side by side, so the cylinder is pinched between F3 and at least one of them.
    (The gauges sense the outer joints only: a finger pressing with its inner link reads little.)
    Over placements, shapes and masses: benchmarks/bench_hold.py."""
    fw, cylinder = grasp_fw
    plant = fw.plant
    command(fw, "GFSET HOLD 0")
    command(fw, "GC")
    assert fw.transact(b"GFGET S\r").split(b"\n\r")[1] == b"0 0 0"
    stalled = finger_forces(plant, cylinder)
    assert stalled[2] > 5.0 and max(stalled[:2]) > 5.0, "the fingers must squeeze the cylinder"
    for _ in range(5):  # the motors are off; the worms keep the squeeze
        fw.run_for(0.1)
        forces = finger_forces(plant, cylinder)
        assert forces[2] > 5.0 and forces.sum() >= 0.7 * stalled.sum()
    start = plant.object_pose(cylinder)[0][2]
    for k in range(1, 401):  # lift the wrist 8 cm in 0.8 s
        plant.set_wrist_pose((0.0, 0.0, WRIST_OVER_CYLINDER + 0.0002 * k), PALM_DOWN)
        fw.run_for(plant.dt)
    fw.run_for(0.3)
    assert plant.object_pose(cylinder)[0][2] - start > 0.07


def test_gravity_cannot_overrun_the_worm(tmp_path):
    """SPEC §1 (worm drives are self-locking) and §4 (TC at MCV runs at MCV/16 counts per sample):
    palm down, where gravity helps the fingers close, TC at MCV 20 runs at about 4,883 counts/s;
    palm up (gravity hinders) it never runs faster than that."""
    speeds = {}
    for name, orientation in (("palm_down", PALM_DOWN), ("palm_up", PALM_UP)):
        plant = HandPlant(seed=0)
        plant.set_wrist_pose((0.0, 0.0, 0.4), orientation, teleport=True)
        fw = Firmware(plant=plant, store_dir=tmp_path / name, seed=0)
        try:
            command(fw, "HI")
            command(fw, "GFSET MCV 20")
            fw.write(b"GTC\r")
            fw.run_for(0.3)  # up to speed
            start = plant.motor_positions()[:3]
            for _ in range(10):  # no 0.1 s window faster than the motor turns
                window_start = plant.motor_positions()[:3]
                fw.run_for(0.1)
                assert np.all(plant.motor_positions()[:3] - window_start < 0.115 * MCV_20_COUNTS_PER_S)
            speeds[name] = plant.motor_positions()[:3] - start
        finally:
            fw.shutdown()
            plant.close()
    assert speeds["palm_down"] == pytest.approx([MCV_20_COUNTS_PER_S] * 3, rel=0.15)
    assert np.all(speeds["palm_up"] < 1.15 * MCV_20_COUNTS_PER_S)


def inner_link_bars(plant: HandPlant, inner_degrees: float) -> None:
    """Fixed bars across the inner links' closing side where the inner links reach `inner_degrees`
    (one bar for F1 and F2, one for F3), clear of the outer links' path."""
    saved = plant.joint_angles()
    angles = saved.copy()
    for inner, outer in ((1, 2), (4, 5), (6, 7)):
        angles[inner], angles[outer] = radians(inner_degrees), radians(inner_degrees / 3)
    plant.set_joint_angles(angles)
    poses = {}
    for finger in (1, 2, 3):
        link = plant._link_index_by_name[f"f{finger}_inner"]
        state = p.getLinkState(plant.hand_id, link, computeForwardKinematics=True, physicsClientId=plant.client)
        poses[finger] = p.multiplyTransforms(state[4], state[5], (0.04, 0.0185, 0.0), (0, 0, 0, 1))
    plant.set_joint_angles(saved)
    middle = (np.array(poses[1][0]) + np.array(poses[2][0])) / 2.0
    add_object(plant, ObjectSpec("box", (0.012, 0.012, 0.08), friction=None), position=middle, orientation=poses[1][1], fixed=True)
    add_object(plant, ObjectSpec("box", (0.012, 0.012, 0.04), friction=None), position=poses[3][0], orientation=poses[3][1], fixed=True)


@pytest.fixture
def bars_fw(tmp_path):
    plant = HandPlant(seed=0)
    inner_link_bars(plant, 60.0)
    fw = Firmware(plant=plant, store_dir=tmp_path, seed=0)
    command(fw, "HI")
    yield fw
    fw.shutdown()
    plant.close()


def test_gc_on_inner_link_bars_breaks_away_and_go_hi_reengage_and_preload(bars_fw):
    """§9.3.1 / SPEC §1: after HI, GC at the default MCV against bars under the inner links breaks the
    clutches away near the bar; the inner links stay while the outer links close to 48°; GO
    re-engages (§9.3.1 opening) and a new HI preloads the clutches again (§8 troubleshooting)."""
    fw = bars_fw
    plant = fw.plant
    assert all(plant.clutch_preload(f) > 2.0 for f in (1, 2, 3))
    track = run_sampling(fw, "GC", lambda: (np.degrees(plant.joint_angles()[[1, 4, 6]]), plant.clutch_engaged(3)))
    angles = np.degrees(plant.joint_angles())
    for finger, (inner, outer) in zip((1, 2, 3), ((1, 2), (4, 5), (6, 7))):
        assert not plant.clutch_engaged(finger)
        at_breakaway = plant.breakaway_position(finger) / 125.0
        assert 55.0 < at_breakaway < 68.0
        assert abs(angles[inner] - at_breakaway) < 2.0
        assert angles[outer] == pytest.approx(48.0, abs=1.0)
    later = np.array([inner for inner, engaged in track if not engaged])  # after F3's breakaway
    assert np.all(later.max(axis=0) - later.min(axis=0) < 2.5)
    command(fw, "GO")
    assert all(plant.clutch_engaged(f) for f in (1, 2, 3))
    command(fw, "HI")
    assert all(plant.clutch_preload(f) > 2.0 for f in (1, 2, 3))


@pytest.mark.parametrize("mcv", [20, 35])
def test_slow_gc_on_inner_link_bars_does_not_break_away(bars_fw, mcv):
    """Manual §8 troubleshooting ("close velocity too slow") / SPEC §8: a slow close stalls on the bars
    with the clutches engaged (3:1 coupling kept)."""
    fw = bars_fw
    command(fw, f"GFSET MCV {mcv}")
    command(fw, "GC")
    angles = np.degrees(fw.plant.joint_angles())
    for finger, (inner, outer) in zip((1, 2, 3), ((1, 2), (4, 5), (6, 7))):
        assert fw.plant.clutch_engaged(finger)
        assert 55.0 < angles[inner] < 68.0
        assert angles[outer] == pytest.approx(angles[inner] / 3.0, abs=1.5)


def test_locked_fingers_do_not_drift_in_loop(tmp_path):
    """§6.2.3 / SPEC §1: after FGET P, LOOP cycles with LCV 0 report zero delta position: an unpowered
    (locked) worm drive holds exactly; FGET P afterwards reads the same counts."""
    fw = Firmware(store_dir=tmp_path, seed=0)
    try:
        command(fw, "HI")
        command(fw, "GFSET LCV 1 LCVC 1 LCPG 0 LFV 0 LFS 0 LFAP 0 LFDP 1 LFDPC 1")
        before = fw.transact(b"FGET P\r")
        assert fw.transact(b"GLOOP\r") == b"GLOOP*"
        layout = fw.loop_layout
        for _ in range(50):
            assert layout.decode_feedback(fw.transact(layout.encode_control([0, 0, 0]))) == (0, 0, 0)
        fw.transact(b"\x03")
        assert fw.transact(b"FGET P\r") == before
    finally:
        fw.shutdown()


def relative_position(plant: HandPlant, body: int) -> np.ndarray:
    """`body`'s position in the wrist frame, metres."""
    wrist_position, wrist_orientation = plant.wrist_pose()
    inverse = p.invertTransform(wrist_position.tolist(), wrist_orientation.tolist())
    return np.array(p.multiplyTransforms(inverse[0], inverse[1], *map(list, plant.object_pose(body)))[0])


def test_a_finger_driven_on_in_loop_does_not_creep(tmp_path):
    """§9.5 Equation 4 / SPEC §1: one motor turns both worms of an engaged finger, so a finger whose
    motor is stalled turns neither link. A LOOP grasp driven on at LCV 100, gain 255 (full torque)
    through the env's lift and a 2 s hold: no engaged finger's outer link runs ahead of the 3:1
    coupling by more than the gears' play (0.05° here, 1° allowed), and the lifted cylinder stays put
    in the hand. (Held back by a velocity target of zero alone, an outer link crept 6° ahead and the
    cylinder slipped; over placements and shapes: benchmarks/bench_hold.py --mode loop.)"""
    plant = HandPlant(seed=0)
    fw = Firmware(plant=plant, store_dir=tmp_path, seed=0)
    try:
        interface = grasp_interface()
        for line in (*interface.setup_commands, interface.baud_command):
            command(fw, line)
        cylinder = add_object(plant, ObjectSpec("cylinder", (0.04, 0.09), mass=0.1, friction=0.5), position=(0.01, 0.0, 0.045))
        wrist_z = 0.09 + 0.02 + hand_urdf.KNUCKLE_HEIGHT + hand_urdf.PALM_TOP
        plant.set_wrist_pose((0.0, 0.0, wrist_z), PALM_DOWN, teleport=True)
        fw.run_for(0.1)
        assert fw.transact(interface.loop_command.encode() + b"\r") == interface.loop_command.encode() + b"*"
        block = interface.encode_action([(0 if motor == 4 else 100) if name == "LCV" else 255
                                         for motor, name in interface.layout.control_fields])
        leads = []

        def cycles(seconds, lift=False):
            start = fw.time
            while fw.time - start < seconds:
                if lift:
                    s = min((fw.time - start) / seconds, 1.0)
                    plant.set_wrist_pose((0.0, 0.0, wrist_z + 0.1 * s ** 3 * (10 - 15 * s + 6 * s * s)), PALM_DOWN)
                fw.transact(block)
                angles = np.degrees(plant.joint_angles())
                leads.extend(angles[outer] - angles[inner] / 3.0 for finger, (inner, outer) in zip((1, 2, 3), ((1, 2), (4, 5), (6, 7)))
                             if plant.clutch_engaged(finger))

        cycles(0.8)
        cycles(0.7, lift=True)
        lifted = relative_position(plant, cylinder)
        cycles(2.0)
        assert max(leads) < 1.0
        assert np.linalg.norm(relative_position(plant, cylinder) - lifted) < 0.5e-3
        assert plant.object_pose(cylinder)[0][2] > 0.08  # lifted with the hand
    finally:
        fw.shutdown()
        plant.close()


def test_processing_time_is_a_per_instance_setting(tmp_path):
    """SPEC §6: a RealTime cycle costs the blocks' bytes at BAUD plus the firmware's processing time,
    now per Firmware instance (randomised by the environments); bad values are rejected."""
    times = []
    for processing in (REALTIME_PROCESSING_S, 3e-3):
        fw = Firmware(store_dir=tmp_path / str(processing), seed=0, processing_time=processing)
        try:
            command(fw, "HI")
            assert fw.transact(b"GLOOP\r") == b"GLOOP*"
            start = fw.time
            fw.transact(b"A")
            times.append(fw.time - start)
        finally:
            fw.shutdown()
    assert times[1] - times[0] == pytest.approx(2e-3, abs=1e-9)
    with pytest.raises(ValueError, match="-1"):
        Firmware(store_dir=tmp_path / "bad", processing_time=-1.0)


def fget(fw: Firmware, line: str) -> list[list[int]]:
    reply = command(fw, line).decode()
    return [[int(v) for v in row.split()] for row in reply.split("\n\r")[1:-1]]


def test_bd_and_bp_follow_the_plant_and_o_to_hi_clear_them(bars_fw):
    """SPEC.md §3.1: BD and BP come from the plant's breakaway record (BP in the HCTL frame, the
    plant's breakaway counts since HI's origin); O, TO and HI clear them, an IO or M does not;
    a 4.4 hand's LFBP reports the same BP."""
    fw = bars_fw
    plant = fw.plant
    command(fw, "GC")
    detected, breakaway = fget(fw, "GFGET BD BP")
    assert detected == [1, 1, 1]
    for finger in (1, 2, 3):
        assert not plant.clutch_engaged(finger)
        assert abs(breakaway[finger - 1] - plant.breakaway_position(finger)) < 200  # HI put the origin near the stop
    command(fw, "GIO 500")
    assert fget(fw, "GFGET BD BP") == [[1, 1, 1], breakaway]
    command(fw, "1O")
    assert fget(fw, "GFGET BD") == [[0, 1, 1]]
    command(fw, "2TO")
    assert fget(fw, "GFGET BD BP") == [[0, 0, 1], [0, 0, breakaway[2]]]
    command(fw, "3HI")
    assert fget(fw, "GFGET BD BP") == [[0, 0, 0], [0, 0, 0]]


def test_bs_stops_a_finger_at_its_breakaway(bars_fw):
    """SPEC.md §3.1 (Barrett's API documentation: the breakaway stop flag "is used to stop a finger
    motor as soon as breakaway is detected"): with BS 1 on F3 only, a GC stops F3 where it broke
    away (HOLD 0: it stays there) while F1 and F2 close on with their outer links."""
    fw = bars_fw
    command(fw, "3FSET BS 1")
    command(fw, "GC")
    detected, breakaway, position = fget(fw, "GFGET BD BP P")
    assert detected == [1, 1, 1]
    assert abs(position[2] - breakaway[2]) < 150
    assert position[0] > breakaway[0] + 2000 and position[1] > breakaway[1] + 2000
    assert fw.plant.breakaway_position(3) / 125.0 == pytest.approx(np.degrees(fw.plant.joint_angles()[6]), abs=2.0)


def test_a_finger_that_meets_nothing_does_not_break_away(tmp_path):
    """§9.3.1 ("If the inner finger link, while closing, contacts a target object ... the clutch will
    disengage"): a breakaway needs something that holds the finger back. After a GC that breaks away
    on a box (the preload goes, manual §8) and a GO (to OT 0, short of the stop: no new preload), the
    box is taken away and a GC closes every finger to CT with its clutch engaged. F2 used to break
    away 8 counts into the close: at its profile's start the HCTL's small duty lets the finger's
    joints stop and start, and the clutch took that for an impact (issue 42)."""
    fw = build_firmware(tmp_path, objects=["box:0.06x0.10x0.06;mass=10"])
    try:
        command(fw, "HI")
        command(fw, "GC")
        assert fget(fw, "GFGET BD")[0] == [1, 1, 1]
        command(fw, "GO")
        plant = fw.plant
        remove_object(plant, p.getBodyUniqueId(p.getNumBodies(physicsClientId=plant.client) - 1, physicsClientId=plant.client))
        assert [plant.clutch_preload(f) for f in (1, 2, 3)] == [0.0, 0.0, 0.0]
        command(fw, "GC")
        detected, position = fget(fw, "GFGET BD P")
        assert detected == [0, 0, 0] and [abs(c - 17000) < 100 for c in position] == [True] * 3, position
    finally:
        shutdown_firmware(fw)


def test_a_close_after_a_breakaway_and_an_open_breaks_away_only_at_its_obstacle(tmp_path):
    """SPEC.md §3.1 (BS: stop a finger "as soon as breakaway is detected"), manual §5.3.2 (BD, BP)
    and §9.3.1 (opening re-engages the clutch): after a GC that breaks away on a box and a GO, a GC
    with BS 1 stops each finger where its inner link meets the box again (P = BP, within 500 counts
    of the first breakaway), not at its start: the rotor's closing speed from the first GC is gone
    once it has turned the other way, so a finger accelerating from the open stop is not taken for
    one held back (F3 stopped at P = 9). The same hand and box as the pty test in
    test_virtual_serial.py."""
    fw = build_firmware(tmp_path, objects=["box:0.06x0.10x0.06;mass=10"])
    try:
        command(fw, "HI")
        command(fw, "GC")
        detected, first, _ = fget(fw, "GFGET BD BP P")
        assert detected == [1, 1, 1]
        command(fw, "GO")
        assert fget(fw, "GFGET BD BP") == [[0, 0, 0], [0, 0, 0]]
        command(fw, "GFSET BS 1 BDAT 250")
        command(fw, "GC")
        detected, stopped_at, position = fget(fw, "GFGET BD BP P")
        assert detected == [1, 1, 1]
        for bp, p, before in zip(stopped_at, position, first):
            assert abs(p - bp) < 150 and abs(bp - before) < 500, (stopped_at, position, first)
    finally:
        shutdown_firmware(fw)
