"""The arm that carries the hand in BH8Grasp-v0: its schedule on the host's clock.

A host knows it (the robot arm runs the same grasp/lift/hold schedule on the real hand), so it is
host-side: the observation's phase entries come from it, and the simulated scene moves the wrist
along it (`scenes.GraspScene.cycle_hook`).
"""
from __future__ import annotations

from dataclasses import dataclass
from math import pi, sin


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

    PHASES = ("grasp", "lift", "hold")

    def __post_init__(self):
        for name in ("grasp_seconds", "lift_seconds", "hold_seconds"):
            if not getattr(self, name) > 0:
                raise ValueError(f"ArmSchedule.{name} must be > 0, got {getattr(self, name)!r}")
        if not (self.lift_height >= 0 and self.shake_amplitude >= 0 and self.shake_frequency > 0):
            raise ValueError(f"invalid ArmSchedule {self!r}")

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
