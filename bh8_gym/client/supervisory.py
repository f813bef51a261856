"""The supervisory command set of a BarrettHand (manual §5.2): movement, parameters and
administration, each a method that sends one GCL line and reads its reply.

`SupervisoryCommands` is one part of `BarrettHand` (a mixin: it sends through the client's
`SerialLine` once the client is at a supervisory prompt), so a program calls `hand.get("P")`,
`hand.close_motors("G")`. Motion commands are answered when the motion ends (§5.5) and get
`motion_timeout`; RESET gets RESET_TIMEOUT_S; everything else the client's `timeout`.
"""
from __future__ import annotations

import re
import time
from typing import Iterable, Mapping

from bh8_gym.client.line import CR, SerialLine, check_baud_rate
from bh8_gym.protocol import LINE_END, MOTOR_PREFIXES, MOTORS, PROMPT
from bh8_gym.status import ProtocolError

BANNER = b"BarrettHand Firmware"  # RESET's banner contains it (SPEC.md §2; Barrett's API checks it)

# RESET is a power cycle (§5.2.4); the 68HC811 reloads its parameters before the banner.
RESET_TIMEOUT_S = 10.0
# Barrett's API 4.4.3 Baud(): after "PSET BAUD n" and its echo it switches the host rate and sleeps
# 1 s before talking at the new rate.
BAUD_SWITCH_SETTLE_S = 1.0

# Commands whose reply comes when the motion ends (§5.5); everything else is answered at once.
MOTION_COMMANDS = frozenset({"HI", "C", "O", "M", "HOME", "IO", "IC", "TC", "TO"})
_COMMAND_WORD = re.compile(r"^\s*([1-4GSgs]*)\s*([A-Za-z?]+)")  # the firmware takes "G C" as "GC"
_PARAMETER_NAME = re.compile(r"^[A-Z][A-Z0-9]*$")
_VERSION = re.compile(r"(\d+)\.(\d+)")


def parse_motors(motors: str | int | Iterable[int] | None) -> tuple[str, tuple[int, ...]]:
    """A motor set as (GCL prefix, motor numbers in order); None is no prefix (a movement command
    then acts on the EN=1 motors, any other motor command on all four).

    Accepts Table 2 prefixes ("1", "G", "GS", "124", "3S", lower case too), a motor number, or an
    iterable of motor numbers 1..4. Raises ValueError naming a bad set.
    """
    if motors is None:
        return "", ()
    selected: set[int] = set()
    if isinstance(motors, str):
        if not motors:
            raise ValueError(f"invalid motor set {motors!r}: empty; use e.g. '1', 'G', 'GS', '124' or None for the EN motors")
        for char in motors.upper():
            if char not in MOTOR_PREFIXES:
                raise ValueError(
                    f"invalid motor set {motors!r}: {char!r} is not one of 1 2 3 4 G S (manual Table 2)"
                )
            selected.update(MOTOR_PREFIXES[char])
    else:
        try:
            items = (motors,) if isinstance(motors, int) else tuple(motors)
        except TypeError:
            raise ValueError(f"invalid motor set {motors!r}: give a prefix such as 'G', a motor number or "
                             "motor numbers") from None
        for item in items:
            if isinstance(item, bool) or not isinstance(item, int) or item not in MOTORS:
                raise ValueError(f"invalid motor set {motors!r}: {item!r} is not a motor number 1..4")
            selected.add(item)
        if not selected:
            raise ValueError(f"invalid motor set {motors!r}: empty; give motor numbers 1..4")
    ordered = tuple(sorted(selected))
    return "".join(str(m) for m in ordered), ordered


def _check_int(name: str, value, low: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{name} must be an integer in {low}..{high}, got {value!r}")
    if not low <= value <= high:
        raise ValueError(f"{name} must be in {low}..{high}, got {value}")
    return value


def _check_parameter_name(name) -> str:
    if not isinstance(name, str) or not _PARAMETER_NAME.match(name.upper()):
        raise ValueError(f"invalid parameter name {name!r}: expected letters and digits such as 'MCV'")
    return name.upper()


def _check_command_line(line) -> str:
    if not isinstance(line, str):
        raise ValueError(f"a command line must be a str, got {line!r}")
    bad = [c for c in line if c in "\r\n\x03" or not c.isprintable()]
    if bad:
        raise ValueError(f"a command line must be printable text without CR, LF or ^C, got {line!r}")
    try:
        line.encode("ascii")
    except UnicodeEncodeError:
        raise ValueError(f"a command line must be ASCII, got {line!r}") from None
    return line


def firmware_profile_of(version: str) -> str:
    """The codec profile ("4.3" or "4.4") of a VERS reply such as "4.34" or "BarrettHand 4.40"."""
    found = _VERSION.search(version)
    if found and found.group(1) == "4" and found.group(2).startswith("4"):
        return "4.4"
    return "4.3"


class SupervisoryCommands:
    """The §5.2 commands of `BarrettHand` (module docstring). From the client it needs `_line`,
    `timeout`, `motion_timeout` and `_ensure_supervisory()` (resynchronise if the line needs it,
    refuse while in RealTime mode)."""

    _line: SerialLine
    timeout: float
    motion_timeout: float

    # -- supervisory transactions ------------------------------------------------------------

    def _budget_for(self, line: str) -> float:
        found = _COMMAND_WORD.match(line)
        word = found.group(2).upper() if found else ""
        if word in MOTION_COMMANDS:
            return self.motion_timeout
        if word == "RESET":
            return RESET_TIMEOUT_S
        return self.timeout

    def _transact(self, line: str, budget_s: float | None = None) -> list[str]:
        """Send one line, return its output lines (echo and prompt stripped), ERR included."""
        self._ensure_supervisory()
        return self._line.transact(line, self._budget_for(line) if budget_s is None else budget_s)

    def _checked(self, line: str, budget_s: float | None = None) -> list[str]:
        self._ensure_supervisory()
        return self._line.checked(line, self._budget_for(line) if budget_s is None else budget_s)

    def command(self, line: str, check: bool = True) -> list[str]:
        """Send one GCL line (no CR) and return the hand's output lines (the escape hatch).

        With `check`, an "ERR n" reply raises HandError; without, it is returned as a line.
        LOOP and PSET BAUD change the line's protocol or rate: use start_loop() and set_baud().
        """
        line = _check_command_line(line)
        tokens = line.upper().split()
        found = _COMMAND_WORD.match(line)
        if found and found.group(2).upper() == "LOOP":
            raise ValueError(f"{line!r}: enter RealTime mode with start_loop(), not command()")
        if tokens and tokens[0] == "PSET" and "BAUD" in tokens[1::2]:
            raise ValueError(f"{line!r}: change the baud rate with set_baud(), which also switches the host")
        return self._checked(line) if check else self._transact(line)

    # -- movement (§5.2.1) -------------------------------------------------------------------

    def _motion(self, motors, verb: str, argument: int | None = None, what: str = "counts") -> None:
        if argument is not None:
            _check_int(what, argument, 0, 20000)  # §5.2.1
        prefix, _ = parse_motors(motors)
        self._checked(f"{prefix}{verb}" if argument is None else f"{prefix}{verb} {argument}")

    def initialize(self, motors="GS") -> None:
        """HI: open each motor against its stop and set its origin (must precede other motions)."""
        self._motion(motors, "HI")

    def open_motors(self, motors="GS") -> None:
        """O: move to the open target OT (never ERR 16)."""
        self._motion(motors, "O")

    def close_motors(self, motors="GS") -> None:
        """C: move to the close target CT (never ERR 16). (`close()` releases the port.)"""
        self._motion(motors, "C")

    def move(self, position: int | None = None, motors="GS") -> None:
        """M: move to `position` counts (0..20000, §5.2.1), or to DP when None."""
        self._motion(motors, "M", position, "position")

    def step_open(self, counts: int | None = None, motors="GS") -> None:
        """IO: open by `counts` (0..20000), or by DS when None."""
        self._motion(motors, "IO", counts)

    def step_close(self, counts: int | None = None, motors="GS") -> None:
        """IC: close by `counts` (0..20000), or by DS when None."""
        self._motion(motors, "IC", counts)

    def home(self, motors="GS") -> None:
        """HOME: move to position 0."""
        self._motion(motors, "HOME")

    def torque_open(self, motors="GS") -> None:
        """TO: velocity-controlled open at MOV until stall."""
        self._motion(motors, "TO")

    def torque_close(self, motors="GS") -> None:
        """TC: velocity-controlled close at MCV until stall (stall force grows with MCV)."""
        self._motion(motors, "TC")

    def terminate(self, motors="GS") -> None:
        """T: turn the motors' power off."""
        self._motion(motors, "T")

    # -- parameters (§5.2.2, §5.2.3) ---------------------------------------------------------

    @staticmethod
    def _names(names) -> list[str]:
        try:
            items = names.split() if isinstance(names, str) else list(names)
        except TypeError:
            raise ValueError(f"parameter names must be a string or strings, got {names!r}") from None
        if not items:
            raise ValueError("give at least one parameter name")
        return [_check_parameter_name(name) for name in items]

    @staticmethod
    def _pairs(values: Mapping | None, pairs: dict) -> list[tuple[str, int]]:
        merged = dict(values or {})
        merged.update(pairs)
        if not merged:
            raise ValueError("give at least one parameter=value pair")
        out = []
        for name, value in merged.items():
            name = _check_parameter_name(name)
            if isinstance(value, bool):
                value = int(value)
            if not isinstance(value, int):
                raise ValueError(f"value of {name} must be an integer, got {value!r}")
            out.append((name, value))
        return out

    @staticmethod
    def _parse_values(line: str, name: str, command: str) -> list[int]:
        try:
            return [int(token) for token in line.split()]
        except ValueError:
            raise ProtocolError(f"{command!r}: expected integers for {name}, got {line!r}") from None

    def get(self, names, motors="GS") -> dict[str, list[int]]:
        """FGET: {name: [value per selected motor, F1 F2 F3 S order]} for names like "P" or ["P", "SG"]."""
        prefix, selected = parse_motors(motors)
        names = self._names(names)
        line = f"{prefix}FGET {' '.join(names)}"
        lines = self._checked(line)
        if len(lines) != len(names):
            self._line.needs_resync = True
            raise ProtocolError(f"{line!r}: expected {len(names)} lines, got {lines!r}")
        result = {}
        for name, text in zip(names, lines):
            values = self._parse_values(text, name, line)
            if selected and len(values) != len(selected):
                raise ProtocolError(f"{line!r}: expected {len(selected)} values for {name}, got {text!r}")
            result[name] = values
        return result

    def set(self, motors="GS", values: Mapping[str, int] | None = None, /, **pairs: int) -> None:
        """FSET several parameters at once: set("G", MCV=80, MOV=80) or set("GS", {"HOLD": 1})."""
        prefix, _ = parse_motors(motors)
        body = " ".join(f"{name} {value}" for name, value in self._pairs(values, pairs))
        self._checked(f"{prefix}FSET {body}")

    def get_global(self, names) -> dict[str, int]:
        """PGET: {name: value} for global parameters such as "TEMP" or ["BAUD", "LFT"]."""
        names = self._names(names)
        line = f"PGET {' '.join(names)}"
        lines = self._checked(line)
        if len(lines) != len(names):
            self._line.needs_resync = True
            raise ProtocolError(f"{line!r}: expected {len(names)} lines, got {lines!r}")
        result = {}
        for name, text in zip(names, lines):
            values = self._parse_values(text, name, line)
            if len(values) != 1:
                raise ProtocolError(f"{line!r}: expected one value for {name}, got {text!r}")
            result[name] = values[0]
        return result

    def set_global(self, values: Mapping[str, int] | None = None, /, **pairs: int) -> None:
        """PSET several global parameters at once (BAUD goes through set_baud())."""
        pairs_list = self._pairs(values, pairs)
        if any(name == "BAUD" for name, _ in pairs_list):
            raise ValueError("change BAUD with set_baud(), which also switches the host's rate")
        self._checked("PSET " + " ".join(f"{name} {value}" for name, value in pairs_list))

    def save(self, motors="GS") -> None:
        """FSAVE: write the motors' parameters to non-volatile storage (≤ 5000 times, §5.2.2)."""
        self._checked(f"{parse_motors(motors)[0]}FSAVE")

    def load(self, motors="GS") -> None:
        """FLOAD: reload the motors' parameters from non-volatile storage."""
        self._checked(f"{parse_motors(motors)[0]}FLOAD")

    def default(self, motors="GS") -> None:
        """FDEF: factory defaults for the motors' parameters (not saved)."""
        self._checked(f"{parse_motors(motors)[0]}FDEF")

    def save_global(self) -> None:
        """PSAVE: write the global parameters to non-volatile storage."""
        self._checked("PSAVE")

    def load_global(self) -> None:
        """PLOAD: reload the global parameters from non-volatile storage."""
        self._checked("PLOAD")

    def default_global(self) -> None:
        """PDEF: factory defaults for the writable global parameters (not saved)."""
        self._checked("PDEF")

    # -- administrative (§5.2.4) -------------------------------------------------------------

    def version(self) -> str:
        """VERS: the firmware version text."""
        lines = self._checked("VERS")
        if not lines:
            raise ProtocolError("VERS printed nothing")
        return " ".join(line.strip() for line in lines)

    def temperature(self) -> float:
        """The CPU board temperature in degrees C (PGET TEMP is in tenths, §5.4.2)."""
        return self.get_global("TEMP")["TEMP"] / 10.0

    def reset(self) -> str:
        """RESET (a power cycle, §5.2.4) and return the banner; checks it names "BarrettHand Firmware".

        As Barrett's API does, a bare CR first clears any error state. Afterwards the motors need
        HI again and the parameters are those of non-volatile storage.
        """
        self._transact("")
        lines = self._transact("RESET")
        banner = "\n".join(lines)
        if BANNER.decode() not in banner:
            self._line.needs_resync = True
            raise ProtocolError(f"RESET: expected a banner containing {BANNER!r}, got {lines!r}")
        return banner

    def set_baud(self, rate: int) -> None:
        """Switch the hand and the host to `rate` bits/s (600..38400, §5.4.1), as Barrett's API does:
        PSET BAUD, read the echo, switch the host, wait 1 s, clear, bare CR, read to the prompt.

        Not saved: PSAVE afterwards makes the rate survive a power cycle (and the next connection
        must then open the port at that rate)."""
        check_baud_rate("baud rate", rate)
        self._ensure_supervisory()
        wire = self._line
        line = f"PSET BAUD {rate // 100}"
        echo = line.encode("ascii")
        try:
            wire.clear_input()
            wire.write(echo + CR)
            got = wire.read_exact(len(echo), self.timeout, repr(line))
            if got != echo:
                raise ProtocolError(f"expected the echo of {line!r}, got {got!r}")
            wire.switch_baud(rate)
            time.sleep(BAUD_SWITCH_SETTLE_S)
            wire.clear_input()
            wire.write(CR)
            reply = wire.read_until(PROMPT, self.timeout, "a bare CR at the new rate")
        except BaseException:
            wire.needs_resync = True
            raise
        if not reply.endswith(LINE_END + PROMPT):
            wire.needs_resync = True
            raise ProtocolError(f"after switching to {rate} baud, a bare CR got {reply!r}")
