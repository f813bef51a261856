"""The calibration excitation: the fixed program of motions `bh8 calibrate record` runs on a hand.

It is built to make the parameters the fit looks for show in the log, inside the safety envelope,
in motions whose outcome depends smoothly on them (the fit compares the log with replays):

1. set-up: factory parameters (FDEF), fingers holding their position (HOLD 1), HI, the LOOP flags
   (every motor, velocity and gain bytes out, strain and absolute position back);
2. with a calibration object on the palm, in LOOP (`SqueezeLaw`): six squeezes of it, at three
   motor duties twice (the gauges read the squeeze: their gain), each finger closing fast to
   SWEEP_HIGH, then at its squeeze's velocity and gain, and stopping if its gauge nears the
   envelope's limit. First, while the object stands where it was put: later the spread swings the
   lifted F1 and F2 over the palm's centre and pushes it off the palm (`CLEAR_SEGMENT`);
3. supervisory moves of the fingers and the spread at two velocities (their durations time the
   motors on a real hand);
4. in LOOP, with an object first one sweep that pushes it off the palm (`CLEAR_SEGMENT`, not
   compared: an object pushed about makes the spread's replay jump), then
   - sweeps (`SweepLaw`): the fingers lifted against their weight at one weak LOOP velocity and
     gain per segment, then brought back stiffly; the spread driven out and back at its own
     velocity and gain. How fast a weak drive lifts a finger tells the drive's strength; how fast
     the spread goes at low gains tells its drive against its friction. Every motor comes to rest
     between phases;
5. fingers back open (M), then `bh8 calibrate record` leaves the hand as it found it.

Each LOOP starts with the clock probe: one block, the host waits `PROBE_WAIT_S`, one more: a real
hand's finger ran on meanwhile, a simulated hand's clock stood still (log_format: "clock").

Every LOOP byte stays in the envelope (|LCV| <= SafetyEnvelope.max_velocity with LCVC 1); the
fingers' sweeps stay between SWEEP_LOW and SWEEP_HIGH, clear of a calibration object resting on
the palm. Segments are counted in cycles (their commands do not depend on the host's speed); a
sweep turns on the positions it reads, so it is the same program on any hand. `scale` stretches
every segment (1.0: about two minutes on a hand at 38,400 baud; the tests run less).
"""
from __future__ import annotations

from dataclasses import dataclass

from bh8_gym.protocol import FINGER_MOTORS, SPREAD_MOTOR

EXCITATION_NAME = "bh8-excitation"
# 2: the squeezes before the moves and sweeps; 3: six squeezes, each finger switched to the squeeze's
# velocity and gain where it moves freely, not when it touches (`SqueezeLaw`)
EXCITATION_VERSION = 3
STEADY_SQUEEZES_SINCE = 3  # the first version whose squeezes a replay can follow (`SqueezeLaw`)
BAUD = 38400  # RealTime cycles of about 7 ms (SPEC.md §6), the environments' rate
LOOP_MOTORS = "1234"
# The LOOP's flags on every motor (FSET before LOOP): velocity and gain bytes out; strain and
# absolute position back (LFV is too coarse at LFVC 1, LFDP adds nothing to LFAP).
LOOP_FLAGS = {"LCV": 1, "LCVC": 1, "LCPG": 1, "LFV": 0, "LFS": 1, "LFAP": 1, "LFDP": 0, "LFDPC": 1}
PROBE_WAIT_S = 0.25
PROBE_VELOCITY = 10  # LCV: 2,441 counts/s, 610 counts in PROBE_WAIT_S on a hand whose clock runs
PROBE_THRESHOLD_COUNTS = 150  # a clock that stood still moves one cycle's worth (about 16 counts)
# LCV of a motor that is to stay (nearly) where it is in LOOP: 1/16 count per sample, not 0. A
# finger told LCV 0 is unpowered and its worm holds it; the simulated hand's link then sags within
# the worm's hold and its encoder jumps when it is driven again (docs/modelling.md), so the
# excitation keeps every motor driven until it leaves LOOP.
CREEP_VELOCITY = 1
SWEEP_LOW, SWEEP_HIGH = 600, 6000  # finger counts: 1,800 counts short of where F3 meets the can (7,800)
SPREAD_LOW, SPREAD_HIGH = 600, 2550  # counts: 600 short of its stops (0, 3150), which an overshoot must not meet
SQUEEZE_VELOCITY = 16  # LCV: 1 count per sample; the duty is LCPG/4 x 1 of 127
SQUEEZE_GAINS = (48, 100, 160)  # LCPG: duties of about 10, 20 and 30 %
# LCV closing on the calibration object up to SWEEP_HIGH (clear of it), stiffly: below a breakaway's speed (§8: MCV 40)
APPROACH_VELOCITY = 24
SQUEEZE_STRAIN_BACK_OFF = 200  # a finger whose gauge reads more stops (the envelope stops at 230)
OPEN_POSITION = 500
SUPERVISORY_VELOCITIES = (40, 100)  # MCV/MOV: up to the default, as the envelope's LCV 100 is


# A finger's sweep lifts it against its weight at the segment's (slow, weak) velocity and gain, and
# brings it back at RETURN_VELOCITY with RETURN_GAIN: a motor its load helps along runs at the speed
# it is told when it is stiff, so its speed tells nothing about its strength then, while a weak one
# lurches (the simulated hand's overrun brake, docs/modelling.md). Against its weight, the speed a
# weak drive reaches tells its strength, smoothly.
RETURN_VELOCITY, RETURN_GAIN = 60, 150
# Cycles every motor creeps (CREEP_VELOCITY, stiff) between phases: the motors come to rest before
# they are driven the other way (turned at once, the simulated finger's two joints may each take the
# other for held back and open at half the speed told, or not, by a hair's breadth: the 3:1
# coupling, docs/modelling.md), and the replay sets the simulated motors to the recorded positions
# there, at rest (replay.py: anchors).
REST_CYCLES = 20
# With a calibration object: a sweep before the others, not compared (residuals.py), whose spread
# swings the lifting F1 and F2 over the palm and pushes the object off it (the moves only nudge it):
# pushed about, a different way in every replay, it made the spread's replay jump by hundreds of
# counts from a billionth of a change.
CLEAR_SEGMENT = "clear"
PHASE_LIMIT_CYCLES = 400  # the longest a phase waits for a motor to reach its end
# The phases a segment record names after its part ("sweep3.lift"): replay.py sets the simulated
# motors to the recorded positions where a lift or return starts, residuals.py compares by phase.
PHASE_LIFT, PHASE_RETURN, PHASE_HOLD = "lift", "return", "hold"
REST_PHASES = ("rest-lift", "rest-return")
CONTACT_STRAIN = 4  # counts above the approach's first reading: the finger touches the object
CONTACT_STALL_COUNTS = 10  # or it moved less than this in two cycles (its inner link met the object)
APPROACH_LIMIT = 14_000  # a finger that got this far without touching the object missed it, and stops


@dataclass(frozen=True)
class Sweep:
    """A LOOP segment: lift, rest, return, rest, ... (module docstring)."""

    name: str
    finger: tuple[int, int]  # (LCV, LCPG) of every finger while it lifts against its weight
    spread: tuple[int, int]  # (LCV, LCPG) of the spread, both ways
    cycles: int


@dataclass(frozen=True)
class Squeeze:
    """A LOOP segment: the fingers approach the calibration object, squeeze it at SQUEEZE_VELOCITY
    with `gain` for `cycles`, then open back to SWEEP_LOW."""

    name: str
    gain: int
    cycles: int


@dataclass(frozen=True)
class Commands:
    """Supervisory lines, one after the other (each answered when its motion ends)."""

    name: str
    lines: tuple[str, ...]


def _cycles(count: int, scale: float) -> int:
    return max(60, int(round(count * scale)))


def excitation_program(scale: float = 1.0, calibration_object: str | None = None) -> list:
    """The excitation's parts in order: Commands, and the LOOP parts (Squeezes, Sweeps) between them."""
    if not 0.01 <= scale <= 100.0:
        raise ValueError(f"scale must be 0.01..100, got {scale!r}")
    moves = []
    for velocity in SUPERVISORY_VELOCITIES:
        moves += [f"1234FSET MCV {velocity} MOV {velocity}", f"123M {SWEEP_HIGH}", "123FGET P", f"4M {SPREAD_HIGH}",
                  "4FGET P", f"123M {SWEEP_LOW}", "123FGET P", f"4M {SPREAD_LOW}", "4FGET P"]
    flags = " ".join(f"{name} {value}" for name, value in LOOP_FLAGS.items())
    program = [Commands("setup", ("1234FDEF", "123FSET HOLD 1", "PSET LFT 0 LFDPD 0", "1234HI", f"1234FSET {flags}"))]
    # The squeezes first, in a LOOP of their own, while the calibration object stands where the lab
    # put it (the spread past about 1,000 counts swings F1 and F2 over it); CLEAR_SEGMENT then
    # pushes it off the palm before the compared sweeps.
    if calibration_object is not None:
        # Twice over: where a fingertip lands on the object scatters each squeeze's load, and the
        # fit reads the gain's uncertainty off how the squeezes disagree (residuals.py).
        for index, gain in enumerate(SQUEEZE_GAINS * 2):
            program.append(Squeeze(f"squeeze{index + 1}", gain, _cycles(150, scale)))
    program.append(Commands("moves", tuple(moves)))
    if calibration_object is not None:
        program.append(Sweep(CLEAR_SEGMENT, (60, 40), (40, 150), _cycles(400, scale)))
    # Finger (LCV, LCPG) while lifting, spread (LCV, LCPG), run together: the fingers' weight and
    # the spread's friction are told apart by their own motors. Weak finger gains (the weight tells
    # the drive's strength) and spread gains from where it barely overcomes its friction up.
    sweeps = [
        ((40, 8), (20, 40)), ((40, 12), (20, 80)), ((40, 16), (40, 60)), ((80, 12), (40, 150)),
        ((80, 24), (40, 100)), ((24, 6), (20, 30)), ((24, 10), (30, 40)), ((60, 40), (30, 200)),
    ]
    for index, (finger, spread) in enumerate(sweeps):
        program.append(Sweep(f"sweep{index + 1}", finger, spread, _cycles(900, scale)))
    program.append(Commands("finish", ("1234FGET P", f"123M {OPEN_POSITION}", f"4M {SPREAD_LOW}", "1234FGET P")))
    return program


def _ends(motor: int) -> tuple[int, int]:
    return (SPREAD_LOW, SPREAD_HIGH) if motor == SPREAD_MOTOR else (SWEEP_LOW, SWEEP_HIGH)


class SweepLaw:
    """A Sweep's phases and blocks. "lift": the fingers go up against their weight (closing palm-up,
    opening palm-down; between SWEEP_LOW and SWEEP_HIGH the inner links stay below 90°); "return":
    back, stiffly; a "rest" after each. A finger that reached its end creeps there until the phase
    ends (every finger there, or PHASE_LIMIT_CYCLES). The spread goes to one end in one lift or
    return, creeps there until the next, then goes back; it rests with the fingers (where the replay
    sets the motors to the recorded positions). Deterministic from the positions read: the same
    program on any hand."""

    def __init__(self, sweep: Sweep, positions: dict[int, int], mounting: str):
        self.sweep = sweep
        self.lifting = 1 if mounting == "palm-up" else -1  # the direction that lifts a finger
        low, high = _ends(SPREAD_MOTOR)
        self.spread_direction = 1 if positions[SPREAD_MOTOR] < (low + high) / 2 else -1
        self.spread_waits = False  # at its end: it creeps until the next lift or return
        # A sweep starts at rest, whatever the part before it was doing (a phase the last sweep's
        # cycles cut short): its first lift starts, like every other, with the motors still.
        self.phase, self.left = "rest-return", REST_CYCLES
        self.phase_started, self._starting = False, True

    def _finger_direction(self) -> int:
        return self.lifting if self.phase in ("lift", "rest-lift") else -self.lifting

    def _arrived(self, position: int) -> bool:
        return position >= SWEEP_HIGH if self._finger_direction() > 0 else position <= SWEEP_LOW

    def control(self, positions: dict[int, int]) -> tuple[list[int], list[int]]:
        """(velocities, gains) of motors 1-4 for the next block, from the positions just read;
        `phase_started` tells whether this block starts a new phase (`phase` names it)."""
        self.phase_started, self._starting = self._starting, False
        self.left -= 1
        if self.phase in ("lift", "return"):
            if self.left <= 0 or all(self._arrived(positions[m]) for m in FINGER_MOTORS):
                self.phase, self.left = f"rest-{self.phase}", REST_CYCLES
                self.phase_started = True
        elif self.left <= 0:
            self.phase = "return" if self.phase == "rest-lift" else "lift"
            self.left = PHASE_LIMIT_CYCLES
            self.phase_started = True
        velocities, gains = [], []
        for motor in FINGER_MOTORS:
            direction = self._finger_direction()
            if self.phase.startswith("rest") or self._arrived(positions[motor]):
                # creeping on the way the next phase goes: no turn at its start
                direction = -direction
                velocity, gain = CREEP_VELOCITY, RETURN_GAIN
            elif self.phase == "lift":
                velocity, gain = self.sweep.finger
            else:
                velocity, gain = RETURN_VELOCITY, RETURN_GAIN
            velocities.append(direction * velocity)
            gains.append(gain)
        # The spread goes towards its end in the direction it is going, then creeps (turned) until
        # the next lift or return; it rests with the fingers.
        low, high = _ends(SPREAD_MOTOR)
        turn = -1 if positions[SPREAD_MOTOR] >= high else (1 if positions[SPREAD_MOTOR] <= low else 0)
        if turn and turn != self.spread_direction:
            self.spread_direction = turn
            self.spread_waits = True
        if self.phase_started and self.phase in ("lift", "return"):
            self.spread_waits = False
        if self.spread_waits or self.phase.startswith("rest"):
            return velocities + [self.spread_direction * CREEP_VELOCITY], gains + [RETURN_GAIN]
        velocity, gain = self.sweep.spread
        return velocities + [self.spread_direction * velocity], gains + [gain]


class SqueezeLaw:
    """A Squeeze's phases: "approach" (every finger closes at APPROACH_VELOCITY, stiffly, up to
    SWEEP_HIGH, clear of the object, then at SQUEEZE_VELOCITY with the segment's gain until its
    gauge reads CONTACT_STRAIN above its first reading or it stalls; one whose gauge passes
    SQUEEZE_STRAIN_BACK_OFF stops), "hold" (the squeeze's cycles once every finger touched, or
    PHASE_LIMIT_CYCLES), "release" (open to SWEEP_LOW); the spread creeps.

    A finger's command changes where it moves freely, not when it touches (excitation 2 closed
    fast and stiffly until then): the replay sends the recorded blocks, so a switch made at the
    recorded finger's touch comes early or late for a replayed finger that lands a little
    differently, and the stiff approach then pressed it in harder. The replays' loads came out up
    to 25 % above the recorded hand's and the gain that much low (issue 40: seed 7)."""

    def __init__(self, squeeze: Squeeze, strains: dict[int, int]):
        self.squeeze = squeeze
        self.first = dict(strains)
        self.touched: set[int] = set()
        self.stopped: set[int] = set()
        self.phase, self.left = "approach", PHASE_LIMIT_CYCLES
        self.phase_started, self._starting = False, True
        self.finished = False
        self.history: list[dict[int, int]] = []

    def control(self, positions: dict[int, int], strains: dict[int, int]) -> tuple[list[int], list[int]]:
        self.phase_started, self._starting = self._starting, False
        self.left -= 1
        self.history = [*self.history[-2:], dict(positions)]
        for motor in FINGER_MOTORS:
            # Touching: past the sweeps (the object lies beyond them) and either the gauge reads the
            # push, or the finger stalled for three cycles (its inner link met the object).
            stalled = len(self.history) == 3 and self.history[-1][motor] - self.history[0][motor] < CONTACT_STALL_COUNTS
            if positions[motor] > SWEEP_HIGH and (strains[motor] - self.first[motor] >= CONTACT_STRAIN or stalled):
                self.touched.add(motor)
            if strains[motor] > SQUEEZE_STRAIN_BACK_OFF or positions[motor] >= APPROACH_LIMIT:
                self.stopped.add(motor)
        if self.phase == "approach" and (len(self.touched) == 3 or self.left <= 0):
            self.phase, self.left, self.phase_started = "hold", self.squeeze.cycles, True
        elif self.phase == "hold" and self.left <= 0:
            self.phase, self.left, self.phase_started = "release", PHASE_LIMIT_CYCLES, True
        elif self.phase == "release" and (self.left <= 0 or all(positions[m] <= SWEEP_LOW for m in FINGER_MOTORS)):
            self.finished = True
        velocities, gains = [], []
        for motor in FINGER_MOTORS:
            if self.phase == "release":
                opening = positions[motor] > SWEEP_LOW
                velocities.append(-RETURN_VELOCITY if opening else -CREEP_VELOCITY)
                gains.append(RETURN_GAIN)
            elif motor in self.stopped:
                velocities.append(0)
                gains.append(self.squeeze.gain)
            elif positions[motor] >= SWEEP_HIGH or motor in self.touched:
                velocities.append(SQUEEZE_VELOCITY)
                gains.append(self.squeeze.gain)
            else:
                velocities.append(APPROACH_VELOCITY)
                gains.append(RETURN_GAIN)
        return velocities + [CREEP_VELOCITY], gains + [RETURN_GAIN]
