"""`Firmware` itself: construction, the public API (docs/architecture.md Contract 2), power-up, the
HCTL position and the breakaway record; the rest of the machine is its mixins (package docstring).

Choices where the documents are silent (SPEC.md §8):

- Power-up: a new `Firmware` behaves like the hand just after power-on: parameters from the store,
  motors uninitialised, and NO banner (a client opening the port expects nothing until it sends a
  CR). RESET prints "\\n\\r" + `BANNER_LINES` each ending "\\n\\r", then the prompt. Barrett's
  C++ API 4.4.3 (BHandSerialDriver::HandReset) searches the reply for "BarrettHand Firmware\\n"
  (LF directly after "Firmware"), so that text ends its own line.
- The HCTL position counter reads 0 at power-up wherever the motor is, as on the chip; HI moves
  the origin (§5.2.1 HI, §5.3.4 IOFF).
- Breakaway (SPEC.md §3.1): the plant's TorqueSwitch slip is the detection (BDAT is stored and
  listed but the simulated hand needs no acceleration threshold). BD is 1 once a finger broke away
  after its last O, TO or HI (those clear BD and BP as they start), BP is the HCTL position of that
  breakaway (0 when none, clipped to 0..20000). With BS 1 a finger's supervisory motion terminates
  (HOLD applies) as soon as the finger breaks away during it; LOOP is not affected.
"""
from __future__ import annotations

from math import exp, isnan

from bh8_gym.firmware.clock import SimulatedClock
from bh8_gym.firmware.counters import StoredCounters
from bh8_gym.firmware.motion import STALL_SMOOTHING_S, MotionTask
from bh8_gym.firmware.parser import LineParser
from bh8_gym.firmware.realtime import RealTimeLoop
from bh8_gym.firmware.snapshot import Snapshots
from bh8_gym.firmware.supervisory import VERSIONS, SupervisoryCommands
from bh8_gym.motion_control import MotorChannel
from bh8_gym.nvstore import NVStore
from bh8_gym.parameters import BREAKAWAY_POSITION_MAX, global_parameters, motor_parameters
from bh8_gym.plant import HandPlant
from bh8_gym.protocol import FIRMWARE_PROFILES, MOTORS, REALTIME_PROCESSING_S, SPREAD_MOTOR
from bh8_gym.realtime_codec import LoopLayout
from bh8_gym.status import Status

# Simulated seconds `transact` waits for a command to finish. A motion can run for ever (a finger
# jittering against an obstacle by more than STALL_DISTANCE_COUNTS never stalls, as on the hand);
# one that stalls ends within TSTOP (at most 65.5 s) of stalling, and a full close at the slowest
# MCV takes about 4.4 s, so only an HI with many IHIT impacts at a huge TSTOP takes longer.
TRANSACT_LIMIT_S = 300.0


class FirmwareBusyError(TimeoutError):
    """`transact` gave up waiting: the command was still running after its simulated-time limit."""


class Firmware(LineParser, SupervisoryCommands, MotionTask, RealTimeLoop, SimulatedClock, StoredCounters,
               Snapshots):
    """The hand's firmware as a byte-stream machine with its own simulated clock (Contract 2).

    The public API is here; each mixin holds one part of the machine (see the package docstring)."""

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

    # ------------------------------------------------------------------ power-up and hand state

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

    def _position(self, m: int) -> float:
        """The HCTL position of motor m in counts (float)."""
        return self._positions[m - 1] - self._origin[m - 1]

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
