"""Forward kinematics and encoder conversions (manual §9.5 Equations 1-5, Tables 8-9; wiki Table 10; SPEC.md §1)."""
from __future__ import annotations

from math import cos, pi, radians, sin

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bh8_gym import kinematics as kin

angles = st.tuples(st.floats(0, pi), st.floats(0, radians(140)), st.floats(0, radians(48)))


def equation_3(finger, t1, t2, t3):
    """Equation 3 written out independently, with Table 9's r·Aw in the x entry (SPEC §1)."""
    r, j = kin.FINGER_R[finger], kin.FINGER_J[finger]
    a, b = t2 + kin.PHI2, t3 + kin.PHI3
    c1, s1 = cos(r * t1 - pi / 2 * j), sin(r * t1 - pi / 2 * j)
    cab, sab, ca, sa = cos(a + b), sin(a + b), cos(a), sin(a)
    A1, A2, A3, D3 = kin.A1, kin.A2, kin.A3, kin.D3
    return np.array(
        [
            [c1 * cab, -s1, -c1 * sab, A3 * c1 * cab - D3 * c1 * sab + A2 * c1 * ca + A1 * c1 + r * kin.AW],
            [s1 * cab, c1, -s1 * sab, A3 * s1 * cab - D3 * s1 * sab + A2 * s1 * ca + A1 * s1],
            [sab, 0.0, cab, A3 * sab + D3 * cab + sa * A2 + kin.DW],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


@settings(max_examples=200, deadline=None)
@given(finger=st.sampled_from(kin.FINGERS), q=angles)
def test_forward_kinematics_matches_equation_3(finger, q):
    """§9.5: Equation 2's product of Equation 1 transforms equals the closed form of Equation 3 (r·Aw)."""
    assert np.allclose(kin.forward_kinematics(finger, *q), equation_3(finger, *q), atol=1e-12)


def test_zero_position_geometry():
    """Figure 29 / Table 8: at zero, F3's tip lies on +y, F1 and F2 on -y at x = -/+Aw; tips above the palm."""
    tips = np.array([kin.forward_kinematics(f, 0.0, 0.0, 0.0)[:3, 3] for f in kin.FINGERS])
    assert tips[0, 0] == pytest.approx(-kin.AW) and tips[1, 0] == pytest.approx(kin.AW) and tips[2, 0] == pytest.approx(0.0)
    assert tips[2, 1] > 0 > tips[0, 1] and tips[1, 1] == pytest.approx(tips[0, 1])
    assert np.all(tips[:, 2] > kin.DW)


def test_full_spread_puts_f1_and_f2_beside_f3():
    """SPEC §1: at 180° spread F1 and F2 lie beside F3 (same y, x = -25, 0, +25 mm)."""
    tips = np.array([kin.forward_kinematics(f, pi, 0.3, 0.2)[:3, 3] for f in kin.FINGERS])
    assert np.allclose(tips[:, 1], tips[2, 1]) and np.allclose(tips[:, 0], [-kin.AW, kin.AW, 0.0])


@pytest.mark.parametrize(
    "model, finger_full, spread_full",
    [("262", 17_500.0, 3_150.0), ("280", 199_111.1, 35_840.0), ("282", 199_111.1, 35_840.0)],
)
def test_encoder_conversions_before_breakaway(model, finger_full, spread_full):
    """Equation 4 / wiki Table 10: full-range counts give inner 140°, outer M/375 (=46.7° on full), spread 180°."""
    inner, outer = kin.finger_angles(finger_full, model)
    assert np.degrees(inner) == pytest.approx(140.0)
    assert np.degrees(outer) == pytest.approx(140.0 / 3.0)  # 125:375 = 3:1 (SPEC §1)
    assert np.degrees(kin.spread_angle(spread_full, model)) == pytest.approx(180.0)
    assert kin.finger_counts_from_inner_angle(radians(140), model) == pytest.approx(finger_full)
    assert kin.spread_counts_from_angle(pi, model) == pytest.approx(spread_full)


def test_262_ratios_are_equation_4():
    """Equation 4 (262): inner = M/125°, outer = M/375°, spread = 2/35° per count."""
    inner, outer = kin.finger_angles(3_750.0)
    assert np.degrees(inner) == pytest.approx(30.0) and np.degrees(outer) == pytest.approx(10.0)
    assert np.degrees(kin.spread_angle(35.0)) == pytest.approx(2.0)


@pytest.mark.parametrize("model", ["262", "280", "282"])
def test_encoder_conversions_after_breakaway(model):
    """Equation 5: after breakaway the inner link stays; the outer link's angle to the palm is M x 4/375° (262)."""
    scale = kin.encoder_scale(model).finger_counts_per_inner_degree
    breakaway, now = 60.0 * scale, 80.0 * scale
    inner, outer = kin.finger_angles(now, model, breakaway_counts=breakaway)
    assert np.degrees(inner) == pytest.approx(60.0)
    assert np.degrees(inner + outer) == pytest.approx(80.0 * 4.0 / 3.0)  # 4/375 per count on the 262


def test_angles_stop_at_the_joint_stops():
    """Table 8 / §9.5: inner 0-140°, outer 0-48° relative. After breakaway at 7,500 counts the outer
    link reaches its stop at 10,125 counts (M/93.75° − 60° = 48°); more counts keep it there."""
    inner, outer = kin.finger_angles(12_000.0, breakaway_counts=7_500.0)
    assert np.degrees(inner) == pytest.approx(60.0) and np.degrees(outer) == pytest.approx(48.0)
    inner, outer = kin.finger_angles(10_000.0, breakaway_counts=7_500.0)
    assert np.degrees(outer) == pytest.approx(10_000 / 93.75 - 60.0)
    inner, outer = kin.finger_angles(-500.0)
    assert inner == 0.0 and outer == 0.0
    assert np.degrees(kin.finger_angles(20_000.0)[0]) == pytest.approx(140.0)


def test_unknown_model_and_finger_raise():
    """Bad arguments raise ValueError naming the value."""
    with pytest.raises(ValueError, match="283"):
        kin.encoder_scale("283")
    with pytest.raises(ValueError, match="4"):
        kin.forward_kinematics(4, 0, 0, 0)


def test_fingertip_positions_from_counts():
    """fingertip_positions(counts) = Equation 3 at the Equation 4/5 joint angles."""
    counts, spread = (3_000.0, 6_000.0, 9_000.0), 1_575.0
    tips = kin.fingertip_positions(counts, spread, breakaway_counts=(None, 4_000.0, None))
    t1 = pi / 2
    expected = [
        equation_3(1, t1, radians(24.0), radians(8.0))[:3, 3],
        equation_3(2, t1, radians(32.0), radians(6_000 / 93.75 - 32.0))[:3, 3],
        equation_3(3, t1, radians(72.0), radians(24.0))[:3, 3],
    ]
    assert np.allclose(tips, expected, atol=1e-12)
    with pytest.raises(ValueError):
        kin.fingertip_positions((1.0, 2.0), 0.0)
