"""The arm that carries the hand in BH8Grasp-v0: its schedule on the host's clock.

A host knows it (the robot arm runs the same grasp/lift/hold schedule on the real hand), so it is
host-side: the observation's phase entries come from it, and the simulated scene moves the wrist
along it (`scenes.GraspScene.cycle_hook`).

For a low object the arm is compliant in z during the grasp (`ArmSchedule.press_rise`: a
surface-constrained grasp, as a back-drivable arm such as Barrett's WAM does it): it comes down until
the hand touches the table and then holds `press_force` down, so a closing fingertip pressed on the
table lifts the hand and slides along the table under the object's base instead of stalling.
"""
from __future__ import annotations

from dataclasses import dataclass
from math import pi, sin

MAX_PHASE_SECONDS = 60.0


@dataclass(frozen=True)
class ArmSchedule:
    """The arm's motion in an episode: grasp (still), lift (minimum-jerk rise), hold (optional shake).

    Durations follow the lead's design: 1.5-2.5 s episodes, a 10 cm lift over about 0.7 s (a
    gentle but realistic pick speed for an industrial arm, peak about 0.27 m/s).
    """

    grasp_seconds: float = 0.8
    lift_seconds: float = 0.7
    hold_seconds: float = 0.5
    lift_height: float = 0.10  # metres
    shake_amplitude: float = 0.0  # metres, horizontal (x) sinusoid during hold; 0 = no shake
    shake_frequency: float = 2.0  # Hz
    # The table-contact grasp (low objects, scenes.PlacementRanges.table_contact_below): the arm is an
    # admittance in z. It holds `press_force` newtons down on whatever the hand touches, beyond the
    # hand's weight (which it carries): a quarter of one finger's 2 kg tip payload (manual App. A),
    # so a single finger on the table lifts the hand long before it stalls, and far inside a WAM's
    # 3-4 kg payload (Barrett's published figure; any arm with a wrist force sensor can hold it).
    press_force: float = 5.0  # N
    # m/s the wrist moves per newton the measured force differs from press_force, up to
    # press_speed: 10 N over press_force rises at 0.2 m/s, about the fingertips' fastest descent
    # when a LOOP close at full speed sweeps them down (so the press stays a few newtons).
    press_admittance: float = 0.02  # (m/s)/N
    press_speed: float = 0.25  # m/s

    PHASES = ("grasp", "lift", "hold")

    def __post_init__(self):
        # Our bounds, checked before a loop uses them (a hold of 1e300 s never ended an episode's
        # step count): an arm's phase lasts a minute at most, lifts at most a metre, shakes at most
        # 20 cm at up to 50 Hz.
        bounds = {"grasp_seconds": (0.0, MAX_PHASE_SECONDS), "lift_seconds": (0.0, MAX_PHASE_SECONDS),
                  "hold_seconds": (0.0, MAX_PHASE_SECONDS), "lift_height": (0.0, 1.0), "shake_amplitude": (0.0, 0.2),
                  "shake_frequency": (0.0, 50.0), "press_force": (0.0, 50.0), "press_admittance": (0.0, 10.0),
                  "press_speed": (0.0, 2.0)}
        for name, (low, high) in bounds.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not low <= value <= high:
                raise ValueError(f"ArmSchedule.{name} must be a number in [{low:g}, {high:g}], got {value!r:.40}")
        for name in ("grasp_seconds", "lift_seconds", "hold_seconds"):
            if not getattr(self, name) > 0:
                raise ValueError(f"ArmSchedule.{name} must be > 0, got {getattr(self, name)!r}")
        if not self.shake_frequency > 0:
            raise ValueError(f"invalid ArmSchedule {self!r}")
        if not (0 <= self.press_force <= 50 and self.press_admittance > 0 and 0 < self.press_speed <= 2):
            raise ValueError(f"ArmSchedule needs press_force 0-50 N, press_admittance > 0 and press_speed "
                             f"0-2 m/s, got {self!r}")

    @property
    def total_seconds(self) -> float:
        return self.grasp_seconds + self.lift_seconds + self.hold_seconds

    @property
    def durations(self) -> tuple[float, float, float]:
        return (self.grasp_seconds, self.lift_seconds, self.hold_seconds)

    def phase(self, elapsed: float) -> tuple[int, float]:
        """(phase index 0..2, seconds in that phase); past the end: (2, time in hold)."""
        if elapsed < self.grasp_seconds:
            return 0, max(elapsed, 0.0)
        elapsed -= self.grasp_seconds
        if elapsed < self.lift_seconds:
            return 1, elapsed
        return 2, elapsed - self.lift_seconds

    def wrist_offset(self, elapsed: float) -> tuple[float, float]:
        """(horizontal x, vertical z) offset of the wrist from its start, metres."""
        index, tau = self.phase(elapsed)
        if index == 0:
            return 0.0, 0.0
        if index == 1:
            s = tau / self.lift_seconds
            return 0.0, self.lift_height * s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)
        return self.shake_amplitude * sin(2.0 * pi * self.shake_frequency * tau), self.lift_height

    def press_rise(self, rise: float, force: float, seconds: float, lowest: float) -> float:
        """The table-contact grasp's wrist height over its planned start (metres, `rise`) after
        `seconds` more with the hand pushed up by `force` newtons (its contacts, not its weight):
        up while the force exceeds press_force, down (a guarded move) while it is less, never below
        `lowest`."""
        speed = min(max((force - self.press_force) * self.press_admittance, -self.press_speed), self.press_speed)
        return max(rise + speed * seconds, lowest)
