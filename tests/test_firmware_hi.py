"""HI does not depend on what the hand did before it (issue 42): after LOOP, RealTime blocks, RESET
and a real client's gains, HI homes every motor at its open stop and answers without error.

Sources: manual §5.2.1 HI ("After an HI, all motors are in their home position; at 0 encoder
counts"), §5.3.4 (IVEL, IOFF, TSTOP "Time in milliseconds before motor is considered stopped"), §5.5
(the commands that report ERR 16; HI is not one), §6 (RealTime blocks), §8 (a finger "not opened
completely" is initialised again); SPEC.md §4 (HI), §5 and §7 (LOOP, LCT); docs/clients.md
(libgripper, the byte sequence below: facts read from its source, no code taken).
"""
from __future__ import annotations

import sys

import pytest
import serial

from conftest import PROMPT, PtyLink
from bh8_gym.firmware import Firmware

# libgripper (dmiller12/libgripper b548d8b, BarrettHand::initialize and BarrettHandDriver::configureRealtime):
# after HI it leaves these gains on the spread (no FSAVE) and configures RealTime so.
LIBGRIPPER_GAINS = (b"SFSET FPG 5 FIP 1 FDZ 100", b"GFSET FPG 10 FIP 0 FDZ 0")
_FINGER_FLAGS = b"FSET LCV 1 LCVC 2 LCPG 0 LCT 0 LFV 0 LFVC 1 LFAP 1 LFS 0 LFDP 0 LFBP 0 LFAIN 0"
LIBGRIPPER_REALTIME = (b"1" + _FINGER_FLAGS, b"2" + _FINGER_FLAGS, b"3" + _FINGER_FLAGS,
                       b"SFSET LCV 0 LCVC 0 LCPG 0 LCT 1 LFV 0 LFVC 1 LFAP 1 LFS 0 LFDP 0 LFBP 0 LFAIN 0",
                       b"PSET LFT 1")
# '*', LFAP of F1 F2 F3 S (two bytes each), LFT (one byte, firmware 4.4)
FEEDBACK_SIZE = 1 + 4 * 2 + 1
OPEN_STOP_COUNTS = 50  # a motor homed at its open stop: the plant's counts (0 = the stop) within this of IOFF
IOFF = (50, 50, 50, 0)  # §5.3.4 defaults: the home lies IOFF counts closed from full open


def ok(fw: Firmware, line: bytes) -> bytes:
    reply = fw.transact(line + b"\r")
    assert reply.startswith(line + b"\n\r") and reply.endswith(PROMPT) and b"ERR" not in reply, reply
    return reply


def assert_homed_at_the_open_stops(fw: Firmware) -> None:
    """§5.2.1: every motor at 0 counts, S 0, and the zero IOFF from where the plant's joint is at its
    open stop (§5.3.4 IOFF)."""
    assert ok(fw, b"FGET S") == b"FGET S\n\r0 0 0 0\n\r=> "
    assert [abs(int(v)) <= OPEN_STOP_COUNTS for v in ok(fw, b"FGET P").split(b"\n\r")[1].split()] == [True] * 4
    plant = fw.plant.motor_positions()
    assert [abs(c - ioff) <= OPEN_STOP_COUNTS for c, ioff in zip(plant, IOFF)] == [True] * 4, plant


@pytest.fixture
def hand(tmp_path):
    fw = Firmware(profile="4.4", store_dir=tmp_path / "store", seed=0)
    ok(fw, b"HI")
    yield fw
    fw.shutdown()


def test_hi_after_one_feedback_block_with_the_spread_under_lct(hand):
    """Issue 42's history: libgripper's gains on the spread, one `A` block in 1234LOOP with the spread
    under LCT (§6, SPEC.md §7), ^C, SC, the same again; the spread is left at rest (LCT's datum 0 holds
    it where it is), and a seek from rest at FPG 5 gathers speed slowly (5 counts in TSTOP). HI used to
    take that for stopped and answer ERR 16; it homes every motor at its open stop."""
    fw = hand
    for line in LIBGRIPPER_GAINS + LIBGRIPPER_REALTIME:
        ok(fw, line)
    for _ in range(2):
        assert fw.transact(b"1234LOOP\r") == b"1234LOOP*"
        assert len(fw.transact(b"A")) == FEEDBACK_SIZE
        assert fw.transact(b"\x03") == b"\n\r=> "
        ok(fw, b"SC")
    assert fw.plant.motor_positions()[3] > 3000
    for _ in range(2):  # not once by luck: the second HI starts at the open stop, at rest
        assert fw.transact(b"HI\r") == b"HI\n\r=> "
        assert_homed_at_the_open_stops(fw)


def test_hi_after_realtime_blocks_that_moved_every_motor(hand):
    """§6 control blocks (LCV and LCPG for the fingers, LCT for the spread, firmware 4.4) close the
    fingers and the spread part way; ^C leaves LOOP holding them (SPEC.md §5); HI homes them all."""
    fw = hand
    ok(fw, b"GFSET LCV 1 LCVC 1 LCPG 1 LCT 0 LFV 0 LFS 0 LFAP 1 LFDP 0")
    ok(fw, b"SFSET LCV 0 LCPG 0 LCT 1 LFV 0 LFS 0 LFAP 1 LFDP 0")
    assert fw.transact(b"1234LOOP\r") == b"1234LOOP*"
    block = b"C" + bytes([100, 200]) * 3 + (300).to_bytes(2, "big")
    for _ in range(60):
        assert fw.transact(block)[:1] == b"*"
    assert fw.transact(b"\x03") == b"\n\r=> "
    assert [c > 1000 for c in fw.plant.motor_positions()] == [True] * 4
    ok(fw, b"SFSET FPG 5 FIP 1 FDZ 100")
    assert fw.transact(b"HI\r") == b"HI\n\r=> "
    assert_homed_at_the_open_stops(fw)


def test_hi_after_reset_from_a_closed_hand(hand):
    """RESET is a power cycle (SPEC.md §2): gains back from the store, motors uninitialised, the
    HCTL counters zero wherever the motors are; HI then homes every motor at its open stop."""
    fw = hand
    ok(fw, b"GC")
    ok(fw, b"SC")
    ok(fw, LIBGRIPPER_GAINS[0])
    assert fw.transact(b"RESET\r").endswith(PROMPT)
    assert fw.transact(b"SC\r") == b"SC\n\rERR 4\n\r=> "
    assert fw.transact(b"HI\r") == b"HI\n\r=> "
    assert_homed_at_the_open_stops(fw)


def _command(port: serial.Serial, line: bytes, deadline_s: float = 30.0) -> bytes:
    """libgripper's supervisory call: the line and CR, read the echo, then up to "\\n\\r=> "."""
    port.write(line + b"\r")
    return _read_until(port, line, deadline_s) + _read_until(port, b"\n\r=> ", deadline_s)


def _read_until(port: serial.Serial, end: bytes, deadline_s: float) -> bytes:
    data = bytearray()
    for _ in range(int(deadline_s / port.timeout)):
        data += port.read(max(1, len(end) - len(data)) if not data.endswith(end) else 0)
        if data.endswith(end):
            return bytes(data)
    raise AssertionError(f"no {end!r}: {bytes(data)!r}")


def _read_exact(port: serial.Serial, count: int) -> bytes:
    data = bytearray()
    for _ in range(200):
        data += port.read(count - len(data))
        if len(data) == count:
            return bytes(data)
    raise AssertionError(f"wanted {count} bytes, got {bytes(data)!r}")


def _loop_with_feedback(port: serial.Serial, blocks: int) -> bytes:
    """1234LOOP, its '*', then `blocks` `A` blocks (libgripper's thread sends `A` while it has no
    setpoint); returns the last feedback block."""
    port.write(b"1234LOOP\r")
    assert _read_exact(port, len(b"1234LOOP*")) == b"1234LOOP*"
    for _ in range(blocks):
        port.write(b"A")
        feedback = _read_exact(port, FEEDBACK_SIZE)
        assert feedback[:1] == b"*"
    return feedback


def _stop_realtime(port: serial.Serial) -> None:
    port.write(b"\x03")
    assert _read_until(port, PROMPT, 30).endswith(b"\n\r=> ")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="pty tests need Linux /dev/pts")
def test_libgrippers_test_bhand_initialises_ten_times_in_a_row(tmp_path):
    """libgripper's `test_bhand` (docs/clients.md), its bytes through a real pty, run 10 times
    against one `bh8 serve --firmware 4.4`: connect (^C, prompt), HI (any ERR reply is "Failed to
    initialize hand"), its gains and RealTime flags, 1234LOOP with `A` blocks, ^C, SC, 1234LOOP again,
    ^C, and ^C on disconnect. Every run initialises (issue 42: runs 2 on answered ERR 16), and the
    spread's LFAP reads 0 after HI and its full range after SC: the zero is at its open stop."""
    link = PtyLink(tmp_path / "store", ("--firmware", "4.4"))
    try:
        link.port.close()
        for run in range(10):
            with serial.Serial(link.device, 9600, timeout=0.05) as port:
                port.write(b"\x03")
                _read_until(port, PROMPT, 30)
                assert _command(port, b"HI") == b"HI\n\r=> ", f"run {run + 1}"
                for line in LIBGRIPPER_GAINS + LIBGRIPPER_REALTIME:
                    assert _command(port, line) == line + b"\n\r=> "
                spread = int.from_bytes(_loop_with_feedback(port, 3)[7:9], "big")
                assert spread <= OPEN_STOP_COUNTS, f"run {run + 1}: the spread reads {spread} after HI"
                _stop_realtime(port)
                assert _command(port, b"SC") == b"SC\n\r=> "
                spread = int.from_bytes(_loop_with_feedback(port, 3)[7:9], "big")
                assert spread > 3000, f"run {run + 1}: the spread reads {spread} after SC"
                _stop_realtime(port)
                port.write(b"\x03")  # libgripper's disconnect
    finally:
        link.close()
