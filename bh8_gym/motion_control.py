"""HCTL-1100 motion control, one channel per motor (manual §9.2; SPEC.md §4; Contract 2).

Each BH8 motor has an HCTL-1100 running at 2 MHz; its sample period is 16·(SAMPLE+1)/2 MHz
(256 µs at SAMPLE 31). Units are the chip's: positions in encoder counts, velocities in counts
per sample (the firmware's velocity parameters are 1/16 count per sample, 12.4 fixed point),
accelerations in counts per sample² (ACCEL is 1/256 count per sample²). The motor command is
U = K/4 × error (the HCTL filter D(z) = K/4 · (z − A/256)/(z + B/256) with the zero A = FDZ and the
pole B = FIP at their default 0, i.e. pure proportional gain; FDZ/FIP are stored by the firmware
but this emulation always uses the default filter), saturating at ±127 = full PWM duty.

The plant (Contract 1) models the motor as a velocity source with a torque limit, so a channel
turns U into a drive (velocity target in counts per second, torque fraction |U|/127):

- OFF: no drive (torque fraction NaN: the plant's "unpowered").
- POSITION: trapezoidal profile (accelerate at ACCEL, cruise at the open/close velocity,
  decelerate onto the target, §9.2.1); U = K/4 × (profile position − position). The velocity
  target is the profile velocity plus the error divided by the physics step, i.e. the velocity
  that closes the error within one step and no more. The HCTL samples at 3.9 kHz, the physics at
  500 Hz: a target that overshoots within a step makes the discrete loop unstable at high gains.
- HOLD: POSITION at a fixed set point (also firmware 4.4 LCT: present position + LCT, SPEC.md §7).
- VELOCITY (TC/TO, §9.2.2) and LOOP (RealTime, §6.1): U = K/4 × (commanded − actual velocity),
  velocities in counts per sample; the velocity target is the commanded velocity. So the stall
  torque grows with the commanded velocity (§9.3.1 Figure 25).

Plain floats and no allocation per step: `drive` is called once per motor per physics step.
"""
from __future__ import annotations

from math import nan, sqrt

HCTL_CLOCK_HZ = 2.0e6  # §5.3.4 SAMPLE note: "The HCTL-1100 clock speed used in the BH8-series Hand is 2.00 MHz"
U_MAX = 127.0  # HCTL motor command register saturates at ±127 (full PWM duty)
VELOCITY_SCALE = 16.0  # velocity parameters are 1/16 count per sample (12.4 fixed point)
ACCEL_SCALE = 256.0  # ACCEL is 1/256 count per sample² (8.8 fixed point)
OFF, POSITION, HOLD, VELOCITY, LOOP = range(5)
MODE_NAMES = ("OFF", "POSITION", "HOLD", "VELOCITY", "LOOP")


def sample_period(sample: int) -> float:
    """Seconds per HCTL sample for the SAMPLE register value (256 µs at the default 31)."""
    if not 0 <= sample <= 255:
        raise ValueError(f"SAMPLE must be 0..255, got {sample!r}")
    return 16.0 * (sample + 1) / HCTL_CLOCK_HZ


class MotorChannel:
    """One HCTL-1100 channel. All state is plain floats; `drive` allocates nothing but its tuple."""

    __slots__ = (
        "mode", "period", "gain", "velocity_command", "set_point",
        "_start", "_target", "_direction", "_accel", "_peak_velocity",
        "_t_accel", "_t_cruise", "_t_total", "_d_accel", "_t0", "motor_command",
    )

    def __init__(self, sample: int = 31):
        self.period = sample_period(sample)
        self.mode = OFF
        self.gain = 0.0  # K/4
        self.velocity_command = 0.0  # counts per sample (VELOCITY, LOOP)
        self.set_point = 0.0  # HOLD position, counts
        self.motor_command = 0.0  # last U
        self._start = self._target = 0.0
        self._direction = 1.0
        self._accel = self._peak_velocity = 0.0
        self._t_accel = self._t_cruise = self._t_total = self._d_accel = self._t0 = 0.0

    # -- mode changes ------------------------------------------------------------------------

    def set_sample(self, sample: int) -> None:
        self.period = sample_period(sample)

    def off(self) -> None:
        self.mode = OFF
        self.motor_command = 0.0

    def hold(self, position: float, gain: int) -> None:
        """Servo at `position` with filter gain `gain` (FPG)."""
        self.mode = HOLD
        self.set_point = float(position)
        self.gain = gain / 4.0

    def velocity(self, velocity_command: float, gain: int, loop: bool = False) -> None:
        """Proportional velocity control at `velocity_command` counts per sample, gain K."""
        self.mode = LOOP if loop else VELOCITY
        self.velocity_command = float(velocity_command)
        self.gain = gain / 4.0

    def move(self, time: float, start: float, target: float, max_velocity: float, accel: float, gain: int) -> None:
        """Trapezoidal move from `start` to `target` counts starting at `time` seconds.

        `max_velocity` in counts per sample, `accel` in counts per sample²; gain K (FPG).
        An `accel` of 0 never leaves `start` (the profile generator cannot accelerate).
        """
        period = self.period
        a = accel / (period * period)  # counts/s²
        v = abs(max_velocity) / period  # counts/s
        distance = abs(target - start)
        self.mode = POSITION
        self.gain = gain / 4.0
        self._t0 = time
        self._start = float(start)
        self._target = float(target)
        self._direction = 1.0 if target >= start else -1.0
        self._accel = a
        if a <= 0.0 or v <= 0.0:
            self._t_accel = self._t_cruise = self._d_accel = self._peak_velocity = 0.0
            self._t_total = float("inf") if distance > 0 else 0.0
            return
        t_accel = v / a
        d_accel = 0.5 * a * t_accel * t_accel
        if 2.0 * d_accel >= distance:  # triangular profile
            t_accel = sqrt(distance / a)
            d_accel = 0.5 * distance
            v = a * t_accel
            t_cruise = 0.0
        else:
            t_cruise = (distance - 2.0 * d_accel) / v
        self._t_accel = t_accel
        self._t_cruise = t_cruise
        self._d_accel = d_accel
        self._peak_velocity = v
        self._t_total = 2.0 * t_accel + t_cruise

    # -- queries -----------------------------------------------------------------------------

    @property
    def target(self) -> float:
        """The position a POSITION move ends at (HOLD: the set point)."""
        return self.set_point if self.mode == HOLD else self._target

    @property
    def profile_frozen(self) -> bool:
        """True for a POSITION move whose trapezoid cannot leave its start: ACCEL 0 (§5.3.4 allows
        it) gives the profile generator no acceleration, so the motor is held where it was."""
        return self.mode == POSITION and self._accel <= 0.0 and self._t_total > 0.0

    def profile_done(self, time: float) -> bool:
        """True when the POSITION profile has reached its target (always True outside POSITION)."""
        return self.mode != POSITION or time - self._t0 >= self._t_total

    def profile(self, time: float) -> tuple[float, float]:
        """(position counts, velocity counts/s) the trapezoid commands at `time`."""
        tau = time - self._t0
        t_accel = self._t_accel
        if tau >= self._t_total:
            return self._target, 0.0
        if self._accel <= 0.0:
            return self._start, 0.0
        a = self._accel
        direction = self._direction
        if tau <= t_accel:
            return self._start + direction * 0.5 * a * tau * tau, direction * a * tau
        if tau <= t_accel + self._t_cruise:
            return (
                self._start + direction * (self._d_accel + self._peak_velocity * (tau - t_accel)),
                direction * self._peak_velocity,
            )
        remaining = self._t_total - tau
        return self._target - direction * 0.5 * a * remaining * remaining, direction * a * remaining

    # -- the per-step law --------------------------------------------------------------------

    def drive(self, time: float, position: float, velocity: float, dt: float) -> tuple[float, float]:
        """(velocity target counts/s, torque fraction 0..1 or NaN for off) for one physics step.

        `position` in counts, `velocity` in counts/s, `dt` the physics step in seconds.
        """
        mode = self.mode
        if mode == LOOP or mode == VELOCITY:  # first: RealTime control runs every motor in LOOP
            u = self.gain * (self.velocity_command - velocity * self.period)
            target_velocity = self.velocity_command / self.period
        elif mode == OFF:
            return 0.0, nan
        else:  # POSITION, HOLD
            if mode == HOLD:
                desired, desired_velocity = self.set_point, 0.0
            else:
                desired, desired_velocity = self.profile(time)
            error = desired - position
            u = self.gain * error
            target_velocity = desired_velocity + error / dt
        if u > U_MAX:
            u = U_MAX
        elif u < -U_MAX:
            u = -U_MAX
        self.motor_command = u
        return target_velocity, abs(u) / U_MAX
