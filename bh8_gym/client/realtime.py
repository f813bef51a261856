"""A RealTime session (manual §6, SPEC.md §5): entered with LOOP, left with ^C, one control block
out and (with "C"/"A") one feedback block back per cycle.

The session owns the block layout, which `BarrettHand.start_loop` builds from the flags the hand
actually has (queried before LOOP, as Barrett's RTStart does), so it cannot disagree with the hand;
every block goes through `realtime_codec.LoopLayout`. It also keeps the hand's "reported position"
(FGET P plus the LFDP deltas, §6.2.3) for each motor.
"""
from __future__ import annotations

from operator import itemgetter
from typing import NamedTuple, Sequence

from bh8_gym.client.line import CR, SerialLine, error_code, split_lines
from bh8_gym.protocol import BITS_PER_BYTE, LINE_END, PROMPT
from bh8_gym.realtime_codec import ACK, HEADER_EXIT, LoopLayout
from bh8_gym.status import HandError, HandTimeout, ProtocolError

# A RealTime reply may take its bytes' transfer time plus this: covers the hand's processing
# (about 1 ms, SPEC.md §6), USB-serial adapter latency timers (16 ms by default on FTDI chips) and
# host scheduling.
REALTIME_MARGIN_S = 0.25

# Motor parameters that configure RealTime blocks (§5.3.3; LCT, LFBP, LFAIN exist on 4.4 only).
REALTIME_MOTOR_PARAMETERS = frozenset(
    {"LCV", "LCVC", "LCPG", "LFV", "LFVC", "LFS", "LFAP", "LFDP", "LFDPC", "LCT", "LFBP", "LFAIN"}
)
FLAG_NAMES_43 = ("LCV", "LCPG", "LFV", "LFS", "LFAP", "LFDP")
FLAG_NAMES_44 = FLAG_NAMES_43 + ("LCT", "LFBP", "LFAIN")
_HEADERS = {b"C": b"C", b"c": b"c", b"A": b"A", b"a": b"a", "C": b"C", "c": b"c", "A": b"A", "a": b"a"}


class MotorFeedback(NamedTuple):
    """One LOOP motor's part of a feedback block; a datum the flags leave out is None."""

    motor: int
    velocity: int | None  # LFV: counts per sample / LFVC
    strain: int | None  # LFS: strain gauge 0..255
    absolute_position: int | None  # LFAP: encoder counts
    delta_position: int | None  # LFDP: as sent, before multiplying by LFDPC
    tracked_position: int | None  # the hand's "reported position" (§6.2.3): FGET P + sum(LFDP * LFDPC)
    breakaway_position: int | None  # LFBP (firmware 4.4)
    analog_input: int | None  # LFAIN (firmware 4.4)


class LoopFeedback(NamedTuple):
    """A decoded feedback block."""

    motors: dict  # {motor number: MotorFeedback}
    temperature: float | None  # LFT in degrees C (4.3 sends tenths, 4.4 whole degrees)
    values: tuple  # the decoded data in LoopLayout.feedback_fields order
    block: bytes  # the block as received, b"*" included


def raise_loop_error(line: SerialLine, what: str) -> None:
    """The hand sent something other than "*": "\\n\\rERR n\\n\\r=> " (back in supervisory
    mode, SPEC.md §5) raises HandError; anything else is a ProtocolError."""
    try:
        reply = line.read_until(PROMPT, line.timeout, what)
    except HandTimeout:
        raise ProtocolError(f"{what}: expected '*', got {bytes(line.rx)!r}") from None
    try:
        code = error_code(split_lines(reply[: -len(PROMPT)]))
    except ProtocolError:
        code = None
    if code is None or not reply.startswith(LINE_END):
        line.needs_resync = True
        raise ProtocolError(f"{what}: expected '*' or an ERR line, got {reply!r}")
    raise HandError(code, what)


class RealTimeSession:
    """One LOOP on a `SerialLine`, `active` from its "*" until ^C or an error ends it.

    `values` holds the FGET values read before LOOP: "P" and "LFDPC" per LOOP motor."""

    @classmethod
    def enter(cls, line: SerialLine, prefix: str, layout: LoopLayout, values: dict[str, list[int]]) -> "RealTimeSession":
        """Send "<prefix>LOOP" and read its echo and "*" (an ERR reply raises HandError)."""
        command = f"{prefix}LOOP"
        echo = command.encode("ascii")
        try:
            line.clear_input()
            line.write(echo + CR)
            got = line.read_exact(len(echo) + 1, line.timeout, repr(command))
        except BaseException:
            line.needs_resync = True
            raise
        if got[:-1] != echo:
            line.needs_resync = True
            raise ProtocolError(f"expected the echo of {command!r}, got {got!r}")
        if got[-1:] != ACK:
            line.rx[:0] = got[-1:]
            raise_loop_error(line, command)
        return cls(line, layout, values)

    def __init__(self, line: SerialLine, layout: LoopLayout, values: dict[str, list[int]]):
        """Everything update() needs, computed once per LOOP entry."""
        self._line = line
        motors = layout.motors
        position_of = {motor: i for i, motor in enumerate(motors)}
        self._tracked = [values["P"][i] for i in range(len(motors))]
        self._delta_scale = [max(1, values["LFDPC"][i]) for i in range(len(motors))]  # 0 acts as 1 (SPEC §3)
        sources = {"LCV": 0, "LCPG": 1, "LCT": 2}
        self._control_plan = tuple((sources[name], position_of[motor]) for motor, name in layout.control_fields)
        self._control_needs = tuple(sorted({source for source, _ in self._control_plan}))
        datum_slot = {"LFV": 0, "LFS": 1, "LFAP": 2, "LFDP": 3, "LFBP": 4, "LFAIN": 5}
        missing = len(layout.feedback_fields)  # index of the None appended to the decoded values
        slots = {motor: [missing] * 6 for motor in motors}
        self._lft_index = None
        for index, (motor, name) in enumerate(layout.feedback_fields):
            if motor is None:
                self._lft_index = index
            else:
                slots[motor][datum_slot[name]] = index
        self._feedback_plan = tuple(
            (motor, position_of[motor], itemgetter(*slots[motor]), slots[motor][3] != missing) for motor in motors
        )
        self._lft_scale = 0.1 if layout.firmware == "4.3" else 1.0
        block_time = BITS_PER_BYTE / line.baudrate
        self._block_budget = {
            header: (layout.control_block_size(code) + (layout.feedback_size if code in b"CA" else 1)) * block_time
            + REALTIME_MARGIN_S
            for header, code in _HEADERS.items()
        }
        self.last_control_block = b""
        self.last_feedback_block = b""
        self.layout = layout
        self.active = True

    def _check_active(self) -> None:
        if not self.active:
            raise RuntimeError("not in RealTime mode (a RealTime error or time-out ends it); call start_loop()")

    def update(self, velocities: Sequence[int] | None, gains: Sequence[int] | None, header: bytes | str,
               torques: Sequence[int] | None) -> LoopFeedback | None:
        """One RealTime cycle (`BarrettHand.update` says what the arguments are)."""
        self._check_active()
        layout = self.layout
        code = _HEADERS.get(header)
        if code is None:
            raise ValueError(f"invalid RealTime header {header!r}; expected 'C', 'c', 'A' or 'a' (§6.2.1)")
        if code in (b"C", b"c"):
            sources = (velocities, gains, torques)
            count = len(layout.motors)
            for source in self._control_needs:
                given = sources[source]
                if given is None or len(given) != count:
                    raise ValueError(
                        f"{('velocities', 'gains', 'torques')[source]} must have one value per LOOP motor "
                        f"{layout.motors}, got {given!r}"
                    )
            values = [sources[source][position] for source, position in self._control_plan]
        else:
            values = ()
        return self._exchange(layout.encode_control(values, code), code)

    def update_raw(self, values: Sequence[int], header: bytes | str = b"C") -> LoopFeedback | None:
        """One RealTime cycle with control values already in `layout.control_fields` order."""
        self._check_active()
        code = _HEADERS.get(header)
        if code is None:
            raise ValueError(f"invalid RealTime header {header!r}; expected 'C', 'c', 'A' or 'a' (§6.2.1)")
        return self._exchange(self.layout.encode_control(values if code in (b"C", b"c") else (), code), code)

    def _exchange(self, block: bytes, code: bytes) -> LoopFeedback | None:
        line = self._line
        budget = self._block_budget[code]
        try:
            line.write(block)
            self.last_control_block = block
            first = line.read_exact(1, budget, "RealTime reply")
            if first != ACK:
                line.rx[:0] = first
                self.active = False
                raise_loop_error(line, "RealTime block")
            if code in (b"a", b"c"):
                self.last_feedback_block = first
                return None
            reply = first + line.read_exact(self.layout.feedback_size - 1, budget, "RealTime feedback block")
        except BaseException as error:
            if not isinstance(error, HandError):  # the line's state is unknown: leave LOOP by resync
                line.needs_resync = True
                self.active = False
            raise
        self.last_feedback_block = reply
        return self._decode(reply)

    def _decode(self, reply: bytes) -> LoopFeedback:
        values = self.layout.decode_feedback(reply)
        padded = values + (None,)
        tracked = self._tracked
        scale = self._delta_scale
        motors = {}
        for motor, position, pick, has_delta in self._feedback_plan:
            velocity, strain, absolute, delta, breakaway, analog = pick(padded)
            if has_delta:
                tracked[position] += delta * scale[position]
                position_now = tracked[position]
            else:
                position_now = None
            motors[motor] = MotorFeedback(motor, velocity, strain, absolute, delta, position_now, breakaway, analog)
        temperature = None if self._lft_index is None else values[self._lft_index] * self._lft_scale
        return LoopFeedback(motors, temperature, values, reply)

    def leave(self) -> None:
        """^C, read to the prompt (an ERR 16384 line there is expected)."""
        line = self._line
        self.active = False
        try:
            line.write(HEADER_EXIT)
            reply = line.read_until(PROMPT, line.timeout, "^C leaving RealTime mode")
        except BaseException:
            line.needs_resync = True
            raise
        code = error_code(split_lines(reply[: -len(PROMPT)]))
        if code is not None and code != 16384:
            raise HandError(code, "^C leaving RealTime mode")
