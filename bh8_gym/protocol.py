"""Facts of the BH8-262 and its serial protocol that every layer shares, each defined once here.

The firmware emulator, the client, the terminal, the environments and `bh8 deploy` import them
from this module, so the simulated hand and the hosts that drive a real one cannot disagree.
Sources: manual §5.1 (motor prefixes), §5.4.1 (BAUD), §9.1 (8N1); SPEC.md §1-§2, §7.
"""
from __future__ import annotations

MOTORS = (1, 2, 3, 4)  # F1, F2, F3, spread
FINGER_MOTORS = (1, 2, 3)
SPREAD_MOTOR = 4  # no strain gauge (§5.3.2: its LFS reads 255)
# The motor prefix of a command (§5.1): a digit names one motor, G the fingers, S the spread.
MOTOR_PREFIXES = {"1": (1,), "2": (2,), "3": (3,), "4": (4,), "G": FINGER_MOTORS, "S": (SPREAD_MOTOR,)}

FIRMWARE_PROFILES = ("4.3", "4.4")  # 4.3x and the 4.4 additions (SPEC.md §7)

# The rates the hand accepts, bits per second: §5.4.1 BAUD is the rate / 100.
BAUD_RATES = (600, 1200, 2400, 4800, 9600, 19200, 38400)
BAUD_VALUES = tuple(rate // 100 for rate in BAUD_RATES)  # 6 12 24 48 96 192 384
BITS_PER_BYTE = 10  # 8N1: start bit, 8 data bits, stop bit (§9.1)
# SPEC.md §6 / Contract 2: the firmware's processing time per RealTime cycle (SPEC.md §8 open point;
# the 68HC811 at 1.25 MHz (§9.1) needs about a millisecond to act on a block and fill a feedback block).
REALTIME_PROCESSING_S = 1.0e-3
PROMPT = b"=> "  # ends every supervisory reply (SPEC.md §2)
LINE_END = b"\n\r"  # the firmware ends its lines LF CR
CTRL_C = 0x03  # ^C: aborts a motion (§5.5 case 4), leaves LOOP; a data byte inside a RealTime block (SPEC.md §2)


def seconds_per_byte(baud: int) -> float:
    """The time one byte takes on the line at `baud` bits per second (SPEC.md §6 charges it)."""
    return BITS_PER_BYTE / baud
