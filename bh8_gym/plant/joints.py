"""The plant's joints as its code indexes them, and the plant's own state of them.

The 8 hand joints in URDF order with the index tuples every part of the plant uses, their ranges,
the BH8-262's counts per radian and gear ratios (from `kinematics`), and `_PlantState`: what the
plant keeps besides PyBullet's state (drives, clutch, worm windows, heat, time), saved and
restored with it.
"""
from __future__ import annotations

import copy

import math
from dataclasses import dataclass, field, fields

from bh8_gym import kinematics as kin

NUM_JOINTS = 8  # URDF order: F1 spread/inner/outer, F2 spread/inner/outer, F3 inner/outer
INNER_INDEX = (1, 4, 6)  # positions of the finger joints in the 8-joint arrays
OUTER_INDEX = (2, 5, 7)
SPREAD_INDEX = (0, 3)
FINGER_JOINTS = ((0, 1, 2), (1, 4, 5), (2, 6, 7))  # (finger index, inner joint, outer joint)
WORM_JOINTS = (1, 2, 4, 5, 6, 7)  # the finger joints, each behind a worm
_THIRD = 1.0 / 3.0
_PALM_TABLE_STEP = 0.05 * math.pi / 180.0  # rad of inner link between entries of the palm-stop table
_IDLE_FORCE = 1e-9  # N·m: a joint motor that must not push (PyBullet skips a motor of force 0 and keeps
#   reporting its last torque)
_JOINT_RANGE_LOW = (kin.SPREAD_RANGE[0], kin.INNER_RANGE[0], kin.OUTER_RANGE[0]) * 2 + (kin.INNER_RANGE[0], kin.OUTER_RANGE[0])
_JOINT_RANGE_HIGH = (kin.SPREAD_RANGE[1], kin.INNER_RANGE[1], kin.OUTER_RANGE[1]) * 2 + (kin.INNER_RANGE[1], kin.OUTER_RANGE[1])

_DEG = math.pi / 180.0
INNER_COUNTS_PER_RAD = kin.INNER_COUNTS_PER_DEG_262 / _DEG
OUTER_ABS_COUNTS_PER_RAD = kin.OUTER_ABS_COUNTS_PER_DEG_262 / _DEG
SPREAD_COUNTS_PER_RAD = kin.SPREAD_COUNTS_PER_DEG_262 / _DEG
# Motor revolutions per joint revolution = counts per joint degree x 360 / (360 counts per motor rev).
INNER_GEAR_RATIO = kin.INNER_COUNTS_PER_DEG_262
OUTER_REL_GEAR_RATIO = kin.OUTER_REL_COUNTS_PER_DEG_262
OUTER_ABS_GEAR_RATIO = kin.OUTER_ABS_COUNTS_PER_DEG_262
SPREAD_GEAR_RATIO = kin.SPREAD_COUNTS_PER_DEG_262

# Bullet's btBroadphaseProxy collision filter groups, PyBullet's defaults for new bodies.
_DEFAULT_FILTER, _STATIC_FILTER, _ALL_FILTERS = 1, 2, -1


@dataclass(slots=True)  # slots: the step reads these fields many times per step
class _PlantState:
    """The plant's own state besides PyBullet's (saved and restored with it)."""

    time: float = 0.0
    temperature: float = 0.0
    drive_velocity: list = field(default_factory=lambda: [0.0] * 4)  # counts/s, clipped
    drive_fraction: list = field(default_factory=lambda: [0.0] * 4)
    drive_on: list = field(default_factory=lambda: [False] * 4)
    engaged: list = field(default_factory=lambda: [True] * 3)
    locked: list = field(default_factory=lambda: [True] * 3)  # unpowered: the worm holds the finger
    breakaway_counts: list = field(default_factory=lambda: [None] * 3)
    preload: list = field(default_factory=lambda: [0.0] * 3)  # N·m, set from params at construction
    closing_peak: list = field(default_factory=lambda: [0.0] * 3)  # rad/s, decaying
    opening_peak: list = field(default_factory=lambda: [0.0] * 3)
    # Joint states of the last step, as PyBullet reported them (replaced whole each step).
    positions: tuple = (0.0,) * NUM_JOINTS
    velocities: tuple = (0.0,) * NUM_JOINTS
    torques: tuple = (0.0,) * NUM_JOINTS  # what each joint motor applied
    outer_loads: tuple = (0.0,) * 3  # torque each outer joint transmits (motor and worm), + = against closing
    motor_torques: list = field(default_factory=lambda: [0.0] * 4)
    hold_positions: list = field(default_factory=lambda: [0.0] * NUM_JOINTS)  # where locked joints are held
    held: list = field(default_factory=lambda: [False] * NUM_JOINTS)
    latched_torque: list = field(default_factory=lambda: [0.0] * NUM_JOINTS)  # N·m a locked joint keeps pressing
    drive_capacity: list = field(default_factory=lambda: [0.0] * 3)  # N·m of last step's drive, + closing, 0 held
    at_stop: list = field(default_factory=lambda: [False] * 3)  # driven into a joint stop: stalled at full push
    # Where each finger joint may be (PyBullet joint limits): the worm's teeth (see PlantParameters.worm_slack).
    window_low: list = field(default_factory=lambda: list(_JOINT_RANGE_LOW))
    window_high: list = field(default_factory=lambda: list(_JOINT_RANGE_HIGH))
    # The joint motor commands of the last step (the next step's decisions depend on them).
    target_positions: list = field(default_factory=lambda: [0.0] * NUM_JOINTS)
    target_velocities: list = field(default_factory=lambda: [0.0] * NUM_JOINTS)
    forces: list = field(default_factory=lambda: [0.0] * NUM_JOINTS)
    position_gains: list = field(default_factory=lambda: [0.0] * NUM_JOINTS)
    wrist_target: tuple = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))

    def copy(self) -> "_PlantState":
        """A copy whose lists are its own (every restore of a saved state takes one)."""
        twin = copy.copy(self)
        for name in _STATE_FIELDS:
            value = getattr(self, name)
            if type(value) is list:
                setattr(twin, name, value.copy())
        return twin


_STATE_FIELDS = tuple(f.name for f in fields(_PlantState))
