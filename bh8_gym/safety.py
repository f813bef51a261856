"""The safety envelope: the limits `bh8 deploy` enforces on a hand, which the environments train in.

One definition for both sides, so the policy evaluated in simulation is the policy that runs on the
hand: the environments' action space holds LCV within ±`max_velocity` (deploy's clamp then never
changes a byte), and an episode in which a finger's strain gauge reads more than `max_strain` ends
as deploy's run would, with a safety stop (no success). Temperature is checked by deploy (PGET TEMP
before LOOP, and every cycle when the LOOP carries LFT); the simulated hand stays far below it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable

from bh8_gym.protocol import SPREAD_MOTOR  # the spread has no strain gauge (§5.3.2: its LFS reads 255)

# LCV is a signed byte: |LCV| 127 is no clamp at all (-128..127).
NO_VELOCITY_CLAMP = 127


@dataclass(frozen=True)
class SafetyEnvelope:
    """Limits on a hand in LOOP.

    max_strain: a finger's 8-bit strain gauge (no-load 100-140, SPEC.md §1) above this stops the
        run; 230 leaves headroom below saturation (255, reached at full motor torque) for a firm grasp.
    max_velocity: |LCV| in bytes; 100 of 127 keeps a finger off full speed when it meets an object.
    max_temperature: degrees C; the hand runs at 40-60 °C (§2).
    """

    max_strain: int = 230
    max_velocity: int = 100
    max_temperature: float = 65.0

    def __post_init__(self):
        for name, high in (("max_strain", 255), ("max_velocity", NO_VELOCITY_CLAMP)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= high:
                raise ValueError(f"SafetyEnvelope.{name} must be an integer 0..{high}, got {value!r}")
        if isinstance(self.max_temperature, bool) or not (isinstance(self.max_temperature, (int, float))
                                                          and math.isfinite(self.max_temperature)):
            raise ValueError(f"SafetyEnvelope.max_temperature must be a finite number, got {self.max_temperature!r}")

    @property
    def velocity_bounds(self) -> tuple[int, int]:
        """The LCV bytes allowed: ±max_velocity, or the whole signed byte when it is 127."""
        if self.max_velocity >= NO_VELOCITY_CLAMP:
            return -128, 127
        return -self.max_velocity, self.max_velocity

    def strain_violation(self, strains: Iterable[tuple[int, int | None]]) -> str | None:
        """Why the run must stop, for (motor, strain) readings (None: not reported), or None."""
        for motor, strain in strains:
            if motor != SPREAD_MOTOR and strain is not None and strain > self.max_strain:
                return f"motor {motor} strain {strain} above the limit {self.max_strain}"
        return None

    def temperature_violation(self, celsius: float | None, when: str = "") -> str | None:
        """Why the run must stop for a temperature reading (None: not reported), or None."""
        if celsius is not None and celsius > self.max_temperature:
            return f"temperature {celsius:.1f} C above the limit {self.max_temperature} C{when}"
        return None
