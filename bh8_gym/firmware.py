"""The BH8-262 firmware 4.3x (and 4.4) as a byte-stream machine over a simulated hand.

`Firmware` (docs/architecture.md Contract 2) takes host bytes with `write`, runs on its own
simulated clock (`run_until_idle`, `run_for`) and hands back the bytes the hand would send
(`read`). Sources: manual §4, §5 (supervisory mode, commands, parameters, termination), §6
(RealTime), §9.1-§9.2 (HCTL-1100); SPEC.md §2-§8, which decides framing, codes and timing.

Choices where the documents are silent (SPEC.md §8 and the firmware brief; each is a named
constant below or documented here):

- Framing (SPEC.md §2): every character is echoed as it arrives, the CR is not; the reply is
  "\\n\\r", output lines each ending "\\n\\r", then the prompt "=> ". An error reply is
  "\\n\\rERR <n>\\n\\r=> ". Lines may be lower case (ASCII letters; 0xDF is not "SS"), numbers are
  ASCII digits with an optional sign. LF (0x0A) is ignored in supervisory mode, so a terminal sending
  CR LF works, but not after LOOP: there the LF is the first block header (ERR 2048). Backspace
  (0x08) and DEL (0x7F) remove the last character of the line and echo "\\b \\b". A line longer
  than `MAX_LINE_LENGTH` characters keeps being echoed but its excess is dropped, and the line then
  fails with ERR 128 (invalid value).
- ^C (0x03) in supervisory mode while no command runs discards the partial line and replies
  "\\n\\r=> ". While a motion runs the firmware only looks for ^C (§5.5 case 4): every motor
  terminates and the reply is "ERR 16384"; other bytes arriving during a motion are discarded (the
  68HC811 polls its serial port for ^C while it supervises the motors; typed-ahead text is lost).
- Power-up: a new `Firmware` behaves like the hand just after power-on: parameters from the store,
  motors uninitialised, and NO banner (a client opening the port expects nothing until it sends a
  CR). RESET prints "\\n\\r" + `BANNER_LINES` each ending "\\n\\r", then the prompt. Barrett's
  C++ API 4.4.3 (BHandSerialDriver::HandReset) searches the reply for "BarrettHand Firmware\\n"
  (LF directly after "Firmware"), so that text ends its own line.
- The HCTL position counter reads 0 at power-up wherever the motor is, as on the chip; HI moves
  the origin (§5.2.1 HI, §5.3.4 IOFF).
- HI (SPEC.md §4): each selected motor opens in velocity mode at IVEL until it stalls against its
  open stop; fingers back off `IHIT_BACKOFF_COUNTS` and hit the stop again until they have hit it
  max(IHIT, 1) times (at most `IHIT_MAX_IMPACTS`); the origin is set so the stop reads −IOFF; a
  trapezoidal move then brings the motor to 0. HOLD decides what happens at the end.
- Stall (§5.5 case 1): a driven motor that has not moved more than `STALL_DISTANCE_COUNTS` for
  TSTOP ms (at least `MIN_STALL_WINDOW_MS`) terminates; a profile move whose motor keeps up with
  its profile is not stalled (at its start the profile has not moved that far yet).
- ACCEL 0 (in range, §5.3.4): the HCTL's trapezoid (§9.2.1) cannot accelerate, so a position move
  never leaves its start; the motor, held at rest, stalls and terminates TSTOP ms later (§5.5
  case 1): C and O answer without error, M/HOME/IO/IC with ERR 16.
- Strain-gauge termination (§5.5 case 2) compares the raw gauge value; SGFLIP only changes what is
  sent to the host (FGET SG, LFS), as §5.3.4 says.
- Over-temperature (§5.4.1 OTEMP): checked when a motor command (HI HOME M IO IC C O TC TO LOOP)
  starts: TEMP > OTEMP with OTEMP ≠ 0 fails it with ERR 8192. T is always allowed (it cools).
- T on an uninitialised motor: §5.2.1 T note: "T will return an ERR 1 if any of the selected
  motor(s) isn't initialized; it will still turn the selected and initialized motor(s)'s power off".
- RealTime (§6, SPEC.md §5-§6): LOOP answers the echo then "*" at once. ^C leaves LOOP with the
  reply "\\n\\r=> " and no ERR line (§6.4: "the hand will respond by printing a prompt"). A bad
  header answers "\\n\\rERR 2048\\n\\r=> ". Leaving LOOP applies HOLD to the LOOP motors. On
  entering LOOP the motors run at velocity 0 with gain FPG until a control block sets them; a
  motor whose LCPG flag is 0 keeps FPG as its gain. Firmware 4.4 LCT is a position-mode datum
  (SPEC.md §7, from Barrett's API documentation): each control block's LCT is added to the motor's
  present position and the sum becomes the commanded position, servoed with gain FPG (so the
  torque is FPG/4 × LCT, saturating at full duty); before the first block an LCT motor holds where
  it is. LFBP reports BP (below); LFAIN reads 0 (no analog input is modelled).
- Breakaway (SPEC.md §3.1): the plant's TorqueSwitch slip is the detection (BDAT is stored and
  listed but the simulated hand needs no acceleration threshold). BD is 1 once a finger broke away
  after its last O, TO or HI (those clear BD and BP as they start), BP is the HCTL position of that
  breakaway (0 when none, clipped to 0..20000). With BS 1 a finger's supervisory motion terminates
  (HOLD applies) as soon as the finger breaks away during it; LOOP is not affected.
- The RealTime cycle_hook runs at the start of every cycle, before the control block's time.
- FLISTV/FLISTAV/PLISTV/PLISTAV lines are "NAME v1 v2 ..."; FLIST/PLIST lines are
  "NAME<padding>description"; FGET/PGET lines are values only (SPEC.md §2 example).
- Only FGET P sets the RealTime "reported position" (§6.2.3); FLISTV does not. With LFDPD set, the
  reported position becomes the present one every cycle: the part of a change LFDP cannot carry,
  overflow or the remainder below LFDPC, is discarded (§5.4.3 LFDPD: "any position change that
  cannot be sent in a delta position datum is discarded").
- LFAP is an unsigned word (SPEC.md §5): a position below 0 (a finger opened past its home, e.g.
  right after HI) is sent as 0, above 65535 as 65535; FGET P reports the signed value.
- FSET/PSET are all-or-nothing: if any pair is bad nothing is set and the codes of all bad pairs
  are summed (§5.1.3: "the sum of the status codes encountered").
"""
from __future__ import annotations

import copy
import re
from math import exp, isnan

from bh8_gym.motion_control import ACCEL_SCALE, HOLD, VELOCITY_SCALE, MotorChannel
from bh8_gym.nvstore import NVStore
from bh8_gym.parameters import (
    BREAKAWAY_POSITION_MAX,
    GLOBAL_TABLE,
    MOTOR_TABLE,
    coefficient,
    default_global_values,
    default_motor_values,
    global_parameters,
    listed,
    motor_parameters,
)
from bh8_gym.plant import HandPlant
from bh8_gym.protocol import (
    FIRMWARE_PROFILES,
    LINE_END,
    MOTOR_PREFIXES,
    MOTORS,
    PROMPT,
    REALTIME_PROCESSING_S,
    SPREAD_MOTOR,
    seconds_per_byte,
)
from bh8_gym.realtime_codec import HEADERS_WITH_DATA, HEADERS_WITH_FEEDBACK, LoopLayout, MotorFlags
from bh8_gym.status import STATUS_DESCRIPTIONS, Status

VERSIONS = {"4.3": "4.34", "4.4": "4.40"}  # our choice of the exact 4.3x / 4.4x version strings
BANNER_LINES = ("BarrettHand Firmware", "Version {version}")  # see module docstring
MAX_LINE_LENGTH = 255  # our choice: longer lines fail with ERR 128
# Our choice (the manual only says "no motion"): movement below this many counts during TSTOP ms
# is a stall. It absorbs a fingertip creeping along a curved object under full force (up to about
# 200 counts/s, 2 degrees of its outer link a second, in PyBullet); the slowest command, MCV 16,
# moves 39 counts in the shortest window (MIN_STALL_WINDOW_MS), and a profile's start is exempt.
STALL_DISTANCE_COUNTS = 10.0
# Our choice: the shortest time a stall is judged over, whatever TSTOP says (0 is in its range):
# a motor starting from rest moves less than STALL_DISTANCE_COUNTS in its first physics step, and
# HI would take that for the open stop (and zero the encoder wherever the finger was).
MIN_STALL_WINDOW_MS = 10.0
# Our choice: the time constant (s) of the smoothing applied to the encoder for stall detection. It
# removes the physics' step-to-step jitter of a finger pressed on an object (a few counts) and keeps
# the motion of a moving motor (a stall needs STALL_DISTANCE_COUNTS of quiet for TSTOP).
STALL_SMOOTHING_S = 0.008
# Our choice for HI: how far a finger backs off the open stop between impacts (§5.3.4 IHIT); about
# 4 degrees of the inner link, enough to reach IVEL again before the next impact.
IHIT_BACKOFF_COUNTS = 500.0
# §5.5 case 3: "As soon as the goal position is reached" (the profile has ended and the motor is
# within MPE) the motor terminates; HOLD 1 then servos at the goal. Our choice: a HOLD 0 motor must
# also have settled below this speed (counts/s), so it is switched off where it will stay (FGET P
# after "M 1000" reads about 1000, not the lag of the decelerating motor).
GOAL_SETTLE_VELOCITY_CPS = 500.0
IHIT_MAX_IMPACTS = 20  # our bound on max(IHIT, 1), so HI always ends in bounded simulated time
# Simulated seconds `transact` waits for a command to finish. A motion can run for ever (a finger
# jittering against an obstacle by more than STALL_DISTANCE_COUNTS never stalls, as on the hand);
# one that stalls ends within TSTOP (at most 65.5 s) of stalling, and a full close at the slowest
# MCV takes about 4.4 s, so only an HI with many IHIT impacts at a huge TSTOP takes longer.
TRANSACT_LIMIT_S = 300.0
MOTION_ARGUMENT_RANGE = (0, 20000)  # §5.2.1 M, IO, IC arguments
# The motion commands that clear BD and BP as they start (SPEC.md §3.1: "cleared after an O, TO, or HI").
BREAKAWAY_CLEARING_COMMANDS = ("O", "TO", "HI")
_EPS = 1e-9
_INTEGER = re.compile(r"[+-]?[0-9]+")

_CTRL_C = 0x03
_CR = 0x0D
_LF = 0x0A
_BACKSPACES = (0x08, 0x7F)

# name: (description, advanced, takes a motor prefix) — §5.2.1-§5.2.5
COMMANDS = {
    "C": ("Close", False, True),
    "HI": ("Hand Initialize", False, True),
    "HOME": ("Home", False, True),
    "IO": ("Incremental Open", False, True),
    "IC": ("Incremental Close", False, True),
    "LOOP": ("Loop", False, True),
    "M": ("Move", False, True),
    "O": ("Open", False, True),
    "T": ("Terminate power", False, True),
    "TC": ("Torque-Controlled Close", False, True),
    "TO": ("Torque-Controlled Open", False, True),
    "FSET": ("Finger Set", False, True),
    "FGET": ("Finger Get", False, True),
    "FLOAD": ("Finger Load", False, True),
    "FSAVE": ("Finger Save", False, True),
    "FDEF": ("Finger Default", False, True),
    "FLIST": ("Finger List", False, False),
    "FLISTV": ("Finger List Value", False, True),
    "PSET": ("Parameter Set", False, False),
    "PGET": ("Parameter Get", False, False),
    "PLOAD": ("Parameter Load", False, False),
    "PSAVE": ("Parameter Save", False, False),
    "PDEF": ("Parameter Default", False, False),
    "PLIST": ("Parameter List", False, False),
    "PLISTV": ("Parameter List Value", False, False),
    "?": ("Help", False, False),
    "RESET": ("Reset", False, False),
    "ERR": ("Error", False, False),
    "VERS": ("Version", False, False),
    "A?": ("Help All", True, False),
    "FLISTA": ("Finger List All", True, False),
    "FLISTAV": ("Finger List All Value", True, True),
    "PLISTA": ("Parameter List All", True, False),
    "PLISTAV": ("Parameter List All Value", True, False),
}
MOTOR_COMMANDS = frozenset(("C", "HI", "HOME", "IO", "IC", "LOOP", "M", "O", "TC", "TO"))
POSITION_COMMANDS = frozenset(("HOME", "IO", "IC", "M"))  # these report ERR 16 (§5.5)
MOVEMENT_COMMANDS = MOTOR_COMMANDS | {"T"}  # §5.2.1; without a prefix they act on the EN=1 motors

# Per-motor run kinds of a motion command.
_RUN_POSITION, _RUN_VELOCITY, _RUN_HI_SEEK, _RUN_HI_BACKOFF, _RUN_HI_HOME = range(5)
_POSITION_RUNS = frozenset((_RUN_POSITION, _RUN_HI_BACKOFF, _RUN_HI_HOME))


class FirmwareBusyError(TimeoutError):
    """`transact` gave up waiting: the command was still running after its simulated-time limit."""


class _FirmwareError(Exception):
    """A command failed with a Table 3 status sum."""

    def __init__(self, code: int):
        super().__init__(code)
        self.code = int(code)


class _MotorRun:
    """Termination bookkeeping of one motor during a motion command (§5.5)."""

    __slots__ = ("motor", "kind", "target", "direction", "progress", "smooth", "stall_time", "impacts_left",
                 "reached")

    def __init__(self, motor: int, kind: int, target: float, position: float, time: float, direction: float = 0.0):
        self.motor = motor
        self.kind = kind
        self.target = target
        self.direction = direction  # velocity runs: the drive's sign (+ closes)
        self.stall_time = time
        self.smooth = position  # the encoder, smoothed over STALL_SMOOTHING_S
        self.progress = self.measure(position)  # where the motor was when it last moved on
        self.impacts_left = 0
        self.reached = True

    def restart(self, kind: int, target: float, position: float, time: float, direction: float = 0.0) -> None:
        self.kind, self.target, self.direction = kind, target, direction
        self.smooth, self.progress, self.stall_time = position, self.measure(position), time

    def measure(self, position: float) -> float:
        """Where a position run's motor is (any way it moves is motion: a servo swinging about its
        goal is not stalled); how far a velocity run's motor has got in its drive's direction (one
        pushed back, against its drive, is stalled)."""
        return position if self.kind in _POSITION_RUNS else self.direction * position

    def moved(self, position: float, smoothing: float) -> bool:
        """Whether the smoothed encoder has moved on by more than STALL_DISTANCE_COUNTS since `progress`."""
        self.smooth += smoothing * (position - self.smooth)
        now = self.measure(self.smooth)
        if self.kind in _POSITION_RUNS:
            return abs(now - self.progress) > STALL_DISTANCE_COUNTS
        return now - self.progress > STALL_DISTANCE_COUNTS


class FirmwareSnapshot:
    """Opaque state of a `Firmware` and its plant; give it back to `Firmware.restore`."""

    __slots__ = ("plant_state", "state", "shared")

    def __init__(self, plant_state, state: dict, shared: dict):
        self.plant_state = plant_state
        self.state = state
        self.shared = shared


class Firmware:
    """The hand's firmware as a byte-stream machine with its own simulated clock (Contract 2)."""

    def __init__(
        self, plant=None, store_dir=None, profile: str = "4.3", seed: int = 0,
        processing_time: float = REALTIME_PROCESSING_S,
    ):
        if profile not in FIRMWARE_PROFILES:
            raise ValueError(f"firmware profile must be one of {FIRMWARE_PROFILES}, got {profile!r}")
        processing_time = float(processing_time)
        if not (processing_time >= 0.0 and processing_time < 1.0):
            raise ValueError(f"processing_time must be in [0, 1) seconds, got {processing_time!r}")
        #: Seconds the firmware spends on one RealTime block (SPEC.md §6); randomised per episode by the envs.
        self.processing_time = processing_time
        self._owns_plant = plant is None
        if plant is None:
            plant = HandPlant(seed=seed)
        self.plant = plant
        self.profile = profile
        self.version = VERSIONS[profile]
        self.store = NVStore(store_dir, profile=profile, seed=seed)
        self.cycle_hook = None
        #: Called as `loop_entry_hook(firmware, layout)` after a LOOP command has queued its "*"
        #: (`bh8 serve --env` starts the env's episode there); may call `restore(..., keep_io=True)`.
        self.loop_entry_hook = None
        #: Called as `other_profile_hook(name, profiles)` when a command names a parameter that only
        #: other firmware profiles have (the reply stays ERR 64, as on a hand of this version);
        #: `bh8 serve` tells its user which `--firmware` the client wants.
        self.other_profile_hook = None
        self._motor_table = motor_parameters(profile)
        self._global_table = global_parameters(profile)
        self._dt = float(plant.dt)
        self._stall_smoothing = 1.0 - exp(-self._dt / STALL_SMOOTHING_S)
        self._time_base = float(plant.time)
        self._steps = 0
        self._physics_time = self._time_base
        self.time = self._time_base
        self._channels = {m: MotorChannel() for m in MOTORS}
        self._channel_list = [self._channels[m] for m in MOTORS]
        self._drive_velocities = [0.0] * 4
        self._drive_fractions = [float("nan")] * 4
        self._input = bytearray()
        self._output = bytearray()
        self._line = bytearray()
        self._line_overflow = False
        self._task = None
        self._wake = 0.0
        self._loop_layout: LoopLayout | None = None
        self._refresh_plant_state()
        self._last_positions = list(self._positions)
        self._power_up()

    # ------------------------------------------------------------------ public API (Contract 2)

    def write(self, data: bytes) -> None:
        """Host -> hand bytes, arriving at the current simulated time."""
        self._input += data

    def read(self) -> bytes:
        """Hand -> host bytes produced so far (drained)."""
        out = bytes(self._output)
        self._output.clear()
        return out

    def run_until_idle(self, max_seconds: float | None = None) -> bool:
        """Advance simulated time until the firmware waits for input, and return True; with
        `max_seconds`, at most that much simulated time: False if a command is still running
        (write ^C to abort a motion that does not end)."""
        if max_seconds is not None and not max_seconds >= 0.0:
            raise ValueError(f"max_seconds must be a non-negative number of seconds, got {max_seconds!r}")
        self._run(None, None if max_seconds is None else self.time + max_seconds)
        return self.idle

    def run_for(self, seconds: float) -> None:
        """Advance at most `seconds` of simulated time; the world keeps running while idle."""
        if not seconds >= 0.0:
            raise ValueError(f"run_for needs a non-negative number of seconds, got {seconds!r}")
        self._run(self.time + seconds)

    def transact(self, data: bytes, max_seconds: float = TRANSACT_LIMIT_S) -> bytes:
        """write + run_until_idle + read. Raises FirmwareBusyError if the command is still running
        after `max_seconds` simulated seconds (it keeps running; ^C aborts it)."""
        self.write(data)
        if not self.run_until_idle(max_seconds):
            raise FirmwareBusyError(f"the hand was still executing {bytes(data)!r} after {max_seconds:g} simulated "
                                    "seconds (a motion that does not end); write b'\\x03' (^C) to abort it")
        return self.read()

    @property
    def idle(self) -> bool:
        """True when waiting for input with no command running."""
        return self._task is None and not self._input_ready()

    @property
    def in_loop(self) -> bool:
        """True in RealTime (LOOP) mode."""
        return self._loop_layout is not None

    @property
    def pending_input(self) -> int:
        """Bytes written and not yet consumed (a server reads no more while this is high)."""
        return len(self._input)

    @property
    def loop_layout(self) -> LoopLayout | None:
        """The RealTime block layout while in LOOP mode, else None."""
        return self._loop_layout

    @property
    def baud(self) -> int:
        """The serial rate in bits per second (PSET BAUD × 100)."""
        return self._globals["BAUD"] * 100

    def shutdown(self) -> None:
        """Persist the never-reset counters (OD, PTEMP, UPSECS), release the store's directory; close
        the plant if we built it."""
        self._save()
        self.store.close()
        if self._owns_plant:
            self._owns_plant = False
            self.plant.close()

    def save_counters(self) -> None:
        """Persist the never-reset counters (OD, PTEMP, UPSECS) now, as the hand keeps them through
        power failures (`bh8 serve` calls this every few seconds after activity)."""
        self._save()

    def snapshot(self) -> FirmwareSnapshot:
        """Firmware and plant state, for `restore` (only between commands: no motion running)."""
        if self._task is not None:
            raise RuntimeError("snapshot() needs the firmware between commands (a motion or RealTime cycle is running)")
        shared = {name: self.__dict__[name] for name in _SHARED_STATE}
        state = {k: v for k, v in self.__dict__.items() if k not in _NOT_SNAPSHOT and k not in _SHARED_STATE}
        return FirmwareSnapshot(self.plant.save_state(), copy.deepcopy(state), shared)

    def restore(self, snapshot: FirmwareSnapshot, keep_io: bool = False) -> None:
        """Return firmware and plant to `snapshot`; later bytes equal those of the original run.

        `keep_io=True` keeps the serial bytes not yet processed (input) and not yet read (output),
        as a live serial line would (used from `loop_entry_hook`)."""
        if not isinstance(snapshot, FirmwareSnapshot):
            raise TypeError(f"restore() needs a FirmwareSnapshot, got {type(snapshot).__name__}")
        pending = (self._input, self._output) if keep_io else None
        self.plant.restore_state(snapshot.plant_state)
        self.__dict__.update(copy.deepcopy(snapshot.state))
        self.__dict__.update(snapshot.shared)
        self._task = None
        self._channel_list = [self._channels[m] for m in MOTORS]
        self._refresh_plant_state()
        if pending is not None:
            self._input, self._output = pending

    # ------------------------------------------------------------------ time and physics

    def _run(self, deadline: float | None, busy_limit: float | None = None) -> None:
        """Run until `deadline` (None: until idle), or until `busy_limit` while a command runs."""
        while True:
            if self._task is None:
                self._consume_input()
                if self._task is None:
                    if deadline is not None and deadline > self.time:
                        self._advance_to(deadline)
                    return
            if deadline is not None and self._wake > deadline:
                self._advance_to(deadline)
                return
            if busy_limit is not None and self._wake > busy_limit:
                self._advance_to(busy_limit)
                return
            self._advance_to(self._wake)
            try:
                self._wake = next(self._task)
            except StopIteration:
                self._task = None

    def _start_task(self, task) -> None:
        try:
            self._wake = next(task)
        except StopIteration:
            return
        self._task = task

    def _advance_to(self, t: float) -> None:
        if t <= self.time:
            return
        step_end = self._physics_time + self._dt
        while step_end <= t + _EPS:
            self._physics_step()
            step_end = self._physics_time + self._dt
        self.time = t

    def _physics_step(self) -> None:
        positions, velocities = self._positions, self._velocities
        origin, last, odometer = self._origin, self._last_positions, self._odometer
        drive_v, drive_f = self._drive_velocities, self._drive_fractions
        t, dt = self._physics_time, self._dt
        for i, channel in enumerate(self._channel_list):
            position = positions[i]
            odometer[i] += abs(position - last[i])
            last[i] = position
            drive_v[i], drive_f[i] = channel.drive(t, position - origin[i], velocities[i], dt)
        self._positions, self._velocities = self.plant.step_with_drives(drive_v, drive_f)
        self._steps += 1
        self._physics_time = self._time_base + self._steps * dt

    def _refresh_plant_state(self) -> None:
        self._positions, self._velocities = self.plant.motor_state_lists()

    # ------------------------------------------------------------------ power-up and store

    def _power_up(self) -> None:
        """State right after power-on (also RESET): store loaded, motors off and uninitialised."""
        contents = self.store.load()
        self._motor_values = contents.motors
        self._globals = contents.globals
        self._odometer = [contents.odometer_counts[m] for m in MOTORS]
        self._peak_temperature = contents.peak_temperature
        self._uptime_base = contents.uptime_seconds
        self._boot_time = self.time
        self._serial_number = contents.serial_number
        self._origin = list(self._positions)  # the HCTL counters read 0 at power-up
        self._last_positions = list(self._positions)
        self._initialized = {m: False for m in MOTORS}
        self._status = {m: int(Status.NOT_INITIALIZED) for m in MOTORS}
        self._reported_position = {m: 0 for m in MOTORS}
        self._breakaway_cleared = [self._plant_breakaway(m) for m in MOTORS]
        for channel in self._channels.values():
            channel.off()
            channel.set_sample(31)
        self._loop_layout = None
        self._line.clear()
        self._line_overflow = False

    def _save(self, motors=(), global_values: bool = False) -> None:
        """One store write: the counters, plus the parameter sets of `motors` and/or the globals."""
        uptime = self._uptime_seconds()
        try:
            peak = self._update_peak_temperature()
        except ValueError:  # a NaN temperature (the physics failed): the counters are saved all the same
            peak = self._peak_temperature
        self.store.save((dict(zip(MOTORS, self._odometer)), peak, uptime),
                        motors={m: self._motor_values[m] for m in motors},
                        global_values=self._globals if global_values else None)
        self._uptime_base = uptime
        self._boot_time = self.time

    def _uptime_seconds(self) -> float:
        return self._uptime_base + (self.time - self._boot_time)

    def _temperature_tenths(self) -> int:
        return max(-550, min(1250, int(round(self.plant.temperature * 10.0))))

    def _update_peak_temperature(self) -> int:
        temp = self._temperature_tenths()
        if temp > self._peak_temperature:
            self._peak_temperature = temp
        return self._peak_temperature

    # ------------------------------------------------------------------ input handling

    def _input_ready(self) -> bool:
        data = self._input
        if not data:
            return False
        layout = self._loop_layout
        if layout is None:
            return True
        header = data[0]
        if header in HEADERS_WITH_DATA:
            return len(data) >= layout.control_block_size(header)
        return True

    def _consume_input(self) -> None:
        """Process arrived bytes until a task starts or the input runs dry."""
        data = self._input
        while data and self._task is None:
            if self._loop_layout is not None:
                if not self._consume_loop_block():
                    return
                continue
            byte = data[0]
            del data[0]
            if byte == _CR:
                line = bytes(self._line)
                overflow = self._line_overflow
                self._line.clear()
                self._line_overflow = False
                self._execute(line, overflow)
            elif byte == _CTRL_C:
                self._line.clear()
                self._line_overflow = False
                self._output += LINE_END + PROMPT
            elif byte == _LF:
                continue
            elif byte in _BACKSPACES:
                if self._line:
                    self._line.pop()
                    self._output += b"\b \b"
            else:
                self._output.append(byte)
                if len(self._line) < MAX_LINE_LENGTH:
                    self._line.append(byte)
                else:
                    self._line_overflow = True

    def _reply(self, lines=(), error: int = 0) -> None:
        out = self._output
        out += LINE_END
        if error:
            out += b"ERR %d" % error + LINE_END
        else:
            for line in lines:
                out += line.encode("latin-1") + LINE_END
        out += PROMPT

    # ------------------------------------------------------------------ supervisory commands

    def _execute(self, raw: bytes, overflow: bool) -> None:
        # Case and whitespace by the bytes' ASCII rules, as the hand's 8-bit parser: str rules would
        # make 0xDF ("ß") upper-case to "SS", a spread prefix, and 0xA0 a separator.
        line = raw.strip().upper()
        text = line.decode("latin-1")
        if overflow:
            self._reply(error=Status.INVALID_VALUE)
            return
        if not text:
            self._reply()
            return
        i = 0
        while i < len(text) and text[i] in MOTOR_PREFIXES:
            i += 1
        prefix = text[:i]
        tokens = [token.decode("latin-1") for token in line[i:].split()]
        word = tokens[0] if tokens else ""
        args = tokens[1:]
        if word.startswith("?") and word != "?":
            args = [word[1:]] + args
            word = "?"
        entry = COMMANDS.get(word)
        if entry is None:
            self._reply(error=Status.UNKNOWN_COMMAND)
            return
        if prefix and not entry[2]:
            self._reply(error=Status.NO_PREFIX_ALLOWED)
            return
        if prefix:
            motors = tuple(sorted({m for c in prefix for m in MOTOR_PREFIXES[c]}))
        elif word in MOVEMENT_COMMANDS:  # §5.3.4 EN: "a motion command with no motor prefix"
            motors = tuple(m for m in MOTORS if self._motor_values[m]["EN"])
        else:  # §5.2: "By default, all four motors are affected"
            motors = MOTORS
        handler = getattr(self, "_cmd_" + _HANDLER_NAMES.get(word, word))
        try:
            if word in MOTOR_COMMANDS:
                self._check_motor_command(word, motors, args)
            lines = handler(motors, args)
        except _FirmwareError as error:
            self._reply(error=error.code)
            return
        if lines is not None:
            self._reply(lines)

    @staticmethod
    def _no_arguments(args) -> None:
        if args:
            raise _FirmwareError(Status.TOO_MANY_ARGUMENTS)

    @staticmethod
    def _integer(text: str) -> int:
        if _INTEGER.fullmatch(text) is None:  # ASCII digits only: str.isdigit() accepts "²"
            raise _FirmwareError(Status.INVALID_VALUE)
        return int(text)

    def _motion_argument(self, args) -> int | None:
        if len(args) > 1:
            raise _FirmwareError(Status.TOO_MANY_ARGUMENTS)
        if not args:
            return None
        value = self._integer(args[0])
        if not MOTION_ARGUMENT_RANGE[0] <= value <= MOTION_ARGUMENT_RANGE[1]:
            raise _FirmwareError(Status.INVALID_VALUE)
        return value

    def _check_motor_command(self, word: str, motors, args) -> None:
        if word in ("M", "IO", "IC"):
            self._motion_argument(args)
        else:
            self._no_arguments(args)
        otemp = self._globals["OTEMP"]
        if otemp and self._temperature_tenths() > otemp:
            raise _FirmwareError(Status.OVER_TEMPERATURE)
        if word != "HI" and any(not self._initialized[m] for m in motors):
            raise _FirmwareError(Status.NOT_INITIALIZED)

    # -- movement (§5.2.1)

    def _cmd_HI(self, motors, args):
        self._start_task(self._motion_task("HI", motors, {}))

    def _cmd_HOME(self, motors, args):
        self._start_position_command("HOME", motors, {m: 0.0 for m in motors})

    def _cmd_M(self, motors, args):
        value = self._motion_argument(args)
        targets = {m: float(self._motor_values[m]["DP"] if value is None else value) for m in motors}
        self._start_position_command("M", motors, targets)

    def _cmd_IC(self, motors, args):
        self._incremental("IC", motors, args, 1.0)

    def _cmd_IO(self, motors, args):
        self._incremental("IO", motors, args, -1.0)

    def _incremental(self, word, motors, args, direction):
        value = self._motion_argument(args)
        targets = {}
        for m in motors:
            step = self._motor_values[m]["DS"] if value is None else value
            # From the HCTL's commanded position: a held motor's set point (a servo still settling,
            # the back-drivable spread, is not a step short), else where the motor is.
            channel = self._channels[m]
            start = channel.set_point if channel.mode == HOLD else round(self._position(m))
            targets[m] = float(start) + direction * step
        self._start_position_command(word, motors, targets)

    def _cmd_C(self, motors, args):
        self._start_position_command("C", motors, {m: float(self._motor_values[m]["CT"]) for m in motors})

    def _cmd_O(self, motors, args):
        self._start_position_command("O", motors, {m: float(self._motor_values[m]["OT"]) for m in motors})

    def _cmd_TC(self, motors, args):
        self._start_task(self._motion_task("TC", motors, {}))

    def _cmd_TO(self, motors, args):
        self._start_task(self._motion_task("TO", motors, {}))

    def _start_position_command(self, word, motors, targets):
        self._start_task(self._motion_task(word, motors, targets))

    def _cmd_T(self, motors, args):
        self._no_arguments(args)
        for m in motors:
            if self._initialized[m]:
                self._channels[m].off()
        if any(not self._initialized[m] for m in motors):
            raise _FirmwareError(Status.NO_MOTOR_BOARD)  # §5.2.1 T note: "ERR 1"
        return []

    def _cmd_LOOP(self, motors, args):
        if not motors:
            raise _FirmwareError(Status.INVALID_VALUE)
        flags = {m: MotorFlags.from_parameters(self._motor_values[m]) for m in motors}
        layout = LoopLayout(motors, flags, lft=bool(self._globals["LFT"]), firmware=self.profile)
        self._enter_loop(layout)
        return None

    # -- motion task (§5.5 termination)

    def _motion_task(self, word: str, motors, targets: dict):
        """Generator run by `_run`: drives `motors` until each terminates, then replies."""
        values = self._motor_values
        channels = self._channels
        t = self._physics_time
        runs = []
        if word in BREAKAWAY_CLEARING_COMMANDS:
            for m in motors:
                self._breakaway_cleared[m - 1] = self._plant_breakaway(m)
        # BS stops a finger at a breakaway during this motion (an edge: an earlier one still in BD does not)
        breakaway_at_start = {m: self._plant_breakaway(m) for m in motors}
        for m in motors:
            v = values[m]
            channel = channels[m]
            channel.set_sample(v["SAMPLE"])
            position = self._position(m)
            if word == "HI":
                channel.velocity(-v["IVEL"] / VELOCITY_SCALE, v["FPG"])
                run = _MotorRun(m, _RUN_HI_SEEK, 0.0, position, t, -1.0)
                impacts = v["IHIT"] if m != SPREAD_MOTOR else 0
                run.impacts_left = min(max(impacts, 1), IHIT_MAX_IMPACTS) - 1
            elif word in ("TC", "TO"):
                speed = v["MCV"] if word == "TC" else -v["MOV"]
                channel.velocity(speed / VELOCITY_SCALE, v["FPG"])
                run = _MotorRun(m, _RUN_VELOCITY, 0.0, position, t, 1.0 if word == "TC" else -1.0)
            else:
                run = _MotorRun(m, _RUN_POSITION, targets[m], position, t)
                self._start_move(channel, v, t, position, targets[m])
            self._status[m] = 0
            runs.append(run)
        abort = False
        while runs:
            yield self._physics_time + self._dt
            if self._input:
                abort = self._scan_for_ctrl_c()
                if abort:
                    break
            t = self._physics_time
            strain = None
            for run in tuple(runs):
                m = run.motor
                v = values[m]
                channel = channels[m]
                position = self._position(m)
                ended = False
                # §5.5 case 1: a motor that has not moved on for TSTOP has stalled ("until no motion
                # is detected", App. B A1). The encoder is smoothed first: a finger pressing on an
                # object can jitter by a few counts from one physics step to the next.
                if run.moved(position, self._stall_smoothing) or (
                        run.kind in _POSITION_RUNS and self._on_profile(channel, t, position)):
                    run.progress = run.measure(run.smooth)
                    run.stall_time = t
                elif (t - run.stall_time) * 1000.0 >= max(v["TSTOP"], MIN_STALL_WINDOW_MS) - _EPS:
                    ended = True
                if not ended and run.kind <= _RUN_VELOCITY and (v["HSG"] < 255 or v["LSG"] < 255):
                    if strain is None:
                        strain = self.plant.strain_gauges()
                    sg = int(strain[m - 1])
                    ended = (v["HSG"] < 255 and sg > v["HSG"]) or (v["LSG"] < 255 and sg < v["LSG"])
                goal = False
                if not ended and v["BS"] and run.kind <= _RUN_VELOCITY and m != SPREAD_MOTOR:
                    ended = self._plant_breakaway(m) not in (None, breakaway_at_start[m])
                if not ended and run.kind in _POSITION_RUNS:
                    ended = goal = (
                        channel.profile_done(t)
                        and abs(round(position) - run.target) <= v["MPE"]
                        and (v["HOLD"] or abs(self._velocities[m - 1]) <= GOAL_SETTLE_VELOCITY_CPS)
                    )
                if not ended:
                    continue
                if run.kind == _RUN_HI_SEEK:
                    if run.impacts_left > 0:
                        run.impacts_left -= 1
                        run.restart(_RUN_HI_BACKOFF, position + IHIT_BACKOFF_COUNTS, position, t)
                        self._start_move(channel, v, t, position, run.target)
                    else:
                        # the stop reads -IOFF from now on (§5.3.4 IOFF), then home to 0
                        self._origin[m - 1] += position + v["IOFF"]
                        if m != SPREAD_MOTOR:
                            self.plant.back_off_stop(m, v["IOFF"])
                        run.restart(_RUN_HI_HOME, 0.0, -float(v["IOFF"]), t)
                        self._start_move(channel, v, t, -float(v["IOFF"]), 0.0)
                    continue
                if run.kind == _RUN_HI_BACKOFF:
                    run.restart(_RUN_HI_SEEK, 0.0, position, t, -1.0)
                    channel.velocity(-v["IVEL"] / VELOCITY_SCALE, v["FPG"])
                    continue
                if run.kind == _RUN_HI_HOME:
                    # §5.2.1 HI: "After an HI, all motors are in their home position; at 0 encoder
                    # counts." The chip's 3.9 kHz loop settles there; ours, at the physics rate, can
                    # stop a count short (a finger lifting its own weight at 1 % duty): home is 0.
                    self._origin[m - 1] += position
                    position = 0.0
                    self._initialized[m] = True
                elif run.kind == _RUN_POSITION:
                    run.reached = abs(round(position) - run.target) <= v["MPE"]  # the HCTL counts whole counts
                    if not run.reached and word in POSITION_COMMANDS:
                        self._status[m] = int(Status.COULD_NOT_REACH_POSITION)
                # Case 3 (goal reached): HOLD 1 servos at the goal, the HCTL's commanded position.
                self._terminate(m, run.target if goal else position)
                runs.remove(run)
        if abort:
            for run in runs:
                self._terminate(run.motor, self._position(run.motor))
                self._status[run.motor] = int(Status.CTRL_C_ABORT)
            self._update_peak_temperature()
            self._reply(error=Status.CTRL_C_ABORT)
            return
        self._update_peak_temperature()
        error = 0
        if word in POSITION_COMMANDS and any(self._status[m] for m in motors):
            error = Status.COULD_NOT_REACH_POSITION
        self._reply(error=error)

    def _start_move(self, channel: MotorChannel, v: dict, t: float, start: float, target: float) -> None:
        speed = v["MCV"] if target >= start else v["MOV"]
        channel.move(t, start, target, speed / VELOCITY_SCALE, v["ACCEL"] / ACCEL_SCALE, v["FPG"])

    def _terminate(self, m: int, position: float) -> None:
        """§5.5: HOLD 1 servos at the termination position, HOLD 0 turns the motor off."""
        if self._motor_values[m]["HOLD"]:
            self._channels[m].hold(position, self._motor_values[m]["FPG"])
        else:
            self._channels[m].off()

    def _scan_for_ctrl_c(self) -> bool:
        """During a motion only ^C counts; other bytes are dropped. True if ^C arrived."""
        data = self._input
        index = data.find(_CTRL_C)
        if index < 0:
            data.clear()
            return False
        del data[: index + 1]
        return True

    @staticmethod
    def _on_profile(channel, t: float, position: float) -> bool:
        """A profile move still running with its motor keeping up: not stalled (§5.5 case 1 is an
        obstacle stopping the motion), however short TSTOP; at the start the profile has not yet
        moved STALL_DISTANCE_COUNTS. Once the profile has ended, a motor at rest stalls as usual,
        and so does one whose profile never moves (ACCEL 0): it ends TSTOP ms later."""
        return (not channel.profile_frozen and not channel.profile_done(t)
                and abs(channel.profile(t)[0] - position) <= STALL_DISTANCE_COUNTS)

    def _position(self, m: int) -> float:
        """The HCTL position of motor m in counts (float)."""
        return self._positions[m - 1] - self._origin[m - 1]

    # -- parameters (§5.2.2, §5.2.3)

    def _motor_value(self, m: int, name: str) -> int:
        if name == "P":
            return int(round(self._position(m)))
        if name == "S":
            return self._status[m]
        if name == "SG":
            return self._strain_gauge(m)
        if name == "OD":
            return int(self._odometer[m - 1] // 1000.0)
        if name == "BD":
            return int(self._breakaway_detected(m))
        if name == "BP":
            return self._breakaway_position(m)
        return self._motor_values[m][self._motor_table[name].stored_name]

    def _strain_gauge(self, m: int) -> int:
        sg = int(self.plant.strain_gauges()[m - 1])
        return 255 - sg if self._motor_values[m]["SGFLIP"] else sg

    def _global_value(self, name: str) -> int:
        if name == "TEMP":
            return self._temperature_tenths()
        if name == "PTEMP":
            return self._update_peak_temperature()
        if name == "UPSECS":
            return int(self._uptime_seconds())
        if name == "SN":
            return self._serial_number
        return self._globals[name]

    def _parse_assignments(self, table: dict, args) -> list[tuple[str, int]]:
        if not args or len(args) % 2:
            raise _FirmwareError(Status.INVALID_VALUE)
        error = 0
        pairs = []
        for name, text in zip(args[0::2], args[1::2]):
            parameter = table.get(name)
            if parameter is None:
                self._note_other_profile(name)
                error |= Status.UNKNOWN_PARAMETER
                continue
            if parameter.read_only:
                error |= Status.READ_ONLY
                continue
            try:
                value = self._integer(text)
            except _FirmwareError as bad:
                error |= bad.code
                continue
            if not parameter.accepts(value):
                error |= Status.INVALID_VALUE
                continue
            pairs.append((parameter.stored_name, value))
        if error:
            raise _FirmwareError(error)
        return pairs

    def _check_names(self, table: dict, names) -> None:
        unknown = [name for name in names if name not in table]
        for name in unknown:
            self._note_other_profile(name)
        if unknown:
            raise _FirmwareError(Status.UNKNOWN_PARAMETER)

    def _note_other_profile(self, name: str) -> None:
        profiles = _PARAMETER_PROFILES.get(name)
        if profiles and self.profile not in profiles and self.other_profile_hook is not None:
            self.other_profile_hook(name, profiles)

    def _cmd_FSET(self, motors, args):
        pairs = self._parse_assignments(self._motor_table, args)
        for m in motors:
            for name, value in pairs:
                self._motor_values[m][name] = value
        return []

    def _cmd_FGET(self, motors, args):
        self._check_names(self._motor_table, args)
        lines = []
        for name in args:
            values = [self._motor_value(m, name) for m in motors]
            if name == "P":
                for m, value in zip(motors, values):
                    self._reported_position[m] = value  # §6.2.3
            lines.append(" ".join(str(value) for value in values))
        return lines

    def _cmd_FLOAD(self, motors, args):
        self._no_arguments(args)
        stored = self.store.load().motors
        for m in motors:
            self._motor_values[m] = dict(stored[m])
        return []

    def _cmd_FSAVE(self, motors, args):
        self._no_arguments(args)
        self._save(motors=motors)
        return []

    def _cmd_FDEF(self, motors, args):
        self._no_arguments(args)
        for m in motors:
            self._motor_values[m] = default_motor_values(m, self.profile)
        return []

    def _cmd_FLIST(self, motors, args):
        self._no_arguments(args)
        return _describe(listed(self._motor_table, advanced=False))

    def _cmd_FLISTA(self, motors, args):
        self._no_arguments(args)
        return _describe(listed(self._motor_table, advanced=True))

    def _cmd_FLISTV(self, motors, args):
        self._no_arguments(args)
        return self._motor_value_lines(motors, advanced=False)

    def _cmd_FLISTAV(self, motors, args):
        self._no_arguments(args)
        return self._motor_value_lines(motors, advanced=True)

    def _motor_value_lines(self, motors, advanced: bool):
        return [
            " ".join([p.name] + [str(self._motor_value(m, p.name)) for m in motors])
            for p in listed(self._motor_table, advanced)
        ]

    def _cmd_PSET(self, motors, args):
        for name, value in self._parse_assignments(self._global_table, args):
            self._globals[name] = value
        return []

    def _cmd_PGET(self, motors, args):
        self._check_names(self._global_table, args)
        return [str(self._global_value(name)) for name in args]

    def _cmd_PLOAD(self, motors, args):
        self._no_arguments(args)
        self._globals = dict(self.store.load().globals)
        return []

    def _cmd_PSAVE(self, motors, args):
        self._no_arguments(args)
        self._save(global_values=True)
        return []

    def _cmd_PDEF(self, motors, args):
        self._no_arguments(args)
        self._globals = default_global_values(self.profile)
        return []

    def _cmd_PLIST(self, motors, args):
        self._no_arguments(args)
        return _describe(listed(self._global_table, advanced=False))

    def _cmd_PLISTA(self, motors, args):
        self._no_arguments(args)
        return _describe(listed(self._global_table, advanced=True))

    def _cmd_PLISTV(self, motors, args):
        self._no_arguments(args)
        return [f"{p.name} {self._global_value(p.name)}" for p in listed(self._global_table, advanced=False)]

    def _cmd_PLISTAV(self, motors, args):
        self._no_arguments(args)
        return [f"{p.name} {self._global_value(p.name)}" for p in listed(self._global_table, advanced=True)]

    # -- administrative (§5.2.4, §5.2.5)

    def _cmd_HELP(self, motors, args):
        if len(args) > 1:
            raise _FirmwareError(Status.TOO_MANY_ARGUMENTS)
        if args:
            entry = COMMANDS.get(args[0])
            if entry is None:
                raise _FirmwareError(Status.UNKNOWN_COMMAND)
            return [_help_line(args[0], entry[0])]
        return [_help_line(name, entry[0]) for name, entry in COMMANDS.items() if not entry[1]]

    def _cmd_HELP_ALL(self, motors, args):
        self._no_arguments(args)
        return [_help_line(name, entry[0]) for name, entry in COMMANDS.items()]

    def _cmd_RESET(self, motors, args):
        self._no_arguments(args)
        self._save()
        self._power_up()
        return [line.format(version=self.version) for line in BANNER_LINES]

    def _cmd_ERR(self, motors, args):
        if len(args) > 1:
            raise _FirmwareError(Status.TOO_MANY_ARGUMENTS)
        if not args:
            return [f"{code} {text}" for code, text in STATUS_DESCRIPTIONS.items()]
        code = self._integer(args[0])
        if code < 0:
            raise _FirmwareError(Status.INVALID_VALUE)
        return [f"{bit} {STATUS_DESCRIPTIONS.get(bit, '(unknown status bit)')}" for bit in _bits(code)]

    def _cmd_VERS(self, motors, args):
        self._no_arguments(args)
        return [self.version]

    # ------------------------------------------------------------------ RealTime (§6)

    def _enter_loop(self, layout: LoopLayout) -> None:
        self._loop_layout = layout
        values = self._motor_values
        self._loop_velocity = {m: 0.0 for m in layout.motors}
        self._loop_gain = {m: values[m]["FPG"] for m in layout.motors}
        for m in layout.motors:
            channel = self._channels[m]
            channel.set_sample(values[m]["SAMPLE"])
            if self.profile == "4.4" and layout.flags[m].LCT:
                channel.hold(self._position(m), values[m]["FPG"])  # datum 0: stay
            else:
                channel.velocity(0.0, self._loop_gain[m], loop=True)
            self._status[m] = 0
        self._loop_velocity_scale = {m: coefficient(values[m]["LCVC"]) / VELOCITY_SCALE for m in layout.motors}
        # Fixed while in LOOP (parameters change only in supervisory mode): looked up once, not per cycle.
        self._seconds_per_byte = seconds_per_byte(self.baud)
        self._feedback_plan = [
            (name, m, self._channels[m].period, values[m]["SGFLIP"], coefficient(values[m]["LFVC"]),
             coefficient(values[m]["LFDPC"])) if m is not None else (name, m, 0.0, 0, 1, 1)  # LFT: no motor
            for m, name in layout.feedback_fields
        ]
        self._output += b"*"
        if self.loop_entry_hook is not None:
            self.loop_entry_hook(self, layout)

    def _leave_loop(self) -> None:
        layout = self._loop_layout
        self._loop_layout = None
        for m in layout.motors:
            self._terminate(m, self._position(m))

    def _consume_loop_block(self) -> bool:
        """Start a cycle for a complete control block; False while a block is incomplete."""
        data = self._input
        header = data[0]
        if header == _CTRL_C:
            del data[0]
            self._leave_loop()
            self._output += LINE_END + PROMPT
            return True
        if header not in b"CcAa":
            del data[0]
            self._leave_loop()
            self._reply(error=Status.INVALID_REALTIME_HEADER)
            return True
        size = self._loop_layout.control_block_size(header)
        if len(data) < size:
            return False
        block = bytes(data[:size])
        del data[:size]
        self._start_task(self._cycle_task(block))
        return True

    def _cycle_task(self, block: bytes):
        """One RealTime cycle on the SPEC.md §6 time model."""
        if self.cycle_hook is not None:
            self.cycle_hook(self)
        layout = self._loop_layout
        header = block[0]
        seconds_per_byte = self._seconds_per_byte
        feedback_size = layout.feedback_size if header in HEADERS_WITH_FEEDBACK else 1
        yield self.time + len(block) * seconds_per_byte
        if len(block) > 1:
            self._apply_control(layout, layout.decode_control(block[1:]))
        yield self.time + self.processing_time
        if header in HEADERS_WITH_FEEDBACK:
            self._output += layout.encode_feedback(self._feedback_values())
        else:
            self._output += b"*"
        yield self.time + feedback_size * seconds_per_byte

    def _apply_control(self, layout: LoopLayout, values) -> None:
        velocity = self._loop_velocity
        gain = self._loop_gain
        torque = None
        for (m, name), value in zip(layout.control_fields, values):
            if name == "LCV":
                velocity[m] = value * self._loop_velocity_scale[m]
            elif name == "LCPG":
                gain[m] = value
            else:  # LCT (4.4)
                if torque is None:
                    torque = {}
                torque[m] = value
        for m in layout.motors:
            if torque is not None and m in torque:
                # SPEC.md §7: LCT is added to the present position; the sum is the commanded position
                self._channels[m].hold(self._position(m) + torque[m], self._motor_values[m]["FPG"])
            else:
                self._channels[m].velocity(velocity[m], gain[m], loop=True)

    def _feedback_values(self) -> list[int]:
        out = []
        append = out.append
        strain = None
        positions, origin, velocities = self._positions, self._origin, self._velocities
        lfdpd = self._globals["LFDPD"]
        for name, m, period, sgflip, lfvc, lfdpc in self._feedback_plan:
            if name == "LFAP":
                position = round(positions[m - 1] - origin[m - 1])
                append(0 if position < 0 else (65535 if position > 65535 else position))
            elif name == "LFS":
                if strain is None:
                    strain = self.plant.strain_gauges_list()
                sg = strain[m - 1]
                append(255 - sg if sgflip else sg)
            elif name == "LFV":
                per_sample = int(velocities[m - 1] * period)
                scaled = int(per_sample / lfvc)
                append(-128 if scaled < -128 else (127 if scaled > 127 else scaled))
            elif name == "LFDP":
                append(self._delta_position(m, lfdpc, lfdpd))
            elif name == "LFBP":
                append(self._breakaway_position(m))
            elif name == "LFAIN":
                append(0)
            else:  # LFT
                if self.profile == "4.4":
                    append(max(-128, min(127, int(round(self.plant.temperature)))))
                else:
                    append(self._temperature_tenths())
        self._update_peak_temperature()
        return out

    def _delta_position(self, m: int, scale: int, discard: int) -> int:
        """§6.2.3: (present − reported) / LFDPC clipped to a signed byte; reported follows."""
        present = int(round(self._position(m)))
        difference = present - self._reported_position[m]
        datum = int(difference / scale)
        datum = max(-128, min(127, datum))
        if discard:
            self._reported_position[m] = present
        else:
            self._reported_position[m] += datum * scale
        return datum

    # -- breakaway (SPEC.md §3.1), from the plant's public breakaway record

    def _plant_breakaway(self, m: int) -> float | None:
        """The plant's last breakaway of finger m in plant counts (None: none; the spread has none)."""
        if m == SPREAD_MOTOR:
            return None
        position = self.plant.breakaway_position(m)
        return None if position is None or isnan(position) else float(position)

    def _breakaway_detected(self, m: int) -> bool:
        """BD: the plant recorded a breakaway of finger m since its last O, TO or HI."""
        position = self._plant_breakaway(m)
        return position is not None and position != self._breakaway_cleared[m - 1]

    def _breakaway_position(self, m: int) -> int:
        """BP (and LFBP): the HCTL position of that breakaway, 0 when there is none."""
        if not self._breakaway_detected(m):
            return 0
        position = self._plant_breakaway(m) - self._origin[m - 1]
        return max(0, min(BREAKAWAY_POSITION_MAX, int(round(position))))


_HANDLER_NAMES = {"?": "HELP", "A?": "HELP_ALL"}
# Every parameter name -> the firmware profiles that have it (for other_profile_hook).
_PARAMETER_PROFILES = {p.name: p.profiles for p in MOTOR_TABLE + GLOBAL_TABLE}
# Attributes a snapshot does not copy: the plant, the store, hooks, the running task and constants.
_NOT_SNAPSHOT = frozenset(
    ("plant", "store", "cycle_hook", "loop_entry_hook", "other_profile_hook", "_task", "_motor_table", "_global_table",
     "_owns_plant", "_channel_list")
)
_SHARED_STATE = ("_loop_layout",)  # immutable after construction; shared, not copied


def _describe(parameters) -> list[str]:
    return [f"{p.name:<7}{p.description}" for p in parameters]


def _help_line(name: str, description: str) -> str:
    return f"{name:<9}{description}"


def _bits(code: int):
    bit = 1
    while bit <= code:
        if code & bit:
            yield bit
        bit <<= 1
