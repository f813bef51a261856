"""`HandPlant`: the simulated BH8-262, the one object the firmware and the environments talk to.

It builds the world (PyBullet client, hand URDF, gear and wrist constraints), derives the per-step
constants from `PlantParameters` (again on `set_parameters`), and steps: the drive train commands
the joints, PyBullet steps, the sensors read them back and the clutch pass follows. Its parts are
mixins, each one piece of hardware: `DriveTrain` (motors, worms, coupling), `Clutch` (TorqueSwitch,
motor torque and heat), `Sensors` (encoders, strain gauges, temperature) and `World` (table, wrist,
bodies, contacts, saved states). Contract 1 in docs/architecture.md.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pybullet as p

from bh8_gym import hand_urdf, pybullet_files
from bh8_gym import kinematics as kin
from bh8_gym.plant.clutch import Clutch
from bh8_gym.plant.drive_train import DriveTrain
from bh8_gym.plant.joints import (
    _JOINT_RANGE_HIGH,
    _JOINT_RANGE_LOW,
    _PALM_TABLE_STEP,
    INNER_GEAR_RATIO,
    NUM_JOINTS,
    OUTER_ABS_GEAR_RATIO,
    OUTER_INDEX,
    SPREAD_GEAR_RATIO,
    WORM_JOINTS,
    _PlantState,
)
from bh8_gym.plant.parameters import DisplayUnavailableError, PlantError, PlantParameters
from bh8_gym.plant.sensors import Sensors
from bh8_gym.plant.world import World
from bh8_gym.rendering import display_available


class HandPlant(DriveTrain, Clutch, Sensors, World):
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
        #: Called before every physics step when set: an arm controller that runs at the physics rate
        #: (the grasp scene's table-contact press); not the hand's, and not part of a saved state.
        self.step_hook = None
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
        with pybullet_files.written([(hand_urdf.urdf_bytes(), ".urdf")]) as (path,):  # a file only we wrote
            self.hand_id = p.loadURDF(path, position, orientation, flags=flags, physicsClientId=cid)
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
        self._finger_links = [(self._link_index_by_name[f"f{finger}_inner"], self._link_index_by_name[f"f{finger}_outer"])
                              for finger in (1, 2, 3)]
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
        self._forget_sent_windows()
        # The last window of each joint that was not inverted (what PyBullet keeps; NaN: none yet).
        self._valid_low, self._valid_high = [math.nan] * NUM_JOINTS, [math.nan] * NUM_JOINTS
        self._unit_masses = [p.getDynamicsInfo(self.hand_id, link, physicsClientId=cid)[0] for link in self._links]
        self._com_offset = p.getDynamicsInfo(self.hand_id, -1, physicsClientId=cid)[3]
        self._com_inverse = p.invertTransform(self._com_offset, (0, 0, 0, 1))  # (wrist_pose)
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

    def _forget_sent_windows(self) -> None:
        """The worm windows PyBullet has are unknown (NaN): the next step sends each one."""
        self._sent_low, self._sent_high = [math.nan] * NUM_JOINTS, [math.nan] * NUM_JOINTS

    def _apply_parameters(self) -> None:
        """Push `self.params` into PyBullet and derive the per-step constants (plain floats)."""
        prm, cid, hand = self.params, self._client, self.hand_id
        p.setGravity(0.0, 0.0, -prm.gravity, physicsClientId=cid)
        p.setPhysicsEngineParameter(numSolverIterations=prm.solver_iterations,
                                    solverResidualThreshold=prm.solver_residual_threshold, physicsClientId=cid)
        pad_torsion = 2.0 / 3.0 * prm.finger_pad_radius * prm.finger_friction  # the pad's patch (parameters.py)
        for link, unit_mass in zip(self._links, self._unit_masses):
            friction = prm.palm_friction if link == -1 else prm.finger_friction
            spinning = 0.0 if link == -1 else pad_torsion
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

    # ---------------------------------------------------------------- time and stepping
    @property
    def time(self) -> float:
        """Simulated seconds since construction."""
        return self._state.time

    def step(self) -> None:
        """Advance one physics step of `dt` seconds."""
        if self.step_hook is not None:
            self.step_hook()
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
        self._send_windows()
        p.stepSimulation(client)  # (positional: see above)
        self._read_joints()
        self._update_after_step()

    def _send_windows(self) -> None:
        """Give PyBullet the worm windows this step needs: each one that changed, unless the joint is
        strictly inside both the new window and the one PyBullet has. Bullet makes no solver row for a
        limit the joint is inside of (btMultiBodyJointLimitConstraint::createConstraintRows skips a
        row of positive distance), so such a change cannot act in this step and is sent once it can:
        the same physics to the bit, and a closing finger, whose window edges move every step, costs
        no changeDynamics. pybullet.changeDynamics ignores an inverted window (low > high), so the
        last one that was not inverted stays in force."""
        state, sent_low, sent_high = self._state, self._sent_low, self._sent_high
        low, high, q = state.window_low, state.window_high, state.positions
        valid_low, valid_high = self._valid_low, self._valid_high
        for joint in WORM_JOINTS:
            lower, upper = low[joint], high[joint]
            if lower <= upper:
                valid_low[joint], valid_high[joint] = lower, upper
            else:
                lower, upper = valid_low[joint], valid_high[joint]
            was_lower, was_upper = sent_low[joint], sent_high[joint]
            if lower == was_lower and upper == was_upper:
                continue
            if was_lower == was_lower:  # (NaN: PyBullet's window unknown)
                position = q[joint]
                if (lower == was_lower or (lower < position and was_lower < position)) and \
                        (upper == was_upper or (position < upper and position < was_upper)):
                    continue
            p.changeDynamics(self.hand_id, self.joint_indices[joint], jointLowerLimit=lower, jointUpperLimit=upper,
                             physicsClientId=self._client)
            sent_low[joint], sent_high[joint] = lower, upper

    def set_joint_angles(self, angles, velocities=None) -> None:
        """Teleport the joints (radians, URDF order) with zero velocity (or `velocities`, rad/s);
        clutch engaged. For tests, resets and the calibration's replay (its anchors)."""
        angles = np.asarray(angles, dtype=float)
        if angles.shape != (NUM_JOINTS,) or not np.all(np.isfinite(angles)):
            raise PlantError(f"set_joint_angles needs 8 finite angles, got {angles!r}")
        velocities = np.zeros(NUM_JOINTS) if velocities is None else np.asarray(velocities, dtype=float)
        if velocities.shape != (NUM_JOINTS,) or not np.all(np.isfinite(velocities)):
            raise PlantError(f"set_joint_angles needs 8 finite velocities, got {velocities!r}")
        for joint, angle, velocity in zip(self.joint_indices, angles, velocities):
            p.resetJointState(self.hand_id, joint, float(angle), float(velocity), physicsClientId=self._client)
        state = self._state
        state.engaged = [True] * 3
        state.locked = [True] * 3
        state.breakaway_counts = [None] * 3
        state.held = [False] * NUM_JOINTS
        state.latched_torque = [0.0] * NUM_JOINTS
        state.drive_capacity = [0.0] * 3
        self._read_joints()
        for joint in WORM_JOINTS:  # the worms hold the fingers where they are now
            self._hold(joint)

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
