"""RealTime (LOOP) mode: entry, block byte counting, feedback contents, §6.2.3, timing, errors.

Sources: manual §6 (§6.1 overview, §6.2 blocks, §6.2.3 LFDP, §6.4 example); SPEC.md §5 (block
layout, byte counting), §6 (time model), §7 (4.4 profile); docs/architecture.md Contract 2.
"""
import pytest

from bh8_gym.firmware import REALTIME_PROCESSING_S, Firmware
from bh8_gym.realtime_codec import LoopLayout, MotorFlags

PROMPT = b"=> "


@pytest.fixture
def fw(tmp_path):
    firmware = Firmware(store_dir=tmp_path, seed=0)
    assert firmware.transact(b"HI\r") == b"HI\n\r=> "
    yield firmware
    firmware.shutdown()


def setup_section_6_4(fw):
    """§6.4 example: fingers 1 and 2 velocity-controlled reporting strain and delta position, the
    spread reporting delta position, plus the temperature."""
    for line in (
        b"12FSET LCV 1 LCVC 1 LCPG 0 LFV 0 LFS 1 LFAP 0 LFDP 1 LFDPC 1\r",
        b"4FSET LCV 0 LCPG 0 LFV 0 LFS 0 LFAP 0 LFDP 1 LFDPC 1\r",
        b"PSET LFT 1\r",
    ):
        assert fw.transact(line).endswith(b"\n\r=> ")


def test_loop_entry_is_echo_then_star(link):
    """SPEC.md §5: "[prefix]LOOP\\r" → the echo, then "*" immediately (no newline)."""
    link.command("HI")
    link.write(b"124LOOP\r")
    assert link.read_exact(len(b"124LOOP*"), 10) == b"124LOOP*"
    link.write(b"\x03")
    assert link.read_until(PROMPT, 10) == b"\n\r=> "


def test_section_6_4_example_block_sizes_and_contents(link):
    """§6.4: 3-byte control blocks ("C" + 2 velocity bytes) and 8-byte feedback blocks
    ("*", strain and delta position for motors 1 and 2, delta position for motor 4, 2 bytes temp)."""
    link.command("HI")
    link.command("12FSET LCV 1 LCVC 1 LCPG 0 LFV 0 LFS 1 LFAP 0 LFDP 1 LFDPC 1")
    link.command("4FSET LCV 0 LCPG 0 LFV 0 LFS 0 LFAP 0 LFDP 1 LFDPC 1")
    link.command("PSET LFT 1")
    link.command("FGET P")  # §6.2.3: sets the reported positions
    link.write(b"124LOOP\r")
    assert link.read_exact(8, 10) == b"124LOOP*"
    layout = LoopLayout(
        (1, 2, 4),
        {1: MotorFlags(LCPG=False, LFV=False, LFAP=False), 2: MotorFlags(LCPG=False, LFV=False, LFAP=False),
         4: MotorFlags(LCV=False, LCPG=False, LFV=False, LFS=False, LFAP=False)},
        lft=True,
    )
    block = layout.encode_control([0, 0])
    assert len(block) == 3 and layout.feedback_size == 8
    link.write(block)
    feedback = link.read_exact(8, 10)
    sg1, dp1, sg2, dp2, dp4, temp = layout.decode_feedback(feedback)
    assert feedback[:1] == b"*"
    assert 0 <= sg1 <= 255 and 0 <= sg2 <= 255
    assert (dp1, dp2, dp4) == (0, 0, 0)  # nothing moved since FGET P
    link.write(b"\x03")
    link.read_until(PROMPT, 10)
    temp_now = int(link.lines("PGET TEMP")[0])
    assert abs(temp - temp_now) <= 5  # tenths of a degree C


def test_headers_c_a_and_ack_replies(fw):
    """§6.2.1: C → feedback block, c → "*", A → feedback block, a → "*"."""
    fw.transact(b"GLOOP\r")
    layout = fw.loop_layout
    assert layout.motors == (1, 2, 3)
    assert len(fw.transact(layout.encode_control([0, 10] * 3, b"C"))) == layout.feedback_size
    assert fw.transact(layout.encode_control([0, 10] * 3, b"c")) == b"*"
    assert len(fw.transact(b"A")) == layout.feedback_size
    assert fw.transact(b"a") == b"*"
    assert fw.transact(b"\x03") == b"\n\r=> "
    assert not fw.in_loop


def test_data_bytes_are_counted_not_parsed(fw):
    """SPEC.md §5: control data may contain 0x03, 0x0D, 0x00 — they are data, not ^C or CR."""
    fw.transact(b"1FSET LCV 1 LCPG 1\r")
    fw.transact(b"1LOOP\r")
    reply = fw.transact(b"C\x03\x0d")
    assert len(reply) == fw.loop_layout.feedback_size and fw.in_loop
    assert fw.transact(b"C\x00\x00").startswith(b"*")
    assert fw.transact(b"C") == b""  # incomplete block: the firmware waits for the rest
    assert fw.idle
    assert fw.transact(b"\x0d\x03").startswith(b"*") and fw.in_loop


def test_bad_header_is_err_2048_and_back_to_supervisory(fw):
    """SPEC.md §5 / §6.2.2: a bad header → "\\n\\rERR 2048\\n\\r=> " and supervisory mode."""
    fw.transact(b"SLOOP\r")
    assert fw.transact(b"X") == b"\n\rERR 2048\n\r=> "
    assert not fw.in_loop
    assert fw.transact(b"SFGET HOLD\r") == b"SFGET HOLD\n\r1\n\r=> "


def test_loop_velocity_moves_the_finger(fw):
    """§6.2.1: LCV·LCVC is the commanded velocity in 1/16 count per sample; LCPG the gain byte."""
    fw.transact(b"1FSET LCVC 4\r")
    fw.transact(b"1LOOP\r")
    layout = fw.loop_layout
    start = layout.feedback_by_motor(layout.decode_feedback(fw.transact(b"A")))[1]["LFAP"]
    t0 = fw.time
    for _ in range(40):  # about 0.4 s: stays clear of the closed stop
        feedback = fw.transact(layout.encode_control([25, 100]))
    end = layout.feedback_by_motor(layout.decode_feedback(feedback))[1]
    elapsed = fw.time - t0
    commanded = 25 * 4 / 16 / 256e-6  # counts per second
    assert end["LFAP"] - start == pytest.approx(commanded * elapsed, rel=0.25)
    assert end["LFV"] == pytest.approx(25 * 4 / 16, abs=1.5)  # counts per sample, LFVC 1


def test_lfv_of_a_free_finger_at_lcv_64_reads_4_counts_per_sample(fw):
    """SPEC.md §4 (velocity tracking): finger 1 from `1M 4000`, LCV 64 with LCVC 1 is 64/16 = 4 counts
    per sample (§6.2.1: the LCV datum is 4 bits of integer and 4 of fraction). Under the HCTL's
    proportional velocity law (§9.2.2) at gain 40 the free finger's speed settles within 0.2 count
    per sample of that, and LFV, the HCTL's whole counts per sample (§6.2.2, LFVC 1), reads 4 in
    every block once it has (it read 3: the speed was truncated, 3.98 to 3)."""
    assert fw.transact(b"1M 4000\r") == b"1M 4000\n\r=> "
    fw.transact(b"1FSET LCV 1 LCVC 1 LCPG 1 LFV 1 LFVC 1 LFS 0 LFAP 1 LFDP 0\r")
    fw.transact(b"1LOOP\r")
    layout = fw.loop_layout
    lfv = [layout.feedback_by_motor(layout.decode_feedback(fw.transact(layout.encode_control([64, 40]))))[1]["LFV"]
           for _ in range(40)]
    assert lfv[10:] == [4] * 30, lfv


def test_loop_gain_zero_does_not_move(fw):
    """§6.1 / SPEC.md §5: LCPG 0 means no torque — the finger does not move."""
    fw.transact(b"1LOOP\r")
    layout = fw.loop_layout
    for _ in range(50):
        feedback = fw.transact(layout.encode_control([100, 0]))
    assert abs(layout.feedback_by_motor(layout.decode_feedback(feedback))[1]["LFAP"]) <= 5


def test_cycle_time_model(fw):
    """SPEC.md §6: each cycle costs (control + feedback bytes) × 10 / BAUD + REALTIME_PROCESSING_S."""
    setup_section_6_4(fw)
    fw.transact(b"124LOOP\r")
    t0 = fw.time
    fw.transact(b"C\x00\x00")
    assert fw.time - t0 == pytest.approx((3 + 8) * 10 / 9600 + REALTIME_PROCESSING_S)
    fw.transact(b"\x03")
    fw.transact(b"PSET BAUD 384\r")
    fw.transact(b"124LOOP\r")
    t0 = fw.time
    fw.transact(b"a")
    assert fw.time - t0 == pytest.approx((1 + 1) * 10 / 38400 + REALTIME_PROCESSING_S)


def test_default_layout_cycle_is_about_29_ms_at_9600(fw):
    """SPEC.md §6: a 5-byte control block plus a 23-byte feedback block at 9600 baud ≈ 29 ms."""
    fw.transact(b"34FSET LCV 0 LCPG 0\r")
    fw.transact(b"PSET LFT 1\r")
    fw.transact(b"LOOP\r")
    layout = fw.loop_layout
    assert layout.control_block_size(b"C") == 5 and layout.feedback_size == 23
    t0 = fw.time
    fw.transact(layout.encode_control([0, 0, 0, 0]))
    assert fw.time - t0 == pytest.approx(28 * 10 / 9600 + REALTIME_PROCESSING_S)
    assert 0.028 < fw.time - t0 < 0.031


@pytest.mark.parametrize("discard, expected", [(0, [127, 123, 0, 0]), (1, [127, 0, 0, 0])])
def test_lfdp_worked_example(fw, discard, expected):
    """§6.2.3 worked example: LFDPC 2, reported 1500, position jumps to 2000 → 127, 123, 0 with
    LFDPD 0; 127 then 0s with LFDPD 1. The reported position is set by FGET P."""
    fw.transact(b"1M 1500\r")
    reported = int(fw.transact(b"1FGET P\r").split(b"\n\r")[1])
    fw.transact(b"1M 2000\r")
    fw.transact(b"1FSET LFDPC 2 LCV 0 LCPG 0 LFV 0 LFS 0\r")
    fw.transact(b"PSET LFDPD %d\r" % discard)
    fw.transact(b"1LOOP\r")
    layout = fw.loop_layout
    data = [layout.decode_feedback(fw.transact(b"A")) for _ in range(4)]
    present = data[0][0]
    deltas = [d[1] for d in data]
    assert deltas[0] == 127
    if discard:
        assert deltas[1:] == [0, 0, 0]
    else:
        assert deltas[1] == (present - (reported + 254)) // 2
        assert deltas[2:] == [0, 0]
        if (present, reported) == (2000, 1500):
            assert deltas == expected


def test_flags_change_only_in_supervisory_mode(fw):
    """§6.1: the block structure can only change in supervisory mode — FSET bytes in LOOP are
    control blocks (here a bad header), not commands."""
    fw.transact(b"SLOOP\r")
    # "F" is a bad header; the rest is supervisory text again, echoed as typed
    assert fw.transact(b"FSET") == b"\n\rERR 2048\n\r=> SET"
    assert not fw.in_loop


def test_cycle_hook_runs_once_per_cycle(fw):
    """Contract 2: cycle_hook(fw) runs once per RealTime cycle."""
    calls = []
    fw.cycle_hook = calls.append
    fw.transact(b"SLOOP\r")
    for header in (b"A", b"a", b"A"):
        fw.transact(header)
    assert calls == [fw, fw, fw]


def test_snapshot_restore_reproduces_bytes(fw):
    """Contract 2 / firmware brief: after restore, the same input yields identical bytes."""
    fw.transact(b"GLOOP\r")
    layout = fw.loop_layout
    blocks = [layout.encode_control([v, 50] * 3) for v in (40, -20, 60, 10, 0, 90)]
    snap = fw.snapshot()
    first = [fw.transact(block) for block in blocks]
    fw.restore(snap)
    second = [fw.transact(block) for block in blocks]
    assert first == second
    assert len({b for b in first}) > 1


def test_profile_44_layout_and_lft_byte(tmp_path):
    """SPEC.md §7: 4.4 adds LCT (2-byte torque instead of LCV/LCPG), LFBP, LFAIN; LFT is one byte."""
    fw = Firmware(store_dir=tmp_path, profile="4.4", seed=0)
    assert fw.transact(b"VERS\r").split(b"\n\r")[1].startswith(b"4.4")
    fw.transact(b"HI\r")
    fw.transact(b"1FSET LCT 1 LFBP 1 LFAIN 1\r")
    fw.transact(b"PSET LFT 1\r")
    fw.transact(b"1LOOP\r")
    layout = fw.loop_layout
    assert layout.control_fields == ((1, "LCT"),)
    block = layout.encode_control([16000])
    assert len(block) == 3
    values = None
    for _ in range(50):
        values = layout.feedback_by_motor(layout.decode_feedback(fw.transact(block)))
    assert values[1]["LFAP"] > 200  # a datum of 16000 counts ahead closes the finger (SPEC.md §7)
    assert values[1]["LFAIN"] == 0
    assert 20 <= values["LFT"] <= 80  # whole degrees C
    fw.transact(b"\x03")
    assert fw.transact(b"1FGET LCT\r") == b"1FGET LCT\n\r1\n\r=> "
    fw.shutdown()
    fw43 = Firmware(store_dir=tmp_path / "43", seed=0)
    assert fw43.transact(b"FGET LCT\r") == b"FGET LCT\n\rERR 64\n\r=> "
    fw43.shutdown()


def _lct_positions(fw: Firmware, motors: str, data: list[int], cycles: int) -> list[int]:
    """LFAP of the first LOOP motor after each of `cycles` C blocks carrying the LCT `data`."""
    layout = fw.loop_layout
    block = layout.encode_control(data)
    first = layout.motors[0]
    return [layout.feedback_by_motor(layout.decode_feedback(fw.transact(block)))[first]["LFAP"] for _ in range(cycles)]


def test_lct_is_a_position_datum_added_to_the_present_position(tmp_path):
    """SPEC.md §7 (LCT on a BH8-262, from Barrett's API 4.4.3 documentation of RTSetTorque: "the
    desired motor torque will be added to the present motor encoder position and be submitted as
    the commanded position"): with the datum a client sends, ±300, the spread crosses most of its
    3150-count range within 20 cycles and comes back (a direct motor command U = LCT/256 moved it
    less than 100 counts in 50 cycles); a datum ten times smaller moves it far less, the sign picks
    the direction, and 0 commands the position it is at. (The spread is still ringing from SM's
    stop when LOOP starts, about 100 counts, docs/modelling.md; with datum 0 nothing stops the
    coast but friction, so the hold is checked once it has settled.)"""
    fw = Firmware(store_dir=tmp_path, profile="4.4", seed=0)
    fw.transact(b"HI\r")
    fw.transact(b"SM 600\r")
    fw.transact(b"SFSET LCT 1 LFV 0 LFS 0 LFAP 1 LFDP 0\r")
    fw.transact(b"SLOOP\r")
    assert fw.loop_layout.control_fields == ((4, "LCT"),)
    _lct_positions(fw, "S", [0], 15)
    start = _lct_positions(fw, "S", [0], 3)
    assert max(start) - min(start) < 10
    snap = fw.snapshot()
    small = _lct_positions(fw, "S", [30], 20)[-1] - start[-1]
    fw.restore(snap)
    large = _lct_positions(fw, "S", [300], 20)[-1] - start[-1]
    assert large > 1500 and 0 < small < large / 3, (small, large)
    back = _lct_positions(fw, "S", [-300], 30)
    assert back[-1] < back[0] - 1500
    fw.transact(b"\x03")
    fw.shutdown()
