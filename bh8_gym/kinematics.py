"""BarrettHand kinematics: D-H forward kinematics and encoder <-> joint-angle conversions.

Sources: manual §9.5 (Equations 1-5, Tables 8-9), §9.6 joint limits, App. A; wiki Table 10
(`seeds/002`, `seeds/003`) for the BH8-280/282 encoder scales; SPEC.md §1 for the resolved typos
(Equation 3's x entry uses r·Aw, not j·Aw; the 125:1 / 375:1 ratio order of Equation 4).

Conventions: metres and radians at the API; the manual's ratios are in degrees per encoder count.
Θk1 is the spread angle of finger k (0 for F3, which does not spread), Θk2 the inner link angle and
Θk3 the outer link angle relative to the inner link, all zero in the manual's zero position
(Figure 29). Frames follow Craig's modified D-H convention: wrist frame {W} at the base of the
hand, z out through the palm, fingers closing towards +z.
"""
from __future__ import annotations

from dataclasses import dataclass
from math import cos, pi, radians, sin

import numpy as np

# Table 8 (metres, radians).
AW = 0.025
A1 = 0.050
A2 = 0.070
A3 = 0.050
DW = 0.084
D3 = 0.0095
PHI2 = radians(2.46)
PHI3 = radians(50.0)

# Table 9 per-finger constants, indexed by finger number 1..3.
FINGER_R = {1: -1, 2: 1, 3: 0}
FINGER_J = {1: 1, 2: 1, 3: -1}
FINGERS = (1, 2, 3)

# §9.6 / App. A joint ranges.
INNER_RANGE = (0.0, radians(140.0))
OUTER_RANGE = (0.0, radians(48.0))  # relative to the inner link
SPREAD_RANGE = (0.0, pi)

# Equations 4-5, BH8-262 (degrees per motor encoder count).
INNER_COUNTS_PER_DEG_262 = 125.0  # clutch engaged: inner = M/125
OUTER_REL_COUNTS_PER_DEG_262 = 375.0  # clutch engaged: outer relative to inner = M/375
OUTER_ABS_COUNTS_PER_DEG_262 = 93.75  # outer link to palm = M/93.75, engaged or not
SPREAD_COUNTS_PER_DEG_262 = 17.5  # Equation 4: 2/35 degree per count


def dh_transform(a: float, alpha: float, d: float, theta: float) -> np.ndarray:
    """Equation 1: the homogeneous transform from frame {i-1} to frame {i} (Craig's convention)."""
    ct, st, ca, sa = cos(theta), sin(theta), cos(alpha), sin(alpha)
    return np.array(
        [
            [ct, -st, 0.0, a],
            [st * ca, ct * ca, -sa, -sa * d],
            [st * sa, ct * sa, ca, ca * d],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def _check_finger(finger: int) -> None:
    if finger not in FINGER_R:
        raise ValueError(f"finger must be 1, 2 or 3, got {finger!r}")


def dh_rows(finger: int, theta1: float, theta2: float, theta3: float) -> list[tuple[float, float, float, float]]:
    """Table 9 rows (a_{i-1}, alpha_{i-1}, d_i, theta_i) for joints 1, 2, 3 and the tip frame T."""
    _check_finger(finger)
    r, j = FINGER_R[finger], FINGER_J[finger]
    return [
        (r * AW, 0.0, DW, r * theta1 - (pi / 2) * j),
        (A1, pi / 2, 0.0, theta2 + PHI2),
        (A2, 0.0, 0.0, theta3 + PHI3),
        (A3, -pi / 2, D3, 0.0),
    ]


def link_frames(finger: int, theta1: float, theta2: float, theta3: float) -> list[np.ndarray]:
    """Wrist-to-frame transforms {W}->{1}, {W}->{2}, {W}->{3}, {W}->{T} (Equation 2's partial products)."""
    frames = []
    transform = np.eye(4)
    for row in dh_rows(finger, theta1, theta2, theta3):
        transform = transform @ dh_transform(*row)
        frames.append(transform)
    return frames


def forward_kinematics(finger: int, theta1: float, theta2: float, theta3: float) -> np.ndarray:
    """Equation 2: the 4x4 transform from the wrist frame to the fingertip frame of `finger`.

    `theta1` is the manual's Θk1 (spread; ignored in effect for F3, whose r is 0), `theta2` Θk2
    (inner link), `theta3` Θk3 (outer link relative to the inner link); radians in, metres out.
    """
    return link_frames(finger, theta1, theta2, theta3)[-1]


@dataclass(frozen=True)
class EncoderScale:
    """Full-range encoder counts of one hand model (wiki Table 10)."""

    model: str
    finger_counts: float  # counts for 140 degrees of the inner link, clutch engaged
    spread_counts: float  # counts for 180 degrees of spread

    @property
    def finger_counts_per_inner_degree(self) -> float:
        return self.finger_counts / 140.0

    @property
    def spread_counts_per_degree(self) -> float:
        return self.spread_counts / 180.0


ENCODER_SCALES = {
    "262": EncoderScale("262", 17_500.0, 3_150.0),
    "280": EncoderScale("280", 199_111.1, 35_840.0),
    "282": EncoderScale("282", 199_111.1, 35_840.0),
}


def encoder_scale(model: str = "262") -> EncoderScale:
    try:
        return ENCODER_SCALES[str(model)]
    except KeyError:
        raise ValueError(f"unknown BarrettHand model {model!r}; expected one of {sorted(ENCODER_SCALES)}") from None


def finger_angles(counts: float, model: str = "262", breakaway_counts: float | None = None) -> tuple[float, float]:
    """(Θk2, Θk3) in radians from a finger motor's encoder counts.

    Before breakaway (Equation 4): inner = M/125°, outer relative = M/375° (262 scale).
    After breakaway at `breakaway_counts` (Equation 5 and wiki Equation 4): the inner link stays at
    its breakaway angle and the outer link's angle to the palm is still M/93.75°, so its angle
    relative to the inner link is M/93.75° - Mb/125°.
    Each link stops at its joint stops (inner 0-140°, outer 0-48° relative): counts past them, which
    the motor cannot reach, give the angle at the stop.
    """
    scale = encoder_scale(model)
    per_deg = scale.finger_counts_per_inner_degree  # inner-link counts per degree (125 on the 262)
    outer_abs_deg = counts / per_deg * (4.0 / 3.0)  # = M/93.75 on the 262
    if breakaway_counts is None:
        inner_deg = counts / per_deg
    else:
        inner_deg = breakaway_counts / per_deg
    inner = min(max(radians(inner_deg), INNER_RANGE[0]), INNER_RANGE[1])
    outer = min(max(radians(outer_abs_deg) - inner, OUTER_RANGE[0]), OUTER_RANGE[1])
    return inner, outer


def spread_angle(counts: float, model: str = "262") -> float:
    """Θ11 = Θ21 in radians from the spread motor's counts (wiki: ENC/CNT·π; Equation 4: 2/35°/count)."""
    return counts / encoder_scale(model).spread_counts * pi


def finger_counts_from_inner_angle(theta2: float, model: str = "262") -> float:
    """Motor counts that put the inner link at `theta2` radians with the clutch engaged."""
    return np.degrees(theta2) * encoder_scale(model).finger_counts_per_inner_degree


def spread_counts_from_angle(theta1: float, model: str = "262") -> float:
    """Spread motor counts for a spread angle of `theta1` radians."""
    return theta1 / pi * encoder_scale(model).spread_counts


def fingertip_positions(
    finger_counts,
    spread_counts: float,
    model: str = "262",
    breakaway_counts=(None, None, None),
) -> np.ndarray:
    """Fingertip positions (3x3, metres, rows F1..F3) in the wrist frame from encoder counts."""
    if len(finger_counts) != 3 or len(breakaway_counts) != 3:
        raise ValueError("finger_counts and breakaway_counts need one entry per finger (3)")
    theta1 = spread_angle(spread_counts, model)
    tips = np.empty((3, 3))
    for index, finger in enumerate(FINGERS):
        theta2, theta3 = finger_angles(finger_counts[index], model, breakaway_counts[index])
        tips[index] = forward_kinematics(finger, theta1, theta2, theta3)[:3, 3]
    return tips
