"""RealTime (LOOP mode) control and feedback blocks: layout from the flags, encode and decode.

One codec serves the firmware emulator, the serial client and the environments, so the simulator
and the real hand cannot drift apart. Sources: manual §6.2-§6.4, Tables 4-5; SPEC.md §5 (block
layout, byte counting) and §7 (firmware 4.4 additions: LCT, LFBP, LFAIN, one-byte LFT).

Layout (SPEC.md §5, §7). Control block: a header byte, then per LOOP motor in motor order
LCV (signed byte) and LCPG (unsigned byte), or on firmware 4.4 a motor with LCT set sends only
LCT (signed big-endian 16-bit). Feedback block: b"*", then per LOOP motor LFV (signed byte),
LFS (unsigned byte), LFAP (unsigned big-endian 16-bit), LFDP (signed byte), and on 4.4 LFBP
(unsigned big-endian 16-bit) and LFAIN (unsigned byte); then LFT: signed big-endian 16-bit tenths
of a degree C on 4.3, one signed byte of whole degrees C on 4.4 (signedness is our choice: SPEC.md
§7 says "one byte"; hand temperatures are positive either way).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, fields
from typing import Mapping, Sequence

from bh8_gym.protocol import FIRMWARE_PROFILES, MOTORS

HEADER_CONTROL_FEEDBACK = b"C"  # control data follows; reply with a feedback block
HEADER_CONTROL_ACK = b"c"  # control data follows; reply "*"
HEADER_FEEDBACK = b"A"  # no control data; reply with a feedback block
HEADER_ACK = b"a"  # no control data; reply "*"
HEADER_EXIT = b"\x03"  # ^C: leave RealTime mode, reply with the prompt
HEADERS_WITH_DATA = frozenset(b"Cc")
HEADERS_WITH_FEEDBACK = frozenset(b"CA")
VALID_HEADERS = frozenset(b"CcAa\x03")
ACK = b"*"

# (struct code, minimum, maximum) of every datum.
_DATUM = {
    "LCV": ("b", -128, 127),
    "LCPG": ("B", 0, 255),
    "LCT": ("h", -32768, 32767),
    "LFV": ("b", -128, 127),
    "LFS": ("B", 0, 255),
    "LFAP": ("H", 0, 65535),
    "LFDP": ("b", -128, 127),
    "LFBP": ("H", 0, 65535),
    "LFAIN": ("B", 0, 255),
    "LFT43": ("h", -32768, 32767),
    "LFT44": ("b", -128, 127),
}


@dataclass(frozen=True)
class MotorFlags:
    """A motor's RealTime flag parameters (§5.3.3 defaults; LCT, LFBP, LFAIN exist on 4.4 only)."""

    LCV: bool = True
    LCPG: bool = True
    LFV: bool = True
    LFS: bool = True
    LFAP: bool = True
    LFDP: bool = True
    LCT: bool = False
    LFBP: bool = False
    LFAIN: bool = False

    @classmethod
    def from_parameters(cls, values: Mapping[str, int]) -> "MotorFlags":
        """Flags from a motor's parameter values (missing names take their defaults)."""
        known = {f.name for f in fields(cls)}
        return cls(**{name: bool(value) for name, value in values.items() if name in known})


class LoopLayout:
    """The byte layout of control and feedback blocks for one LOOP configuration."""

    def __init__(
        self,
        motors: Sequence[int] = MOTORS,
        flags: MotorFlags | Mapping[int, MotorFlags] = MotorFlags(),
        lft: bool = False,
        firmware: str = "4.3",
    ):
        motors = tuple(sorted(set(int(m) for m in motors)))
        if not motors or any(m not in MOTORS for m in motors):
            raise ValueError(f"LOOP motors must be a non-empty subset of 1..4, got {motors!r}")
        if firmware not in FIRMWARE_PROFILES:
            raise ValueError(f"firmware profile must be one of {FIRMWARE_PROFILES}, got {firmware!r}")
        if isinstance(flags, MotorFlags):
            flags = {m: flags for m in motors}
        missing = [m for m in motors if m not in flags]
        if missing:
            raise ValueError(f"no flags given for LOOP motor(s) {missing}")
        self.motors = motors
        self.flags = {m: flags[m] for m in motors}
        self.lft = bool(lft)
        self.firmware = firmware
        is_44 = firmware == "4.4"

        control: list[tuple[int, str]] = []
        feedback: list[tuple[int | None, str]] = []
        for m in motors:
            f = self.flags[m]
            if is_44 and f.LCT:
                control.append((m, "LCT"))
            else:
                if f.LCV:
                    control.append((m, "LCV"))
                if f.LCPG:
                    control.append((m, "LCPG"))
            for name in ("LFV", "LFS", "LFAP", "LFDP") + (("LFBP", "LFAIN") if is_44 else ()):
                if getattr(f, name):
                    feedback.append((m, name))
        if self.lft:
            feedback.append((None, "LFT"))
        self.control_fields = tuple(control)
        self.feedback_fields = tuple(feedback)
        lft_key = "LFT44" if is_44 else "LFT43"
        self._control_limits = tuple(_DATUM[name][1:] for _, name in control)
        self._feedback_limits = tuple(_DATUM[lft_key if name == "LFT" else name][1:] for _, name in feedback)
        self._control_struct = struct.Struct(">" + "".join(_DATUM[name][0] for _, name in control))
        self._feedback_struct = struct.Struct(
            ">" + "".join(_DATUM[lft_key if name == "LFT" else name][0] for _, name in feedback)
        )
        self.control_payload_size = self._control_struct.size
        self.feedback_size = 1 + self._feedback_struct.size

    def __repr__(self) -> str:
        return (
            f"LoopLayout(motors={self.motors}, control={[f'{m}:{n}' for m, n in self.control_fields]}, "
            f"feedback={[f'{m}:{n}' if m else n for m, n in self.feedback_fields]}, firmware={self.firmware!r})"
        )

    def __eq__(self, other) -> bool:
        return isinstance(other, LoopLayout) and (
            self.motors, self.flags, self.lft, self.firmware
        ) == (other.motors, other.flags, other.lft, other.firmware)

    def same_blocks(self, other: "LoopLayout") -> bool:
        """True if both layouts encode and decode the very same bytes, whatever firmware they name
        (4.3 and 4.4 differ only with LFT, or 4.4's own data)."""
        return (self.control_fields, self.feedback_fields, self._control_struct.format, self._feedback_struct.format) == (
            other.control_fields, other.feedback_fields, other._control_struct.format, other._feedback_struct.format)

    def control_block_size(self, header: bytes | int) -> int:
        """Bytes in a control block with this header (b'C', b'c', b'A', b'a', b'\\x03' or its byte
        value), the header included."""
        code = header[0] if isinstance(header, (bytes, bytearray)) and len(header) == 1 else header
        if not isinstance(code, int) or code not in VALID_HEADERS:
            raise ValueError(f"invalid RealTime header {header!r}; expected one of b'C', b'c', b'A', b'a', b'\\x03' "
                             "or their byte values")
        return 1 + (self.control_payload_size if code in HEADERS_WITH_DATA else 0)

    def encode_control(self, values: Sequence[int], header: bytes = HEADER_CONTROL_FEEDBACK) -> bytes:
        """A control block: `header` then `values` in `control_fields` order (none for A/a/^C)."""
        if header not in (HEADER_CONTROL_FEEDBACK, HEADER_CONTROL_ACK, HEADER_FEEDBACK, HEADER_ACK, HEADER_EXIT):
            raise ValueError(f"invalid RealTime header {header!r}; expected one of b'C', b'c', b'A', b'a', b'\\x03'")
        if header[0] not in HEADERS_WITH_DATA:
            if len(values):
                raise ValueError(f"header {header!r} carries no control data, got {len(values)} values")
            return header
        if len(values) != len(self.control_fields):
            raise ValueError(
                f"expected {len(self.control_fields)} control values {self.control_fields}, got {len(values)}"
            )
        return header + _checked_pack(self._control_struct, self._control_limits, self.control_fields, values,
                                      "control")

    def decode_control(self, payload: bytes) -> tuple[int, ...]:
        """The control values of a block's data bytes (header excluded)."""
        if len(payload) != self.control_payload_size:
            raise ValueError(f"control data must be {self.control_payload_size} bytes, got {len(payload)}")
        return self._control_struct.unpack(payload)

    def encode_feedback(self, values: Sequence[int]) -> bytes:
        """A feedback block: b'*' then `values` in `feedback_fields` order, each range-checked."""
        if len(values) != len(self.feedback_fields):
            raise ValueError(
                f"expected {len(self.feedback_fields)} feedback values {self.feedback_fields}, got {len(values)}"
            )
        return ACK + _checked_pack(self._feedback_struct, self._feedback_limits, self.feedback_fields, values,
                                   "feedback")

    def decode_feedback(self, block: bytes) -> tuple[int, ...]:
        """The feedback values of a whole block (starting with b'*'), in `feedback_fields` order."""
        if len(block) != self.feedback_size or block[:1] != ACK:
            raise ValueError(
                f"a feedback block is b'*' plus {self.feedback_size - 1} bytes; got {len(block)} bytes "
                f"starting {bytes(block[:1])!r}"
            )
        return self._feedback_struct.unpack_from(block, 1)

    def feedback_by_motor(self, values: Sequence[int]) -> dict:
        """Decoded values keyed like {1: {"LFS": 120, ...}, ..., "LFT": 412}."""
        out: dict = {m: {} for m in self.motors}
        for value, (motor, name) in zip(values, self.feedback_fields):
            if motor is None:
                out[name] = value
            else:
                out[motor][name] = value
        return out


def _checked_pack(packer: struct.Struct, limits, fields, values, kind: str) -> bytes:
    """`values` packed after checking each against its datum's range (a ValueError naming it)."""
    try:
        for value, (lo, hi), (motor, name) in zip(values, limits, fields):
            if not lo <= value <= hi:
                raise ValueError(f"{name} for motor {motor} must be in {lo}..{hi}, got {value!r}")
        return packer.pack(*values)
    except (struct.error, TypeError):  # not a number ("5"), or in range but not an integer (1.5)
        raise ValueError(f"{kind} values must be integers, got {list(values)!r}") from None
