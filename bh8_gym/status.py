"""Hand status codes (manual §5.1.3 Table 3; SPEC.md §2) and the exceptions that carry them."""
from __future__ import annotations

from enum import IntFlag


class Status(IntFlag):
    """Table 3. A reported status is the sum (bitwise OR) of these powers of two."""

    NO_MOTOR_BOARD = 1
    NO_MOTOR = 2
    NOT_INITIALIZED = 4
    COULD_NOT_REACH_POSITION = 16
    UNKNOWN_COMMAND = 32
    UNKNOWN_PARAMETER = 64
    INVALID_VALUE = 128
    READ_ONLY = 256
    TOO_MANY_ARGUMENTS = 1024
    INVALID_REALTIME_HEADER = 2048
    NO_PREFIX_ALLOWED = 4096
    OVER_TEMPERATURE = 8192
    CTRL_C_ABORT = 16384


STATUS_DESCRIPTIONS = {
    1: "No motor board found",
    2: "No motor found",
    4: "Motor not initialized",
    8: "(not used)",
    16: "Couldn't reach position",
    32: "Unknown command",
    64: "Unknown parameter name",
    128: "Invalid value",
    256: "Tried to write a read only parameter",
    512: "(not used)",
    1024: "Too many arguments for this command",
    2048: "Invalid RealTime control block header",
    4096: "Command can't have motor prefix",
    8192: "Overtemperature fault tripped",
    16384: "Cntl-C abort command received",
}
# Every Table 3 bit set (32767): the largest status sum a hand can report.
STATUS_MAX = sum(STATUS_DESCRIPTIONS)


def decode_status(code: int) -> list[tuple[int, str]]:
    """Split a status sum into its Table 3 bits with their descriptions, lowest bit first."""
    if code < 0:
        raise ValueError(f"a status code is a non-negative sum of Table 3 bits, got {code}")
    bits = []
    bit = 1
    while bit <= code:
        if code & bit:
            bits.append((bit, STATUS_DESCRIPTIONS.get(bit, "(unknown status bit)")))
        bit <<= 1
    return bits


class BH8Error(Exception):
    """Base class of every error bh8-gym raises on purpose."""


class HandError(BH8Error):
    """The hand answered `ERR <code>`; `code` is the status sum and `bits` its Table 3 meanings."""

    def __init__(self, code: int, command: str | None = None):
        self.code = int(code)
        self.command = command
        self.bits = decode_status(self.code)
        meanings = "; ".join(f"{bit} {text}" for bit, text in self.bits) or "no status bits"
        where = f" after {command!r}" if command else ""
        super().__init__(f"hand reported ERR {self.code}{where}: {meanings}")


class HandTimeout(BH8Error):
    """The hand did not answer within the time the command needs."""


class ProtocolError(BH8Error):
    """The hand's bytes do not match the protocol (garbage, a truncated or malformed reply)."""


def parse_status(digits: str) -> int:
    """The status sum written as the ASCII `digits` of an "ERR n" line. ProtocolError when it is
    no Table 3 sum (above STATUS_MAX: a garbled line), checked before int() sees the digits (a
    5000-digit number is past Python's integer-string limit)."""
    if not (digits.isascii() and digits.isdigit()) or len(digits.lstrip("0")) > len(str(STATUS_MAX)) \
            or int(digits) > STATUS_MAX:
        shown = digits if len(digits) <= 20 else f"{digits[:20]}... ({len(digits)} characters)"
        raise ProtocolError(f"ERR {shown} is not a status sum of Table 3 (0..{STATUS_MAX}): a garbled reply")
    return int(digits)
