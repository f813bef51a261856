"""`BarrettHand`: a supervisory and RealTime client for a BH8-262 over any pyserial port.

The same code drives a real hand (`/dev/ttyUSB0`, `COM3`, `socket://host:port` through a serial
server), `bh8 serve` on a pseudo-terminal, and the in-process simulator (`bh8sim://?seed=0`).

Framing (SPEC.md §2, following Barrett's C++ API 4.4.3): a supervisory call clears the input
buffer, writes the line and a CR, reads the echo and everything up to the prompt "=> ", and raises
`HandError` when the first output line is "ERR <n>". RealTime (manual §6, SPEC.md §5): the layout of
the control and feedback blocks is built from the flags the hand actually has (queried before
LOOP, as RTStart does) and every block goes through `realtime_codec.LoopLayout`.

Failure handling: a reply that does not come in time raises `HandTimeout`, bytes that do not fit
the protocol raise `ProtocolError`, a port that fails raises `HandConnectionError`. After any of
these (or a KeyboardInterrupt in the middle of a transaction) the client resynchronises before its
next call: it sends ^C (leaves LOOP, aborts a motion), then a bare CR, and discards everything up to
a fresh prompt. A port that failed is reopened first.
"""
from __future__ import annotations

import re
import time
from operator import itemgetter
from typing import Iterable, Mapping, NamedTuple, Sequence

import serial

try:
    from termios import error as _TermiosError
except ImportError:  # Windows
    _TermiosError = OSError

from bh8_gym.protocol import BAUD_RATES, BITS_PER_BYTE, FIRMWARE_PROFILES, LINE_END, MOTOR_PREFIXES, MOTORS, PROMPT
from bh8_gym.realtime_codec import ACK, HEADER_EXIT, LoopLayout, MotorFlags
from bh8_gym.status import BH8Error, HandError, HandTimeout, ProtocolError, parse_status

CR = b"\r"
BANNER = b"BarrettHand Firmware"  # RESET's banner contains it (SPEC.md §2; Barrett's API checks it)

# How long one port.read() may block before the client looks at its own deadline again. Set once
# on the port (changing a pyserial timeout reconfigures the tty every time).
READ_SLICE_S = 0.02
# Default time a non-motion reply may take (FGET, FSET, VERS, ...), and the longest silence
# tolerated while a reply is streaming (long listings at 600 baud keep extending the deadline).
DEFAULT_TIMEOUT_S = 2.0
# Default budget of a motion command. App. A: a finger closes in about 1 s at default MCV; the
# slowest legal velocity (MCV/MOV 16 = 1/6 of the default) stretches that to about 6 s, and HI
# opens against the stop IHIT times per finger before the spread; 30 s covers all of that.
DEFAULT_MOTION_TIMEOUT_S = 30.0
# RESET is a power cycle (§5.2.4); the 68HC811 reloads its parameters before the banner.
RESET_TIMEOUT_S = 10.0
# Barrett's API 4.4.3 Baud(): after "PSET BAUD n" and its echo it switches the host rate and sleeps
# 1 s before talking at the new rate.
BAUD_SWITCH_SETTLE_S = 1.0
# A RealTime reply may take its bytes' transfer time plus this: covers the hand's processing
# (about 1 ms, SPEC.md §6), USB-serial adapter latency timers (16 ms by default on FTDI chips) and
# host scheduling.
REALTIME_MARGIN_S = 0.25
# Resynchronising: the line counts as quiet when no byte arrived for this long (plus two
# characters' transfer time at the current rate).
RESYNC_QUIET_S = 0.1
# Resynchronising gives up when the hand keeps talking for longer than this without a prompt.
RESYNC_DRAIN_LIMIT_S = 5.0
# A reply still streaming is waited for at most this many bytes' time past its budget (the longest,
# A? or FLISTAV, is about 2 KB): a line that trickles bytes without a prompt cannot hang a call.
REPLY_STREAM_LIMIT_BYTES = 8192
# Attempts of ^C + CR before resynchronisation gives up. Each attempt pushes two bytes into a
# control block the hand may still be waiting to complete (lost bytes in RealTime).
RESYNC_ATTEMPTS = 4

# Commands whose reply comes when the motion ends (§5.5); everything else is answered at once.
MOTION_COMMANDS = frozenset({"HI", "C", "O", "M", "HOME", "IO", "IC", "TC", "TO"})
_ERR_LINE = re.compile(r"^ERR\s*(\d+)\s*$")
_COMMAND_WORD = re.compile(r"^\s*([1-4GSgs]*)\s*([A-Za-z?]+)")  # the firmware takes "G C" as "GC"
_PARAMETER_NAME = re.compile(r"^[A-Z][A-Z0-9]*$")
_VERSION = re.compile(r"(\d+)\.(\d+)")

# Motor parameters that configure RealTime blocks (§5.3.3; LCT, LFBP, LFAIN exist on 4.4 only).
REALTIME_MOTOR_PARAMETERS = frozenset(
    {"LCV", "LCVC", "LCPG", "LFV", "LFVC", "LFS", "LFAP", "LFDP", "LFDPC", "LCT", "LFBP", "LFAIN"}
)
_FLAG_NAMES_43 = ("LCV", "LCPG", "LFV", "LFS", "LFAP", "LFDP")
_FLAG_NAMES_44 = _FLAG_NAMES_43 + ("LCT", "LFBP", "LFAIN")
_HEADERS = {b"C": b"C", b"c": b"c", b"A": b"A", b"a": b"a", "C": b"C", "c": b"c", "A": b"A", "a": b"a"}


# What a failing port raises: pyserial's own errors, OS errors, and on POSIX termios.error (which
# is neither; tcflush on a pty whose server died raises it).
PORT_ERRORS = (serial.SerialException, OSError, _TermiosError)


class HandConnectionError(BH8Error):
    """The serial port could not be opened, or failed (unplugged adapter, closed pty, lost socket)."""


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


def _check_baud_rate(name: str, rate) -> None:
    """An int among BAUD_RATES (38400.0 would go out as "PSET BAUD 384.0", refused by the hand
    after the host has switched)."""
    if isinstance(rate, bool) or not isinstance(rate, int) or rate not in BAUD_RATES:
        raise ValueError(f"{name} must be one of {BAUD_RATES} (manual §5.4.1 BAUD), got {rate!r}")


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


def _split_lines(body: bytes) -> list[str]:
    """Output lines of a reply body (between the echo and the prompt); tolerant of CR LF order."""
    text = body.decode("latin-1")
    return [line for line in re.split(r"[\r\n]+", text) if line.strip()]


def _error_code(lines: list[str]) -> int | None:
    """The status sum when the reply is an error (its first line is "ERR <n>", SPEC.md §2);
    ProtocolError when n is no status sum."""
    if lines:
        found = _ERR_LINE.match(lines[0].strip())
        if found:
            return parse_status(found.group(1))
    return None


def _open_error_detail(error: Exception, port_name: str) -> str:
    """What went wrong opening a port, said once: pyserial wraps the OS error in "could not open
    port X: [Errno 2] ..." and bh8sim:// already says "cannot open 'bh8sim://...': ..."."""
    cause = error.__cause__ or error.__context__
    if isinstance(error, serial.SerialException) and type(cause) in (OSError, FileNotFoundError, PermissionError) \
            and cause.strerror:
        return cause.strerror
    return str(error).removeprefix(f"cannot open {port_name!r}: ")


class BarrettHand:
    """A BarrettHand on a serial port (manual §5, §6; SPEC.md §2, §5).

    `port` is a device name (`/dev/ttyUSB0`, `COM3`), any pyserial URL (`socket://host:4001`,
    `bh8sim://?seed=0`), or an already-open pyserial object (its `timeout` is set to the client's
    read slice; `disconnect()` leaves it open). Device names are opened exclusively (POSIX).
    `baudrate` is the host's rate (the hand's BAUD parameter must match; 9600 by default).
    `timeout` bounds non-motion replies and silences inside a reply; `motion_timeout` bounds a
    motion command. `firmware` is "4.3" or "4.4" (RealTime layout profile, SPEC.md §7), or None
    to ask VERS when it is first needed.

    The constructor resynchronises with the hand (^C, CR, prompt), so a hand that does not answer
    raises HandTimeout from the constructor, after RESYNC_ATTEMPTS tries of about `timeout` each
    (~8 s at the defaults).
    """

    def __init__(
        self,
        port,
        baudrate: int = 9600,
        timeout: float = DEFAULT_TIMEOUT_S,
        firmware: str | None = None,
        motion_timeout: float = DEFAULT_MOTION_TIMEOUT_S,
    ):
        _check_baud_rate("baudrate", baudrate)
        if firmware is not None and firmware not in FIRMWARE_PROFILES:
            raise ValueError(f"firmware must be '4.3', '4.4' or None (ask VERS), got {firmware!r}")
        for name, value in (("timeout", timeout), ("motion_timeout", motion_timeout)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
                raise ValueError(f"{name} must be a positive number of seconds, got {value!r}")
        self.timeout = float(timeout)
        self.motion_timeout = float(motion_timeout)
        self.baudrate = baudrate
        self._firmware = firmware
        self._rx = bytearray()
        self._needs_resync = True
        self._port_failed = False
        self._closed = False  # by close()/disconnect(): for good, never reopened
        self._layout: LoopLayout | None = None
        if isinstance(port, str):
            self._port_name = port
            self._owns_port = True
            self._port = None
            self._open_port()
        elif hasattr(port, "read") and hasattr(port, "write"):
            self._port_name = getattr(port, "port", None) or repr(port)
            self._owns_port = False
            self._port = port
            port.timeout = READ_SLICE_S
        else:
            raise ValueError(f"port must be a port name, a pyserial URL or a pyserial port object, got {port!r}")
        try:
            self.resync()
        except BaseException:
            self.disconnect()
            raise

    # -- life cycle --------------------------------------------------------------------------

    def _open_port(self) -> None:
        import bh8_gym.urlhandler  # noqa: F401  (registers bh8sim:// with pyserial)

        options = {"baudrate": self.baudrate, "timeout": READ_SLICE_S, "write_timeout": self.timeout}
        if "://" not in self._port_name:
            options["exclusive"] = True  # a second program on the same port garbles both (§8)
        try:
            self._port = serial.serial_for_url(self._port_name, **options)
        except (*PORT_ERRORS, ValueError) as error:
            raise HandConnectionError(f"cannot open {self._port_name!r}: {_open_error_detail(error, self._port_name)}") from error
        self._port_failed = False

    def disconnect(self) -> None:
        """Leave RealTime mode if active (best effort) and close the port if this client opened it."""
        self._closed = True
        if self._port is None:
            return
        if self._layout is not None and not self._port_failed:
            try:
                self.stop_loop()
            except BH8Error:
                pass  # closing anyway; the hand leaves LOOP on the next ^C
        if self._owns_port:
            try:
                self._port.close()
            except PORT_ERRORS:
                pass
        self._port = None

    def close(self) -> None:
        """The same as `disconnect()`, under the name pyserial and `contextlib.closing` use: it never
        moves the hand (the GCL C command is `close_motors()`)."""
        self.disconnect()

    def __enter__(self) -> "BarrettHand":
        return self

    def __exit__(self, *exc_info) -> None:
        self.disconnect()

    def __repr__(self) -> str:
        mode = "RealTime" if self._layout is not None else "supervisory"
        return f"BarrettHand({self._port_name!r}, baudrate={self.baudrate}, {mode})"

    @property
    def port(self):
        """The underlying pyserial object."""
        return self._port

    @property
    def port_name(self) -> str:
        """The port name or URL this client talks through."""
        return self._port_name

    @property
    def in_loop(self) -> bool:
        """True between start_loop() and stop_loop() (or a RealTime error)."""
        return self._layout is not None

    @property
    def layout(self) -> LoopLayout | None:
        """The RealTime block layout in use, None in supervisory mode."""
        return self._layout

    @property
    def firmware(self) -> str:
        """The firmware profile ("4.3" or "4.4"), asked of the hand (VERS) the first time if not given."""
        if self._firmware is None:
            self._firmware = firmware_profile_of(self.version())
        return self._firmware

    # -- bytes on the wire ------------------------------------------------------------------

    def _io_failed(self, error: Exception) -> HandConnectionError:
        self._port_failed = True
        self._needs_resync = True
        return HandConnectionError(f"serial port {self._port_name!r} failed: {error}")

    def _write(self, data: bytes) -> None:
        if self._port is None:
            raise HandConnectionError(f"{self._port_name!r} is closed")
        try:
            self._port.write(data)
        except serial.SerialTimeoutException as error:
            self._needs_resync = True
            raise HandTimeout(f"could not write to {self._port_name!r} within {self.timeout} s") from error
        except PORT_ERRORS as error:
            raise self._io_failed(error) from error

    def _read_some(self, count: int) -> bytes:
        try:
            return self._port.read(count)
        except PORT_ERRORS as error:
            raise self._io_failed(error) from error

    def _clear_input(self) -> None:
        self._rx.clear()
        if self._port is None:
            raise HandConnectionError(f"{self._port_name!r} is closed")
        try:
            self._port.reset_input_buffer()
        except PORT_ERRORS as error:
            raise self._io_failed(error) from error

    def _read_until(self, terminator: bytes, budget_s: float, what: str) -> bytes:
        """Bytes up to and including `terminator`. The deadline is `budget_s` from now, pushed
        to at least `self.timeout` after the latest byte while a reply is streaming."""
        rx = self._rx
        gap = self.timeout
        now = time.monotonic()
        deadline = now + budget_s
        limit = deadline + REPLY_STREAM_LIMIT_BYTES * BITS_PER_BYTE / self.baudrate
        start = 0
        while True:
            index = rx.find(terminator, start)
            if index >= 0:
                end = index + len(terminator)
                data = bytes(rx[:end])
                del rx[:end]
                return data
            start = max(0, len(rx) - len(terminator) + 1)
            if now > deadline:
                self._needs_resync = True
                raise HandTimeout(f"no reply to {what} within {budget_s:.3g} s; received {bytes(rx)!r}")
            waiting = getattr(self._port, "in_waiting", 0)
            chunk = self._read_some(waiting if waiting > 1 else 1)
            now = time.monotonic()
            if chunk:
                rx += chunk
                if now + gap > deadline:
                    deadline = min(now + gap, limit)

    def _read_exact(self, count: int, budget_s: float, what: str) -> bytes:
        rx = self._rx
        deadline = time.monotonic() + budget_s
        while len(rx) < count:
            chunk = self._read_some(count - len(rx))
            if chunk:
                rx += chunk
            elif time.monotonic() > deadline:
                self._needs_resync = True
                raise HandTimeout(
                    f"{what}: expected {count} bytes within {budget_s:.3g} s, received {bytes(rx)!r}"
                )
        data = bytes(rx[:count])
        del rx[:count]
        return data

    def _drain_quiet(self) -> bytes:
        """Everything the hand sends until it has been silent for a while (resynchronising)."""
        quiet = RESYNC_QUIET_S + 2 * BITS_PER_BYTE / self.baudrate
        received = bytearray(self._rx)
        self._rx.clear()
        start = last = time.monotonic()
        while True:
            chunk = self._read_some(64)
            now = time.monotonic()
            if chunk:
                received += chunk
                last = now
                if now - start > RESYNC_DRAIN_LIMIT_S:
                    raise ProtocolError(
                        f"the hand on {self._port_name!r} kept sending for {RESYNC_DRAIN_LIMIT_S} s "
                        f"without pausing (wrong baud rate?): {bytes(received[-40:])!r}"
                    )
            elif now - last >= quiet:
                return bytes(received)

    # -- recovery ----------------------------------------------------------------------------

    def resync(self) -> None:
        """Get back to a clean supervisory prompt, whatever state the line and the hand are in.

        Sends ^C (leaves RealTime mode, aborts a running motion; idle it only gets a prompt,
        SPEC.md §2), discards the hand's output until the line is quiet, then checks that a bare
        CR gets exactly "\\n\\r=> ". A port that failed is reopened first (if this client opened it);
        a client closed with close()/disconnect() stays closed (HandConnectionError).
        """
        if self._closed:
            raise HandConnectionError(f"{self._port_name!r} was closed with close(); make a new BarrettHand")
        if self._port_failed or self._port is None or not getattr(self._port, "is_open", True):
            self._reopen()
        self._layout = None
        last = b""
        for _ in range(RESYNC_ATTEMPTS):
            self._clear_input()
            self._write(HEADER_EXIT)
            self._drain_quiet()
            self._clear_input()
            self._write(CR)
            try:
                last = self._read_until(PROMPT, self.timeout, "a bare CR")
            except HandTimeout:
                last = bytes(self._rx)
                continue
            if last.endswith(LINE_END + PROMPT):
                self._rx.clear()
                self._needs_resync = False
                return
        self._needs_resync = True
        raise HandTimeout(
            f"the hand on {self._port_name!r} does not answer a bare CR with a prompt (last: {last!r}); "
            f"check power, cable and that the hand's BAUD matches {self.baudrate} (manual §8)"
        )

    def _reopen(self) -> None:
        if self._owns_port:
            if self._port is not None:
                try:
                    self._port.close()
                except PORT_ERRORS:
                    pass
            self._port = None
            self._open_port()
        else:
            if self._port is None:
                raise HandConnectionError(f"{self._port_name!r} was closed")
            try:
                if getattr(self._port, "is_open", True):
                    self._port.close()
                self._port.open()
            except PORT_ERRORS as error:
                raise HandConnectionError(f"cannot reopen {self._port_name!r}: {error}") from error
            self._port_failed = False

    def _ensure_supervisory(self) -> None:
        if self._layout is not None and not self._needs_resync:
            raise RuntimeError("the hand is in RealTime mode; call stop_loop() before supervisory commands")
        if self._needs_resync:
            self.resync()

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
        echo = line.encode("ascii")
        budget = self._budget_for(line) if budget_s is None else budget_s
        try:
            self._clear_input()
            self._write(echo + CR)
            reply = self._read_until(PROMPT, budget, repr(line))
        except BaseException:
            self._needs_resync = True
            raise
        if not reply.startswith(echo):
            self._needs_resync = True
            raise ProtocolError(f"expected the echo of {line!r}, got {reply!r}")
        return _split_lines(reply[len(echo):-len(PROMPT)])

    def _checked(self, line: str, budget_s: float | None = None) -> list[str]:
        lines = self._transact(line, budget_s)
        try:
            code = _error_code(lines)
        except ProtocolError:
            self._needs_resync = True
            raise
        if code is not None:
            raise HandError(code, line)
        return lines

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

    def _motion(self, motors, verb: str, argument: int | None = None) -> None:
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
        if position is not None:
            _check_int("position", position, 0, 20000)
        self._motion(motors, "M", position)

    def step_open(self, counts: int | None = None, motors="GS") -> None:
        """IO: open by `counts` (0..20000), or by DS when None."""
        if counts is not None:
            _check_int("counts", counts, 0, 20000)
        self._motion(motors, "IO", counts)

    def step_close(self, counts: int | None = None, motors="GS") -> None:
        """IC: close by `counts` (0..20000), or by DS when None."""
        if counts is not None:
            _check_int("counts", counts, 0, 20000)
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
            self._needs_resync = True
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
            self._needs_resync = True
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
            self._needs_resync = True
            raise ProtocolError(f"RESET: expected a banner containing {BANNER!r}, got {lines!r}")
        return banner

    def set_baud(self, rate: int) -> None:
        """Switch the hand and the host to `rate` bits/s (600..38400, §5.4.1), as Barrett's API does:
        PSET BAUD, read the echo, switch the host, wait 1 s, clear, bare CR, read to the prompt.

        Not saved: PSAVE afterwards makes the rate survive a power cycle (and the next connection
        must then open the port at that rate)."""
        _check_baud_rate("baud rate", rate)
        self._ensure_supervisory()
        line = f"PSET BAUD {rate // 100}"
        echo = line.encode("ascii")
        try:
            self._clear_input()
            self._write(echo + CR)
            got = self._read_exact(len(echo), self.timeout, repr(line))
            if got != echo:
                raise ProtocolError(f"expected the echo of {line!r}, got {got!r}")
            try:
                self._port.baudrate = rate
            except (*PORT_ERRORS, ValueError) as error:
                raise self._io_failed(error) from error
            self.baudrate = rate
            time.sleep(BAUD_SWITCH_SETTLE_S)
            self._clear_input()
            self._write(CR)
            reply = self._read_until(PROMPT, self.timeout, "a bare CR at the new rate")
        except BaseException:
            self._needs_resync = True
            raise
        if not reply.endswith(LINE_END + PROMPT):
            self._needs_resync = True
            raise ProtocolError(f"after switching to {rate} baud, a bare CR got {reply!r}")

    def abort(self) -> list[str]:
        """Send ^C: abort a running motion (the hand replies ERR 16384, §5.5 case 4) or leave LOOP.

        Returns the lines the hand sent after the ^C until the line went quiet (e.g. ["ERR 16384"]);
        the client is at a clean prompt afterwards.
        """
        try:
            self._clear_input()  # the rest of an interrupted reply is of no interest now
            self._write(HEADER_EXIT)
            # The answer always ends in a prompt; wait for it rather than for a pause, which a
            # busy host or a paced hand can produce before the ERR line. Then collect stragglers.
            try:
                text = self._read_until(PROMPT, self.timeout, "^C")
            except HandTimeout:
                text = b""
            text += self._drain_quiet()
        except BaseException:
            self._needs_resync = True
            raise
        self._layout = None
        self._needs_resync = PROMPT not in text  # quiet after a prompt: the line is clean again
        return [line for line in _split_lines(text.replace(PROMPT, b"\n")) if line.strip() != "*"]

    # -- RealTime (§6) -----------------------------------------------------------------------

    def configure_loop(self, motors="GS", *, lft: bool | None = None, lfdpd: bool | None = None, **flags) -> None:
        """Set RealTime flags and coefficients of `motors` (FSET) and the global LFT/LFDPD (PSET).

        Example (manual §6.4): configure_loop("12", LCV=1, LCVC=1, LCPG=0, LFV=0, LFS=1, LFAP=0,
        LFDP=1, LFDPC=1, lft=True). Only RealTime parameter names are accepted here.
        """
        unknown = sorted(set(name.upper() for name in flags) - REALTIME_MOTOR_PARAMETERS)
        if unknown:
            raise ValueError(
                f"not RealTime motor parameters: {unknown}; expected some of {sorted(REALTIME_MOTOR_PARAMETERS)}"
            )
        if flags:
            self.set(motors, {name.upper(): value for name, value in flags.items()})
        global_pairs = {name: int(bool(value)) for name, value in (("LFT", lft), ("LFDPD", lfdpd)) if value is not None}
        if global_pairs:
            self._checked("PSET " + " ".join(f"{name} {value}" for name, value in global_pairs.items()))

    def start_loop(self, motors="GS") -> LoopLayout:
        """Enter RealTime mode on `motors` and return the block layout in use.

        Like Barrett's RTStart, the layout comes from the hand's own flags (FGET per motor, PGET
        LFT), so it cannot disagree with the hand. The same FGET reads P, which sets the hand's
        reported position that LFDP counts from (§6.2.3), seeding `tracked_position`.
        """
        if motors is None:
            raise ValueError("start_loop needs the LOOP motors, e.g. 'GS' or '124' (None = EN motors is ambiguous)")
        prefix, selected = parse_motors(motors)
        profile = self.firmware
        flag_names = _FLAG_NAMES_44 if profile == "4.4" else _FLAG_NAMES_43
        names = list(flag_names) + ["LFDPC", "P"]
        values = self.get(names, prefix)
        lft = bool(self.get_global("LFT")["LFT"])
        flags = {
            motor: MotorFlags(**{name: bool(values[name][i]) for name in flag_names})
            for i, motor in enumerate(selected)
        }
        layout = LoopLayout(selected, flags, lft=lft, firmware=profile)
        line = f"{prefix}LOOP"
        echo = line.encode("ascii")
        self._ensure_supervisory()
        try:
            self._clear_input()
            self._write(echo + CR)
            got = self._read_exact(len(echo) + 1, self.timeout, repr(line))
        except BaseException:
            self._needs_resync = True
            raise
        if got[:-1] != echo:
            self._needs_resync = True
            raise ProtocolError(f"expected the echo of {line!r}, got {got!r}")
        if got[-1:] != ACK:
            self._rx[:0] = got[-1:]
            self._raise_loop_error(line)
        self._prepare_loop(layout, values)
        return layout

    def _raise_loop_error(self, what: str) -> None:
        """The hand sent something other than "*": "\\n\\rERR n\\n\\r=> " (back in supervisory
        mode, SPEC.md §5) raises HandError; anything else is a ProtocolError."""
        self._layout = None
        try:
            reply = self._read_until(PROMPT, self.timeout, what)
        except HandTimeout:
            raise ProtocolError(f"{what}: expected '*', got {bytes(self._rx)!r}") from None
        try:
            code = _error_code(_split_lines(reply[: -len(PROMPT)]))
        except ProtocolError:
            code = None
        if code is None or not reply.startswith(LINE_END):
            self._needs_resync = True
            raise ProtocolError(f"{what}: expected '*' or an ERR line, got {reply!r}")
        raise HandError(code, what)

    def _prepare_loop(self, layout: LoopLayout, values: dict[str, list[int]]) -> None:
        """Everything update() needs, computed once per LOOP entry."""
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
        block_time = BITS_PER_BYTE / self.baudrate
        self._block_budget = {
            header: (layout.control_block_size(code) + (layout.feedback_size if code in b"CA" else 1)) * block_time
            + REALTIME_MARGIN_S
            for header, code in _HEADERS.items()
        }
        self.last_control_block = b""
        self.last_feedback_block = b""
        self._layout = layout

    def update(
        self,
        velocities: Sequence[int] | None = None,
        gains: Sequence[int] | None = None,
        header: bytes | str = b"C",
        torques: Sequence[int] | None = None,
    ) -> LoopFeedback | None:
        """One RealTime cycle. Sequences have one entry per LOOP motor in motor order: velocities
        are LCV bytes (-128..127, times LCVC in 1/16 count per sample), gains LCPG bytes (0..255),
        torques LCT words (4.4); entries of motors whose flag is off are ignored. Header "C" sends
        data and returns the decoded feedback, "c" sends data and returns None, "A"/"a" send none.
        """
        layout = self._layout
        if layout is None:
            raise RuntimeError("not in RealTime mode (a RealTime error or time-out ends it); call start_loop()")
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
        layout = self._layout
        if layout is None:
            raise RuntimeError("not in RealTime mode (a RealTime error or time-out ends it); call start_loop()")
        code = _HEADERS.get(header)
        if code is None:
            raise ValueError(f"invalid RealTime header {header!r}; expected 'C', 'c', 'A' or 'a' (§6.2.1)")
        return self._exchange(layout.encode_control(values if code in (b"C", b"c") else (), code), code)

    def _exchange(self, block: bytes, code: bytes) -> LoopFeedback | None:
        layout = self._layout
        budget = self._block_budget[code]
        try:
            self._write(block)
            self.last_control_block = block
            first = self._read_exact(1, budget, "RealTime reply")
            if first != ACK:
                self._rx[:0] = first
                self._raise_loop_error("RealTime block")
            if code in (b"a", b"c"):
                self.last_feedback_block = first
                return None
            reply = first + self._read_exact(layout.feedback_size - 1, budget, "RealTime feedback block")
        except BaseException as error:
            if not isinstance(error, HandError):  # the line's state is unknown: leave LOOP by resync
                self._needs_resync = True
                self._layout = None
            raise
        self.last_feedback_block = reply
        return self._decode(reply)

    def _decode(self, reply: bytes) -> LoopFeedback:
        values = self._layout.decode_feedback(reply)
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

    def stop_loop(self) -> None:
        """Leave RealTime mode (^C) and read to the prompt (an ERR 16384 line there is expected).

        After a RealTime time-out or interruption this resynchronises instead (which also sends ^C)."""
        if self._needs_resync:
            self.resync()
            return
        if self._layout is None:
            raise RuntimeError("not in RealTime mode")
        self._layout = None
        try:
            self._write(HEADER_EXIT)
            reply = self._read_until(PROMPT, self.timeout, "^C leaving RealTime mode")
        except BaseException:
            self._needs_resync = True
            raise
        code = _error_code(_split_lines(reply[: -len(PROMPT)]))
        if code is not None and code != 16384:
            raise HandError(code, "^C leaving RealTime mode")
