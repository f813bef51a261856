"""`BarrettHand`: the client a program holds, for a BH8-262 on any pyserial port (manual §5, §6).

It owns the `SerialLine` (opened, resynchronised, closed), speaks the supervisory command set it
inherits from `SupervisoryCommands`, aborts with ^C, and enters and leaves RealTime mode, whose
cycles a `RealTimeSession` runs (`start_loop`, `update`, `stop_loop`).

After a time-out, a protocol error, a failed port (or a KeyboardInterrupt in the middle of a
transaction) the client resynchronises before its next call: it sends ^C (leaves LOOP, aborts a
motion), then a bare CR, and discards everything up to a fresh prompt. A port that failed is
reopened first.
"""
from __future__ import annotations

from typing import Sequence

from bh8_gym.client.line import SerialLine, check_baud_rate, split_lines
from bh8_gym.client.realtime import (
    FLAG_NAMES_43,
    FLAG_NAMES_44,
    REALTIME_MOTOR_PARAMETERS,
    LoopFeedback,
    RealTimeSession,
)
from bh8_gym.client.supervisory import SupervisoryCommands, firmware_profile_of, parse_motors
from bh8_gym.protocol import FIRMWARE_PROFILES, PROMPT
from bh8_gym.realtime_codec import HEADER_EXIT, LoopLayout, MotorFlags
from bh8_gym.status import BH8Error, HandTimeout

# Default time a non-motion reply may take (FGET, FSET, VERS, ...), and the longest silence
# tolerated while a reply is streaming (long listings at 600 baud keep extending the deadline).
DEFAULT_TIMEOUT_S = 2.0
# Default budget of a motion command. App. A: a finger closes in about 1 s at default MCV; the
# slowest legal velocity (MCV/MOV 16 = 1/6 of the default) stretches that to about 6 s, and HI
# opens against the stop IHIT times per finger before the spread; 30 s covers all of that.
DEFAULT_MOTION_TIMEOUT_S = 30.0


def _of_line(name: str, doc: str) -> property:
    """A read-only property showing attribute `name` of the client's `SerialLine`."""
    return property(lambda hand: getattr(hand._line, name), doc=doc)


def _latest_block(name: str, doc: str) -> property:
    """A property reading `name` of the client's latest RealTime session (it outlives the LOOP)."""
    return property(lambda hand: getattr(hand._session, name) if hand._session is not None else b"", doc=doc)


class BarrettHand(SupervisoryCommands):
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
        check_baud_rate("baudrate", baudrate)
        if firmware is not None and firmware not in FIRMWARE_PROFILES:
            raise ValueError(f"firmware must be '4.3', '4.4' or None (ask VERS), got {firmware!r}")
        for name, value in (("timeout", timeout), ("motion_timeout", motion_timeout)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
                raise ValueError(f"{name} must be a positive number of seconds, got {value!r}")
        self.motion_timeout = float(motion_timeout)
        self._firmware = firmware
        self._session: RealTimeSession | None = None  # the latest; `in_loop` while it is active
        self._line = SerialLine(port, baudrate, float(timeout))
        try:
            self.resync()
        except BaseException:
            self.disconnect()
            raise

    # -- life cycle --------------------------------------------------------------------------

    def disconnect(self) -> None:
        """Leave RealTime mode if active (best effort) and close the port if this client opened it."""
        self._line.closed = True  # for good: a failed ^C below does not reopen the port
        if self._line.port is not None and self.in_loop and not self._line.port_failed:
            try:
                self.stop_loop()
            except BH8Error:
                pass  # closing anyway; the hand leaves LOOP on the next ^C
        self._line.close()

    def close(self) -> None:
        """The same as `disconnect()`, under the name pyserial and `contextlib.closing` use: it never
        moves the hand (the GCL C command is `close_motors()`)."""
        self.disconnect()

    def __enter__(self) -> "BarrettHand":
        return self

    def __exit__(self, *exc_info) -> None:
        self.disconnect()

    def __repr__(self) -> str:
        mode = "RealTime" if self.in_loop else "supervisory"
        return f"BarrettHand({self.port_name!r}, baudrate={self.baudrate}, {mode})"

    port = _of_line("port", "The underlying pyserial object.")
    port_name = _of_line("name", "The port name or URL this client talks through.")
    baudrate = _of_line("baudrate", "The host's rate, bits per second (`set_baud` changes it with the hand's).")
    timeout = _of_line("timeout", "The budget of a non-motion reply and the longest silence inside one, seconds.")

    @property
    def in_loop(self) -> bool:
        """True between start_loop() and stop_loop() (or a RealTime error)."""
        return self._session is not None and self._session.active

    @property
    def layout(self) -> LoopLayout | None:
        """The RealTime block layout in use, None in supervisory mode."""
        return self._session.layout if self.in_loop else None

    last_control_block = _latest_block("last_control_block", "The latest RealTime control block sent (b\"\" before any).")
    last_feedback_block = _latest_block("last_feedback_block",
                                        "The latest RealTime reply received, b\"*\" included (b\"\" before any).")

    @property
    def firmware(self) -> str:
        """The firmware profile ("4.3" or "4.4"), asked of the hand (VERS) the first time if not given."""
        if self._firmware is None:
            self._firmware = firmware_profile_of(self.version())
        return self._firmware

    def _end_loop(self) -> None:
        if self._session is not None:
            self._session.active = False

    # -- recovery ----------------------------------------------------------------------------

    def resync(self) -> None:
        """Get back to a clean supervisory prompt, whatever state the line and the hand are in.

        Sends ^C (leaves RealTime mode, aborts a running motion; idle it only gets a prompt,
        SPEC.md §2), discards the hand's output until the line is quiet, then checks that a bare
        CR gets exactly "\\n\\r=> ". A port that failed is reopened first (if this client opened it);
        a client closed with close()/disconnect() stays closed (HandConnectionError).
        """
        if not self._line.closed:
            self._end_loop()
        self._line.resync()

    def _ensure_supervisory(self) -> None:
        if self.in_loop and not self._line.needs_resync:
            raise RuntimeError("the hand is in RealTime mode; call stop_loop() before supervisory commands")
        if self._line.needs_resync:
            self.resync()

    # -- abort --------------------------------------------------------------------------------

    def abort(self) -> list[str]:
        """Send ^C: abort a running motion (the hand replies ERR 16384, §5.5 case 4) or leave LOOP.

        Returns the lines the hand sent after the ^C until the line went quiet (e.g. ["ERR 16384"]);
        the client is at a clean prompt afterwards.
        """
        wire = self._line
        try:
            wire.clear_input()  # the rest of an interrupted reply is of no interest now
            wire.write(HEADER_EXIT)
            # The answer always ends in a prompt; wait for it rather than for a pause, which a
            # busy host or a paced hand can produce before the ERR line. Then collect stragglers.
            try:
                text = wire.read_until(PROMPT, self.timeout, "^C")
            except HandTimeout:
                text = b""
            text += wire.drain_quiet()
        except BaseException:
            wire.needs_resync = True
            raise
        self._end_loop()
        wire.needs_resync = PROMPT not in text  # quiet after a prompt: the line is clean again
        return [line for line in split_lines(text.replace(PROMPT, b"\n")) if line.strip() != "*"]

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
        flag_names = FLAG_NAMES_44 if profile == "4.4" else FLAG_NAMES_43
        names = list(flag_names) + ["LFDPC", "P"]
        values = self.get(names, prefix)
        lft = bool(self.get_global("LFT")["LFT"])
        flags = {
            motor: MotorFlags(**{name: bool(values[name][i]) for name in flag_names})
            for i, motor in enumerate(selected)
        }
        layout = LoopLayout(selected, flags, lft=lft, firmware=profile)
        self._ensure_supervisory()
        self._session = RealTimeSession.enter(self._line, prefix, layout, values)
        return layout

    def _active_session(self) -> RealTimeSession:
        if not self.in_loop:
            raise RuntimeError("not in RealTime mode (a RealTime error or time-out ends it); call start_loop()")
        return self._session

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
        return self._active_session().update(velocities, gains, header, torques)

    def update_raw(self, values: Sequence[int], header: bytes | str = b"C") -> LoopFeedback | None:
        """One RealTime cycle with control values already in `layout.control_fields` order."""
        return self._active_session().update_raw(values, header)

    def stop_loop(self) -> None:
        """Leave RealTime mode (^C) and read to the prompt (an ERR 16384 line there is expected).

        After a RealTime time-out or interruption this resynchronises instead (which also sends ^C)."""
        if self._line.needs_resync:
            self.resync()
            return
        if not self.in_loop:
            raise RuntimeError("not in RealTime mode")
        self._session.leave()
