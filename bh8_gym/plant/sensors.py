"""What the simulated hand senses: encoders, strain gauges, temperature (manual §9.4, §2).

`Sensors` is one part of `HandPlant` (a mixin on the plant's `_state`): the joint states read back
from PyBullet after each step (`_read_joints`), the motor encoders (a locked finger reads where its
worm holds it), the 8-bit strain gauges (offset + gain x the torque its outer joint transmits),
the motor torques and the hand temperature the clutch pass computed, and the joints' and
fingertips' positions.
"""
from __future__ import annotations

import numpy as np
import pybullet as p

from bh8_gym.plant.joints import OUTER_ABS_COUNTS_PER_RAD, SPREAD_COUNTS_PER_RAD, _PlantState
from bh8_gym.plant.parameters import PlantParameters


class Sensors:
    """The encoders, strain gauges and temperature of `HandPlant` (module docstring)."""

    params: PlantParameters
    _state: _PlantState

    @property
    def temperature(self) -> float:
        """Hand temperature, °C (lumped thermal mass)."""
        return self._state.temperature

    def _read_joints(self) -> None:
        """Joint positions, velocities, applied torques and the outer joints' transmitted torques."""
        state = self._state
        joints = p.getJointStates(self.hand_id, self.joint_indices, self._client)  # (body, joints, physicsClientId)
        state.positions, state.velocities, reactions, state.torques = zip(*joints)
        # The sensor gives the load the joint carries about its axis (z); a load against closing is +.
        state.outer_loads = (-reactions[2][5], -reactions[5][5], -reactions[7][5])

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

    def joint_angles(self) -> np.ndarray:
        """The 8 joint angles, radians, URDF order (F1 spread/inner/outer, F2 ..., F3 inner/outer)."""
        return np.array(self._state.positions)

    def fingertip_positions(self) -> np.ndarray:
        """World positions (3x3, rows F1..F3) of the fingertip frames {T}."""
        states = p.getLinkStates(self.hand_id, self.tip_link_indices, computeForwardKinematics=True, physicsClientId=self._client)
        return np.array([s[4] for s in states])
