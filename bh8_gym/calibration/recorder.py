"""`Recorder`: runs the excitation (excitation.py) on a `BarrettHand` and logs it (log_format.py).

The same code drives a real BH8-262 and the simulated one (`bh8 serve`, bh8sim://): everything
goes through `bh8_gym.client`. Before anything moves it reads the hand's version and the
parameters it was found with (the header keeps them) and checks the temperature. It then switches
to the excitation's rate, runs the program, logging every command and reply and every RealTime
block with the host's monotonic time, each record written as it happens.

Leaving the hand safe, however it ends: Ctrl-C, SIGTERM or SIGHUP ask for a stop at the next block
or command (a second Ctrl-C sends ^C at once, which stops a motion in progress); a finger's gauge
above the envelope's limit, a temperature above it, an ERR reply or a log that cannot be written
stop it too. The stop is: a block of zero velocity and gain, ^C out of LOOP (the fingers' worms
hold them unpowered), the parameters put back as found, the rate switched back. The log's end
record says whether the whole excitation ran, or why it stopped.
"""
from __future__ import annotations

import contextlib
import datetime
import signal
import threading
import time

from bh8_gym.calibration.excitation import (
    BAUD,
    CREEP_VELOCITY,
    EXCITATION_NAME,
    EXCITATION_VERSION,
    LOOP_MOTORS,
    PHASE_LIMIT_CYCLES,
    PROBE_THRESHOLD_COUNTS,
    PROBE_VELOCITY,
    PROBE_WAIT_S,
    Commands,
    Squeeze,
    SqueezeLaw,
    Sweep,
    SweepLaw,
    excitation_program,
)
from bh8_gym.calibration.log_format import LOG_FORMAT, LOG_VERSION, LogWriter, is_motion
from bh8_gym.cli import handling_signals
from bh8_gym.client.line import error_code
from bh8_gym.client.supervisory import firmware_profile_of
from bh8_gym.parameters import global_parameters, motor_parameters
from bh8_gym.protocol import MOTORS
from bh8_gym.safety import SafetyEnvelope
from bh8_gym.status import BH8Error

PARAMETER_CHUNK = 6  # names per FGET/FSET line: well inside the firmware's 255-character line


STALL_ERROR = 16


class Stop(Exception):
    """The excitation stops early (the message is the reason the log's end record keeps)."""


class Recorder:
    """Runs the excitation on `hand`, logging to `log_path`."""

    def __init__(self, hand, log_path, mounting: str, calibration_object: str | None = None, scale: float = 1.0,
                 envelope: SafetyEnvelope = SafetyEnvelope(), progress=None):
        self.hand = hand
        self.log_path = log_path
        self.mounting = mounting
        self.calibration_object = calibration_object
        self.scale = scale
        self.envelope = envelope
        self.program = excitation_program(scale, calibration_object)
        self.progress = progress  # called with (part name, index, parts) as each part starts
        self.log: LogWriter | None = None
        self.log_error: OSError | None = None
        self.found_baud = hand.baudrate
        self.found_motor: dict[str, list[int]] = {}
        self.found_global: dict[str, int] = {}
        self.safe_exit_error: BH8Error | None = None
        self.blocks = 0
        self._stop_request: str | None = None
        self._positions: dict[int, int] = {}
        self._strains: dict[int, int] = {}

    # -- the log ---------------------------------------------------------------------------

    def _record(self, record: dict) -> None:
        """Log one record; a write that fails ends the logging and asks for a stop."""
        if self.log is None or self.log_error is not None:
            return
        try:
            self.log.write(record)
        except OSError as error:
            self.log_error = error
            self._request_stop(f"the log cannot be written ({error.strerror or error})")

    def _request_stop(self, reason: str) -> None:
        if self._stop_request is None:
            self._stop_request = reason

    def _check_stop(self) -> None:
        if self._stop_request is not None:
            raise Stop(self._stop_request)

    # -- before anything moves -------------------------------------------------------------

    def survey(self) -> dict:
        """Read what the header keeps: VERS, the serial number, the parameters as found; check the
        temperature. Sends nothing that changes the hand."""
        hand = self.hand
        version = hand.version()
        profile = firmware_profile_of(version)
        motor_names = [p.name for p in motor_parameters(profile).values() if not p.read_only and p.alias_of is None]
        for start in range(0, len(motor_names), PARAMETER_CHUNK):
            self.found_motor.update(hand.get(motor_names[start:start + PARAMETER_CHUNK], "1234"))
        global_names = [p.name for p in global_parameters(profile).values() if not p.read_only and p.name != "BAUD"]
        self.found_global = hand.get_global(global_names)
        try:
            serial_number = hand.get_global("SN")["SN"]
        except BH8Error:
            serial_number = None
        temperature = hand.temperature()
        problem = self.envelope.temperature_violation(temperature, " before the excitation")
        if problem is not None:
            raise Stop(problem)
        return {"version_text": version, "profile": profile, "serial_number": serial_number}

    def open_log(self, hand_info: dict) -> None:
        self.log = LogWriter(self.log_path)
        self._record({
            "kind": "header", "format": LOG_FORMAT, "version": LOG_VERSION,
            "excitation": {"name": EXCITATION_NAME, "version": EXCITATION_VERSION, "scale": self.scale,
                           "mounting": self.mounting, "object": self.calibration_object},
            "hand": hand_info,
            "port": {"name": str(self.hand.port_name)[:200], "baud_found": self.found_baud},
            "found": {"motors": self.found_motor, "globals": self.found_global},
            "started": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        })

    # -- running ---------------------------------------------------------------------------

    def run(self) -> tuple[bool, str]:
        """The whole excitation (survey, log, program, safe exit); (complete, reason)."""
        with self._stop_on_signals():
            try:
                self.open_log(self.survey())
                self._switch_baud(BAUD)
                for index, part in enumerate(self.program):
                    self._check_stop()
                    if self.progress is not None:
                        self.progress(part.name, index, len(self.program))
                    self._record({"kind": "segment", "name": part.name, "t": time.monotonic()})
                    if isinstance(part, Commands):
                        self._leave_loop()
                        for line in part.lines:
                            self._command(line)
                    else:
                        self._loop_part(part)
                self._leave_loop()
                complete, reason = self._stop_request is None, self._stop_request or "done"
            except Stop as stop:
                complete, reason = False, str(stop)
            except KeyboardInterrupt:
                complete, reason = False, "interrupted (Ctrl-C twice: ^C sent at once)"
                self._abort()
            except BH8Error as error:
                complete, reason = False, f"hand/port error: {error}"
            finally:
                self._finish()
        if self.safe_exit_error is not None:
            reason += f"; leaving the hand safe failed: {self.safe_exit_error}"
        self._record({"kind": "end", "complete": complete, "reason": reason[:400], "t": time.monotonic()})
        if self.log is not None:
            self.log.close()
        return complete, reason

    def _command(self, line: str, check: bool = True) -> list[str]:
        start = time.monotonic()
        lines = self.hand.command(line, check=False)
        code = error_code(lines)
        self._record({"kind": "command", "line": line, "reply": lines, "error": code, "t": start,
                      "dt": time.monotonic() - start})
        # A motion that stalls short of its target (ERR 16, §5.5: e.g. the spread's friction against the
        # position loop's last counts) is part of what the log records; any other error stops.
        if code is not None and check and not (code == STALL_ERROR and is_motion(line)):
            raise Stop(f"the hand answered ERR {code} to {line!r}")
        return lines

    def _switch_baud(self, rate: int) -> None:
        if self.hand.baudrate != rate:
            self.hand.set_baud(rate)
            self._record({"kind": "baud", "rate": rate, "t": time.monotonic()})

    def _enter_loop(self) -> None:
        temperature = self.hand.temperature()
        problem = self.envelope.temperature_violation(temperature, " before LOOP")
        if problem is not None:
            raise Stop(problem)
        layout = self.hand.start_loop(LOOP_MOTORS)
        self._record({"kind": "loop", "motors": LOOP_MOTORS, "t": time.monotonic(), "layout": {
            "motors": list(layout.motors), "lft": layout.lft, "firmware": layout.firmware,
            "flags": {str(m): _flags(flags) for m, flags in layout.flags.items()}}})
        self._exchange(header=b"A")
        self._probe_clock()

    def _exchange(self, velocities=None, gains=None, header: bytes = b"C"):
        start = time.monotonic()
        if header == b"A":
            feedback = self.hand.update(header=b"A")
        else:
            feedback = self.hand.update(velocities, gains)
        self._record({"kind": "block", "control": self.hand.last_control_block.hex(),
                      "feedback": self.hand.last_feedback_block.hex(), "t": start, "dt": time.monotonic() - start})
        self.blocks += 1
        self._positions = {m: data.absolute_position for m, data in feedback.motors.items()}
        self._strains = {m: data.strain for m, data in feedback.motors.items()}
        problem = self.envelope.strain_violation(self._strains.items())
        if problem is not None:
            raise Stop(f"safety stop: {problem}")
        return feedback

    def _probe_clock(self) -> None:
        """Does the hand's clock run while the host waits? (log_format: the clock record)"""
        before = self._positions[1]
        creep = [CREEP_VELOCITY] * 3
        self._exchange([PROBE_VELOCITY, *creep], [100, 100, 100, 100])
        time.sleep(PROBE_WAIT_S)
        self._exchange(header=b"A")
        moved = abs(self._positions[1] - before)
        self._exchange([CREEP_VELOCITY] * 4, [100, 100, 100, 100])
        clock = "wall" if moved > PROBE_THRESHOLD_COUNTS else "line"
        self._record({"kind": "clock", "hand_clock": clock, "moved": float(moved), "waited": PROBE_WAIT_S,
                      "t": time.monotonic()})

    def _loop_part(self, part) -> None:
        if not self.hand.in_loop:
            self._enter_loop()
        if isinstance(part, Sweep):
            law = SweepLaw(part, self._positions, self.mounting)
            for _ in range(part.cycles):
                self._check_stop()
                control = law.control(self._positions)
                self._phase(part, law)
                self._exchange(*control)
        elif isinstance(part, Squeeze):
            law = SqueezeLaw(part, self._strains)
            for _ in range(part.cycles + 3 * PHASE_LIMIT_CYCLES):
                self._check_stop()
                control = law.control(self._positions, self._strains)
                if law.finished:
                    break
                self._phase(part, law)
                self._exchange(*control)
        else:
            raise TypeError(f"not a LOOP part: {part!r}")

    def _phase(self, part, law) -> None:
        """A segment record where a LOOP part's law starts a phase ("sweep3.lift", ...)."""
        if law.phase_started:
            self._record({"kind": "segment", "name": f"{part.name}.{law.phase}", "t": time.monotonic()})

    def _leave_loop(self) -> None:
        if self.hand.in_loop:
            self._exchange([0, 0, 0, 0], [0, 0, 0, 0])
            self.hand.stop_loop()
            self._record({"kind": "loop_exit", "t": time.monotonic()})

    # -- leaving the hand safe -------------------------------------------------------------

    def _abort(self) -> None:
        """^C at once: stops a motion in progress, or leaves LOOP."""
        try:
            self.hand.abort()
        except BH8Error as error:
            self.safe_exit_error = error

    def _finish(self) -> None:
        """Zero block and ^C out of LOOP, the parameters and the rate as found (never raises)."""
        hand = self.hand
        try:
            if hand.in_loop:
                try:
                    self._exchange([0, 0, 0, 0], [0, 0, 0, 0])
                except (Stop, BH8Error):
                    pass  # ^C all the same
                hand.stop_loop()
                self._record({"kind": "loop_exit", "t": time.monotonic()})
            # (after a failed block the client resynchronises, ^C, before its next command)
            if self.found_motor:
                self._restore_parameters()
            if self.found_baud != hand.baudrate:
                self._switch_baud(self.found_baud)
        except (BH8Error, Stop) as error:
            if self.safe_exit_error is None:
                self.safe_exit_error = error if isinstance(error, BH8Error) else BH8Error(str(error))

    def _restore_parameters(self) -> None:
        names = list(self.found_motor)
        now: dict[str, list[int]] = {}
        for start in range(0, len(names), PARAMETER_CHUNK):
            now.update(self.hand.get(names[start:start + PARAMETER_CHUNK], "1234"))
        for index, motor in enumerate(MOTORS):
            changed = [(name, self.found_motor[name][index]) for name in names
                       if now[name][index] != self.found_motor[name][index]]
            for start in range(0, len(changed), PARAMETER_CHUNK):
                pairs = " ".join(f"{name} {value}" for name, value in changed[start:start + PARAMETER_CHUNK])
                self._command(f"{motor}FSET {pairs}", check=False)
        if self.found_global:
            pairs = " ".join(f"{name} {value}" for name, value in self.found_global.items())
            self._command(f"PSET {pairs}", check=False)

    @contextlib.contextmanager
    def _stop_on_signals(self):
        """Ctrl-C, SIGTERM, SIGHUP: stop at the next block or command; a second Ctrl-C at once."""
        if threading.current_thread() is not threading.main_thread():
            yield
            return

        def request_stop(signum, _frame):
            if signum == signal.SIGINT and self._stop_request is not None:
                raise KeyboardInterrupt
            self._request_stop("interrupted (Ctrl-C)" if signum == signal.SIGINT
                               else f"terminated ({signal.Signals(signum).name})")

        with handling_signals((signal.SIGINT, signal.SIGTERM, signal.SIGHUP), request_stop):
            yield


def _flags(flags) -> dict:
    return {name: bool(getattr(flags, name)) for name in flags.__dataclass_fields__}
