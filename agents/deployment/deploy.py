"""`bh8 deploy --port PORT --policy FILE`: run a policy closed-loop on a hand over a serial port.

The sequence is what the environment does to its simulated firmware, sent through
`bh8_gym.client.BarrettHand` to whatever is on the port (a real BH8-262, `bh8 serve`, bh8sim://),
from the same `LoopInterface` (`envs.interfaces.interface_for` builds it from the policy's env id
and keyword arguments without the simulator: deploy never loads PyBullet):

1. connect at `--baud` (the hand's current rate, 9600 after power-up), switch to the env's rate
   with PSET BAUD (client.set_baud), then send the env's supervisory setup script (HI, the LOOP
   flags and coefficients, LFT/LFDPD) and enter LOOP on the env's motors; the blocks the hand
   reports must be the env's, or deploy refuses to run; Ctrl-C here sends ^C (stopping HI) and
   switches the rate back;
2. every cycle: policy(observation) -> floats in [-1, 1] -> LOOP bytes with the env's own mapping
   (action_bytes.unit_to_bytes), clamped to the safety velocity limit; one "C" block; the feedback
   block is decoded by the client's LoopLayout and turned into the next observation by the
   interface's observation builder (the same code the policy was trained on);
3. stop on the cycle budget, Ctrl-C, SIGTERM or SIGHUP (at the next cycle boundary: a block is
   never cut in half), a strain above `--max-strain` or a temperature above
   `--max-temperature` (read with PGET TEMP before LOOP, and every cycle if the env's LOOP has
   LFT): one last block with zero velocity, ^C to leave LOOP, then the exit
   action (`--on-exit`, default "GT": finger power off; the worm drives hold the grasp unpowered,
   SPEC.md §1, so nothing drops and nothing heats; "T": every motor off, the spread becomes
   back-drivable; "none": leave LOOP only);
4. switch the hand back to `--baud`, the rate it was found at.

Every control and feedback block is logged as one JSONL line (hex bytes, cycle, and `t`: seconds
of the host's monotonic clock, for intervals between records), each record whole or not at all
(`RecordLog`). The log never stands in the way of the safe exit: a record that cannot be written
(a full disk) ends the logging and stops the run at the next cycle boundary like a limit, and the
zero-velocity block, ^C, the exit action and the switch back to `--baud` follow as always.
The arm phase in the observation follows the env's ArmSchedule from the first control block:
the robot arm carrying the hand must run the same grasp/lift/hold schedule.
Policies trained with privileged (simulation-only) observations are refused, and so is a policy
file that is damaged (an .npz whose layers do not chain), whose observation or action size is not
the env's, or that gives no finite action for a test observation (one forward pass), all before
the port is opened. An SB3 .zip
is loaded without unpickling anything (`--trust-file` allows it); its pickle-free export beside
it (`bh8 export`'s `MODEL.npz`, not older than the .zip) is deployed instead when there is one.
A policy that fails mid-run (raises) is a stop like a safety limit, with exit status 2.
"""
from __future__ import annotations

import argparse
import contextlib
import errno
import json
import math
import os
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

from bh8_gym.action_bytes import unit_to_bytes
from bh8_gym.agents.deployment.policy_file import PolicyFileError, add_trust_argument, check_policy_runs, load_policy
from bh8_gym.cli import handling_signals, integer_argument
from bh8_gym.client import BarrettHand
from bh8_gym.envs.interfaces import interface_for
from bh8_gym.loop_interface import LoopInterface
from bh8_gym.protocol import BAUD_RATES
from bh8_gym.safety import NO_VELOCITY_CLAMP, SafetyEnvelope
from bh8_gym.status import BH8Error

EXIT_ACTIONS = ("GT", "T", "none")
# The host clock the observation's elapsed time uses: wall seconds since the first block (a real
# hand and arm), or the env's own clock summed cycle by cycle with the nominal processing time
# (`LoopInterface.next_elapsed`; an unpaced simulator: bit-identical to the env's without latency
# randomisation, e.g. `bh8 serve --env ID --seed N --env-kwargs '{"randomize": false}'`).
CLOCKS = ("wall", "cycles")
# The default limits are the policy's env's safety envelope (bh8_gym.safety, the env trains inside
# it): these are the envelope's defaults, for the help text.
DEFAULT_ENVELOPE = SafetyEnvelope()


class DeployError(RuntimeError):
    """A policy or hand that deploy refuses to run (the message says why)."""


class RecordLog:
    """A JSONL log file written a record at a time, each whole or not at all: one unbuffered write
    per record, cut back off the file if the disk took only part of it (on a full disk the log
    ended mid-record). `write` raises the OSError of a record it could not write."""

    def __init__(self, path: Path):
        try:
            self._file = open(path, "wb", buffering=0)  # noqa: SIM115 (closed by close())
        except OSError as error:
            raise DeployError(f"cannot write the log: {error}") from None
        self._size = 0

    def write(self, text: str) -> None:
        data = memoryview(text.encode())
        written = 0
        try:
            while written < len(data):  # a write cut short is retried: the next one says why (a full disk)
                count = self._file.write(data[written:])
                if not count:
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                written += count
        except OSError:
            with contextlib.suppress(OSError):
                self._file.truncate(self._size)
                self._file.seek(self._size)
            raise
        self._size += written

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> "RecordLog":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


class SafetyStop(Exception):
    """A safety limit tripped; the message names the limit and the reading."""


class PolicyFailure(Exception):
    """The policy raised instead of giving an action (the message names the error)."""


def check_deployable(policy, interface: LoopInterface) -> None:
    """Refuse privileged policies, policies whose observation or action size is not the env's, and
    policies that do not give a finite action for the first observation a host builds (a feedback
    block of zeros) and for zeros: all before the port is opened (PolicyFileError for the last)."""
    if policy.privileged or interface.privileged:
        raise DeployError("this policy was trained with privileged (simulation-only) observations; "
                          "a real hand cannot provide them - retrain with privileged=False")
    if getattr(policy, "needs_feedback", False):
        check_feedback_policy(policy, interface)
        return
    host_size = interface.host_observation_size
    if policy.observation_dim != host_size:
        raise DeployError(f"the policy expects {policy.observation_dim} observations but a host builds "
                          f"{host_size} from a feedback block")
    fields = interface.layout.control_fields
    if policy.action_dim != len(fields):
        raise DeployError(f"the policy gives {policy.action_dim} actions but the env's control block has "
                          f"{len(fields)} fields ({', '.join(f'{name} {motor}' for motor, name in fields)})")
    first = interface.observation_from_feedback([0] * len(interface.layout.feedback_fields), [0] * len(fields), 0.0,
                                              interface.new_history())
    check_policy_runs(policy, [first, np.zeros(host_size, dtype=np.float32)], interface.action_space.shape)


def deploy_envelope(interface: LoopInterface, max_velocity: int | None = None, max_strain: int | None = None,
                    max_temperature: float | None = None, allow_looser: bool = False) -> SafetyEnvelope:
    """The limits deploy enforces. A limit given on the command line is taken as it is. Otherwise the
    policy's env envelope (`interface.safety`, which it trained in, from the policy file) may tighten
    deploy's defaults (DEFAULT_ENVELOPE), never loosen them unless `allow_looser` (the command line's
    --allow-looser-limits says so): a file's metadata asking for strain 255, |LCV| 127 and 1e300 C
    once had deploy send LCV 127 where its default clamp is 100."""
    trained = interface.safety
    if not allow_looser:
        trained = SafetyEnvelope(max_strain=min(trained.max_strain, DEFAULT_ENVELOPE.max_strain),
                                 max_velocity=min(trained.max_velocity, DEFAULT_ENVELOPE.max_velocity),
                                 max_temperature=min(trained.max_temperature, DEFAULT_ENVELOPE.max_temperature))
    try:
        return SafetyEnvelope(
            max_strain=trained.max_strain if max_strain is None else max_strain,
            max_velocity=trained.max_velocity if max_velocity is None else max_velocity,
            max_temperature=trained.max_temperature if max_temperature is None else max_temperature)
    except ValueError as error:
        raise ValueError(str(error).replace("SafetyEnvelope.", "")) from None


def looser_limits(interface: LoopInterface) -> list[str]:
    """The limits of the policy's env envelope that are looser than deploy's defaults."""
    trained, default = interface.safety, DEFAULT_ENVELOPE
    return [f"{name} {getattr(trained, name)} (default {getattr(default, name)})"
            for name in ("max_strain", "max_velocity", "max_temperature") if getattr(trained, name) > getattr(default, name)]


def check_feedback_policy(policy, interface: LoopInterface) -> None:
    """A policy that acts on the feedback blocks themselves (the grasp choice): it must be able to run
    on this env's blocks (bound to the interface) and give a finite action of the control block's
    size for a block of zeros, all before the port is opened."""
    fields = interface.layout.feedback_fields
    try:
        policy.bind(interface)
        zeros = interface.layout.encode_feedback([0] * len(fields))
        first = interface.observation_from_feedback([0] * len(fields), [0] * len(interface.layout.control_fields), 0.0,
                                                    interface.new_history())
        action = np.asarray(policy.act(first, {"feedback_block": zeros}), dtype=np.float64)
        policy.reset()
    except (ValueError, KeyError, TypeError) as error:
        raise DeployError(f"the policy cannot run on this env's blocks: {error}") from None
    if action.shape != interface.action_space.shape or not np.all(np.isfinite(action)):
        raise PolicyFileError(f"the policy's test action {action.tolist()} is not {interface.action_space.shape[0]} "
                              "finite numbers")


class Deployment:
    """A policy driving a `BarrettHand` in LOOP, cycle by cycle, with limits and a block log."""

    def __init__(self, hand, policy, interface: LoopInterface, log_file, max_velocity: int | None = None,
                 max_strain: int | None = None, max_temperature: float | None = None,
                 on_exit: str = "GT", clock: str = "wall", allow_looser_limits: bool = False):
        """Limits None: the env's safety envelope (`interface.safety`), which it trained in, as far as
        it is no looser than deploy's defaults (`deploy_envelope`)."""
        if clock not in CLOCKS:
            raise ValueError(f"clock must be one of {CLOCKS}, got {clock!r}")
        if on_exit not in EXIT_ACTIONS:
            raise ValueError(f"on_exit must be one of {EXIT_ACTIONS}, got {on_exit!r}")
        check_deployable(policy, interface)
        self.hand, self.policy, self.interface = hand, policy, interface
        self.envelope = deploy_envelope(interface, max_velocity, max_strain, max_temperature, allow_looser_limits)
        max_velocity = self.envelope.max_velocity
        self.max_strain, self.max_temperature = self.envelope.max_strain, self.envelope.max_temperature
        self.log_file = log_file
        self.on_exit = on_exit
        space = interface.action_space
        self._low = space.low.astype(np.float64)
        self._high = space.high.astype(np.float64)
        fields = interface.layout.control_fields
        is_velocity = np.array([name == "LCV" for _, name in fields])
        floor = -max_velocity if max_velocity < NO_VELOCITY_CLAMP else self._low
        self._clamp_low = np.where(is_velocity, np.maximum(self._low, floor), self._low).astype(np.int64)
        self._clamp_high = np.where(is_velocity, np.minimum(self._high, max_velocity), self._high).astype(np.int64)
        # LCV 0 and LCPG 0: no motion and no torque (SPEC.md §5); the block sent before leaving LOOP
        self._stop_values = [0] * len(fields)
        self._action = np.zeros(len(fields), dtype=np.int64)
        self.clock = clock
        self.layout = None
        self.blocks = 0  # blocks exchanged: the "A" block is cycle 0 in the log, policy cycle k is cycle k
        self.policy_cycles = 0
        self.hand_error = None  # the port or hand failure that ended the run (BH8Error), if one did
        self.policy_error = None  # the policy's failure that ended the run (PolicyFailure), if one did
        self.safe_exit_error = None  # why finish() could not leave the hand safe (BH8Error), if it could not
        self.log_error = None  # why the log stopped (OSError), if a record could not be written
        self._stop_request = None  # set by a signal handler: why to stop at the next cycle boundary
        self.found_baud = hand.baudrate
        self.baud_error = None  # why the hand could not be switched back to found_baud, if it could not

    def _log(self, record: dict) -> None:
        """Log one record; a failure ends the logging (the file keeps the records before it) and
        asks for a stop at the next cycle boundary, never interrupting what the hand is sent."""
        if self.log_error is not None:
            return
        try:
            self.log_file.write(json.dumps(record) + "\n")
        except OSError as error:
            self.log_error = error
            if self._stop_request is None:
                self._stop_request = f"the log cannot be written ({error.strerror or error})"

    def setup(self, baud_rate: int) -> None:
        """Switch the rate, run the env's setup script, enter LOOP; check the layout agrees."""
        hand, interface = self.hand, self.interface
        if hand.baudrate != baud_rate:
            hand.set_baud(baud_rate)  # the interface's baud_command, switching the host's rate too
            self._log({"event": "baud", "rate": baud_rate, "t": time.monotonic()})
        for line in interface.setup_commands:
            hand.command(line)
            self._log({"event": "command", "line": line, "t": time.monotonic()})
        # The shipped envs' feedback has no LFT: the limit is checked here, before LOOP, and every
        # cycle only when the env's LOOP carries the temperature.
        temperature = hand.temperature()
        self._log({"event": "temperature", "celsius": temperature, "t": time.monotonic()})
        stop = self.envelope.temperature_violation(temperature, " before LOOP")
        if stop is not None:
            raise SafetyStop(stop)
        loop_line = interface.loop_command
        self.layout = hand.start_loop(loop_line[: -len("LOOP")] or "GS")
        self._log({"event": "loop", "line": loop_line, "layout": repr(self.layout), "t": time.monotonic()})
        if not self.layout.same_blocks(interface.layout):
            hand.stop_loop()
            raise DeployError(f"the hand's LOOP blocks are not the env's: the hand's feedback is "
                              f"{self.layout.feedback_fields} and control {self.layout.control_fields}, "
                              f"the env's {interface.layout.feedback_fields} and {interface.layout.control_fields}")

    def _exchange(self, values, header: bytes = b"C"):
        feedback = self.hand.update_raw(values, header)
        self._log({"cycle": self.blocks, "t": time.monotonic(),
                   "control": self.hand.last_control_block.hex(), "feedback": self.hand.last_feedback_block.hex()})
        self.blocks += 1
        return feedback

    def _stop_on_strain_or_temperature(self, feedback) -> None:
        """SafetyStop when the feedback block shows a finger's strain above the envelope's limit
        (`--max-strain`) or the hand hotter than its `--max-temperature`: `run` then sends the zero
        block, ^C and the exit action."""
        stop = (self.envelope.strain_violation((motor, data.strain) for motor, data in feedback.motors.items())
                or self.envelope.temperature_violation(feedback.temperature))
        if stop is not None:
            raise SafetyStop(stop)

    def run(self, cycles: int) -> str:
        """Run up to `cycles` policy cycles; returns why it stopped, which the log's stop record
        also holds. Always tries to leave the hand safe. A port or hand failure is a stop too: its
        reason names the failed cycle, `hand_error` holds it, and `safe_exit_error` is set if
        finish() failed as well (a dead port cannot be reopened for the zero block, ^C and exit action)."""
        if cycles < 1:
            raise ValueError(f"cycles must be positive, got {cycles!r}")
        reason = "done"
        previous = np.zeros(len(self._stop_values), dtype=np.int64)
        base, hand, on_cycles = self.interface, self.hand, self.clock == "cycles"
        processing_time = base.nominal_processing_time
        history = base.new_history()  # the haptic history, built from this hand's blocks as the env builds it
        with self._stop_on_signals():
            try:
                # Like the env's reset: an "A" block (no control data) starts the host's clock and
                # gives the first observation, at the clock's reading after that block.
                start = time.monotonic()
                feedback = self._exchange((), header=b"A")
                elapsed = (base.next_elapsed(0.0, len(hand.last_control_block), processing_time) if on_cycles
                           else time.monotonic() - start)
                observation = base.observation_from_feedback(feedback.values, previous, elapsed, history)
                on_blocks = getattr(self.policy, "needs_feedback", False)  # acts on the blocks themselves
                if on_blocks:
                    self.policy.reset()
                while self.policy_cycles < cycles and self._stop_request is None:
                    self._stop_on_strain_or_temperature(feedback)
                    try:
                        if on_blocks:
                            unit = self.policy.act(observation, {"feedback_block": hand.last_feedback_block})
                        else:
                            unit, _ = self.policy.predict(observation, deterministic=True)
                    except Exception as error:  # the hand still gets the stop block, ^C and exit action
                        raise PolicyFailure(f"{type(error).__name__}: {error}") from error
                    if not np.all(np.isfinite(unit)):
                        raise SafetyStop(f"the policy's action {np.asarray(unit).tolist()} is not finite")
                    unit_to_bytes(unit, self._low, self._high, out=self._action)
                    np.clip(self._action, self._clamp_low, self._clamp_high, out=self._action)
                    previous[:] = self._action
                    feedback = self._exchange(previous.tolist())
                    self.policy_cycles += 1
                    elapsed = (base.next_elapsed(elapsed, len(hand.last_control_block), processing_time) if on_cycles
                               else time.monotonic() - start)
                    observation = base.observation_from_feedback(feedback.values, previous, elapsed, history)
                self._stop_on_strain_or_temperature(feedback)
                if self._stop_request is not None:
                    reason = self._stop_request
            except SafetyStop as stop:
                reason = f"safety stop: {stop}"
            except PolicyFailure as failure:
                self.policy_error = failure
                reason = f"policy error at cycle {self.blocks}: {failure}"
            except KeyboardInterrupt:
                reason = "interrupted (Ctrl-C)"
            except BH8Error as error:
                self.hand_error = error
                reason = f"hand/port error at cycle {self.blocks}: {error}"  # the block being exchanged
            finally:
                try:
                    self.finish()
                except BH8Error as error:
                    # Kept apart from the reason: after a dead port this is only the failed reopen.
                    self.safe_exit_error = error
        self.log_stop(reason)
        return reason

    def log_stop(self, reason: str) -> None:
        """The log's last record: why the run stopped."""
        # blocks: all exchanged ("A" and stop block included); policy_cycles: those the policy chose
        stop = {"event": "stop", "reason": reason, "blocks": self.blocks, "policy_cycles": self.policy_cycles,
                "t": time.monotonic()}
        if self.safe_exit_error is not None:
            stop["safe_exit_error"] = error_text(self.safe_exit_error)
        self._log(stop)

    @contextlib.contextmanager
    def _stop_on_signals(self):
        """While running: Ctrl-C, SIGTERM and SIGHUP (a lab's supervisor, `kill`, a closed terminal)
        ask for a safe stop at the next cycle boundary, so the hand never sees half a block and the
        zero-velocity block is sent (a KeyboardInterrupt mid-exchange lost both). Signal handlers can
        only be set from the main thread; elsewhere a KeyboardInterrupt still stops the run."""
        if threading.current_thread() is not threading.main_thread():
            yield
            return

        def request_stop(signum, _frame):
            if self._stop_request is None:
                self._stop_request = ("interrupted (Ctrl-C)" if signum == signal.SIGINT
                                      else f"terminated ({signal.Signals(signum).name})")

        with handling_signals((signal.SIGINT, signal.SIGTERM, signal.SIGHUP), request_stop):
            yield

    def finish(self) -> None:
        """Zero velocity, leave LOOP, then the exit action (also after Ctrl-C or a limit)."""
        hand = self.hand
        if hand.in_loop:
            try:
                self._exchange(self._stop_values)
            except BH8Error as error:
                # ^C all the same (the hand may be running the last velocities); the block's failure
                # came first and is the one reported.
                try:
                    hand.stop_loop()
                except BH8Error as second:
                    error.add_note(f"then leaving LOOP (^C) failed: {second}")
                raise
            hand.stop_loop()
        else:
            # A RealTime block failed (time-out, garbled reply): the client dropped its layout, but
            # the hand may still be in LOOP running the last velocities; resync sends it ^C.
            hand.resync()
        if self.on_exit != "none":
            hand.command(self.on_exit, check=False)
            self._log({"event": "command", "line": self.on_exit, "t": time.monotonic()})
        self.restore_baud()

    def abandon_setup(self, reason: str, *, interrupted: bool = False) -> None:
        """The setup stopped short of the policy: after Ctrl-C (`interrupted`; HI takes seconds) ^C
        stops a motion in progress or leaves LOOP; then the rate goes back to the one found, and the
        log gets its stop record."""
        if interrupted:
            try:
                self.hand.abort()
            except BH8Error as error:
                self.safe_exit_error = error  # the port is gone: no rate to switch back either
                self.log_stop(reason)
                return
            self._log({"event": "command", "line": "^C", "t": time.monotonic()})
        self.restore_baud()
        self.log_stop(reason)

    def restore_baud(self) -> None:
        """Switch the hand back to the rate it was found at, so the next `bh8 deploy` or `bh8 term`
        with the same `--baud` reaches it (PSET BAUD lasts until power-off). Not a safety matter:
        a failure is kept in `baud_error` and reported, never raised."""
        if self.hand.baudrate == self.found_baud:
            return
        try:
            self.hand.set_baud(self.found_baud)
        except BH8Error as error:
            self.baud_error = error
            return
        self._log({"event": "baud", "rate": self.found_baud, "t": time.monotonic()})


def error_text(error: BaseException) -> str:
    """The error's message and its notes (a later failure while leaving the hand safe)."""
    return "; ".join([str(error), *getattr(error, "__notes__", ())])


def _finite_float(text: str) -> float:
    """argparse `type=`: a finite number (a NaN or infinite limit would never trip)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


EXIT_STATUS_HELP = """\
the same blocks, byte for byte, as `bh8 eval` of the policy (on `bh8 serve --env ID --seed N`):
  --on-exit none --clock cycles (the default limits are the env's own safety envelope: deploy
  clamps nothing the env allows and stops where the env's episode ends with a safety stop; a
  policy's envelope looser than deploy's defaults needs --allow-looser-limits)

exit status:
  0    the cycles ran; the hand was left safe
  1    the port or the hand failed (connecting, in the setup or mid-run: the stop record in the log
       names the cycle), or the safe-exit commands could not be sent
  2    usage error: a bad option value, an unwritable log, or a policy deploy refuses (a damaged or
       privileged policy file, before the port is opened; or one that fails mid-run: the hand is
       left safe and the stop record names the cycle)
  3    stopped early, safely: a safety limit, a non-finite policy output, Ctrl-C, SIGTERM or SIGHUP,
       or a log record that could not be written (a full disk: the log keeps the whole records before it)
  130  Ctrl-C while connecting or in the setup, before the first block (in the setup: ^C to the
       hand, which stops HI, and the rate switched back)
"""


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.epilog = EXIT_STATUS_HELP
    parser.formatter_class = argparse.RawDescriptionHelpFormatter  # keeps the epilog's lines
    parser.add_argument("--port", required=True, help="serial port or pyserial URL (e.g. /dev/ttyUSB0, bh8sim://)")
    parser.add_argument("--policy", required=True, type=Path, help="policy file (.npz export or SB3 .zip)")
    parser.add_argument("--baud", type=int, choices=BAUD_RATES, default=9600, metavar="RATE",
                        help="the hand's current rate, one of %(choices)s (default %(default)s, after power-up)")
    parser.add_argument("--cycles", type=integer_argument(1), default=None,
                        help="policy cycles after the first 'A' block, >= 1 "
                             "(default: one env episode at the nominal latency)")
    parser.add_argument("--log", type=Path, default=Path("deploy_log.jsonl"),
                        help="JSONL block log (default %(default)s)")
    envelope = "the safety envelope the policy's env trained in"
    parser.add_argument("--max-velocity", type=integer_argument(0, NO_VELOCITY_CLAMP, "LCV byte magnitude"),
                        default=None,
                        help=f"|LCV| limit in bytes, 0..127; 127: no clamp, -128..127 (default: {envelope}, "
                             f"by default {DEFAULT_ENVELOPE.max_velocity})")
    parser.add_argument("--max-strain", type=integer_argument(0, 255, "8-bit strain gauge"), default=None,
                        help=f"stop when a finger's strain exceeds this, 0..255 (default: {envelope}, by default "
                             f"{DEFAULT_ENVELOPE.max_strain})")
    parser.add_argument("--max-temperature", type=_finite_float, default=None,
                        help=f"stop when the hand's temperature exceeds this, degrees C (default: {envelope}, by "
                             f"default {DEFAULT_ENVELOPE.max_temperature})")
    parser.add_argument("--clock", choices=CLOCKS, default="wall",
                        help="elapsed time in the observation: wall clock (real hand) or the env's clock "
                             "summed per cycle at the nominal latency (unpaced simulator, e.g. bh8 serve --env); "
                             "default: %(default)s")
    parser.add_argument("--on-exit", choices=EXIT_ACTIONS, default="GT",
                        help="after leaving LOOP: GT fingers off (default), T all motors off, none")
    parser.add_argument("--allow-looser-limits", action="store_true",
                        help="let the policy file's env envelope loosen deploy's default limits (strain "
                             f"{DEFAULT_ENVELOPE.max_strain}, |LCV| {DEFAULT_ENVELOPE.max_velocity}, "
                             f"{DEFAULT_ENVELOPE.max_temperature:g} C); without it a policy's envelope can only "
                             "tighten them (--max-* set a limit outright)")
    add_trust_argument(parser)


def preferred_policy_file(path: Path, trust: bool) -> Path:
    """The file to deploy for --policy `path`: an SB3 .zip's pickle-free export beside it
    (`bh8 export`'s MODEL.npz, not older than the .zip) when there is one and the .zip is not
    trusted; else `path`. Says so on stderr when it takes the export."""
    if path.suffix != ".zip" or trust:
        return path
    export = path.with_suffix(".npz")
    try:
        fresh = export.is_file() and export.stat().st_mtime >= path.stat().st_mtime
    except OSError:
        fresh = False
    if fresh:
        print(f"bh8 deploy: deploying {str(export)!r}, the pickle-free export of {str(path)!r} "
              "(--trust-file deploys the .zip itself)", file=sys.stderr)
        return export
    return path


def run(args: argparse.Namespace) -> int:
    try:
        policy = load_policy(preferred_policy_file(args.policy, args.trust_file), trust=args.trust_file)
        env_id = policy.metadata.get("env_id")
        if env_id is None:
            raise DeployError(f"{str(args.policy)!r} does not name its environment; export it with `bh8 export`")
        env_kwargs = policy.metadata.get("env_kwargs", {})
        if not isinstance(env_id, str) or not isinstance(env_kwargs, dict):
            raise DeployError(f"{str(args.policy)!r}: its env_id must be a string and env_kwargs a table")
        interface = interface_for(env_id, env_kwargs)
        check_deployable(policy, interface)
        # Everything the policy file decides, checked before the port is opened (exit 2, not 1).
        cycles = interface.nominal_episode_steps() if args.cycles is None else args.cycles
        deploy_envelope(interface, args.max_velocity, args.max_strain, args.max_temperature, args.allow_looser_limits)
        looser = looser_limits(interface)
        if looser and not args.allow_looser_limits:
            print(f"bh8 deploy: the policy's env allows {', '.join(looser)}; deploy keeps its defaults "
                  "(--allow-looser-limits to take the policy's)", file=sys.stderr)
    except (PolicyFileError, FileNotFoundError, DeployError, ValueError, TypeError) as exc:
        print(f"bh8 deploy: {exc}", file=sys.stderr)
        return 2
    try:
        args.log.open("a").close()  # writable? (without truncating: the old log survives a bad port)
    except OSError as exc:
        print(f"bh8 deploy: cannot write the log: {exc}", file=sys.stderr)
        return 2
    try:
        with BarrettHand(args.port, baudrate=args.baud) as hand, RecordLog(args.log) as log_file:
            deployment = Deployment(hand, policy, interface, log_file, max_velocity=args.max_velocity,
                                    max_strain=args.max_strain, max_temperature=args.max_temperature,
                                    on_exit=args.on_exit, clock=args.clock,
                                    allow_looser_limits=args.allow_looser_limits)
            try:
                deployment.setup(interface.baud)
            except SafetyStop as stop:
                deployment.abandon_setup(f"safety stop: {stop}")
                print(f"bh8 deploy: safety stop before LOOP: {stop}; log in {args.log}", file=sys.stderr)
                return 3
            except DeployError as refused:
                deployment.abandon_setup(f"refused: {refused}")
                raise
            except KeyboardInterrupt:
                deployment.abandon_setup("interrupted (Ctrl-C) during the setup", interrupted=True)
                print(f"bh8 deploy: interrupted (Ctrl-C) during the setup, before the first block; log in {args.log}",
                      file=sys.stderr)
                return 130
            reason = deployment.run(cycles)
    except (DeployError, BH8Error, ValueError) as exc:
        print(f"bh8 deploy: {exc}", file=sys.stderr)
        return 1
    failed = (deployment.hand_error is not None or deployment.safe_exit_error is not None
              or deployment.policy_error is not None)
    print(f"bh8 deploy: {deployment.policy_cycles} policy cycles, stopped: {reason}; log in {args.log}",
          file=sys.stderr if failed else sys.stdout)
    if deployment.safe_exit_error is not None:
        commands = "zero-velocity block, ^C" + ("" if args.on_exit == "none" else f", {args.on_exit}")
        print(f"bh8 deploy: the safe-exit commands ({commands}) could not be sent: {error_text(deployment.safe_exit_error)}",
              file=sys.stderr)
    if deployment.log_error is not None:
        print(f"bh8 deploy: the log {str(args.log)!r} stopped at a record it could not write "
              f"({error_text(deployment.log_error)}); the records before it are whole", file=sys.stderr)
    if deployment.baud_error is not None:
        print(f"bh8 deploy: the hand stays at {interface.baud} baud (switching back to {args.baud} failed: "
              f"{deployment.baud_error}); connect with --baud {interface.baud}", file=sys.stderr)
    if deployment.hand_error is not None or deployment.safe_exit_error is not None:
        return 1
    if deployment.policy_error is not None:
        return 2  # a bad policy, found mid-run: the hand was left safe
    return 0 if reason == "done" and deployment.log_error is None else 3
