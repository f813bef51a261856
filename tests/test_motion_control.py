"""HCTL-1100 channel: units, trapezoid profile, control laws, saturation.

Sources: manual §9.2 (trapezoidal and velocity control), §5.3.4 (SAMPLE, ACCEL, FPG); SPEC.md §4
(units: 1/16 count per sample velocities, 1/256 count per sample² ACCEL, U = K/4 × error, ±127);
docs/architecture.md Contract 2 (no overshoot within one physics step).
"""
import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from bh8_gym import motion_control as mc

DT = 0.002


def test_sample_period_units():
    """SPEC.md §4: sample period 16·(SAMPLE+1)/2 MHz = 256 µs at SAMPLE 31."""
    assert mc.sample_period(31) == pytest.approx(256e-6)
    assert mc.sample_period(15) == pytest.approx(128e-6)
    with pytest.raises(ValueError, match="300"):
        mc.sample_period(300)


def test_default_finger_close_profile_takes_about_0_8_seconds():
    """§9.2.1 trapezoid at finger defaults (MCV 100, ACCEL 4): 0 → 17000 counts within App. A's 1 s ±30%."""
    ch = mc.MotorChannel()
    ch.move(0.0, 0.0, 17000.0, 100 / 16, 4 / 256, 10)
    total = ch._t_total
    assert 0.7 < total < 1.3
    # cruise speed: 6.25 counts per 256 µs sample
    _, v = ch.profile(total / 2)
    assert v == pytest.approx(6.25 / 256e-6)


def test_spread_profile_takes_about_0_3_seconds():
    """App. A: full spread about 0.3 s at spread defaults (MCV 60, ACCEL 2), ±30%."""
    ch = mc.MotorChannel()
    ch.move(0.0, 0.0, 3150.0, 60 / 16, 2 / 256, 10)
    assert 0.21 < ch._t_total < 0.39


@given(
    start=st.floats(-5000, 20000),
    distance=st.floats(-20000, 20000),
    velocity=st.integers(16, 4080),
    accel=st.integers(1, 65535),
)
def test_profile_is_monotonic_bounded_and_ends_on_target(start, distance, velocity, accel):
    """§9.2.1: accelerate at ACCEL, cruise at ≤ velocity, decelerate onto the target; never past it."""
    ch = mc.MotorChannel()
    target = start + distance
    ch.move(0.0, start, target, velocity / 16, accel / 256, 10)
    v_max = velocity / 16 / ch.period
    previous = start
    n = 50
    for k in range(n + 1):
        t = ch._t_total * k / n
        p, v = ch.profile(t)
        assert min(start, target) - 1e-6 <= p <= max(start, target) + 1e-6
        assert abs(v) <= v_max * (1 + 1e-9) + 1e-9
        assert (p - previous) * (target - start) >= -1e-6
        previous = p
    assert ch.profile(ch._t_total + 1.0) == (target, 0.0)
    assert ch.profile_done(ch._t_total + 1e-9)


def test_accel_zero_never_leaves_the_start():
    """§5.3.4 ACCEL 0: the profile generator cannot accelerate; the command position stays put."""
    ch = mc.MotorChannel()
    ch.move(0.0, 100.0, 5000.0, 100 / 16, 0.0, 10)
    assert ch.profile(10.0) == (100.0, 0.0)
    assert not ch.profile_done(10.0)
    assert ch.profile_frozen  # the firmware lets such a motor stall (§5.5 case 1)
    ch.move(0.0, 100.0, 5000.0, 100 / 16, 4 / 256, 10)
    assert not ch.profile_frozen


def test_position_law_gain_and_saturation():
    """SPEC.md §4: U = FPG/4 × position error, saturating at ±127 (torque fraction 1)."""
    ch = mc.MotorChannel()
    ch.hold(1000.0, 10)
    _, fraction = ch.drive(0.0, 990.0, 0.0, DT)
    assert fraction == pytest.approx(2.5 * 10 / 127)
    assert ch.motor_command == pytest.approx(25.0)
    _, fraction = ch.drive(0.0, 0.0, 0.0, DT)
    assert fraction == 1.0 and ch.motor_command == 127.0
    _, fraction = ch.drive(0.0, 2000.0, 0.0, DT)
    assert fraction == 1.0 and ch.motor_command == -127.0


@given(error=st.floats(-20000, 20000), gain=st.integers(0, 255))
def test_hold_never_overshoots_within_a_step(error, gain):
    """Contract 2 stability note: the velocity target reaches the set point in one step, no further."""
    ch = mc.MotorChannel()
    ch.hold(0.0, gain)
    velocity, fraction = ch.drive(0.0, -error, 0.0, DT)
    assert 0.0 <= fraction <= 1.0
    assert velocity * DT == pytest.approx(error)


def test_velocity_law_stall_torque_grows_with_commanded_velocity():
    """§9.2.2/§9.3.1 Fig. 25: U = FPG/4 × velocity error (counts/sample); at stall it grows with MCV."""
    fractions = []
    for mcv in (50, 100, 200):
        ch = mc.MotorChannel()
        ch.velocity(mcv / 16, 10)
        velocity, fraction = ch.drive(0.0, 0.0, 0.0, DT)
        assert velocity == pytest.approx(mcv / 16 / 256e-6)
        assert fraction == pytest.approx(2.5 * mcv / 16 / 127)
        fractions.append(fraction)
    assert fractions[0] < fractions[1] < fractions[2]
    ch = mc.MotorChannel()
    ch.velocity(100 / 16, 10)
    _, fraction = ch.drive(0.0, 0.0, 100 / 16 / 256e-6, DT)
    assert fraction == pytest.approx(0.0, abs=1e-12)


def test_loop_gain_zero_gives_no_torque():
    """§6.1 RealTime: motor torque = velocity error × the proportional gain; LCPG 0 → no torque."""
    ch = mc.MotorChannel()
    ch.velocity(50.0, 0, loop=True)
    _, fraction = ch.drive(0.0, 0.0, 0.0, DT)
    assert fraction == 0.0 and ch.mode == mc.LOOP


def test_off_mode_is_unpowered():
    """OFF is unpowered (NaN torque, Contract 1 set_drives)."""
    ch = mc.MotorChannel()
    velocity, fraction = ch.drive(0.0, 0.0, 0.0, DT)
    assert math.isnan(fraction)


def test_position_move_tracks_a_first_order_motor_to_the_target():
    """§9.2.1 end to end: a simple torque-limited motor driven by the channel ends at the target."""
    ch = mc.MotorChannel()
    ch.move(0.0, 0.0, 3000.0, 100 / 16, 4 / 256, 10)
    position = velocity = 0.0
    peak_accel = 4.0e6  # counts/s² at full torque (a light finger)
    t = 0.0
    overshoot = 0.0
    for _ in range(1000):
        target_v, fraction = ch.drive(t, position, velocity, DT)
        dv = max(-fraction * peak_accel * DT, min(fraction * peak_accel * DT, target_v - velocity))
        velocity += dv
        position += velocity * DT
        overshoot = max(overshoot, position - 3000.0)
        t += DT
    assert position == pytest.approx(3000.0, abs=5.0)
    assert overshoot < 50.0  # within the default MPE
