"""The environments' tasks: each owns its scene, its reward and its simulator-only observations.

A task is the simulated half of an environment (`base.BH8LoopEnv` is the loop, `LoopInterface`
the host's half, panda-gym's robot/task/sim split): `build_scene(plant)` makes its static world,
`begin_episode(rng)` draws and places an episode, `reward(...)` scores a step and the privileged
entries read the world. It reads PyBullet through the plant (`HandPlant.contacts_by_link`,
`link_positions`, `body_position`, `body_bounds`), never around it.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from bh8_gym.envs.arm import ArmSchedule
from bh8_gym.envs.interfaces import ReachTargetObservation
from bh8_gym.envs.objects import ObjectSet
from bh8_gym.envs.scenes import GraspScene, PlacementRanges, ReachEpisode, ReachRanges, ReachScene
from bh8_gym.protocol import SPREAD_MOTOR
from bh8_gym.rendering import Camera


_KINDS = ("box", "capsule", "cylinder", "sphere")  # the privileged one-hot's order, then "mesh"


@dataclass(frozen=True)
class GraspRewardWeights:
    """Per-step shaping weights and the success bonus (return scale ~10 over ~300 steps)."""

    reach: float = 0.02
    contact: float = 0.02
    lift: float = 0.05
    success: float = 10.0
    reach_scale: float = 0.10  # metres: a distance of this size costs `reach` per step
    safety_stop: float = 5.0  # the penalty of a step that ends the episode with a safety stop


@dataclass(frozen=True)
class ReachTolerance:
    """Success tolerance, encoder counts: 2° of the inner link (fingers), 3° of spread."""

    finger: int = 250
    spread: int = 52


class GraspTask:
    """Grasp an object on a table, then survive the arm's lift (see grasp.py for the reward)."""

    def __init__(self, object_set: ObjectSet, placement: PlacementRanges, arm: ArmSchedule,
                 success_height: float, weights: GraspRewardWeights, visuals: bool):
        self.object_set = object_set
        self.placement = placement
        self.arm = arm
        self.success_height = float(success_height)
        self.weights = weights
        self.visuals = visuals
        self.scene: GraspScene | None = None
        self.plant = None
        # What this cycle's world gives, read once for the reward and the privileged entries alike.
        self._object_position = self._touching = None
        self._object_entries: list[float] = []  # the episode's object in the privileged entries

    def plant_parameters(self, params):
        return params

    def build_scene(self, plant) -> GraspScene:
        """The table, the palm-down hand on its arm, the object loader; the tips' and fingers' links."""
        self.plant = plant
        self.scene = GraspScene(plant, self.object_set, self.placement, self.arm, visuals=self.visuals)
        self._tip_links = [plant.link_index(f"f{k}_tip") for k in (1, 2, 3)]
        # Contacts count per finger: any of its links (inner, outer, tip) touching.
        self._finger_of_link = {plant.link_index(f"f{k}_{part}"): k - 1 for k in (1, 2, 3)
                                for part in ("inner", "outer", "tip")}
        return self.scene

    def begin_episode(self, rng: np.random.Generator) -> None:
        self.scene.begin_episode(self.scene.sample_episode(rng))
        self.new_cycle()
        spec = self.scene.episode.spec
        kind = [0.0] * (len(_KINDS) + 1)
        kind[_KINDS.index(spec.kind) if spec.kind in _KINDS else len(_KINDS)] = 1.0
        self._object_entries = kind + [extent * 10.0 for extent in self.scene.object_extents] + [
            spec.mass or 0.0, spec.friction or 0.0]

    def new_cycle(self) -> None:
        """The world has moved on (the env ran a RealTime cycle): the queries read afresh."""
        self._object_position = self._touching = None

    def _position(self) -> tuple[float, float, float]:
        """The object's position (world, metres), read once per cycle."""
        if self._object_position is None:
            self._object_position = self.plant.body_position(self.scene.object_body)
        return self._object_position

    def _touching_fingers(self) -> tuple[set, bool]:
        """(the set of finger indices 0-2 touching the object, whether any part of the hand touches it),
        from one contact query of the last physics step (once per cycle)."""
        if self._touching is None:
            links = self.plant.contacts_by_link(self.scene.object_body)
            fingers = {self._finger_of_link.get(link) for link in links}
            fingers.discard(None)
            self._touching = fingers, bool(links)
        return self._touching

    def _finger_contacts(self) -> np.ndarray:
        touching = np.zeros(3)
        for finger in self._touching_fingers()[0]:
            touching[finger] = 1.0
        return touching

    def reward(self, values, elapsed: float, done: bool) -> tuple[float, dict, bool, bool]:
        """Reward (simulation only; uses privileged state), each term in info["reward_terms"]."""
        plant, w, body = self.plant, self.weights, self.scene.object_body
        x, y, z = self._position()
        distance = 0.0
        for tip_x, tip_y, tip_z in plant.link_positions(self._tip_links):
            distance += ((tip_x - x) ** 2 + (tip_y - y) ** 2 + (tip_z - z) ** 2) ** 0.5
        distance /= 3.0
        fingers, held = self._touching_fingers()
        lowest = plant.body_bounds(body)[0][2]
        rise = z - self.scene.object_rest_z
        lift_height = self.arm.lift_height
        lift_fraction = min(max(rise / lift_height, 0.0), 1.0) if lift_height > 0 else 0.0
        success = bool(lowest > self.scene.table_top + self.success_height and held)
        terms = {
            "reach": -w.reach * distance / w.reach_scale,
            "contact": w.contact * float(len(fingers)) / 3.0,
            "lift": w.lift * lift_fraction,
            "success": w.success if (done and success) else 0.0,
        }
        # The arm's schedule is the task, not a time limit outside it: its end is terminal (no
        # bootstrapping past it), and the observation carries the clock that leads there.
        return sum(terms.values()), terms, success, done

    def safety_stop_reward(self) -> float:
        return -self.weights.safety_stop

    def fill_privileged(self, out: np.ndarray) -> None:
        """object_dx/dy/dz from the wrist, object_rise, contact_f1..3, then what the object is: a
        one-hot of its kind (a mesh for anything not a primitive), its extents at rest (dm), mass
        (kg) and friction (`GRASP_PRIVILEGED_NAMES`): an asymmetric critic that knows the object
        can value a grasp chosen for it."""
        x, y, z = self._position()
        wrist_x, wrist_y, wrist_z = self.plant.wrist_pose()[0]
        fingers = self._touching_fingers()[0]
        out[:] = [x - wrist_x, y - wrist_y, z - wrist_z, z - self.scene.object_rest_z,
                  *(1.0 if finger in fingers else 0.0 for finger in range(3)), *self._object_entries]

    def privileged_info(self) -> dict:
        position = np.asarray(self._position())
        return {
            "object_position": position,
            "object_rise": float(position[2] - self.scene.object_rest_z),
            "finger_contacts": self._finger_contacts(),
            "object": self.scene.episode.spec,
            "table_top": self.scene.table_top,
        }

    def camera(self) -> Camera:
        # Fixed on the object's start, wide enough to watch the 10 cm lift.
        return Camera(target=(0.0, 0.0, self.scene.table_top + 0.07), distance=0.5, yaw=40.0, pitch=-18.0)


class ReachTask:
    """Drive each LOOP motor to a target encoder count; the host knows the targets (`observation`)."""

    def __init__(self, observation: ReachTargetObservation, ranges: ReachRanges, tolerance: ReachTolerance,
                 success_bonus: float):
        self.observation = observation
        self.ranges = ranges
        self.success_bonus = float(success_bonus)
        self.motors = observation.motors
        self._tolerances = [tolerance.spread if m == SPREAD_MOTOR else tolerance.finger for m in self.motors]
        self.scene: ReachScene | None = None
        self.plant = None

    def plant_parameters(self, params):
        # No table: the hand reaches in free space (and PyBullet has one body fewer to collide).
        return replace(params, table=False)

    def build_scene(self, plant) -> ReachScene:
        self.plant = plant
        self.scene = ReachScene(plant, self.motors, self.ranges)
        return self.scene

    def begin_episode(self, rng: np.random.Generator) -> None:
        episode = self.scene.sample_episode(rng)
        self.scene.begin_episode(episode)
        self.observation.set(episode.targets)

    def new_cycle(self) -> None:
        """The reach reads nothing of the world but the feedback block."""

    def set_targets(self, counts: Sequence[float]) -> None:
        self.scene.begin_episode(ReachEpisode(tuple(int(c) for c in counts)))
        self.observation.set(counts)

    def reward(self, values, elapsed: float, done: bool) -> tuple[float, dict, bool, bool]:
        """"error" = −mean |target − position| / full range; "success" = +bonus within tolerance (ends the episode)."""
        obs = self.observation
        errors = [abs(t - values[i]) for t, i in zip(obs.targets, obs.lfap_index)]
        success = all(e <= tolerance for e, tolerance in zip(errors, self._tolerances))
        terms = {
            "error": -(sum(e / r for e, r in zip(errors, obs.full_range)) / len(errors)),
            "success": self.success_bonus if success else 0.0,
        }
        return terms["error"] + terms["success"], terms, success, success

    def safety_stop_reward(self) -> float:
        return 0.0

    def fill_privileged(self, out: np.ndarray) -> None:
        """The reach has no privileged observation entries."""

    def privileged_info(self) -> dict:
        return {"motor_positions": self.plant.motor_positions(), "joint_angles": self.plant.joint_angles()}

    def camera(self):
        return None
