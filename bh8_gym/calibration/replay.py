"""Replaying a calibration log in the simulator: the log's commands and blocks sent to a simulated
hand with given PlantParameters, and what it answers set beside what the recorded hand answered.

`observed(log)` takes the recorded hand's signals out of the log once; `replay(log, hand)` runs the
simulator and returns the same signals (`Signals`): the LOOP feedback's absolute positions and
strains per block, the positions FGET P answered, and the durations of the motion commands.

Time. The simulated hand runs each command's motion and each RealTime cycle on its own clock
(SPEC.md §6: bytes at BAUD and the processing time). What the recorded hand did between the
host's blocks depends on its clock (the log's clock record): a real hand's motors ran on while the
host prepared the next block ("wall": the replay lets the simulated hand run for the time between
the logged blocks beyond what their bytes and processing took); a simulated hand's clock stood
still ("line": nothing is added).

A log whose non-motion commands (parameters, FDEF, ...) do not get the replies they got on the
recorded hand was not recorded by this excitation on a BH8 (or was edited): `ReplayMismatch`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bh8_gym.calibration.excitation import PHASE_LIFT, PHASE_RETURN
from bh8_gym.calibration.log_format import CalibrationLog, command_word, is_motion
from bh8_gym.calibration.scene import replay_plant
from bh8_gym.protocol import BITS_PER_BYTE, FINGER_MOTORS, LINE_END, PROMPT, SPREAD_MOTOR
from bh8_gym.realtime_codec import LoopLayout, MotorFlags

COMMAND_LIMIT_S = 60.0
# Phases of the excitation (excitation.py) that start with every motor at rest: the replay sets the
# simulated motors to the recorded hand's positions there, so what went differently before (a
# finger its weight helped down, which the simulated hand does not repeat to the count) does not
# carry over: each phase is predicted from where the recorded one started.
ANCHOR_PHASES = (f".{PHASE_LIFT}", f".{PHASE_RETURN}")
ANCHORED_MOTORS = (*FINGER_MOTORS, SPREAD_MOTOR)  # simulated seconds a replayed motion may run (the excitation's take under 2 s)


class ReplayMismatch(ValueError):
    """The simulated hand does not answer the log's commands as the recorded hand did."""


@dataclass
class Signals:
    """A hand's signals over one log (the recorded hand's, or a replay's)."""

    positions: np.ndarray  # (blocks, LOOP motors): LFAP, counts
    strains: np.ndarray  # (blocks, fingers): LFS, counts (NaN: the block had none)
    queried: np.ndarray  # positions FGET P answered, in order, counts
    queried_motors: np.ndarray  # the motor of each
    durations: np.ndarray  # seconds each motion command took
    motors: tuple  # the LOOP motors, the columns of `positions`
    segments: list = field(default_factory=list)  # the excitation part of each block
    times: np.ndarray | None = None  # the simulated hand's clock at each block, seconds
    errors: list = field(default_factory=list)  # (command, recorded ERR, replayed ERR) that differ


def _split_reply(line: str, reply: bytes) -> list[str]:
    """The output lines of a supervisory reply (echo and prompt stripped), as the client gives them."""
    body = reply
    echo = line.encode("ascii")
    if body.startswith(echo):
        body = body[len(echo):]
    if body.endswith(PROMPT):
        body = body[: -len(PROMPT)]
    text = body.decode("latin-1").replace("\r", "")
    return [item for item in text.split("\n") if item.strip()]


def _error_of(lines: list[str]) -> int | None:
    for item in lines:
        words = item.split()
        if len(words) == 2 and words[0] == "ERR" and words[1].isdigit():
            return int(words[1])
    return None


def _layout_of(record: dict) -> LoopLayout:
    layout = record["layout"]
    flags = {m: MotorFlags(**layout["flags"][str(m)]) for m in layout["motors"]}
    return LoopLayout(layout["motors"], flags, lft=layout["lft"], firmware=layout["firmware"])


def _collect(layout: LoopLayout, feedback: bytes, positions: list, strains: list) -> None:
    values = layout.feedback_by_motor(layout.decode_feedback(feedback))
    positions.append([values[m].get("LFAP", np.nan) for m in layout.motors])
    strains.append([values[m].get("LFS", np.nan) if m in values else np.nan for m in FINGER_MOTORS])


def _queried(line: str, lines: list[str], values: list, motors: list) -> None:
    """FGET P answers: one value per motor of the prefix."""
    words = line.upper().split()
    if len(words) != 2 or not words[0].endswith("FGET") or words[1] != "P" or len(lines) != 1:
        return
    prefix = words[0][: -len("FGET")]
    selected = [int(c) for c in prefix if c in "1234"]
    try:
        numbers = [int(v) for v in lines[0].split()]
    except ValueError:
        return
    if len(numbers) == len(selected):
        values.extend(numbers)
        motors.extend(selected)


def observed(log: CalibrationLog) -> Signals:
    """The recorded hand's signals (what the replays are compared with)."""
    positions, strains, queried, queried_motors, durations, segments = [], [], [], [], [], []
    layout, motors, segment = None, (), ""
    for record in log.records:
        kind = record["kind"]
        if kind == "segment":
            segment = record["name"]
        elif kind == "loop":
            layout = _layout_of(record)
            motors = layout.motors
        elif kind == "block":
            _collect(layout, bytes.fromhex(record["feedback"]), positions, strains)
            segments.append(segment)
        elif kind == "command":
            _queried(record["line"], record["reply"], queried, queried_motors)
            if is_motion(record["line"]):
                durations.append(record["dt"])
    return Signals(np.array(positions, dtype=float).reshape(-1, len(motors)),
                   np.array(strains, dtype=float).reshape(-1, 3), np.array(queried, dtype=float),
                   np.array(queried_motors, dtype=int), np.array(durations, dtype=float), motors, segments)


def replay(log: CalibrationLog, hand: dict, hand_clock: str | None = None, anchored: bool = True) -> Signals:
    """The simulated hand with PlantParameters fields `hand` driven by the log's commands and
    blocks (module docstring). `hand_clock` overrides the log's clock record; `anchored`: set the
    simulated motors to the recorded positions where a sweep's phase starts (module docstring)."""
    from bh8_gym.firmware import Firmware

    clock = hand_clock or log.hand_clock or "line"
    header = log.header
    plant = replay_plant(header.mounting, header.calibration_object, hand)
    try:
        firmware = Firmware(plant=plant, store_dir=None, profile=header.profile, seed=0)
        return _Replayer(firmware, clock, anchored).run(log)
    finally:
        plant.close()


def anchor_plant(plant, motor_counts, motor_velocities) -> None:
    """Set the plant's joints so that its four motors read `motor_counts` (plant counts) and turn at
    `motor_velocities` (counts/s), each finger engaged (3:1)."""
    from bh8_gym.plant.joints import INNER_COUNTS_PER_RAD, SPREAD_COUNTS_PER_RAD

    angles, velocities = [], []
    spread_angle = float(motor_counts[3]) / SPREAD_COUNTS_PER_RAD
    spread_speed = float(motor_velocities[3]) / SPREAD_COUNTS_PER_RAD
    for finger in range(3):
        inner = float(motor_counts[finger]) / INNER_COUNTS_PER_RAD
        speed = float(motor_velocities[finger]) / INNER_COUNTS_PER_RAD
        if finger < 2:  # F1 and F2 turn about the spread
            angles.append(spread_angle)
            velocities.append(spread_speed)
        angles += [inner, inner / 3.0]
        velocities += [speed, speed / 3.0]
    plant.set_joint_angles(angles, velocities)


class _Replayer:
    def __init__(self, firmware, clock: str, anchored: bool):
        self.firmware = firmware
        self.wall = clock == "wall"
        self.anchored = anchored
        self.last_recorded = None  # the recorded hand's LFAP of the last block
        self.before_recorded = None  # and of the block before it
        self.positions, self.strains, self.times = [], [], []
        self.queried, self.queried_motors, self.durations, self.errors = [], [], [], []
        self.layout = None
        self.previous_block = None  # (t, bytes) of the last block, for the wall clock's gaps

    def run(self, log: CalibrationLog) -> Signals:
        for number, record in enumerate(log.records, start=2):
            handler = getattr(self, "_" + record["kind"], None)
            if handler is not None:
                handler(record, number)
        motors = self.layout.motors if self.layout is not None else ()
        if not motors:  # the log never entered LOOP: take the LOOP motors from its records
            motors = next((tuple(r["layout"]["motors"]) for r in log.records if r["kind"] == "loop"), ())
        return Signals(np.array(self.positions, dtype=float).reshape(-1, len(motors)),
                       np.array(self.strains, dtype=float).reshape(-1, 3), np.array(self.queried, dtype=float),
                       np.array(self.queried_motors, dtype=int), np.array(self.durations, dtype=float), motors,
                       times=np.array(self.times, dtype=float), errors=self.errors)

    def _transact(self, data: bytes, what: str, number: int) -> bytes:
        firmware = self.firmware
        firmware.write(data)
        if not firmware.run_until_idle(COMMAND_LIMIT_S):
            raise ReplayMismatch(f"line {number}: {what} was still running in the simulator after "
                                 f"{COMMAND_LIMIT_S:g} s; it ended on the recorded hand")
        return firmware.read()

    def _command(self, record: dict, number: int) -> None:
        line = record["line"]
        start = self.firmware.time
        lines = _split_reply(line, self._transact(line.encode("ascii") + b"\r", repr(line), number))
        recorded, replayed = record["error"], _error_of(lines)
        word = command_word(line)
        if is_motion(line):
            self.durations.append(self.firmware.time - start)
            if recorded != replayed:
                self.errors.append((line, recorded, replayed))
        elif recorded != replayed or (word not in ("FGET", "PGET") and lines != record["reply"]):
            raise ReplayMismatch(f"line {number}: {line!r} answered {record['reply']!r} on the recorded hand but "
                                 f"{lines!r} in the simulator: the log was not recorded by `bh8 calibrate record` "
                                 "or was edited")
        _queried(line, lines, self.queried, self.queried_motors)

    def _baud(self, record: dict, number: int) -> None:
        line = f"PSET BAUD {record['rate'] // 100}"
        self._transact(line.encode("ascii") + b"\r", repr(line), number)

    def _loop(self, record: dict, number: int) -> None:
        command = f"{record['motors']}LOOP".encode("ascii")
        reply = self._transact(command + b"\r", "LOOP", number)
        if reply != command + b"*":
            raise ReplayMismatch(f"line {number}: LOOP answered {reply!r} in the simulator")
        self.layout = _layout_of(record)
        self.previous_block = None

    def _segment(self, record: dict, number: int) -> None:
        if self.anchored and record["name"].endswith(ANCHOR_PHASES) and self.last_recorded is not None \
                and self.layout is not None:
            self._anchor()

    def _anchor(self) -> None:
        """The simulated motors to where the recorded hand's last feedback put them, at the speed
        its last two blocks give."""
        plant = self.firmware.plant
        simulated, speeds = plant.motor_positions(), plant.motor_velocities()
        reported = dict(zip(self.layout.motors, self.positions[-1]))
        recorded = dict(zip(self.layout.motors, self.last_recorded))
        before = dict(zip(self.layout.motors, self.before_recorded or self.last_recorded))
        interval = self.times[-1] - self.times[-2] if len(self.times) > 1 else 0.0
        counts, velocities = list(simulated), list(speeds)
        for m in self.layout.motors:
            if m in ANCHORED_MOTORS:
                counts[m - 1] = simulated[m - 1] + recorded[m] - reported[m]
                velocities[m - 1] = (recorded[m] - before[m]) / interval if interval > 0.0 else 0.0
        anchor_plant(plant, counts, velocities)

    def _block(self, record: dict, number: int) -> None:
        firmware = self.firmware
        control = bytes.fromhex(record["control"])
        if self.wall and self.previous_block is not None:
            last_t, last_bytes = self.previous_block
            modelled = last_bytes * BITS_PER_BYTE / firmware.baud + firmware.processing_time
            gap = record["t"] - last_t - modelled
            if gap > 0.0:
                firmware.run_for(min(gap, 10.0))
        feedback = self._transact(control, "a RealTime block", number)
        try:
            _collect(self.layout, feedback, self.positions, self.strains)
        except ValueError:
            raise ReplayMismatch(f"line {number}: the simulator answered a RealTime block with {feedback[:40]!r}") from None
        self.times.append(firmware.time)
        self.previous_block = (record["t"], len(control) + len(bytes.fromhex(record["feedback"])))
        if self.anchored:
            values = self.layout.feedback_by_motor(self.layout.decode_feedback(bytes.fromhex(record["feedback"])))
            self.before_recorded = self.last_recorded
            self.last_recorded = [values[m].get("LFAP") for m in self.layout.motors]

    def _loop_exit(self, record: dict, number: int) -> None:
        reply = self._transact(b"\x03", "^C", number)
        if not reply.endswith(LINE_END + PROMPT):
            raise ReplayMismatch(f"line {number}: ^C answered {reply!r} in the simulator")
