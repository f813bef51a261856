"""The calibration excitation: the fixed program of motions `bh8 calibrate record` runs on a hand.

It is built to make the parameters the fit looks for show in the log, inside the safety envelope:

1. set-up: factory parameters (FDEF), then HI;
2. supervisory moves of the fingers and the spread at three velocities (their durations time the
   motors on a real hand);
3. in LOOP (every motor, velocity and gain bytes out, strain and absolute position back):
   - the clock probe: one block, the host waits `PROBE_WAIT_S`, one more: a real hand's finger
     ran on meanwhile, a simulated hand's clock stood still (log_format: "clock");
   - sweeps: each finger and the spread driven back and forth between two positions at one LOOP
     velocity and gain per segment. At low gains the motor's torque barely lifts a finger against
     its weight, so how fast it goes tells the drive's strength; the spread's speed at low gains
     tells its drive against its friction;
   - with a calibration object on the palm: squeezes of it at three motor duties (the gauges read
     the squeeze: their gain), each finger backing off if its gauge nears the envelope's limit;
4. fingers back open (GM), then `bh8 calibrate record` leaves the hand as it found it.

Every LOOP byte stays in the envelope (|LCV| <= SafetyEnvelope.max_velocity with LCVC 1); the
fingers' sweeps stay between SWEEP_LOW and SWEEP_HIGH, clear of a calibration object resting on
the palm. Segments are counted in cycles (their commands do not depend on the host's speed); a
sweep reverses on the position it reads, so it is the same program on any hand. `scale` stretches
every segment (1.0: about two minutes on a hand at 38,400 baud; the tests run 0.1).
"""
from __future__ import annotations

from dataclasses import dataclass

from bh8_gym.protocol import FINGER_MOTORS, SPREAD_MOTOR

EXCITATION_NAME = "bh8-excitation"
EXCITATION_VERSION = 1
BAUD = 38400  # RealTime cycles of about 7 ms (SPEC.md §6), the environments' rate
LOOP_MOTORS = "1234"
# The LOOP's flags on every motor (FSET before LOOP): velocity and gain bytes out; strain and
# absolute position back (LFV is too coarse at LFVC 1, LFDP adds nothing to LFAP).
LOOP_FLAGS = {"LCV": 1, "LCVC": 1, "LCPG": 1, "LFV": 0, "LFS": 1, "LFAP": 1, "LFDP": 0, "LFDPC": 1}
PROBE_WAIT_S = 0.25
PROBE_VELOCITY = 10  # LCV: 2,441 counts/s, 610 counts in PROBE_WAIT_S on a hand whose clock runs
PROBE_THRESHOLD_COUNTS = 150  # a clock that stood still moves one cycle's worth (about 16 counts)
SWEEP_LOW, SWEEP_HIGH = 600, 7000  # finger counts: clear of a calibration object on the palm
SPREAD_LOW, SPREAD_HIGH = 300, 2800
SQUEEZE_VELOCITY = 16  # LCV: 1 count per sample; the duty is LCPG/4 x 1 of 127
SQUEEZE_STRAIN_BACK_OFF = 200  # a finger whose gauge reads more stops (the envelope stops at 230)
OPEN_POSITION = 500
SUPERVISORY_VELOCITIES = (30, 60, 100)  # MCV/MOV: up to the default, as the envelope's LCV 100 is


@dataclass(frozen=True)
class Sweep:
    """A LOOP segment: fingers and spread each driven back and forth at (LCV, LCPG)."""

    name: str
    finger: tuple[int, int]  # (LCV, LCPG) of every finger; LCV 0: the fingers stay
    spread: tuple[int, int]
    cycles: int


@dataclass(frozen=True)
class Squeeze:
    """A LOOP segment: the fingers close on the calibration object at SQUEEZE_VELOCITY with `gain`,
    then open back to SWEEP_LOW at the same gain."""

    name: str
    gain: int
    cycles: int


@dataclass(frozen=True)
class Commands:
    """Supervisory lines, one after the other (each answered when its motion ends)."""

    name: str
    lines: tuple[str, ...]


def _cycles(count: int, scale: float) -> int:
    return max(20, int(round(count * scale)))


def excitation_program(scale: float = 1.0, calibration_object: str | None = None) -> list:
    """The excitation's parts in order: Commands before and after one LOOP of Sweeps and Squeezes."""
    if not 0.01 <= scale <= 100.0:
        raise ValueError(f"scale must be 0.01..100, got {scale!r}")
    moves = []
    for velocity in SUPERVISORY_VELOCITIES:
        moves += [f"1234FSET MCV {velocity} MOV {velocity}", f"123M {SWEEP_HIGH}", "123FGET P", f"123M {SWEEP_LOW}",
                  "123FGET P", f"4M {SPREAD_HIGH}", "4FGET P", f"4M {SPREAD_LOW}", "4FGET P"]
    flags = " ".join(f"{name} {value}" for name, value in LOOP_FLAGS.items())
    program = [
        Commands("setup", ("1234FDEF", "PSET LFT 0 LFDPD 0", "1234HI")),
        Commands("moves", (*moves, f"1234FSET {flags}")),
    ]
    # Finger (LCV, LCPG) against spread (LCV, LCPG), run together: the fingers' weight and the
    # spread's friction are told apart by their own motors. Low finger gains first (the weight
    # dominates), then stiffer ones (the speed follows the command: the drive's limits show less).
    sweeps = [
        ((40, 4), (20, 40)), ((40, 8), (20, 80)), ((40, 16), (40, 60)), ((80, 8), (40, 150)),
        ((80, 24), (60, 100)), ((20, 4), (20, 30)), ((20, 12), (60, 40)), ((60, 48), (30, 200)),
    ]
    for index, (finger, spread) in enumerate(sweeps):
        program.append(Sweep(f"sweep{index + 1}", finger, spread, _cycles(900, scale)))
    if calibration_object is not None:
        for index, gain in enumerate((48, 100, 160)):
            program.append(Squeeze(f"squeeze{index + 1}", gain, _cycles(300, scale)))
    program.append(Commands("finish", ("1234FGET P", f"123M {OPEN_POSITION}", f"4M {SPREAD_LOW}", "1234FGET P")))
    return program


class SweepLaw:
    """Which way each motor goes in a Sweep: up to its high position, then down to its low one.

    Deterministic from the positions read, so the same program runs on any hand."""

    def __init__(self, sweep: Sweep, positions: dict[int, int]):
        self.sweep = sweep
        self.direction = {}
        for motor, position in positions.items():
            low, high = (SPREAD_LOW, SPREAD_HIGH) if motor == SPREAD_MOTOR else (SWEEP_LOW, SWEEP_HIGH)
            self.direction[motor] = 1 if position < (low + high) / 2 else -1

    def control(self, positions: dict[int, int]) -> tuple[list[int], list[int]]:
        """(velocities, gains) of motors 1-4 for the next block, from the positions just read."""
        velocities, gains = [], []
        for motor in (*FINGER_MOTORS, SPREAD_MOTOR):
            spread = motor == SPREAD_MOTOR
            velocity, gain = self.sweep.spread if spread else self.sweep.finger
            low, high = (SPREAD_LOW, SPREAD_HIGH) if spread else (SWEEP_LOW, SWEEP_HIGH)
            position = positions[motor]
            if position >= high:
                self.direction[motor] = -1
            elif position <= low:
                self.direction[motor] = 1
            velocities.append(self.direction[motor] * velocity)
            gains.append(gain)
        return velocities, gains


class SqueezeLaw:
    """A Squeeze: every finger closes at SQUEEZE_VELOCITY until half the segment is over (a finger
    whose gauge reads more than SQUEEZE_STRAIN_BACK_OFF stops where it is), then opens back to
    SWEEP_LOW; the spread holds."""

    def __init__(self, squeeze: Squeeze):
        self.squeeze = squeeze
        self.stopped: set[int] = set()
        self.cycle = 0

    def control(self, positions: dict[int, int], strains: dict[int, int]) -> tuple[list[int], list[int]]:
        closing = self.cycle < self.squeeze.cycles // 2
        self.cycle += 1
        velocities = []
        for motor in FINGER_MOTORS:
            if strains[motor] > SQUEEZE_STRAIN_BACK_OFF:
                self.stopped.add(motor)
            if closing:
                velocities.append(0 if motor in self.stopped else SQUEEZE_VELOCITY)
            else:
                velocities.append(-SQUEEZE_VELOCITY * 2 if positions[motor] > SWEEP_LOW else 0)
        gains = [self.squeeze.gain] * 3
        return velocities + [0], gains + [100]
