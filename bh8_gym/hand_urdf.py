"""Generate the BH8-262 URDF from the D-H constants in `bh8_gym.kinematics` (one source of truth).

Every link frame is the D-H frame of manual §9.5 Table 9 (Craig's modified convention, Equation 1),
so PyBullet's link frames equal `kinematics.link_frames`:

* `palm` (the base) is the wrist frame {W}: z out through the palm, palm face at PALM_TOP (≈ Dw).
* `fK_knuckle` is frame {1} of finger K: F1/F2 turn about it (the spread joint, axis r·z so that the
  joint angle is the manual's Θk1 >= 0); F3's knuckle is fixed (r = 0: F3 does not spread).
* `fK_inner` is frame {2} (joint angle Θk2), `fK_outer` frame {3} (Θk3, relative to the inner link),
  `fK_tip` the fixed fingertip frame {T}.

Joint ranges are §9.6 / App. A (inner 0-140°, outer 0-48°, spread 0-180°). Collision shapes (the
visual shapes are the same) are boxes and cylinders of Barrett's CAD outline (the constants below;
docs/modelling.md shows them): at full spread F1, F3 and F2 lie 25 mm apart centre to centre and
close side by side with a gap of `AW - FINGER_WIDTH`; the outer link ends at the D-H tip, so closed
fingers rest on the palm face (`palm_stop`); the masses add up to App. A's 1.18 kg.

`python -m bh8_gym.hand_urdf [--output PATH]` writes the URDF (default: assets/bh8_262.urdf).
"""
from __future__ import annotations

import argparse
import functools
import sys
from math import atan2, pi, sqrt
from pathlib import Path

import numpy as np

from bh8_gym import kinematics as kin

# App. A: 1.18 kg for the whole hand. The split between palm (motors, electronics) and finger
# links is our estimate: the palm houses all four motors and the electronics.
TOTAL_MASS = 1.18
KNUCKLE_MASS = 0.035
INNER_LINK_MASS = 0.055
OUTER_LINK_MASS = 0.035
TIP_FRAME_MASS = 0.001  # the fixed tip frame is a marker; PyBullet wants a non-zero mass
PALM_MASS = TOTAL_MASS - 3 * (KNUCKLE_MASS + INNER_LINK_MASS + OUTER_LINK_MASS + TIP_FRAME_MASS)

# Shape dimensions (metres). The manual gives the D-H frames (§9.5) but no outline (App. A's
# dimension drawing is an image); these come from Barrett's CAD as published in the community
# description `barrett_hand_description` (BH8-280/282 meshes, whose palm, knuckles and links are the
# 262's): facts measured off the meshes, recorded in docs/SPEC.md §1.
PALM_RADIUS = 0.0445  # palm_280/palm_282 meshes: a 89 mm disc
# The palm face is 0.9 mm above the inner joint axes (CAD), which are at z = Dw (Table 9). §8 ("adjust
# CT so that it is at or just beyond the actual palm surface") agrees: at the default CT (17,000 counts)
# Equation 3 puts the pad point {T} at z = 84.4 mm, on the palm face.
PALM_TOP = kin.DW + 0.0009
FINGER_WIDTH = 0.021  # inner link 21 mm across (CAD); neighbours at full spread, Aw = 25 mm apart, keep 4 mm
INNER_HALF_THICKNESS = 0.0105  # inner link about 21 mm deep in its bending plane (CAD: 20-25 mm)
INNER_START = 0.008  # the inner link's box starts this far past its joint axis (the knuckle covers the joint)
INNER_PAST_OUTER_JOINT = 0.0095  # the inner link reaches 9.5 mm past the outer joint axis (CAD)
OUTER_HALF_THICKNESS = kin.D3  # the pad is the plane y3 = D3 (§9.5: {T} is on it) and the CAD link is 19 mm deep
OUTER_START = 0.006
TIP_RADIUS = 0.002  # rounds the pad's end, so a fingertip touching an object is not a sharp edge
# Knuckle housings (CAD knuckle meshes), in the finger's frame {1} along its x axis, and their height
# above the inner joint axis (= the palm face). F1/F2's turns with the spread about the axis r·Aw from
# the palm centre and spans from 12.3 mm behind that axis to 15 mm past the inner joint; F3's frame {1}
# is the palm centre and its fixed housing spans 35-61 mm from it. Below the palm face they are inside
# the palm; only the part above it can touch an object.
KNUCKLE_WIDTH = 0.0246
SPREAD_KNUCKLE = (-0.0123, kin.A1 + 0.015, 0.015)  # (start, end along x1, top above the palm face)
FIXED_KNUCKLE = (0.035, 0.061, 0.009)
KNUCKLE_BELOW = 0.010  # how far the housing's box reaches below the palm face (into the palm)
KNUCKLE_HEIGHT = max(SPREAD_KNUCKLE[2], FIXED_KNUCKLE[2])  # how far the hand stands proud of its palm face
# How far below the palm face a closing finger reaches (its collision shapes along the 3:1 coupling
# before breakaway: deepest at about 7,250 counts, the outer link's pad then facing the palm axis).
# A palm-down hand whose palm face is higher than this above a table closes without touching it.
FINGER_SWEEP_DEPTH = 0.1006

PALM_RGBA = (0.22, 0.23, 0.25, 1.0)
KNUCKLE_RGBA = (0.12, 0.12, 0.13, 1.0)
LINK_RGBA = (0.78, 0.79, 0.82, 1.0)
TIP_RGBA = (0.35, 0.36, 0.40, 1.0)

FINGER_JOINT_EFFORT = 5.0  # N·m; informative only (the plant sets motor forces itself)
FINGER_JOINT_VELOCITY = 10.0  # rad/s; informative only
JOINT_DAMPING = 0.002  # N·m·s/rad: small viscous loss in the finger bearings (our estimate)

JOINT_NAMES = (
    "f1_spread_joint",
    "f1_inner_joint",
    "f1_outer_joint",
    "f2_spread_joint",
    "f2_inner_joint",
    "f2_outer_joint",
    "f3_inner_joint",
    "f3_outer_joint",
)
TIP_LINK_NAMES = ("f1_tip", "f2_tip", "f3_tip")
# Link pairs whose contact is off (PyBullet already skips a link and its parent). Each inner link
# leaves its knuckle housing through a slot above the palm face, so it cannot meet the palm; the
# knuckle housings are parts of the palm, kept apart by the spread's stops (at full spread they are
# 0.4 mm apart). An outer link meets the palm only with its end, when the finger closes onto the
# palm face (§8: CT at the palm surface): the palm stop (palm_stop) holds it there as a joint limit,
# which costs PyBullet far less than a contact between two links of the hand (25 % of the grasp env's
# time). Everything else touches as on the hand: fingers meet each other (§9.6) and every link objects.
NO_CONTACT_PAIRS = (
    ("palm", "f1_inner"), ("palm", "f2_inner"), ("palm", "f3_inner"),
    ("palm", "f1_outer"), ("palm", "f2_outer"), ("palm", "f3_outer"),  # the palm stop instead: palm_stop()
    ("f1_knuckle", "f2_knuckle"), ("f1_knuckle", "f3_knuckle"), ("f2_knuckle", "f3_knuckle"),
)


def _fmt(value: float) -> str:
    text = f"{value:.9g}"
    return "0" if text == "-0" else text


def _vec(values) -> str:
    return " ".join(_fmt(v) for v in values)


def _rpy(rotation: np.ndarray) -> tuple[float, float, float]:
    """URDF roll-pitch-yaw (R = Rz(yaw)·Ry(pitch)·Rx(roll)) of a rotation matrix."""
    pitch = atan2(-rotation[2, 0], sqrt(rotation[0, 0] ** 2 + rotation[1, 0] ** 2))
    if abs(abs(pitch) - pi / 2) < 1e-9:  # gimbal lock: fold yaw into roll
        return atan2(-rotation[1, 2], rotation[1, 1]), pitch, 0.0
    return atan2(rotation[2, 1], rotation[2, 2]), pitch, atan2(rotation[1, 0], rotation[0, 0])


def _origin(transform: np.ndarray) -> str:
    return f'<origin xyz="{_vec(transform[:3, 3])}" rpy="{_vec(_rpy(transform[:3, :3]))}"/>'


def _box_inertia(mass: float, size) -> tuple[float, float, float]:
    x, y, z = size
    return mass * (y * y + z * z) / 12.0, mass * (x * x + z * z) / 12.0, mass * (x * x + y * y) / 12.0


def _cylinder_inertia(mass: float, radius: float, length: float) -> tuple[float, float, float]:
    side = mass * (3.0 * radius * radius + length * length) / 12.0
    return side, side, mass * radius * radius / 2.0


def _inertial(mass: float, center, diagonal) -> str:
    ixx, iyy, izz = diagonal
    return (
        f'    <inertial>\n      <origin xyz="{_vec(center)}" rpy="0 0 0"/>\n'
        f'      <mass value="{_fmt(mass)}"/>\n'
        f'      <inertia ixx="{_fmt(ixx)}" ixy="0" ixz="0" iyy="{_fmt(iyy)}" iyz="0" izz="{_fmt(izz)}"/>\n'
        f"    </inertial>\n"
    )


def _shape(geometry: str, center, rgba, rpy=(0.0, 0.0, 0.0)) -> str:
    origin = f'<origin xyz="{_vec(center)}" rpy="{_vec(rpy)}"/>'
    return (
        f"    <visual>\n      {origin}\n      <geometry>{geometry}</geometry>\n"
        f'      <material name="c{_vec(rgba).replace(" ", "_")}"><color rgba="{_vec(rgba)}"/></material>\n'
        f"    </visual>\n"
        f"    <collision>\n      {origin}\n      <geometry>{geometry}</geometry>\n    </collision>\n"
    )


def _box(extent_min, extent_max, rgba) -> tuple[str, np.ndarray, np.ndarray]:
    lo, hi = np.asarray(extent_min, float), np.asarray(extent_max, float)
    size, center = hi - lo, (hi + lo) / 2.0
    return _shape(f'<box size="{_vec(size)}"/>', center, rgba), size, center


def _palm_link() -> str:
    length = PALM_TOP
    center = (0.0, 0.0, length / 2.0)
    body = _shape(f'<cylinder radius="{_fmt(PALM_RADIUS)}" length="{_fmt(length)}"/>', center, PALM_RGBA)
    inertia = _cylinder_inertia(PALM_MASS, PALM_RADIUS, length)
    return f'  <link name="palm">\n{_inertial(PALM_MASS, center, inertia)}{body}  </link>\n'


def _knuckle_link(name: str, spreads: bool) -> str:
    start, end, top = SPREAD_KNUCKLE if spreads else FIXED_KNUCKLE
    half = KNUCKLE_WIDTH / 2.0
    shape, size, center = _box((start, -half, -KNUCKLE_BELOW), (end, half, top), KNUCKLE_RGBA)
    return f'  <link name="{name}">\n{_inertial(KNUCKLE_MASS, center, _box_inertia(KNUCKLE_MASS, size))}{shape}  </link>\n'


def _inner_link(name: str) -> str:
    half_w, half_t = FINGER_WIDTH / 2.0, INNER_HALF_THICKNESS
    shape, size, center = _box((INNER_START, -half_t, -half_w), (kin.A2 + INNER_PAST_OUTER_JOINT, half_t, half_w), LINK_RGBA)
    return f'  <link name="{name}">\n{_inertial(INNER_LINK_MASS, center, _box_inertia(INNER_LINK_MASS, size))}{shape}  </link>\n'


def _outer_link(name: str) -> str:
    """The outer link from its joint to the D-H tip: the pad is the plane y3 = D3 and the link ends at
    x3 = A3 (§9.5: {T} is the pad's end), so a finger at CT meets the palm face (§8). The pad's end is
    rounded with TIP_RADIUS; the back of the tip is rounded off (its full thickness), as the CAD's
    tapered tip is, so a closed finger sweeping with the spread clears F3's knuckle."""
    half_w, r, back = FINGER_WIDTH / 2.0, TIP_RADIUS, OUTER_HALF_THICKNESS
    heel = kin.A3 - back  # where the rounded back of the tip starts
    body, _, _ = _box((OUTER_START, -back, -half_w), (heel, kin.D3 - r, half_w), LINK_RGBA)
    pad, _, _ = _box((OUTER_START, kin.D3 - r, -half_w), (kin.A3 - r, kin.D3, half_w), LINK_RGBA)
    end, _, _ = _box((heel, 0.0, -half_w), (kin.A3, kin.D3 - r, half_w), LINK_RGBA)
    cylinder = '<cylinder radius="{}" length="{}"/>'
    corner = _shape(cylinder.format(_fmt(r), _fmt(FINGER_WIDTH)), (kin.A3 - r, kin.D3 - r, 0.0), TIP_RGBA)
    rounded = _shape(cylinder.format(_fmt(back), _fmt(FINGER_WIDTH)), (heel, 0.0, 0.0), TIP_RGBA)
    full = np.array([kin.A3 - OUTER_START, kin.D3 + back, FINGER_WIDTH])
    middle = np.array([(OUTER_START + kin.A3) / 2.0, (kin.D3 - back) / 2.0, 0.0])
    inertia = _inertial(OUTER_LINK_MASS, middle, _box_inertia(OUTER_LINK_MASS, full))
    return f'  <link name="{name}">\n{inertia}{body}{pad}{end}{corner}{rounded}  </link>\n'


def _tip_link(name: str) -> str:
    tiny = 1e-7  # kg·m², a point-like marker
    return f'  <link name="{name}">\n{_inertial(TIP_FRAME_MASS, (0.0, 0.0, 0.0), (tiny, tiny, tiny))}  </link>\n'


def _joint(name: str, kind: str, parent: str, child: str, transform: np.ndarray, axis=None, limits=None) -> str:
    text = f'  <joint name="{name}" type="{kind}">\n    <parent link="{parent}"/>\n    <child link="{child}"/>\n'
    text += f"    {_origin(transform)}\n"
    if axis is not None:
        text += f'    <axis xyz="{_vec(axis)}"/>\n'
    if limits is not None:
        lower, upper = limits
        text += (
            f'    <limit lower="{_fmt(lower)}" upper="{_fmt(upper)}" effort="{_fmt(FINGER_JOINT_EFFORT)}" '
            f'velocity="{_fmt(FINGER_JOINT_VELOCITY)}"/>\n'
            f'    <dynamics damping="{_fmt(JOINT_DAMPING)}" friction="0"/>\n'
        )
    return text + "  </joint>\n"


def generate_urdf() -> str:
    """The BH8-262 URDF text (deterministic: equal inputs give byte-identical output)."""
    parts = ['<?xml version="1.0"?>\n', "<!-- Generated by bh8_gym.hand_urdf from bh8_gym.kinematics. Do not edit. -->\n"]
    parts.append('<robot name="bh8_262">\n')
    parts.append(_palm_link())
    for finger in kin.FINGERS:
        prefix = f"f{finger}"
        rows = kin.dh_rows(finger, 0.0, 0.0, 0.0)
        # Joint 1: theta = r·Θk1 - (π/2)·j, so a fixed offset of -(π/2)·j and an axis of r·z.
        knuckle_transform = kin.dh_transform(*rows[0])
        parts.append(_knuckle_link(f"{prefix}_knuckle", kin.FINGER_R[finger] != 0))
        if kin.FINGER_R[finger] == 0:
            parts.append(_joint(f"{prefix}_knuckle_fixed", "fixed", "palm", f"{prefix}_knuckle", knuckle_transform))
        else:
            parts.append(
                _joint(
                    f"{prefix}_spread_joint", "revolute", "palm", f"{prefix}_knuckle", knuckle_transform,
                    axis=(0.0, 0.0, float(kin.FINGER_R[finger])), limits=kin.SPREAD_RANGE,
                )
            )
        # Joints 2 and 3: theta = Θ + Φ, fixed offset Φ, axis z. Tip: fixed.
        parts.append(_inner_link(f"{prefix}_inner"))
        parts.append(
            _joint(f"{prefix}_inner_joint", "revolute", f"{prefix}_knuckle", f"{prefix}_inner",
                   kin.dh_transform(*rows[1]), axis=(0.0, 0.0, 1.0), limits=kin.INNER_RANGE)
        )
        parts.append(_outer_link(f"{prefix}_outer"))
        parts.append(
            _joint(f"{prefix}_outer_joint", "revolute", f"{prefix}_inner", f"{prefix}_outer",
                   kin.dh_transform(*rows[2]), axis=(0.0, 0.0, 1.0), limits=kin.OUTER_RANGE)
        )
        parts.append(_tip_link(f"{prefix}_tip"))
        parts.append(_joint(f"{prefix}_tip_fixed", "fixed", f"{prefix}_outer", f"{prefix}_tip", kin.dh_transform(*rows[3])))
    parts.append("</robot>\n")
    return "".join(parts)


def _outer_outline() -> np.ndarray:
    """Points (x3, y3) and radii of the outer link's outline in its frame {3}: the corners of its
    boxes (radius 0) and its two end cylinders."""
    r, back = TIP_RADIUS, OUTER_HALF_THICKNESS
    heel = kin.A3 - back
    return np.array([
        (OUTER_START, -back, 0.0), (OUTER_START, kin.D3, 0.0), (heel, -back, 0.0), (kin.A3 - r, kin.D3, 0.0),
        (kin.A3 - r, kin.D3 - r, r), (heel, 0.0, back), (kin.A3, kin.D3 - r, 0.0), (kin.A3, 0.0, 0.0),
    ])


@functools.lru_cache(maxsize=None)
def palm_stop_table(start: float, step: float, count: int) -> tuple[float, ...]:
    """palm_stop at `count` inner angles from `start` in steps of `step` (rad), computed once a process."""
    return tuple(palm_stop(start + k * step) for k in range(count))


def palm_stop(inner: float) -> float:
    """The outer joint's angle (rad, relative to the inner link) at which the outer link's end meets
    the palm face when the inner link is at `inner` rad; the outer joint's upper limit if it never
    does. The same for every finger: each finger closes in its own plane square to the palm face."""
    outline = _outer_outline()
    low, high = kin.OUTER_RANGE

    def clearance(outer: float) -> float:
        frame = kin.link_frames(3, 0.0, inner, outer)[2]
        points = frame[:3, :3] @ np.column_stack((outline[:, 0], outline[:, 1], np.zeros(len(outline)))).T
        return float(np.min(points[2] + frame[2, 3] - outline[:, 2])) - PALM_TOP

    if clearance(high) >= 0.0:
        return high
    if clearance(low) < 0.0:
        return low
    for _ in range(40):  # bisection to far below a motor count
        middle = 0.5 * (low + high)
        low, high = (middle, high) if clearance(middle) >= 0.0 else (low, middle)
    return low


def default_output_path() -> Path:
    """assets/bh8_262.urdf in the source checkout."""
    return Path(__file__).resolve().parent.parent / "assets" / "bh8_262.urdf"


@functools.lru_cache(maxsize=1)
def urdf_bytes() -> bytes:
    """The generated URDF as bytes, made once per process: the plant has PyBullet load it from a file
    this process writes (`bh8_gym.pybullet_files`), never from a cache another process could change."""
    return generate_urdf().encode()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bh8_gym.hand_urdf", description=__doc__.splitlines()[0])
    parser.add_argument("--output", type=Path, default=default_output_path(), help="where to write (default: %(default)s)")
    args = parser.parse_args(argv)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(generate_urdf())
    print(args.output)
    return 0


if __name__ == "__main__":
    sys.exit(main())
