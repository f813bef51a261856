"""The simulated BH8-262: a PyBullet world with the hand on a movable wrist, its drive train and sensors.

This is the hardware below the HCTL-1100 chips (docs/architecture.md, Contract 1): four motors
(1-3 fingers, 4 spread; positive motion closes), worm gears, the TorqueSwitch clutch, strain gauges
and heat. Sources: manual §9.3 (TorqueSwitch, spread), §9.4 (strain gauges), §9.5 Equations 4-5
(ratios), Table 7 (motors), §2 (temperature), App. A (speeds, mass); SPEC.md §1 and §8.

Drive-train model (one finger; docs/modelling.md tells the why and the numbers):
* The motor is a velocity source with a torque limit: `set_drive(m, counts_per_s, fraction)`.
* Worm drives: each finger joint has a window it cannot leave, set as PyBullet joint limits. An
  unpowered joint's window is where it stopped; a driven joint's back edge follows the furthest
  position its drive reached (`worm_slack` behind, moved lazily), its front edge is its stop, or the
  palm (`hand_urdf.palm_stop`: a closed fingertip rests on the palm face). A load helping the motion
  cannot make it run faster than its motor turns (`overrun_brake_torque`). The encoder of a locked
  finger reads its hold position (the worm holds the motor shaft).
* Clutch engaged: the inner joint turns at M/125 degrees and the outer joint (relative to the inner
  link) at M/375, so the outer link's angle to the palm is always M/93.75 (SPEC §1): the motor
  position reported is 93.75 x that angle. Both joints are driven; their targets are corrected
  towards the exact 3:1 relation every step (`coupling_rate`) and neither leads the other by more
  than three worm slacks, so a blocked link stops the whole finger (a joint its partner holds back
  is held there by its window's front edge, not by a zero velocity target alone); the motor's torque
  budget is shared: inner torque + outer torque / 3 <= fraction x peak x 125 x efficiency.
* TorqueSwitch: while closing, the torque the clutch passes to the inner link (its share of the
  motor torque plus the rotor's impact when the link is stopped suddenly, unless the outer link took
  the blow, App. B A1) above `breakaway_base_torque + breakaway_preload_slope x preload` disengages
  the clutch: the inner link locks where it is and the motor drives the outer link alone at
  M/93.75 degrees. Opening re-engages it at the breakaway position. The preload is the peak clutch
  torque of the last drive against the open stop, up to `preload_limit`; backing off the stop
  (`back_off_stop`, HI's IOFF) unwinds part of it; a breakaway resets it to zero.
* A finger that locks while its drive squeezes an object keeps pressing with the latched torque
  (elastic wind-up, at most `lock_elastic_travel` further closed, never opening), so a grasp
  survives HOLD 0 (§9.3.1, FAQ A1).
* The spread is back-drivable: unpowered it has only `spread_friction_torque`; F1 and F2 spread
  symmetrically (a gear constraint couples them).
* Contact: friction anchors on the hand's links (no creep of a held object), split impulse off.
* `set_parameters` applies new PlantParameters to a live plant (domain randomisation).
* Strain gauge = offset + gain x the torque the outer joint transmits, 8 bits. Heat: electronics +
  sum (torque/Km)^2.
"""
from __future__ import annotations

import math
from bisect import bisect_left
from dataclasses import dataclass, field, fields, replace

import numpy as np
import pybullet as p

from bh8_gym import hand_urdf
from bh8_gym import kinematics as kin
from bh8_gym.protocol import MOTORS
from bh8_gym.rendering import display_available
from bh8_gym.settings import dataclass_from, matches_annotation

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


class PlantError(ValueError):
    """A bad argument to the plant's API (names the offending value)."""


class DisplayUnavailableError(RuntimeError):
    """gui=True (render_mode="human", `bh8 serve --gui`) on a machine without a display."""


@dataclass
class PlantParameters:
    """Physical constants of the simulated hand and world; the domain-randomisation knobs.

    Values the documents give cite them; the others are our estimates, each with its reason.
    """

    # Physics.
    time_step: float = 0.002  # s; 500 Hz keeps contact stable with the light finger links (<= 2 ms)
    solver_iterations: int = 50  # PyBullet's default
    # The solver stops early once an iteration changes the impulses by less than this (PyBullet's
    # solverResidualThreshold, default 1e-7): 8 % of the grasp env's time, the same holds in bench_hold.
    solver_residual_threshold: float = 1e-4
    gravity: float = 9.81  # m/s^2

    # Motors (Table 7) and gears.
    motor_peak_torque: float = 0.05  # N·m: Table 7, 5 N·cm
    motor_constant: float = 0.0083  # N·m/sqrt(W): Table 7, 0.83 N·cm/sqrt(W)
    motor_no_load_speed: float = 54_000.0  # counts/s (150 rev/s): above App. A's need (MCV 100 = 24,400/s)
    finger_drive_efficiency: float = 0.4  # worm + cable drive (self-locking worms run below 50 %)
    spread_drive_efficiency: float = 0.7  # spur gears of the back-drivable spread
    worm_lock_torque: float = 40.0  # N·m at a joint: a self-locking worm holds any realistic load
    spread_friction_torque: float = 0.03  # N·m per spread joint, unpowered (back-drivable, §9.3.2)
    coupling_rate: float = 250.0  # 1/s: how fast joint targets pull the 3:1 relation back (stiff gearing)
    # Share of the finger drive's torque the outer joint keeps when the inner one takes the load
    # (stalled, engaged; the inner keeps 5 %): a rigid gear train splits the load by contact geometry,
    # which rigid PyBullet contacts do not resolve. 6.5 % keeps a fingertip pressing (§5.5 HSG) after the
    # inner link touched first, yet leaves the inner enough torque to break away (§9.3.1).
    coupled_torque_floor: float = 0.065
    lock_position_gain: float = 0.2  # PyBullet position gain that holds the spread at a stop it is driven into
    # A worm is not back-drivable: a load cannot turn a finger joint against its drive, nor turn an
    # unpowered one at all. Each finger joint has a window it may not leave (PyBullet joint limits, hard
    # as the worm's teeth): a driven joint cannot go back more than this (to twice this, as the window
    # is moved lazily) behind the furthest position its drive has reached; an unpowered one stays where
    # it stopped. The slack is the drive train's compliance (gear backlash, cable and link elasticity),
    # and it keeps the limits out of the solver until a load pushes against the worm: with none, the
    # grasp env steps 14 % slower (callgrind).
    worm_slack: float = 0.05 * _DEG
    # Nor can a load helping the motion make a finger joint run faster than the motor turns it. A joint
    # within this fraction of its target speed (or faster) is braked at its target speed unless its
    # motor has to push at its limit.
    overrun_tolerance: float = 0.02
    # N·m at a joint available to brake an overrunning joint. Physically the worm's lock torque, but a
    # PyBullet motor's limit is symmetric: the brake also pushes forward until the next step notices a
    # stop or an object. The full motor torque at the inner joint (0.05 x 125 x 0.4) is far above the
    # aiding loads (finger weight about 0.05 N·m) and no more than the motor itself could push.
    overrun_brake_torque: float = 0.3
    # Squeeze kept by a locked finger (§9.3.1, FAQ A1: the grasp stays with the motor current removed).
    # The finger links and cable are elastic: a drive stalled against a load winds them up, and the
    # self-locking worm keeps that load when it locks. Our estimate of the elastic travel: about 1° at
    # a joint under full motor torque (aluminium links, steel cable).
    lock_elastic_travel: float = 1.0 * _DEG  # rad of closing travel allowed beyond the hold position
    # A drive pushing at this fraction of its torque limit or more is stalled against a load (not just
    # moving the link), so its torque is latched when the finger locks.
    squeeze_latch_fraction: float = 0.5

    # TorqueSwitch (SPEC §8: our choice, documented in the module docstring).
    breakaway_base_torque: float = 0.25  # N·m at the inner joint with no preload (10 % of full motor torque)
    breakaway_preload_slope: float = 1.0  # §9.3.1: loosening torque equals tightening torque (screw)
    # N·m per rad/s of inner-link speed lost at impact: the rotor's inertia reflected through 125:1
    # against the drive's compliance (a 1e-6 kg·m² rotor, 125², 50 N·m/rad: about 0.9). With
    # preload_limit it puts the breakaway of a C against a blocked inner link, after a default HI, at
    # MCV 37.5: from MCV 40 up it breaks away, at 35 it does not (manual §8 troubleshooting: "The close
    # velocity is too slow. Increase the close velocity greater than or equal to 40").
    rotor_impact_gain: float = 1.0
    impact_memory_time: float = 0.5  # s: the decay of the inner link's remembered speed, what an impact loses
    # N·m on the outer joint when the finger stops: from none to this much, less and less of the
    # rotor's impact reaches the clutch (App. B A1: a fingertip that makes first contact stalls the
    # finger; only an inner link that does breaks away). A finger stopped at its inner link carries
    # about 0.01 N·m there, one stopped at its fingertip about 0.85 (measured at MCV 100).
    tip_impact_load: float = 0.3
    stop_tolerance: float = 0.05 * _DEG  # rad: a joint this close to its limit is against its stop
    initial_preload: float = 3.47  # N·m: the hand starts as a default HI leaves it (0.9 x preload_limit)
    # §5.3.4 IOFF: "Larger values result in less compression of the Belleville washer ... its true range
    # of useful values is from 0 to approximately 500". Backing off the open stop (HI's move to 0 closes
    # IOFF counts) unwinds the preload linearly over this many counts (`back_off_stop`).
    preload_release_counts: float = 500.0
    # N·m: the most the Belleville washers take. Their force is nearly flat over their working travel
    # (the reason for Belleville springs), so slamming the finger open harder than HI does (IVEL 300)
    # preloads no more.
    preload_limit: float = 3.86

    # Strain gauges (§9.4, SPEC §1).
    strain_gain: float = 100.0  # counts per N·m about the outer joint: Figure 28 plots ΔSG -100..100 over -1..1 N·m
    strain_offsets: tuple[int, int, int] | None = None  # no-load values; None: seeded in 100..140

    # Thermal (§2: the hand runs at 40-60 °C).
    ambient_temperature: float = 22.0  # °C, a lab
    electronics_power: float = 8.0  # W dissipated by the CPU and power boards at idle (estimate)
    thermal_resistance: float = 2.9  # K/W to ambient: idle steady state 22 + 8 x 2.9 = 45 °C
    heat_capacity: float = 1000.0  # J/K: 1.18 kg of mostly aluminium (900 J/kg/K)
    initial_temperature: float | None = None  # °C; None: the idle steady state

    # Contact.
    finger_friction: float = 0.8  # finger links on typical objects (aluminium/rubber-ish pads)
    palm_friction: float = 0.6
    table_friction: float = 0.6
    object_friction: float = 0.7  # default of an object placed by hand (bh8_gym.objects.add_object)
    # Static friction that holds: PyBullet's friction anchors keep a sticking contact's anchor point, so
    # a held object does not creep through solver error (without them a worm-locked grasp slipped 9 mm
    # and turned 33° in 5 s).
    friction_anchors: bool = True
    # m: PyBullet's torsional friction (torque per newton of normal force) of the finger links' contacts.
    # The rubber pads are areas, not points (a 4 mm patch at friction 0.8 resists about 0.002 N·m per N),
    # but with friction anchors a pinched object does not turn about the line between its contacts
    # anyway (benchmarks/bench_hold.py), and each torsional row costs 12 % of the grasp env's speed: off.
    finger_spinning_friction: float = 0.0
    link_mass_scale: float = 1.0  # scales every hand link's mass (randomisation)

    # World.
    table: bool = True  # a table whose top is the plane z = 0
    wrist_position: tuple[float, float, float] = (0.0, 0.0, 0.30)  # m: initial arm flange
    wrist_orientation: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)  # palm down (xyzw)
    wrist_max_force: float = 2000.0  # N: the arm is much stronger than the hand

    @classmethod
    def from_overrides(cls, overrides) -> "PlantParameters":
        """The defaults with some fields replaced: `overrides` is a PlantParameters (returned as it
        is) or a mapping of field names to values, as a TOML config or JSON env kwargs give them."""
        params = dataclass_from(cls, overrides, "plant parameters", error=PlantError)
        params.validate()
        return params

    def validate(self) -> None:
        for item in fields(self):
            value = getattr(self, item.name)
            if not matches_annotation(item.type, value):
                raise PlantError(f"{item.name} must be {item.type}, got {value!r}")
        if not 0.0 < self.time_step <= 0.002:
            raise PlantError(f"time_step must be in (0, 0.002] s, got {self.time_step!r}")
        if self.solver_iterations < 1:
            raise PlantError(f"solver_iterations must be at least 1, got {self.solver_iterations!r}")
        if not self.solver_residual_threshold >= 0.0:
            raise PlantError(f"solver_residual_threshold must be >= 0, got {self.solver_residual_threshold!r}")
        if not self.preload_release_counts > 0.0:
            raise PlantError(f"preload_release_counts must be > 0, got {self.preload_release_counts!r}")
        if not self.worm_slack >= 0.0:
            raise PlantError(f"worm_slack must be >= 0, got {self.worm_slack!r}")


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
    previous_positions: tuple = (0.0,) * NUM_JOINTS
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
        return replace(self, **{f.name: list(getattr(self, f.name)) for f in fields(self) if isinstance(getattr(self, f.name), list)})


class HandPlant:
    """The BH8-262 in PyBullet (Contract 1 in docs/architecture.md)."""

    def __init__(self, params: PlantParameters | None = None, seed: int = 0, gui: bool = False):
        self.params = params = replace(params) if params is not None else PlantParameters()
        params.validate()
        self._rng = np.random.default_rng(seed)
        if gui and not display_available():
            raise DisplayUnavailableError("gui=True needs a display and DISPLAY is not set (a headless machine): "
                                          "use gui=False / render_mode='rgb_array', or run under xvfb-run")
        self._client = p.connect(p.GUI if gui else p.DIRECT)
        if self._client < 0:
            raise RuntimeError("PyBullet could not connect (gui=True needs a display)")
        self._saved: dict[int, _PlantState] = {}
        try:
            self._build_world()
        except Exception:
            p.disconnect(self._client)
            raise

    # ---------------------------------------------------------------- construction
    def _build_world(self) -> None:
        prm, cid = self.params, self._client
        self.dt = prm.time_step
        p.setTimeStep(self.dt, physicsClientId=cid)
        p.setGravity(0.0, 0.0, -prm.gravity, physicsClientId=cid)
        # Split impulse off: with it PyBullet never corrects a joint-limit violation deeper than 0.04 rad
        # (the worm's windows), only stops it growing; contacts are shallower than its threshold anyway.
        p.setPhysicsEngineParameter(numSolverIterations=prm.solver_iterations, deterministicOverlappingPairs=1,
                                    useSplitImpulse=0, physicsClientId=cid)
        self.table_id = self._make_table() if prm.table else None
        position, orientation = tuple(prm.wrist_position), tuple(prm.wrist_orientation)
        # Implicit cylinders: URDF cylinders otherwise load as polygonal hulls, whose facets make a
        # rolling contact (palm face, fingertips) jump.
        flags = p.URDF_USE_SELF_COLLISION | p.URDF_USE_INERTIA_FROM_FILE | p.URDF_USE_IMPLICIT_CYLINDER
        self.hand_id = p.loadURDF(str(hand_urdf.cached_urdf_path()), position, orientation, flags=flags, physicsClientId=cid)
        self._joint_index_by_name = {}
        self._link_index_by_name = {"palm": -1}
        for index in range(p.getNumJoints(self.hand_id, physicsClientId=cid)):
            info = p.getJointInfo(self.hand_id, index, physicsClientId=cid)
            self._joint_index_by_name[info[1].decode()] = index
            self._link_index_by_name[info[12].decode()] = index
        for first, second in hand_urdf.NO_CONTACT_PAIRS:
            p.setCollisionFilterPair(self.hand_id, self.hand_id, self._link_index_by_name[first],
                                     self._link_index_by_name[second], 0, physicsClientId=cid)
        self.joint_names = hand_urdf.JOINT_NAMES
        self.joint_indices = [self._joint_index_by_name[name] for name in self.joint_names]
        self.tip_link_indices = [self._link_index_by_name[name] for name in hand_urdf.TIP_LINK_NAMES]
        # Every joint motor off first (PyBullet enables velocity motors by default).
        all_joints = list(range(p.getNumJoints(self.hand_id, physicsClientId=cid)))
        p.setJointMotorControlArray(self.hand_id, all_joints, p.VELOCITY_CONTROL, forces=[0.0] * len(all_joints), physicsClientId=cid)
        self._links = [-1] + all_joints
        # Where a closing outer link meets the palm, against the inner link's angle (hand_urdf.palm_stop):
        # from 120° (it never does below) to the inner stop, as plain floats for the per-step path.
        self._palm_table_start = math.radians(120.0)
        count = int(round((kin.INNER_RANGE[1] - self._palm_table_start) / _PALM_TABLE_STEP)) + 1
        self._palm_table = hand_urdf.palm_stop_table(self._palm_table_start, _PALM_TABLE_STEP, count)
        self._palm_table_descending = [-value for value in self._palm_table]  # ascending, for bisect
        # The strain gauges measure the torque the outer joints transmit (§9.4), motor and worm together.
        for outer in OUTER_INDEX:
            p.enableJointForceTorqueSensor(self.hand_id, self.joint_indices[outer], True, physicsClientId=cid)
        self._sent_windows = {}  # joint -> (low, high) last sent to PyBullet
        self._unit_masses = [p.getDynamicsInfo(self.hand_id, link, physicsClientId=cid)[0] for link in self._links]
        self._com_offset = p.getDynamicsInfo(self.hand_id, -1, physicsClientId=cid)[3]
        # F1 and F2 spread through one motor: a gear constraint keeps their angles equal.
        self._spread_gear = p.createConstraint(
            self.hand_id, self.joint_indices[0], self.hand_id, self.joint_indices[3], p.JOINT_GEAR,
            [0, 0, 1], [0, 0, 0], [0, 0, 0], physicsClientId=cid,
        )
        # The arm flange: a fixed constraint whose world pose set_wrist_pose moves.
        self._wrist_constraint = p.createConstraint(
            self.hand_id, -1, -1, -1, p.JOINT_FIXED, [0, 0, 0],
            parentFramePosition=[-c for c in self._com_offset], childFramePosition=position,
            childFrameOrientation=orientation, physicsClientId=cid,
        )
        self._velocity_gains = [1.0] * NUM_JOINTS
        self._sent_command = None  # the joint motor command last sent to PyBullet (resent only on change)
        self._apply_parameters()
        idle = prm.ambient_temperature + prm.electronics_power * prm.thermal_resistance
        self._state = _PlantState(
            temperature=idle if prm.initial_temperature is None else float(prm.initial_temperature),
            wrist_target=(position, orientation),
            preload=[float(prm.initial_preload)] * 3,
        )
        self._read_joints()
        for joint in WORM_JOINTS:  # unpowered: the worms hold the fingers where they are
            self._hold(joint)

    def _apply_parameters(self) -> None:
        """Push `self.params` into PyBullet and derive the per-step constants (plain floats)."""
        prm, cid, hand = self.params, self._client, self.hand_id
        p.setGravity(0.0, 0.0, -prm.gravity, physicsClientId=cid)
        p.setPhysicsEngineParameter(numSolverIterations=prm.solver_iterations,
                                    solverResidualThreshold=prm.solver_residual_threshold, physicsClientId=cid)
        for link, unit_mass in zip(self._links, self._unit_masses):
            friction = prm.palm_friction if link == -1 else prm.finger_friction
            spinning = 0.0 if link == -1 else prm.finger_spinning_friction
            p.changeDynamics(hand, link, lateralFriction=friction, mass=unit_mass * prm.link_mass_scale,
                             spinningFriction=spinning, frictionAnchor=int(prm.friction_anchors), physicsClientId=cid)
        if self.table_id is not None:
            p.changeDynamics(self.table_id, -1, lateralFriction=prm.table_friction, physicsClientId=cid)
        p.changeConstraint(self._spread_gear, gearRatio=-1.0, maxForce=prm.worm_lock_torque, erp=0.2, physicsClientId=cid)
        p.changeConstraint(self._wrist_constraint, maxForce=prm.wrist_max_force, physicsClientId=cid)
        if prm.strain_offsets is None:
            if getattr(self, "strain_offsets", None) is None:
                self.strain_offsets = tuple(int(v) for v in self._rng.integers(100, 141, size=3))
        else:
            self.strain_offsets = tuple(int(v) for v in prm.strain_offsets)
        self._finger_capacity = prm.motor_peak_torque * INNER_GEAR_RATIO * prm.finger_drive_efficiency  # N·m, inner joint
        self._outer_capacity = prm.motor_peak_torque * OUTER_ABS_GEAR_RATIO * prm.finger_drive_efficiency  # after breakaway
        self._spread_capacity = prm.motor_peak_torque * SPREAD_GEAR_RATIO * prm.spread_drive_efficiency
        self._spread_torque_scale = 1.0 / (SPREAD_GEAR_RATIO * prm.spread_drive_efficiency)
        self._inner_torque_scale = 1.0 / (INNER_GEAR_RATIO * prm.finger_drive_efficiency)
        self._outer_torque_scale = 1.0 / (OUTER_ABS_GEAR_RATIO * prm.finger_drive_efficiency)
        self._impact_decay = math.exp(-self.dt / prm.impact_memory_time)
        stop = prm.stop_tolerance
        self._inner_open, self._inner_closed = kin.INNER_RANGE[0] + stop, kin.INNER_RANGE[1] - stop
        self._outer_open, self._outer_closed = kin.OUTER_RANGE[0] + stop, kin.OUTER_RANGE[1] - stop
        self._spread_low, self._spread_high = kin.SPREAD_RANGE
        self._joint_low, self._joint_high = _JOINT_RANGE_LOW, _JOINT_RANGE_HIGH
        self._slack = prm.worm_slack
        self._coupling_play = 3.0 * prm.worm_slack  # rad of inner-link lead (q2 - 3 q3) the gears allow
        self._held_back_speed = prm.worm_slack / self.dt  # rad/s: a coupled joint with less room is held back
        self._spread_low_stop, self._spread_high_stop = self._spread_low + stop, self._spread_high - stop
        self._brake_torque = prm.overrun_brake_torque
        self._speed_limit = prm.motor_no_load_speed
        self._overrun_speed_fraction = 1.0 - prm.overrun_tolerance
        self._half_coupling_rate = 0.5 * prm.coupling_rate
        self._torque_floor_fraction = prm.coupled_torque_floor
        self._sent_command = None

    def set_parameters(self, params: PlantParameters) -> None:
        """Apply new PlantParameters to the live plant (domain randomisation between episodes).

        Frictions, masses, motor strength, drive efficiencies, TorqueSwitch, strain gauges (gain and
        offsets; offsets None keeps the current ones), thermal constants, gravity and solver
        iterations take effect from the next step. The state (joint angles, clutch, preload, heat)
        is kept; construction-only fields (time_step, table, wrist_position/orientation,
        initial_temperature, initial_preload) must equal the current ones.
        """
        if not isinstance(params, PlantParameters):
            raise PlantError(f"set_parameters needs PlantParameters, got {params!r}")
        params = replace(params)
        params.validate()
        for name in ("time_step", "table", "wrist_position", "wrist_orientation", "initial_temperature", "initial_preload"):
            new, old = getattr(params, name), getattr(self.params, name)
            if new != old and not (isinstance(new, tuple) and tuple(new) == tuple(old)):
                raise PlantError(f"{name} is fixed at construction ({old!r}); set_parameters got {new!r}")
        self.params = params
        self._apply_parameters()

    def _make_table(self) -> int:
        cid = self._client
        half = (1.0, 1.0, 0.02)
        collision = p.createCollisionShape(p.GEOM_BOX, halfExtents=half, physicsClientId=cid)
        visual = p.createVisualShape(p.GEOM_BOX, halfExtents=half, rgbaColor=(0.62, 0.47, 0.32, 1.0), physicsClientId=cid)
        body = p.createMultiBody(0.0, collision, visual, basePosition=(0.0, 0.0, -half[2]), physicsClientId=cid)
        p.changeDynamics(body, -1, lateralFriction=self.params.table_friction, physicsClientId=cid)
        return body

    # ---------------------------------------------------------------- properties
    @property
    def time(self) -> float:
        """Simulated seconds since construction."""
        return self._state.time

    @property
    def temperature(self) -> float:
        """Hand temperature, °C (lumped thermal mass)."""
        return self._state.temperature

    @property
    def client(self) -> int:
        """The PyBullet physics client id (for callers adding their own bodies or queries)."""
        return self._client

    # ---------------------------------------------------------------- drives
    def _check_motor(self, motor) -> int:
        if motor not in MOTORS or isinstance(motor, bool):
            raise PlantError(f"motor must be 1, 2, 3 or 4, got {motor!r}")
        return int(motor)

    def set_drive(self, motor: int, velocity: float, torque_fraction: float) -> None:
        """Power `motor`: drive towards `velocity` counts/s (+ closes) with at most torque_fraction x peak."""
        index = self._check_motor(motor) - 1
        velocity, torque_fraction = float(velocity), float(torque_fraction)
        if not math.isfinite(velocity):
            raise PlantError(f"velocity must be finite, got {velocity!r}")
        if not 0.0 <= torque_fraction <= 1.0:
            raise PlantError(f"torque_fraction must be in [0, 1], got {torque_fraction!r}")
        limit = self.params.motor_no_load_speed
        state = self._state
        state.drive_velocity[index] = min(max(velocity, -limit), limit)
        state.drive_fraction[index] = torque_fraction
        state.drive_on[index] = True

    def set_drive_off(self, motor: int) -> None:
        """Unpower `motor`: finger worm drives self-lock; the spread is back-drivable."""
        index = self._check_motor(motor) - 1
        self._state.drive_on[index] = False
        self._state.drive_velocity[index] = 0.0
        self._state.drive_fraction[index] = 0.0

    def set_drives(self, velocities, torque_fractions) -> None:
        """All four motors at once. A NaN torque fraction turns that motor off."""
        if len(velocities) != 4 or len(torque_fractions) != 4:
            raise PlantError(f"set_drives needs 4 velocities and 4 torque fractions, got {velocities!r}, {torque_fractions!r}")
        for index in 0, 1, 2, 3:
            velocity, fraction = velocities[index], torque_fractions[index]
            if fraction == fraction and (not 0.0 <= fraction <= 1.0 or not math.isfinite(velocity)):
                raise PlantError(f"motor {index + 1}: velocity {velocity!r} must be finite and torque fraction {fraction!r} in [0, 1]")
        fractions = [float(fraction) for fraction in torque_fractions]
        # the velocity of a motor turned off is not looked at
        self._store_drives([float(v) if f == f else 0.0 for v, f in zip(velocities, fractions)], fractions)

    def step_with_drives(self, velocities: list[float], torque_fractions: list[float]) -> tuple[list[float], list[float]]:
        """The firmware's per-physics-step path: `set_drives` without its checks (the HCTL emulation
        gives finite floats, fractions in [0, 1] or NaN for off), `step`, then `motor_state_lists()`."""
        self._store_drives(velocities, torque_fractions)
        self.step()
        return self.motor_state_lists()

    def _store_drives(self, velocities: list[float], torque_fractions: list[float]) -> None:
        state, limit = self._state, self._speed_limit
        drive_on, drive_velocity, drive_fraction = state.drive_on, state.drive_velocity, state.drive_fraction
        for index in 0, 1, 2, 3:
            fraction = torque_fractions[index]
            if fraction != fraction:  # NaN: off
                drive_on[index] = False
                drive_velocity[index] = drive_fraction[index] = 0.0
            else:
                velocity = velocities[index]
                drive_velocity[index] = limit if velocity > limit else (-limit if velocity < -limit else velocity)
                drive_fraction[index] = fraction
                drive_on[index] = True

    # ---------------------------------------------------------------- stepping
    def step(self) -> None:
        """Advance one physics step of `dt` seconds."""
        self._command_joints()
        state = self._state
        client = self._client
        command = (state.target_positions, state.target_velocities, state.forces, state.position_gains)
        if command != self._sent_command:
            # POSITION_CONTROL with position gain 0 is a pure velocity motor (the spread driven into a
            # stop gets a gain to hold the stop).
            # Positional arguments (targetPositions, targetVelocities, forces, positionGains,
            # velocityGains, physicsClientId): PyBullet parses keywords 0.4 µs slower, every step.
            p.setJointMotorControlArray(self.hand_id, self.joint_indices, p.POSITION_CONTROL, *command,
                                        self._velocity_gains, client)
            self._sent_command = tuple(map(list, command))  # copies: the state lists are updated in place
        sent, low, high = self._sent_windows, state.window_low, state.window_high
        for joint in WORM_JOINTS:
            window = (low[joint], high[joint])
            if sent.get(joint) != window:
                p.changeDynamics(self.hand_id, self.joint_indices[joint], jointLowerLimit=window[0],
                                 jointUpperLimit=window[1], physicsClientId=client)
                sent[joint] = window
        p.stepSimulation(physicsClientId=client)
        self._read_joints()
        self._update_after_step()

    def _read_joints(self) -> None:
        """Joint positions, velocities, applied torques and the outer joints' transmitted torques."""
        state = self._state
        joints = p.getJointStates(self.hand_id, self.joint_indices, self._client)  # (body, joints, physicsClientId)
        state.previous_positions = state.positions
        state.positions, state.velocities, reactions, state.torques = zip(*joints)
        # The sensor gives the load the joint carries about its axis (z); a load against closing is +.
        state.outer_loads = (-reactions[2][5], -reactions[5][5], -reactions[7][5])

    def _hold(self, joint: int, latch: float = 0.0) -> None:
        """Lock `joint` (worm self-locking) where it is now, if it is not held already.

        A joint locked with a `latch` torque (its drive was pushing a load closing) keeps pressing with
        it (the elastic wind-up of link and cable), at most `lock_elastic_travel` beyond the hold
        position; it never opens more than the worm's slack below it.
        """
        state, prm = self._state, self.params
        if state.held[joint]:
            return
        state.held[joint] = True
        position = state.positions[joint]
        # Within the joint's range: a link bouncing past a stop (PyBullet's soft limit) is held at it.
        low, high = self._joint_low[joint], self._joint_high[joint]
        position = low if position < low else (high if position > high else position)
        state.hold_positions[joint] = state.target_positions[joint] = position
        state.latched_torque[joint] = latch
        state.position_gains[joint] = 0.0
        # No slack: a limit acts only once a joint is at it, and a light link under a sudden load
        # would cross a slack in one step.
        above = position + prm.lock_elastic_travel if latch > 0.0 else position
        state.window_low[joint] = position
        state.window_high[joint] = above if above < high else high
        if latch > 0.0:
            state.target_velocities[joint], state.forces[joint] = prm.lock_elastic_travel / self.dt, latch
        else:
            state.target_velocities[joint], state.forces[joint] = 0.0, _IDLE_FORCE

    def _squeeze(self, f: int, load: float) -> bool:
        """True if finger f's drive was pushing `load` (N·m, reflected to its joint) closing at its limit."""
        capacity = self._state.drive_capacity[f]
        return capacity > 0.0 and load >= self.params.squeeze_latch_fraction * capacity

    def _drive(self, joint: int, target: float, force: float) -> None:
        state = self._state
        state.held[joint] = False
        state.target_velocities[joint] = target
        state.forces[joint] = force
        state.position_gains[joint] = 0.0

    def _drive_worm(self, joint: int, target: float, force: float, sign: float, high: float | None = None,
                    low: float | None = None) -> None:
        """Drive a finger joint through its worm at `target` rad/s (`sign`: + closes) with at most `force`.

        The worm lets it move only in the drive's direction: its window's back edge follows the
        furthest position reached (lazily, within two `worm_slack`), its front edge is the joint's stop.
        A load helping the motion cannot make it run faster than `target` (the brake), and the motor's
        speed is capped at what ends the step at the stop (PyBullet enforces a limit only once the joint
        is at it, so a fast joint would otherwise overshoot it). `high`, `low`: a closing or opening stop
        short of the joint's own (the palm, for an outer link; a coupled partner held back).
        """
        state = self._state
        state.held[joint] = False
        position = state.positions[joint]
        velocity = state.velocities[joint]
        slack = self._slack
        if high is None:
            high = self._joint_high[joint]
        if low is None:
            low = self._joint_low[joint]
        forward = sign * target
        # (a joint told to wait, forward 0, is braked too: gravity must not turn it either way)
        if forward >= 0.0 and sign * velocity >= forward * self._overrun_speed_fraction \
                and sign * state.torques[joint] < force and self._brake_torque > force:
            force = self._brake_torque
        # The back edge follows the joint only up to the front edge: a joint pushed past its front edge
        # (a limit gives a little under load) is held there, not followed on step by step.
        if sign > 0.0:
            back = position - slack
            if back - state.window_low[joint] > slack or state.window_high[joint] != high:
                if back > high:
                    back = high
                if back < state.window_low[joint]:
                    back = state.window_low[joint]  # the back edge never moves back while closing
                back = back if back > low else low
                # (where a stop short of the joint's own, the palm, and the worm's back edge cross, the
                # worm holds: the inner link, stopped by the palm at the outer link's angle, cannot
                # wind the outer link back along the palm)
                state.window_low[joint], state.window_high[joint] = back, (high if high > back else back)
            reach = (high - position) / self.dt if position < high else 0.0
            target = target if target < reach else reach
        else:
            back = position + slack
            if state.window_high[joint] - back > slack or state.window_low[joint] != low:
                if back < low:
                    back = low
                if back > state.window_high[joint]:
                    back = state.window_high[joint]  # nor forward while opening
                state.window_low[joint], state.window_high[joint] = low, (back if back < high else high)
            reach = (low - position) / self.dt if position > low else 0.0
            target = target if target > reach else reach
        state.target_velocities[joint] = target
        state.forces[joint] = force
        state.position_gains[joint] = 0.0

    def _coupled_edge(self, joint: int, edge: float, sign: float, stop: float | None) -> float:
        """The front edge (rad) of an engaged finger joint its partner holds back: `edge`, where the
        coupling's play ends, not past `stop` (None: the joint's own). It never moves back: a joint
        already past `edge` is held where it was first held back (the worm's teeth do not ratchet on
        with the limit's give), and it moves on only by more than a worm slack at a time (each move
        costs a changeDynamics)."""
        state = self._state
        if stop is None:
            stop = self._joint_high[joint] if sign > 0.0 else self._joint_low[joint]
        current = state.window_high[joint] if sign > 0.0 else state.window_low[joint]
        held = current if sign * (stop - current) > 0.0 else state.positions[joint]
        if sign * (edge - held) <= self._slack:
            edge = held
        return edge if sign * (stop - edge) > 0.0 else stop

    def _palm_stop(self, inner: float) -> float:
        """Where the outer link's end meets the palm face (rad, outer joint) with the inner link at `inner`."""
        table, start = self._palm_table, self._palm_table_start
        if inner <= start:
            return table[0]
        place = (inner - start) / _PALM_TABLE_STEP
        index = int(place)
        if index >= len(table) - 1:
            return table[-1]
        fraction = place - index
        return table[index] + fraction * (table[index + 1] - table[index])

    def _palm_stop_inner(self, outer: float) -> float:
        """The inner link's angle (rad) at which the outer link, at `outer`, meets the palm face."""
        table, descending = self._palm_table, self._palm_table_descending
        index = bisect_left(descending, -outer)  # the first entry at or below `outer`
        if index == 0:
            return self._palm_table_start if table[0] <= outer else self._joint_high[1]
        if index >= len(table):
            return self._joint_high[1]
        above, below = table[index - 1], table[index]
        fraction = (above - outer) / (above - below) if above > below else 0.0
        return self._palm_table_start + (index - 1 + fraction) * _PALM_TABLE_STEP

    def _command_joints(self) -> None:
        """Joint targets, force limits and worm windows for this step from the drives and the clutch."""
        prm, state = self.params, self._state
        q, w, tau = state.positions, state.velocities, state.torques
        inner_open, inner_closed = self._inner_open, self._inner_closed
        outer_open, outer_closed = self._outer_open, self._outer_closed
        hold, drive_worm = self._hold, self._drive_worm
        dt, coupling_play = self.dt, self._coupling_play
        drive_on, drive_velocity, drive_fraction = state.drive_on, state.drive_velocity, state.drive_fraction
        locked_fingers, engaged, drive_capacity, at_stop = state.locked, state.engaged, state.drive_capacity, state.at_stop
        targets = state.target_velocities  # last step's, until drive_worm sets this step's
        for f, i2, i3 in FINGER_JOINTS:
            velocity = drive_velocity[f]
            fraction = drive_fraction[f]
            if not (drive_on[f] and velocity != 0.0 and fraction > 0.0):
                at_stop[f] = False
                if not locked_fingers[f]:
                    # The motor stops: the worms hold the finger where it is; a drive that was pushing
                    # a load closing leaves it wound up against that load.
                    locked_fingers[f] = True
                    t2, t3 = tau[i2], tau[i3]
                    squeeze = self._squeeze(f, t2 + t3 / 3.0 if engaged[f] else t3)
                    hold(i2, t2 if squeeze and t2 > 0.0 and engaged[f] else 0.0)
                    hold(i3, t3 if squeeze and t3 > 0.0 else 0.0)
                    drive_capacity[f] = 0.0
                continue
            locked_fingers[f] = False
            closing = velocity > 0.0
            sign = 1.0 if closing else -1.0
            if engaged[f]:
                capacity = fraction * self._finger_capacity
                drive_capacity[f] = sign * capacity
                omega = velocity / INNER_COUNTS_PER_RAD
                # One motor turns both worms: a link against its stop (or the palm) stalls the whole finger.
                palm = self._palm_stop(q[i2])
                inner_high, inner_low, outer_high, outer_low = self._palm_stop_inner(q[i3]) if closing else None, None, palm, None
                at_stop[f] = (q[i2] >= inner_closed or q[i3] >= (palm if palm < outer_closed else outer_closed)
                              ) if closing else q[i2] <= inner_open
                if at_stop[f]:
                    inner_target = outer_target = 0.0
                else:
                    ahead = q[i2] - 3.0 * q[i3]  # rad the inner link leads the 3:1 relation
                    correction = self._half_coupling_rate * ahead
                    inner_target, outer_target = omega - correction, (omega + correction) * _THIRD
                    # Neither joint runs ahead of the other by more than the gear's play: a link held
                    # back stops its partner (the whole finger stalls), however fast the motor is told
                    # to turn. The coupling correction may slow a joint, never turn it against the drive.
                    # A partner counts as held back when it ran at less than half the speed it was told
                    # last step (an obstacle); otherwise it goes on at its own share of the drive. (Its
                    # speed alone would make the two joints take turns: each one's room the other's
                    # last speed, zero when the other had no room, a limit cycle of two steps.)
                    partner_inner, partner_outer = sign * w[i2], sign * w[i3]  # how fast each partner is going along
                    told_inner, told_outer = sign * targets[i2], sign * targets[i3]
                    if partner_inner >= 0.5 * told_inner and sign * inner_target > partner_inner:
                        partner_inner = sign * inner_target
                    if partner_outer >= 0.5 * told_outer and sign * outer_target > partner_outer:
                        partner_outer = sign * outer_target
                    inner_room = 3.0 * (partner_outer if partner_outer > 0.0 else 0.0) + (coupling_play - sign * ahead) / dt
                    outer_room = ((partner_inner if partner_inner > 0.0 else 0.0) + (coupling_play + sign * ahead) / dt) * _THIRD
                    # A joint its partner holds back is held by the worms' teeth where the coupling's play
                    # ends (a velocity target of zero alone lets the solver's residual creep it on, 2°/s
                    # for an outer link beside an inner link stalled at full torque).
                    if sign * inner_target > inner_room:
                        inner_target = sign * inner_room
                        if inner_room < self._held_back_speed:
                            edge = self._coupled_edge(i2, 3.0 * q[i3] + sign * coupling_play, sign, inner_high)
                            inner_high, inner_low = (edge, None) if closing else (None, edge)
                    if sign * outer_target > outer_room:
                        outer_target = sign * outer_room
                        if outer_room < self._held_back_speed:
                            edge = self._coupled_edge(i3, (q[i2] + sign * coupling_play) * _THIRD, sign, outer_high if closing else None)
                            outer_high, outer_low = (edge, None) if closing else (palm, edge)
                    if sign * inner_target < 0.0:
                        inner_target = 0.0
                    if sign * outer_target < 0.0:
                        outer_target = 0.0
                # One motor: inner torque + outer torque / 3 within capacity (last step's loads).
                inner_floor, outer_floor = 0.05 * capacity, self._torque_floor_fraction * capacity
                inner_load, outer_load = sign * tau[i3], sign * tau[i2]
                inner_force = capacity - inner_load / 3.0 if inner_load > 0.0 else capacity
                outer_force = capacity - outer_load if outer_load > 0.0 else capacity
                drive_worm(i2, inner_target, inner_force if inner_force > inner_floor else inner_floor, sign,
                           inner_high, inner_low)
                drive_worm(i3, outer_target, 3.0 * (outer_force if outer_force > outer_floor else outer_floor), sign,
                           outer_high, outer_low)
            else:
                hold(i2)  # the inner link stays where the clutch let go (its load slipped)
                palm = self._palm_stop(q[i2])
                at_stop[f] = q[i3] >= (palm if palm < outer_closed else outer_closed) if closing else q[i3] <= outer_open
                capacity = fraction * self._outer_capacity
                drive_worm(i3, velocity / OUTER_ABS_COUNTS_PER_RAD, capacity, sign, palm)
                drive_capacity[f] = sign * capacity
        # Spread: back-drivable; F2 follows F1 through the gear constraint.
        s1, s2 = SPREAD_INDEX
        friction = prm.spread_friction_torque
        velocity = state.drive_velocity[3]
        self._drive(s2, 0.0, friction)
        if not state.drive_on[3]:
            self._drive(s1, 0.0, friction)
            return
        force = state.drive_fraction[3] * self._spread_capacity
        if force < friction:
            force = friction
        spread = q[s1]
        if (velocity > 0.0 and spread >= self._spread_high_stop) or (velocity < 0.0 and spread <= self._spread_low_stop):
            # Stalled at a stop: hold the stop itself (fighting PyBullet's limit row would drift).
            state.hold_positions[s1] = state.target_positions[s1] = self._spread_high if velocity > 0.0 else self._spread_low
            state.held[s1] = True
            state.target_velocities[s1], state.forces[s1], state.position_gains[s1] = 0.0, force, prm.lock_position_gain
        else:
            self._drive(s1, velocity / SPREAD_COUNTS_PER_RAD, force)

    def _update_after_step(self) -> None:
        """Clutch events, preload, motor torques, heat and time, from the joint states just read."""
        prm, state = self.params, self._state
        q, w, tau = state.positions, state.velocities, state.torques
        decay = self._impact_decay
        heat = 0.0
        inner_open, inner_closed, outer_closed = self._inner_open, self._inner_closed, self._outer_closed
        impact_gain, tip_blow = prm.rotor_impact_gain, prm.tip_impact_load
        drive_on, drive_velocity, drive_fraction = state.drive_on, state.drive_velocity, state.drive_fraction
        closing_peaks, opening_peaks, motor_torques = state.closing_peak, state.opening_peak, state.motor_torques
        for f, i2, i3 in FINGER_JOINTS:
            inner_speed = w[i2]
            previous_closing, previous_opening = closing_peaks[f], opening_peaks[f]
            # Decaying peaks of the inner link's closing and opening speeds (rotor impact memory).
            closing_peak, opening_peak = previous_closing * decay, previous_opening * decay
            if inner_speed > closing_peak:
                closing_peak = inner_speed
            elif -inner_speed > opening_peak:
                opening_peak = -inner_speed
            velocity = drive_velocity[f]
            fraction = drive_fraction[f]
            if velocity < 0.0 and drive_on[f]:
                # A rotor driven open keeps no closing speed: the next close's impacts lose only what
                # that close reached (a remembered faster close made its start look held back).
                closing_peak = 0.0
            closing_peaks[f], opening_peaks[f] = closing_peak, opening_peak
            if not (drive_on[f] and velocity != 0.0 and fraction > 0.0):
                motor_torques[f] = 0.0
                continue
            if state.engaged[f]:
                capacity = fraction * self._finger_capacity
                if velocity > 0.0 and q[i3] < outer_closed:
                    # Closing: the torque the clutch passes to the inner link when something holds that
                    # link back (not while it merely accelerates), the outer link's load excluded.
                    commanded = velocity / INNER_COUNTS_PER_RAD
                    if q[i2] >= inner_closed:
                        clutch = capacity
                    elif inner_speed < 0.5 * commanded and inner_speed <= previous_closing + 0.02 * commanded:
                        outer_load = tau[i3]
                        clutch = capacity - outer_load / 3.0 if outer_load > 0.0 else capacity
                        if tau[i2] < clutch:
                            clutch = tau[i2]
                    else:
                        clutch = 0.0
                    if clutch > 0.0:
                        lost = previous_closing - (inner_speed if inner_speed > 0.0 else 0.0)
                        if lost > commanded:  # the worm: the link ran no faster than the motor turns
                            lost = commanded
                        # App. B A1: a fingertip making first contact stalls the finger (no breakaway):
                        # a loaded outer joint took the blow, and the rotor's impact went into its worm.
                        blow = 1.0 - state.outer_loads[f] / tip_blow if state.outer_loads[f] > 0.0 else 1.0
                        if lost > 0.0 and blow > 0.0:
                            clutch += impact_gain * lost * blow * (clutch / capacity if clutch < capacity else 1.0)
                        if clutch > prm.breakaway_base_torque + prm.breakaway_preload_slope * state.preload[f]:
                            self._break_away(f)
                elif velocity < 0.0 and q[i2] <= inner_open:
                    # Driven against the open stop: the clutch is tightened with the motor's torque plus
                    # the rotor's impact (§9.3.1; slamming open harder preloads more, manual §8).
                    lost = previous_opening - (-inner_speed if inner_speed < 0.0 else 0.0)
                    if lost > -velocity / INNER_COUNTS_PER_RAD:  # the worm: no faster than the motor turns
                        lost = -velocity / INNER_COUNTS_PER_RAD
                    preload = capacity + (impact_gain * lost if lost > 0.0 else 0.0)
                    if preload > prm.preload_limit:
                        preload = prm.preload_limit
                    if preload > state.preload[f]:
                        state.preload[f] = preload
            elif velocity < 0.0 and q[i3] <= q[i2] / 3.0:
                # Opening: the outer link is back at the engaged relation (M at the breakaway position).
                state.engaged[f] = True
            limit = fraction * prm.motor_peak_torque
            if state.at_stop[f]:
                torque = limit if velocity > 0.0 else -limit  # stalled against the stop: full push
            elif state.engaged[f]:
                torque = (tau[i2] + tau[i3] / 3.0) * self._inner_torque_scale
            else:
                torque = tau[i3] * self._outer_torque_scale
            torque = limit if torque > limit else (-limit if torque < -limit else torque)
            motor_torques[f] = torque
            heat += torque * torque
        if state.drive_on[3]:
            limit = state.drive_fraction[3] * prm.motor_peak_torque
            if state.held[SPREAD_INDEX[0]]:  # stalled against a stop (the stop, not the motor, holds the joint)
                torque = limit if state.drive_velocity[3] > 0.0 else -limit
            else:
                torque = tau[SPREAD_INDEX[0]] * self._spread_torque_scale
                torque = limit if torque > limit else (-limit if torque < -limit else torque)
            heat += torque * torque
        else:
            torque = 0.0
        state.motor_torques[3] = torque
        km = prm.motor_constant
        power = prm.electronics_power + heat / (km * km)
        loss = (state.temperature - prm.ambient_temperature) / prm.thermal_resistance
        state.temperature += self.dt * (power - loss) / prm.heat_capacity
        state.time += self.dt

    def _break_away(self, f: int) -> None:
        state = self._state
        state.engaged[f] = False
        state.breakaway_counts[f] = self._finger_counts(f)
        state.preload[f] = 0.0  # manual §8: the clutch needs a full open to be preloaded again

    def back_off_stop(self, finger: int, counts: float) -> None:
        """Finger 1-3 is about to move `counts` closed from its open stop after being driven against it
        (HI's move to 0 closes IOFF counts): that unwinds part of the clutch's preload (§5.3.4 IOFF:
        "Larger values result in less compression of the Belleville washer", no effect beyond about
        500 counts; `preload_release_counts`)."""
        f, release = self._check_finger(finger), self.params.preload_release_counts
        counts = float(counts)
        if not (math.isfinite(counts) and counts >= 0.0):
            raise PlantError(f"counts must be a finite number >= 0, got {counts!r}")
        self._state.preload[f] *= 1.0 - counts / release if counts < release else 0.0

    def _finger_counts(self, f: int) -> float:
        q = self._state.positions
        return (q[INNER_INDEX[f]] + q[OUTER_INDEX[f]]) * OUTER_ABS_COUNTS_PER_RAD

    # ---------------------------------------------------------------- sensors
    def motor_positions(self) -> np.ndarray:
        """Motor counts (BH8-262 scale); 0 = the joint against its mechanical open stop.

        The encoders sit on the motors: a locked finger joint reads where its worm holds it (its
        link may still flex elastically, or sag within PyBullet's soft hold, without turning the motor).
        """
        return np.array(self.motor_state_lists()[0])

    def motor_velocities(self) -> np.ndarray:
        """Motor velocities, counts per second; a locked finger's motor stands still."""
        return np.array(self.motor_state_lists()[1])

    def motor_state_lists(self) -> tuple[list[float], list[float]]:
        """(motor positions, motor velocities) as plain lists, as `motor_positions`/`motor_velocities`
        give them (the firmware's per-step path)."""
        state = self._state
        q, w, hold, held = state.positions, state.velocities, state.hold_positions, state.held
        scale = OUTER_ABS_COUNTS_PER_RAD
        positions = [
            ((hold[1] if held[1] else q[1]) + (hold[2] if held[2] else q[2])) * scale,
            ((hold[4] if held[4] else q[4]) + (hold[5] if held[5] else q[5])) * scale,
            ((hold[6] if held[6] else q[6]) + (hold[7] if held[7] else q[7])) * scale,
            q[0] * SPREAD_COUNTS_PER_RAD,
        ]
        velocities = [
            ((0.0 if held[1] else w[1]) + (0.0 if held[2] else w[2])) * scale,
            ((0.0 if held[4] else w[4]) + (0.0 if held[5] else w[5])) * scale,
            ((0.0 if held[6] else w[6]) + (0.0 if held[7] else w[7])) * scale,
            w[0] * SPREAD_COUNTS_PER_RAD,
        ]
        return positions, velocities

    def motor_torques(self) -> np.ndarray:
        """Motor-shaft torques of the last step, N·m (signed, + closes)."""
        return np.array(self._state.motor_torques)

    def outer_joint_torques(self) -> np.ndarray:
        """Torque about each finger's outer joint (N·m, + = load against closing), what the gauges sense:
        what the drive train transmits to the outer link, the motor's push and the worm's hold alike."""
        return np.array(self._state.outer_loads)

    def strain_gauges(self) -> np.ndarray:
        """8-bit strain gauge values (§9.4): offset + gain x outer-joint torque; the spread reads 255."""
        return np.array(self.strain_gauges_list(), dtype=np.int64)

    def strain_gauges_list(self) -> list[int]:
        """`strain_gauges` as a plain list (the firmware's per-cycle path)."""
        gain, loads, offsets = self.params.strain_gain, self._state.outer_loads, self.strain_offsets
        values = [round(offset + gain * load) for offset, load in zip(offsets, loads)]
        return [255 if v > 255 else (0 if v < 0 else v) for v in values] + [255]

    def clutch_engaged(self, finger: int) -> bool:
        """True while finger 1-3's TorqueSwitch couples both joints to the motor."""
        return self._state.engaged[self._check_finger(finger)]

    def breakaway_position(self, finger: int) -> float | None:
        """Motor counts at finger 1-3's last breakaway, or None if it never broke away."""
        return self._state.breakaway_counts[self._check_finger(finger)]

    def clutch_preload(self, finger: int) -> float:
        """The clutch preload of finger 1-3 (N·m at the inner joint)."""
        return self._state.preload[self._check_finger(finger)]

    def breakaway_threshold(self, finger: int) -> float:
        """Inner-joint torque (N·m) above which finger 1-3's clutch breaks away now."""
        prm = self.params
        return prm.breakaway_base_torque + prm.breakaway_preload_slope * self._state.preload[self._check_finger(finger)]

    def _check_finger(self, finger) -> int:
        if finger not in (1, 2, 3) or isinstance(finger, bool):
            raise PlantError(f"finger must be 1, 2 or 3, got {finger!r}")
        return int(finger) - 1

    def joint_angles(self) -> np.ndarray:
        """The 8 joint angles, radians, URDF order (F1 spread/inner/outer, F2 ..., F3 inner/outer)."""
        return np.array(self._state.positions)

    def fingertip_positions(self) -> np.ndarray:
        """World positions (3x3, rows F1..F3) of the fingertip frames {T}."""
        states = p.getLinkStates(self.hand_id, self.tip_link_indices, computeForwardKinematics=True, physicsClientId=self._client)
        return np.array([s[4] for s in states])

    def set_joint_angles(self, angles) -> None:
        """Teleport the joints (radians, URDF order) with zero velocity; clutch engaged. For tests and resets."""
        angles = np.asarray(angles, dtype=float)
        if angles.shape != (NUM_JOINTS,) or not np.all(np.isfinite(angles)):
            raise PlantError(f"set_joint_angles needs 8 finite angles, got {angles!r}")
        for joint, angle in zip(self.joint_indices, angles):
            p.resetJointState(self.hand_id, joint, float(angle), 0.0, physicsClientId=self._client)
        state = self._state
        state.engaged = [True] * 3
        state.locked = [True] * 3
        state.breakaway_counts = [None] * 3
        state.held = [False] * NUM_JOINTS
        state.latched_torque = [0.0] * NUM_JOINTS
        state.drive_capacity = [0.0] * 3
        self._read_joints()
        state.previous_positions = state.positions
        for joint in WORM_JOINTS:  # the worms hold the fingers where they are now
            self._hold(joint)

    # ---------------------------------------------------------------- wrist and world
    def set_wrist_pose(self, position, orientation=(0.0, 0.0, 0.0, 1.0), teleport: bool = False) -> None:
        """Move the arm flange to `position` (m) and `orientation` (quaternion xyzw); the wrist follows.

        `teleport=True` also puts the hand there at once (resets, not motion).
        """
        # Unpacked by hand: the grasp scene moves the wrist every RealTime cycle.
        try:
            x, y, z = position
            x, y, z = float(x), float(y), float(z)
        except (TypeError, ValueError):
            raise PlantError(f"wrist position must be 3 finite numbers, got {position!r}") from None
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            raise PlantError(f"wrist position must be 3 finite numbers, got {position!r}")
        try:
            qx, qy, qz, qw = orientation
            qx, qy, qz, qw = float(qx), float(qy), float(qz), float(qw)
        except (TypeError, ValueError):
            raise PlantError(f"wrist orientation must be a unit quaternion (x, y, z, w), got {orientation!r}") from None
        norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
        if not math.isfinite(norm) or abs(norm - 1.0) > 1e-3:
            raise PlantError(f"wrist orientation must be a unit quaternion (x, y, z, w), got {orientation!r}")
        position = (x, y, z)
        orientation = (qx / norm, qy / norm, qz / norm, qw / norm)
        self._state.wrist_target = (position, orientation)
        p.changeConstraint(
            self._wrist_constraint, jointChildPivot=position, jointChildFrameOrientation=orientation,
            maxForce=self.params.wrist_max_force, physicsClientId=self._client,
        )
        if teleport:
            com = p.multiplyTransforms(position, orientation, self._com_offset, (0, 0, 0, 1))
            p.resetBasePositionAndOrientation(self.hand_id, com[0], com[1], physicsClientId=self._client)
            p.resetBaseVelocity(self.hand_id, (0, 0, 0), (0, 0, 0), physicsClientId=self._client)

    def wrist_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """The wrist frame's actual world pose: (position (3,), quaternion xyzw (4,))."""
        com_position, com_orientation = p.getBasePositionAndOrientation(self.hand_id, physicsClientId=self._client)
        inverse = p.invertTransform(self._com_offset, (0, 0, 0, 1))
        position, orientation = p.multiplyTransforms(com_position, com_orientation, inverse[0], inverse[1])
        return np.array(position), np.array(orientation)

    def object_pose(self, body: int) -> tuple[np.ndarray, np.ndarray]:
        position, orientation = p.getBasePositionAndOrientation(body, physicsClientId=self._client)
        return np.array(position), np.array(orientation)

    def contacts(self, body_a: int, body_b: int | None = None) -> list:
        """PyBullet contact points of body_a (with body_b if given), from the last step."""
        if body_b is None:
            return list(p.getContactPoints(bodyA=body_a, physicsClientId=self._client))
        return list(p.getContactPoints(bodyA=body_a, bodyB=body_b, physicsClientId=self._client))

    def link_index(self, name: str) -> int:
        """PyBullet's index of the hand's link `name` (hand_urdf's names; the palm is -1)."""
        return self._link_index_by_name[name]

    def contacts_by_link(self, body: int) -> list[int]:
        """The hand's link index of each contact point between the hand and `body`, from the last step."""
        return [contact[3] for contact in p.getContactPoints(self.hand_id, body, physicsClientId=self._client)]

    def link_positions(self, links: list[int]) -> list[tuple[float, float, float]]:
        """World positions of the hand's link frames `links` as the last step left them."""
        return [state[4] for state in p.getLinkStates(self.hand_id, links, physicsClientId=self._client)]

    def body_position(self, body: int) -> tuple[float, float, float]:
        """World position of `body`'s base."""
        return p.getBasePositionAndOrientation(body, physicsClientId=self._client)[0]

    def body_bounds(self, body: int) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """(lowest, highest) corner of `body`'s base's axis-aligned bounding box."""
        return p.getAABB(body, -1, physicsClientId=self._client)

    # ---------------------------------------------------------------- state
    def save_state(self) -> int:
        """Snapshot PyBullet and the plant's own state; returns an id for `restore_state`.

        Bodies added or removed after the snapshot make it unrestorable (PyBullet's rule).
        """
        state_id = p.saveState(physicsClientId=self._client)
        self._saved[state_id] = self._state.copy()
        return state_id

    def restore_state(self, state_id: int) -> None:
        """Return PyBullet and the plant (clutch, preload, heat, drives, wrist target, time) to a snapshot."""
        if state_id not in self._saved:
            raise PlantError(f"no saved plant state with id {state_id!r}")
        p.restoreState(stateId=state_id, physicsClientId=self._client)
        self._renew_contact_pairs()
        self._state = self._saved[state_id].copy()
        self._sent_command = None  # resend the joint motor command and worm windows of the restored state
        self._sent_windows = {}
        position, orientation = self._state.wrist_target
        p.changeConstraint(
            self._wrist_constraint, jointChildPivot=position, jointChildFrameOrientation=orientation,
            maxForce=self.params.wrist_max_force, physicsClientId=self._client,
        )

    def _renew_contact_pairs(self) -> None:
        """Drop every body's broadphase pairs and contact manifolds, re-adding its links in body order.

        restoreState restores poses and velocities but keeps the contact manifolds the last episode
        left and their order, which sets the solver's order and warm start: the same seed then gave
        a trajectory that depended on the episodes run before (diverging after ~250 steps). Changing
        a link's collision filter removes and re-adds it, so every reset starts from the same contact
        state. The filters set are PyBullet's defaults: static bodies (no mass, no joints) group 2,
        mask all but static; everything else group 1, mask all.
        """
        client = self._client
        for index in range(p.getNumBodies(physicsClientId=client)):
            body = p.getBodyUniqueId(index, physicsClientId=client)
            joints = p.getNumJoints(body, physicsClientId=client)
            static = joints == 0 and p.getDynamicsInfo(body, -1, physicsClientId=client)[0] == 0.0
            group, mask = (_STATIC_FILTER, _ALL_FILTERS ^ _STATIC_FILTER) if static else (_DEFAULT_FILTER, _ALL_FILTERS)
            for link in range(-1, joints):
                p.setCollisionFilterGroupMask(body, link, 0, 0, physicsClientId=client)
                p.setCollisionFilterGroupMask(body, link, group, mask, physicsClientId=client)

    def remove_state(self, state_id: int) -> None:
        if self._saved.pop(state_id, None) is None:
            raise PlantError(f"no saved plant state with id {state_id!r}")
        p.removeState(state_id, physicsClientId=self._client)

    # ---------------------------------------------------------------- teardown
    def close(self) -> None:
        if self._client is not None and self._client >= 0:
            try:
                p.disconnect(self._client)
            except p.error:
                pass
        self._client = -1

    def __enter__(self) -> "HandPlant":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:  # a forgotten close must not leak the physics server
        try:
            self.close()
        except Exception:
            pass
