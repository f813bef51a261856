"""The simulated hand's world: the PyBullet client, the table, the wrist on its arm flange, the
bodies and contacts in it, and saved states of all of it.

`World` is one part of `HandPlant` (a mixin on the plant's PyBullet client and `_state`). Objects
are not the plant's (`bh8_gym.objects` puts them in this world); the queries here read any body.
A restored state also renews every body's contact pairs, so an episode does not depend on the
ones before it.
"""
from __future__ import annotations

import math

import numpy as np
import pybullet as p

from bh8_gym.plant.joints import _ALL_FILTERS, _DEFAULT_FILTER, _STATIC_FILTER, _PlantState
from bh8_gym.plant.parameters import PlantError, PlantParameters


class World:
    """The PyBullet world around `HandPlant`'s hand (module docstring)."""

    params: PlantParameters
    _state: _PlantState
    _client: int
    hand_id: int

    @property
    def client(self) -> int:
        """The PyBullet physics client id (for callers adding their own bodies or queries)."""
        return self._client

    def _make_table(self) -> int:
        cid = self._client
        half = (1.0, 1.0, 0.02)
        collision = p.createCollisionShape(p.GEOM_BOX, halfExtents=half, physicsClientId=cid)
        visual = p.createVisualShape(p.GEOM_BOX, halfExtents=half, rgbaColor=(0.62, 0.47, 0.32, 1.0), physicsClientId=cid)
        body = p.createMultiBody(0.0, collision, visual, basePosition=(0.0, 0.0, -half[2]), physicsClientId=cid)
        p.changeDynamics(body, -1, lateralFriction=self.params.table_friction, physicsClientId=cid)
        return body

    # ---------------------------------------------------------------- wrist
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
        inverse = self._com_inverse
        position, orientation = p.multiplyTransforms(com_position, com_orientation, inverse[0], inverse[1])
        return np.array(position), np.array(orientation)

    # ---------------------------------------------------------------- bodies and contacts
    def object_pose(self, body: int) -> tuple[np.ndarray, np.ndarray]:
        position, orientation = p.getBasePositionAndOrientation(body, physicsClientId=self._client)
        return np.array(position), np.array(orientation)

    def contacts(self, body_a: int, body_b: int | None = None) -> list:
        """PyBullet contact points of body_a (with body_b if given), from the last step."""
        if body_b is None:
            return list(p.getContactPoints(bodyA=body_a, physicsClientId=self._client))
        return list(p.getContactPoints(bodyA=body_a, bodyB=body_b, physicsClientId=self._client))

    def contact_lift(self) -> float:
        """The upward force (N) on the hand from its contacts with other bodies in the last step:
        what a wrist force sensor reads beyond the hand's weight (normal forces; a table's
        friction on the hand is horizontal)."""
        hand = self.hand_id
        return sum(c[9] * c[7][2] for c in self.contacts(hand) if c[2] != hand)

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

    # ---------------------------------------------------------------- saved states
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
        self._forget_sent_windows()
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
