"""The serial line to a BarrettHand: the port (opened, failed, reopened, closed) and the line
discipline of supervisory mode (SPEC.md §2): a line and a CR out, its echo, the output lines and
the prompt "=> " back, "ERR <n>" as `HandError`, and resynchronisation to a clean prompt.

Following Barrett's C++ API 4.4.3, a transaction clears the input buffer, writes the line and a CR,
and reads everything up to the prompt. Reads are bounded: a reply that does not come in time raises
`HandTimeout`, bytes that do not fit the protocol raise `ProtocolError`, a port that fails raises
`HandConnectionError`; after any of these the line `needs_resync`.
"""
from __future__ import annotations

import re
import time

import serial

try:
    from termios import error as _TermiosError
except ImportError:  # Windows
    _TermiosError = OSError

from bh8_gym.protocol import BAUD_RATES, BITS_PER_BYTE, LINE_END, PROMPT
from bh8_gym.realtime_codec import HEADER_EXIT
from bh8_gym.status import BH8Error, HandError, HandTimeout, ProtocolError, parse_status

CR = b"\r"

# How long one port.read() may block before the client looks at its own deadline again. Set once
# on the port (changing a pyserial timeout reconfigures the tty every time).
READ_SLICE_S = 0.02
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

_ERR_LINE = re.compile(r"^ERR\s*(\d+)\s*$")

# What a failing port raises: pyserial's own errors, OS errors, and on POSIX termios.error (which
# is neither; tcflush on a pty whose server died raises it).
PORT_ERRORS = (serial.SerialException, OSError, _TermiosError)


class HandConnectionError(BH8Error):
    """The serial port could not be opened, or failed (unplugged adapter, closed pty, lost socket)."""


def check_baud_rate(name: str, rate) -> None:
    """An int among BAUD_RATES (38400.0 would go out as "PSET BAUD 384.0", refused by the hand
    after the host has switched)."""
    if isinstance(rate, bool) or not isinstance(rate, int) or rate not in BAUD_RATES:
        raise ValueError(f"{name} must be one of {BAUD_RATES} (manual §5.4.1 BAUD), got {rate!r}")


def split_lines(body: bytes) -> list[str]:
    """Output lines of a reply body (between the echo and the prompt); tolerant of CR LF order."""
    text = body.decode("latin-1")
    return [line for line in re.split(r"[\r\n]+", text) if line.strip()]


def error_code(lines: list[str]) -> int | None:
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


class SerialLine:
    """A pyserial port and the bytes on it, for one client.

    `port` is a device name or pyserial URL (opened here, exclusively for a device) or an already
    open pyserial object (its `timeout` is set to READ_SLICE_S; `close()` leaves it open).
    `timeout` bounds a reply that has no budget of its own and the silence inside a streaming one.
    """

    def __init__(self, port, baudrate: int, timeout: float):
        self.timeout = timeout
        self.baudrate = baudrate
        self.rx = bytearray()  # bytes read and not yet consumed
        self.needs_resync = True
        self.port_failed = False
        self.closed = False  # by close(): for good, never reopened
        if isinstance(port, str):
            self.name = port
            self.owns_port = True
            self.port = None
            self.open()
        elif hasattr(port, "read") and hasattr(port, "write"):
            self.name = getattr(port, "port", None) or repr(port)
            self.owns_port = False
            self.port = port
            port.timeout = READ_SLICE_S
        else:
            raise ValueError(f"port must be a port name, a pyserial URL or a pyserial port object, got {port!r}")

    # -- the port ----------------------------------------------------------------------------

    def open(self) -> None:
        import bh8_gym.urlhandler  # noqa: F401  (registers bh8sim:// with pyserial)

        options = {"baudrate": self.baudrate, "timeout": READ_SLICE_S, "write_timeout": self.timeout}
        if "://" not in self.name:
            options["exclusive"] = True  # a second program on the same port garbles both (§8)
        try:
            self.port = serial.serial_for_url(self.name, **options)
        except (*PORT_ERRORS, ValueError) as error:
            raise HandConnectionError(f"cannot open {self.name!r}: {_open_error_detail(error, self.name)}") from error
        self.port_failed = False

    def close(self) -> None:
        """Close the port if this line opened it; the line stays closed for good."""
        self.closed = True
        if self.port is None:
            return
        if self.owns_port:
            try:
                self.port.close()
            except PORT_ERRORS:
                pass
        self.port = None

    def reopen(self) -> None:
        if self.owns_port:
            if self.port is not None:
                try:
                    self.port.close()
                except PORT_ERRORS:
                    pass
            self.port = None
            self.open()
        else:
            if self.port is None:
                raise HandConnectionError(f"{self.name!r} was closed")
            try:
                if getattr(self.port, "is_open", True):
                    self.port.close()
                self.port.open()
            except PORT_ERRORS as error:
                raise HandConnectionError(f"cannot reopen {self.name!r}: {error}") from error
            self.port_failed = False

    def switch_baud(self, rate: int) -> None:
        """The host's side of a rate change (the hand's is PSET BAUD)."""
        try:
            self.port.baudrate = rate
        except (*PORT_ERRORS, ValueError) as error:
            raise self.io_failed(error) from error
        self.baudrate = rate

    # -- bytes on the wire ------------------------------------------------------------------

    def io_failed(self, error: Exception) -> HandConnectionError:
        self.port_failed = True
        self.needs_resync = True
        return HandConnectionError(f"serial port {self.name!r} failed: {error}")

    def write(self, data: bytes) -> None:
        if self.port is None:
            raise HandConnectionError(f"{self.name!r} is closed")
        try:
            self.port.write(data)
        except serial.SerialTimeoutException as error:
            self.needs_resync = True
            raise HandTimeout(f"could not write to {self.name!r} within {self.timeout} s") from error
        except PORT_ERRORS as error:
            raise self.io_failed(error) from error

    def read_some(self, count: int) -> bytes:
        try:
            return self.port.read(count)
        except PORT_ERRORS as error:
            raise self.io_failed(error) from error

    def clear_input(self) -> None:
        self.rx.clear()
        if self.port is None:
            raise HandConnectionError(f"{self.name!r} is closed")
        try:
            self.port.reset_input_buffer()
        except PORT_ERRORS as error:
            raise self.io_failed(error) from error

    def read_until(self, terminator: bytes, budget_s: float, what: str) -> bytes:
        """Bytes up to and including `terminator`. The deadline is `budget_s` from now, pushed
        to at least `self.timeout` after the latest byte while a reply is streaming."""
        rx = self.rx
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
                self.needs_resync = True
                raise HandTimeout(f"no reply to {what} within {budget_s:.3g} s; received {bytes(rx)!r}")
            waiting = getattr(self.port, "in_waiting", 0)
            chunk = self.read_some(waiting if waiting > 1 else 1)
            now = time.monotonic()
            if chunk:
                rx += chunk
                if now + gap > deadline:
                    deadline = min(now + gap, limit)

    def read_exact(self, count: int, budget_s: float, what: str) -> bytes:
        rx = self.rx
        deadline = time.monotonic() + budget_s
        while len(rx) < count:
            chunk = self.read_some(count - len(rx))
            if chunk:
                rx += chunk
            elif time.monotonic() > deadline:
                self.needs_resync = True
                raise HandTimeout(
                    f"{what}: expected {count} bytes within {budget_s:.3g} s, received {bytes(rx)!r}"
                )
        data = bytes(rx[:count])
        del rx[:count]
        return data

    def drain_quiet(self) -> bytes:
        """Everything the hand sends until it has been silent for a while (resynchronising)."""
        quiet = RESYNC_QUIET_S + 2 * BITS_PER_BYTE / self.baudrate
        received = bytearray(self.rx)
        self.rx.clear()
        start = last = time.monotonic()
        while True:
            chunk = self.read_some(64)
            now = time.monotonic()
            if chunk:
                received += chunk
                last = now
                if now - start > RESYNC_DRAIN_LIMIT_S:
                    raise ProtocolError(
                        f"the hand on {self.name!r} kept sending for {RESYNC_DRAIN_LIMIT_S} s "
                        f"without pausing (wrong baud rate?): {bytes(received[-40:])!r}"
                    )
            elif now - last >= quiet:
                return bytes(received)

    # -- recovery ----------------------------------------------------------------------------

    def resync(self) -> None:
        """Get back to a clean supervisory prompt (`BarrettHand.resync`)."""
        if self.closed:
            raise HandConnectionError(f"{self.name!r} was closed with close(); make a new BarrettHand")
        if self.port_failed or self.port is None or not getattr(self.port, "is_open", True):
            self.reopen()
        last = b""
        for _ in range(RESYNC_ATTEMPTS):
            self.clear_input()
            self.write(HEADER_EXIT)
            self.drain_quiet()
            self.clear_input()
            self.write(CR)
            try:
                last = self.read_until(PROMPT, self.timeout, "a bare CR")
            except HandTimeout:
                last = bytes(self.rx)
                continue
            if last.endswith(LINE_END + PROMPT):
                self.rx.clear()
                self.needs_resync = False
                return
        self.needs_resync = True
        raise HandTimeout(
            f"the hand on {self.name!r} does not answer a bare CR with a prompt (last: {last!r}); "
            f"check power, cable and that the hand's BAUD matches {self.baudrate} (manual §8)"
        )

    # -- supervisory transactions ------------------------------------------------------------

    def transact(self, line: str, budget_s: float) -> list[str]:
        """Send one line, return its output lines (echo and prompt stripped), ERR included."""
        echo = line.encode("ascii")
        try:
            self.clear_input()
            self.write(echo + CR)
            reply = self.read_until(PROMPT, budget_s, repr(line))
        except BaseException:
            self.needs_resync = True
            raise
        if not reply.startswith(echo):
            self.needs_resync = True
            raise ProtocolError(f"expected the echo of {line!r}, got {reply!r}")
        return split_lines(reply[len(echo):-len(PROMPT)])

    def checked(self, line: str, budget_s: float) -> list[str]:
        """`transact`, with an "ERR n" reply raised as HandError."""
        lines = self.transact(line, budget_s)
        try:
            code = error_code(lines)
        except ProtocolError:
            self.needs_resync = True
            raise
        if code is not None:
            raise HandError(code, line)
        return lines
