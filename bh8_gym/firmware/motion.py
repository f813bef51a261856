"""The motion task of the supervisory motor commands (HI, HOME, M, IO, IC, C, O, TC, TO) and their
termination (manual §5.5, §9.2 HCTL-1100): stall after TSTOP, strain-gauge limits, breakaway
stop (BS), goal reached, ^C; HOLD decides what a terminated motor does.

Choices where the documents are silent (SPEC.md §4, §8):

- HI (SPEC.md §4): each selected motor opens in velocity mode at IVEL until it stops (TSTOP, as
  §5.3.4 defines it); fingers back off `IHIT_BACKOFF_COUNTS` and hit the stop again until they have
  hit it max(IHIT, 1) times (at most `IHIT_MAX_IMPACTS`); the origin is set so where it stopped
  reads −IOFF; a trapezoidal move then brings the motor to 0. HOLD decides what happens at the end.
  A motor still opening faster than `HI_SEEK_MOVING_CPS`, or still gaining opening speed, has not
  stopped. HI has no status of its own (§5.2.1, §5.5 lists it among no terminating commands): a
  motor stopped short of its open stop (an obstacle, a drive too weak to move it) gets its origin
  where it stopped, as §8 describes ("The finger was not opened completely ... Initialize the
  finger"), and HI answers without error.
- Stall (§5.5 case 1): a driven motor that has not moved more than `STALL_DISTANCE_COUNTS` for
  TSTOP ms (at least `MIN_STALL_WINDOW_MS`) terminates; a profile move whose motor keeps up with
  its profile is not stalled (at its start the profile has not moved that far yet).
- ACCEL 0 (in range, §5.3.4): the HCTL's trapezoid (§9.2.1) cannot accelerate, so a position move
  never leaves its start; the motor, held at rest, stalls and terminates TSTOP ms later (§5.5
  case 1): C and O answer without error, M/HOME/IO/IC with ERR 16.
- Strain-gauge termination (§5.5 case 2) compares the raw gauge value; SGFLIP only changes what is
  sent to the host (FGET SG, LFS), as §5.3.4 says.
"""
from __future__ import annotations

from bh8_gym.firmware.clock import TIME_EPS
from bh8_gym.motion_control import ACCEL_SCALE, VELOCITY_SCALE, MotorChannel
from bh8_gym.protocol import CTRL_C, SPREAD_MOTOR
from bh8_gym.status import Status

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
# Our choice for HI (SPEC.md §4): a seeking motor still opening faster than this (counts/s) has not
# stalled, however little its smoothed encoder moved in TSTOP. Driven at IVEL from rest, the spread
# gathers speed slowly (about 1000 counts/s after 30 ms at the default FPG) and was taken for stalled
# wherever it started; at the open stop a motor reads about 0.
HI_SEEK_MOVING_CPS = 500.0
# Our choice for HI: a seeking motor whose opening speed beats its best so far in this seek by more
# than this (counts/s) is still getting going, not stopped. Driven from rest at a low gain it gathers
# speed slowly (the spread at libgripper's FPG 5: 9 % duty, about 10,000 counts/s², 5 counts in the
# first 30 ms), and the stall rule alone took it for stopped where it stood.
HI_SEEK_GAINING_CPS = 50.0
# The motion commands that clear BD and BP as they start (SPEC.md §3.1: "cleared after an O, TO, or HI").
BREAKAWAY_CLEARING_COMMANDS = ("O", "TO", "HI")
POSITION_COMMANDS = frozenset(("HOME", "IO", "IC", "M"))  # these report ERR 16 (§5.5)

# Per-motor run kinds of a motion command.
_RUN_POSITION, _RUN_VELOCITY, _RUN_HI_SEEK, _RUN_HI_BACKOFF, _RUN_HI_HOME = range(5)
_POSITION_RUNS = frozenset((_RUN_POSITION, _RUN_HI_BACKOFF, _RUN_HI_HOME))


class _MotorRun:
    """Termination bookkeeping of one motor during a motion command (§5.5)."""

    __slots__ = ("motor", "kind", "target", "direction", "progress", "smooth", "stall_time", "impacts_left",
                 "reached", "top_speed")

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
        self.top_speed = 0.0  # HI's seek: the fastest it has opened so far (counts/s)

    def restart(self, kind: int, target: float, position: float, time: float, direction: float = 0.0) -> None:
        self.kind, self.target, self.direction = kind, target, direction
        self.smooth, self.progress, self.stall_time = position, self.measure(position), time
        self.top_speed = 0.0

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

    def gaining(self, opening_speed: float) -> bool:
        """HI's seek: whether the motor opens faster than ever in this seek (by HI_SEEK_GAINING_CPS):
        a motor still gathering speed has not stopped, however little it has moved yet."""
        if opening_speed > self.top_speed + HI_SEEK_GAINING_CPS:
            self.top_speed = opening_speed
            return True
        return False


class MotionTask:
    """The generator `_motion_task` run by the clock, one physics step per wake-up, and the
    termination helpers LOOP shares (uses `_channels`, `_motor_values`, `_status`, `_origin`,
    `_initialized`, `_stall_smoothing`, the plant)."""

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
                        run.kind in _POSITION_RUNS and self._on_profile(channel, t, position)) or (
                        run.kind == _RUN_HI_SEEK and run.gaining(-self._velocities[m - 1])):
                    run.progress = run.measure(run.smooth)
                    run.stall_time = t
                elif (t - run.stall_time) * 1000.0 >= max(v["TSTOP"], MIN_STALL_WINDOW_MS) - TIME_EPS:
                    ended = run.kind != _RUN_HI_SEEK or -self._velocities[m - 1] <= HI_SEEK_MOVING_CPS
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
                    # Stopped: at the open stop, or short of it (SPEC.md §4: the origin goes where the
                    # motor stopped, as on the hand, §8 "not opened completely"; HI reports nothing).
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
        index = data.find(CTRL_C)
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
