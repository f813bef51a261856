"""Motion commands on the real HandPlant: HI, timing, the four termination cases, HOLD, OD.

Sources: manual §5.2.1 (movement commands), §5.3.4 (IOFF, TSTOP, HOLD), §5.5 (termination),
§9.2 (HCTL control), §9.3.1 (TorqueSwitch, Fig. 25), App. A (speeds); SPEC.md §4.
"""
import pytest

from bh8_gym.firmware import Firmware
from bh8_gym.objects import ObjectSpec, add_object
from bh8_gym.plant import HandPlant

PROMPT = b"=> "
# A fixed post under the palm (palm down at the default wrist pose): the fingers close onto it.
# Palm face at z = 0.30 − 0.084 m; the post's top is 16 mm below it.
POST = dict(spec=ObjectSpec("box", (0.06, 0.06, 0.16), friction=None), position=(0.0, 0.0, 0.12), fixed=True)


def reply_lines(fw: Firmware, line: str) -> list[str]:
    reply = fw.transact(line.encode() + b"\r")
    assert reply.startswith(line.encode() + b"\n\r") and reply.endswith(PROMPT), reply
    body = reply[len(line) + 2 : -len(PROMPT)]
    return body.decode().split("\n\r")[:-1] if body else []


def values(fw: Firmware, line: str) -> list[int]:
    return [int(v) for v in reply_lines(fw, line)[0].split()]


def timed(fw: Firmware, line: str) -> tuple[list[str], float]:
    t0 = fw.time
    lines = reply_lines(fw, line)
    return lines, fw.time - t0


@pytest.fixture(scope="module")
def free_hand(tmp_path_factory):
    fw = Firmware(store_dir=tmp_path_factory.mktemp("store"), seed=0)
    assert reply_lines(fw, "HI") == []
    snap = fw.snapshot()
    yield fw, snap
    fw.shutdown()


@pytest.fixture
def fw(free_hand):
    firmware, snap = free_hand
    firmware.restore(snap)
    firmware.cycle_hook = None
    return firmware


@pytest.fixture(scope="module")
def hand_with_post(tmp_path_factory):
    plant = HandPlant(seed=0)
    add_object(plant, **POST)
    fw = Firmware(plant=plant, store_dir=tmp_path_factory.mktemp("store"), seed=0)
    assert reply_lines(fw, "HI") == []
    snap = fw.snapshot()
    yield fw, snap
    fw.shutdown()
    plant.close()


@pytest.fixture
def post(hand_with_post):
    firmware, snap = hand_with_post
    firmware.restore(snap)
    return firmware


def test_hi_sets_the_origin_iof_from_the_open_stop(fw):
    """§5.2.1 HI: motors end at 0 counts; §5.3.4 IOFF: the origin lies IOFF counts closed from full
    open, so driving to the open stop reads about −IOFF (SPEC.md §4)."""
    assert values(fw, "FGET P") == pytest.approx([0, 0, 0, 0], abs=50)
    assert values(fw, "FGET S") == [0, 0, 0, 0]
    reply_lines(fw, "GTO")
    assert values(fw, "GFGET P") == pytest.approx([-50, -50, -50], abs=25)


def test_hi_after_reset_homes_a_closed_spread(fw):
    """Issue 31 (Barrett's InitSoftware sends RESET): after RESET, HI, SC, RESET, HI the spread is at
    home at its open stop (§5.2.1 HI: "After an HI, all motors are in their home position; at 0
    encoder counts"), SC closes it over its whole range (about 3150 counts, §5.3.4 MPE note) and
    SM 1575 gets there within MPE without a status (§5.5 case 3). The second HI used to take the
    spread, still gathering speed from the closed end, for stalled after TSTOP and put the zero
    there (SC then moved 21 counts and SM 1575 answered ERR 16)."""
    for line in ("RESET", "HI", "SC", "RESET", "HI"):
        assert fw.transact(line.encode() + b"\r").endswith(b"\n\r=> ") and b"ERR" not in fw.read()
    assert values(fw, "SFGET P") == pytest.approx([0], abs=50)
    assert reply_lines(fw, "SC") == []
    assert values(fw, "SFGET P")[0] > 3000
    assert reply_lines(fw, "SM 1575") == []
    assert values(fw, "SFGET P") == pytest.approx([1575], abs=50) and values(fw, "SFGET S") == [0]


def test_hi_with_libgrippers_spread_gains_still_homes_at_the_open_stop(fw):
    """Issue 31: libgripper leaves SFSET FPG 5 FIP 1 FDZ 100; the spread then opens at about half
    the default duty, slowly, and HI must still set the zero at the open stop (§5.2.1 HI), never at
    the closed end: SO afterwards reads about 0 (it read -3144: the zero was at the closed end)."""
    assert reply_lines(fw, "SC") == []
    assert reply_lines(fw, "SFSET FPG 5 FIP 1 FDZ 100") == []
    assert reply_lines(fw, "HI") == []
    assert values(fw, "SFGET P") == pytest.approx([0], abs=50) and values(fw, "SFGET S") == [0]
    assert reply_lines(fw, "SO") == []
    assert values(fw, "SFGET P") == pytest.approx([0], abs=50)
    assert reply_lines(fw, "SC") == []
    assert values(fw, "SFGET P")[0] > 3000


def test_hi_that_cannot_open_a_motor_sets_its_origin_where_it_stopped(fw):
    """SPEC.md §4 (from §5.2.1, §5.5 and §8): HI has no status of its own; a motor that stops short
    of its open stop gets its origin where it stopped (§8 premature breakaway: "The finger was not
    opened completely ... Initialize the finger"). With a drive too weak to move the closed spread
    (IVEL 16 at FPG 1: 0.2 % duty against its friction) SHI answers without error, S reads 0 and
    the zero is at the closed end (the plant's spread still about 3150 counts from its open stop).
    §8's remedy (defaults back, initialise again) homes it at the open stop."""
    assert reply_lines(fw, "SC") == []
    closed = fw.plant.motor_positions()[3]
    assert closed > 3000
    assert reply_lines(fw, "SFSET IVEL 16 FPG 1") == []
    assert fw.transact(b"SHI\r") == b"SHI\n\r=> "
    assert values(fw, "SFGET S") == [0] and values(fw, "SFGET P") == pytest.approx([0], abs=50)
    assert fw.plant.motor_positions()[3] == pytest.approx(closed, abs=50)
    assert reply_lines(fw, "SFSET IVEL 150 FPG 10") == []
    assert reply_lines(fw, "SHI") == []
    assert values(fw, "SFGET S") == [0] and values(fw, "SFGET P") == pytest.approx([0], abs=50)
    assert fw.plant.motor_positions()[3] == pytest.approx(0, abs=50)


def test_finger_close_and_open_take_about_one_second(fw):
    """App. A: finger fully open to fully closed about 1.0 s at the defaults (±30%)."""
    lines, seconds = timed(fw, "GC")
    assert lines == [] and 0.7 <= seconds <= 1.3
    assert values(fw, "GFGET P") == pytest.approx([17000] * 3, abs=50)
    lines, seconds = timed(fw, "GO")
    assert lines == [] and 0.7 <= seconds <= 1.3
    assert values(fw, "GFGET P") == pytest.approx([0] * 3, abs=50)


def test_full_spread_takes_about_0_3_seconds(fw):
    """App. A: full 180° spread about 0.3 s at the defaults (±30%)."""
    lines, seconds = timed(fw, "SC")
    assert lines == [] and 0.21 <= seconds <= 0.39
    assert values(fw, "SFGET P") == pytest.approx([3150], abs=50)


def test_position_commands_reach_their_targets(fw):
    """§5.2.1 M, IC, IO, HOME and §5.5 case 3: goal reached within MPE, S = 0, no error."""
    assert reply_lines(fw, "13M 4000") == []
    assert values(fw, "13FGET P") == pytest.approx([4000, 4000], abs=50)
    assert reply_lines(fw, "1IC 1000") == [] and values(fw, "1FGET P") == pytest.approx([5000], abs=60)
    assert reply_lines(fw, "1IO") == [] and values(fw, "1FGET P") == pytest.approx([3300], abs=80)
    assert reply_lines(fw, "SM") == [] and values(fw, "SFGET P") == pytest.approx([1575], abs=50)
    assert reply_lines(fw, "HOME") == []
    assert values(fw, "FGET P") == pytest.approx([0, 0, 0, 0], abs=50)
    assert values(fw, "FGET S") == [0, 0, 0, 0]


def test_move_past_the_joint_stop_is_err_16_near_the_stop(fw):
    """§5.5 case 1: the motor stalls at the joint stop; after TSTOP it terminates; a position
    command ending outside MPE reports ERR 16 (Table 3 / SPEC.md §2) and S shows 16."""
    reply = fw.transact(b"1M 20000\r")
    assert reply == b"1M 20000\n\rERR 16\n\r=> "
    position = values(fw, "1FGET P")[0]
    assert 16500 < position < 19000
    assert values(fw, "FGET S") == [16, 0, 0, 0]


def test_close_never_reports_err_16(fw):
    """§5.2.1 C/O notes: C and O do not report "couldn't reach position" (CT beyond the stop)."""
    reply_lines(fw, "1FSET CT 20000")
    assert reply_lines(fw, "1C") == []
    assert 16500 < values(fw, "1FGET P")[0] < 19000


def test_tstop_delays_stall_termination(fw):
    """§5.3.4 TSTOP / §5.5 case 1: the controller keeps driving TSTOP ms after the stall."""
    snap = fw.snapshot()
    _, short = timed_err(fw, "1M 20000")
    fw.restore(snap)
    reply_lines(fw, "1FSET TSTOP 330")
    _, long = timed_err(fw, "1M 20000")
    assert long - short == pytest.approx(0.3, abs=0.02)


def test_accel_0_moves_nothing_and_ends_as_a_stall_after_tstop(fw):
    """§5.3.4 ACCEL accepts 0 (0 to 65,535). §9.2.1: the HCTL-1100's trapezoid accelerates at
    ACCEL, so at 0 its command position never leaves the start: the motor is held where it is.
    Not moving, it terminates TSTOP ms later (§5.5 case 1), as any stalled motor: C answers
    without error (C never reports ERR 16), M with ERR 16 (its goal was not reached, §5.5 case 3).
    It used to wait for a profile that never ended: GC never answered."""
    start = values(fw, "GFGET P")
    assert reply_lines(fw, "GFSET ACCEL 0 TSTOP 200") == []
    t0 = fw.time
    assert fw.transact(b"GC\r", max_seconds=5.0) == b"GC\n\r=> "
    assert fw.time - t0 == pytest.approx(0.2, abs=0.02)
    assert values(fw, "GFGET P") == pytest.approx(start, abs=5)
    assert fw.transact(b"GM 5000\r", max_seconds=5.0) == b"GM 5000\n\rERR 16\n\r=> "
    assert values(fw, "GFGET S") == [16, 16, 16]
    assert values(fw, "GFGET P") == pytest.approx(start, abs=5)
    assert reply_lines(fw, "GFSET ACCEL 4") == [] and reply_lines(fw, "GM 5000") == []  # the default moves again


@pytest.mark.parametrize("tstop", [0, 2, 5])
def test_a_tstop_below_a_few_ms_does_not_end_moves_before_they_start(fw, tstop):
    """§5.3.4 TSTOP (0 to 65,535 ms) / §5.5 case 1, an obstacle stopping the motion: a motor at rest
    as its move starts has not been stopped. With TSTOP 0 a move still ends at its goal, and HI
    from a closed finger still finds the open stop (it used to take the first 2 ms step, before the
    motor had moved, for the stop: "success" with P = -51 and the finger at 76 degrees)."""
    reply_lines(fw, "GM 9000")
    reply_lines(fw, f"GFSET TSTOP {tstop}")
    assert reply_lines(fw, "GM 5000") == []
    assert values(fw, "GFGET P") == pytest.approx([5000] * 3, abs=10)
    assert reply_lines(fw, "GC") == []
    assert min(values(fw, "GFGET P")) > 16000
    assert reply_lines(fw, "GHI") == []
    assert values(fw, "GFGET S") == [0, 0, 0]
    assert values(fw, "GFGET P") == pytest.approx([0] * 3, abs=50)  # MPE
    inner = fw.plant.joint_angles()[[1, 4, 6]]
    assert max(abs(inner)) < 0.02  # rad: at the open stop's home, not where the finger was


def test_mpe_compares_whole_counts(fw):
    """§5.3.4 MPE with §5.5 case 3: the HCTL counts whole encoder counts, so with MPE 0 a move that
    ends where FGET P reads its goal succeeded (it gave ERR 16 for a fraction of a count)."""
    reply_lines(fw, "GFSET MPE 0")
    assert reply_lines(fw, "GM 5000") == []
    assert values(fw, "GFGET P") == [5000] * 3 and values(fw, "GFGET S") == [0] * 3


def timed_err(fw, line):
    t0 = fw.time
    reply = fw.transact(line.encode() + b"\r")
    return reply, fw.time - t0


def test_odometer_counts_thousands_of_counts(fw):
    """§5.3.2 OD: total counts travelled / 1000 — a close and open of 17,000 counts adds about 34."""
    before = values(fw, "GFGET OD")
    reply_lines(fw, "GC")
    reply_lines(fw, "GO")
    after = values(fw, "GFGET OD")
    for b, a in zip(before, after):
        assert 32 <= a - b <= 36


def test_hold_keeps_the_spread_servoed_and_off_releases_it(fw):
    """§5.3.4 HOLD (spread default 1) servoes after a move; T turns the power off (§5.2.1)."""
    reply_lines(fw, "SM 1000")
    assert fw._channels[4].mode != 0  # HOLD 1: still energised
    reply_lines(fw, "ST")
    assert fw._channels[4].mode == 0
    reply_lines(fw, "1M 2000")
    assert fw._channels[1].mode == 0  # finger HOLD 0: off after the move


def test_close_on_an_object_stalls_and_stays_with_hold_0(post):
    """§5.5 case 1 with an obstacle: the fingers stall on the post, C returns without error, and
    with HOLD 0 (finger default) each finger stays where it stopped (worm drive, SPEC.md §1)."""
    assert reply_lines(post, "GC") == []
    stopped = values(post, "GFGET P")
    assert all(p < 16000 for p in stopped)
    assert values(post, "GFGET S") == [0, 0, 0]
    post.run_for(0.5)
    assert values(post, "GFGET P") == pytest.approx(stopped, abs=5)


def test_move_onto_an_object_reports_err_16(post):
    """§5.5 case 1: a position command stopped by an obstacle outside MPE reports ERR 16."""
    assert post.transact(b"GM 15000\r") == b"GM 15000\n\rERR 16\n\r=> "


def while_running(fw: Firmware, command: bytes, seconds: float, probe):
    """`probe(plant)` taken `seconds` into `command` (paced), then the command runs to its end."""
    fw.write(command)
    fw.run_for(seconds)
    value = probe(fw.plant)
    fw.run_until_idle()
    fw.read()
    return value


def test_hsg_stops_a_finger_pressing_on_an_object(post):
    """§5.5 case 2: as soon as SG rises above HSG the motor terminates — before the stall would."""
    snap = post.snapshot()
    no_load = values(post, "1FGET SG")[0]
    t0 = post.time
    assert reply_lines(post, "1C") == []
    stall_time = post.time - t0
    post.restore(snap)
    reply_lines(post, "1FSET TSTOP 1000")
    pressing = while_running(post, b"1C\r", stall_time, lambda plant: int(plant.strain_gauges()[0]))
    assert pressing > no_load + 30, "pressing on the post must load the strain gauge"
    post.restore(snap)
    reply_lines(post, f"1FSET HSG {no_load + 20}")
    t0 = post.time
    assert reply_lines(post, "1C") == []
    assert post.time - t0 < stall_time - 0.02  # ended by the gauge, not TSTOP ms after the stall
    assert values(post, "1FGET S") == [0]


def test_torque_close_stall_force_grows_with_velocity(post):
    """§9.3.1 Fig. 25 / SPEC.md §4: TC's stall torque grows with the commanded velocity MCV."""
    snap = post.snapshot()
    torques = []
    for mcv in (40, 120):
        post.restore(snap)
        reply_lines(post, f"1FSET MCV {mcv} TSTOP 2000")  # both stalled on the post, still driving
        torques.append(while_running(post, b"1TC\r", 1.4, lambda plant: float(plant.motor_torques()[0])))
    assert 0.0 < torques[0] < torques[1]
    assert torques[1] / torques[0] == pytest.approx(3.0, rel=0.3)  # U = FPG/4 × MCV/16 at stall


def test_ctrl_c_aborts_at_once_and_hold_1_servoes(fw):
    """§5.5 case 4: ^C terminates all motors at once; HOLD 1 motors are then servoed."""
    fw.write(b"C\r\x03")
    fw.run_until_idle()
    assert fw.read() == b"C\n\rERR 16384\n\r=> "
    assert values(fw, "FGET S") == [16384] * 4
    assert fw._channels[4].mode != 0 and fw._channels[1].mode == 0
