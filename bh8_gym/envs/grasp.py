"""BH8Grasp-v0: grasp an object on a table with LOOP velocity and gain bytes, then survive the lift.

The hand hangs palm-down on an arm above a table with one object (objects.py); the arm placed it
with a realistic error (±2 cm, ±15°, palm 1-3 cm above the object). Phases on the host's clock
(scenes.ArmSchedule): grasp 0.8 s (the policy drives the fingers, the arm is still), lift 0.7 s
(the wrist rises 10 cm), hold 0.5 s (optionally shaking). At 38400 baud one step is 6.47 ms
(9-byte control block + 12-byte feedback block + 1 ms), so an episode is 309 steps.

Default LOOP configuration (the lead's design): motors 1-4; per motor LCV (signed velocity byte,
LCVC 1: 1/16 count per sample per unit) and LCPG (gain byte: the grasp force, U = LCPG/4 × velocity
error, §6.1); feedback LFS (strain, the fingers only: the spread has no gauge) and LFAP (absolute
position); no LFV, LFDP, LFT.

Reward (simulation only; may use privileged state), each term in info["reward_terms"]:
"reach" −w·mean fingertip-to-object distance / 10 cm; "contact" +w·(fingers touching)/3;
"lift" +w·clip(object rise / lift height, 0, 1); "success" +bonus on the last step if successful.
Success: the object's lowest point is more than `success_height` above the table and it touches
the hand (info["is_success"] every step; the last step's value is the episode's result). The end of
the arm's schedule ends the episode as `terminated`: it is part of the task (the observation has the
clock), so learners must not bootstrap a value past it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from bh8_gym.envs.base import BH8LoopEnv, check_switch
from bh8_gym.envs.objects import ObjectSet, ObjectSpec
from bh8_gym.envs.randomization import RandomizationRanges
from bh8_gym.envs.scenes import ArmSchedule, GraspScene, PlacementRanges
from bh8_gym.plant import dataclass_from
from bh8_gym.realtime_codec import MotorFlags


@dataclass(frozen=True)
class GraspRewardWeights:
    """Per-step shaping weights and the success bonus (return scale ~10 over ~300 steps)."""

    reach: float = 0.02
    contact: float = 0.02
    lift: float = 0.05
    success: float = 10.0
    reach_scale: float = 0.10  # metres: a distance of this size costs `reach` per step
    safety_stop: float = 5.0  # the penalty of a step that ends the episode with a safety stop


SHAKE_AMPLITUDE = 0.01  # metres; `shake=True` shakes the wrist ±1 cm at 2 Hz during hold


class BH8GraspEnv(BH8LoopEnv):
    """Grasp and lift; see the module docstring. Keyword arguments configure every choice."""

    env_id = "BH8Grasp-v0"

    def __init__(
        self,
        *,
        object_set: str | ObjectSet = "primitives",
        object_files: Sequence[str | ObjectSpec] | None = None,
        baud: int = 38400,
        motors: Sequence[int] = (1, 2, 3, 4),
        lcv: bool = True,
        lcpg: bool = True,
        lfv: bool = False,
        lfs: bool = True,
        lfap: bool = True,
        lfdp: bool = False,
        lft: bool = False,
        lcvc: int = 1,
        lfvc: int = 1,
        lfdpc: int = 1,
        lfdpd: bool = False,
        firmware_profile: str = "4.3",
        arm: ArmSchedule | None = None,
        shake: bool = False,
        placement: PlacementRanges | None = None,
        success_height: float = 0.03,
        reward_weights: GraspRewardWeights | None = None,
        randomize: bool = True,
        randomization: RandomizationRanges | None = None,
        plant_parameters=None,
        privileged: bool = False,
        render_mode: str | None = None,
        render_size: tuple[int, int] = (320, 240),
        safety=None,
    ):
        if object_files is not None:  # replaces object_set; an empty list is an error, not primitives
            self.object_set = ObjectSet.from_files(object_files)
        elif isinstance(object_set, ObjectSet):
            self.object_set = object_set
        else:
            self.object_set = ObjectSet.named(object_set)
        check_switch("shake", shake)
        arm = dataclass_from(ArmSchedule, arm, "arm")
        if shake and arm.shake_amplitude == 0.0:
            arm = ArmSchedule(arm.grasp_seconds, arm.lift_seconds, arm.hold_seconds, arm.lift_height,
                              SHAKE_AMPLITUDE, arm.shake_frequency)
        self.arm = arm
        self.placement = dataclass_from(PlacementRanges, placement, "placement")
        self.success_height = float(success_height)
        self.weights = dataclass_from(GraspRewardWeights, reward_weights, "reward_weights")
        self._n_phases = len(ArmSchedule.PHASES)
        super().__init__(
            motors=motors,
            flags=MotorFlags(LCV=lcv, LCPG=lcpg, LFV=lfv, LFS=lfs, LFAP=lfap, LFDP=lfdp),
            lft=lft, lcvc=lcvc, lfvc=lfvc, lfdpc=lfdpc, lfdpd=lfdpd, baud=baud,
            firmware_profile=firmware_profile, extra_motor_settings="",
            episode_seconds=arm.total_seconds, randomize=randomize, randomization=randomization,
            plant_parameters=plant_parameters, privileged=privileged, render_mode=render_mode,
            render_size=render_size, safety=safety,
        )
        self._phase_durations = self.arm.durations

    def _world_built(self) -> None:
        import pybullet

        self._p = pybullet
        hand = self.plant.hand_id
        client = self.plant.client
        links = {pybullet.getJointInfo(hand, j, physicsClientId=client)[12].decode(): j
                 for j in range(pybullet.getNumJoints(hand, physicsClientId=client))}
        self._tip_links = [links[f"f{k}_tip"] for k in (1, 2, 3)]
        # Contacts count per finger: any of its links (knuckle, inner, outer, tip) touching.
        self._finger_of_link = {links[f"f{k}_{part}"]: k - 1 for k in (1, 2, 3)
                                for part in ("inner", "outer", "tip")}
        self._hand = hand
        self._client = client

    # ------------------------------------------------------------------ scene and observation

    def _build_scene(self) -> GraspScene:
        return GraspScene(self.plant, self.object_set, self.placement, self.arm, visuals=self.render_mode is not None)

    def _extra_observation_names(self) -> list[str]:
        return [f"phase_{name}" for name in ArmSchedule.PHASES] + ["phase_fraction"]

    def _privileged_observation_names(self) -> list[str]:
        return ["object_dx", "object_dy", "object_dz", "object_rise", "contact_f1", "contact_f2", "contact_f3"]

    def _extra_observation(self, values, elapsed: float) -> list[float]:
        index, in_phase = self.arm.phase(elapsed)
        phases = [0.0] * self._n_phases
        phases[index] = 1.0
        phases.append(min(in_phase / self._phase_durations[index], 1.0))
        return phases

    def _object_state(self):
        p = self._p
        position, _ = p.getBasePositionAndOrientation(self.scene.object_body, physicsClientId=self._client)
        return np.asarray(position)

    def _finger_contacts(self) -> tuple[np.ndarray, bool]:
        """(per-finger touching flags, whether any part of the hand touches the object)."""
        touching = np.zeros(3)
        fingers, any_contact = self._touching_fingers()
        for finger in fingers:
            touching[finger] = 1.0
        return touching, any_contact

    def _touching_fingers(self) -> tuple[set, bool]:
        """(the set of finger indices 0-2 touching the object, whether any part of the hand touches it),
        from one contact query of the last physics step."""
        contacts = self._p.getContactPoints(self._hand, self.scene.object_body, physicsClientId=self._client)
        finger_of_link = self._finger_of_link
        fingers = {finger_of_link.get(contact[3]) for contact in contacts}
        fingers.discard(None)
        return fingers, bool(contacts)

    def _fill_privileged(self, out: np.ndarray) -> None:
        position = self._object_state()
        wrist, _ = self.plant.wrist_pose()
        out[:3] = position - np.asarray(wrist)
        out[3] = position[2] - self.scene.object_rest_z
        out[4:7] = self._finger_contacts()[0]

    def _privileged_info(self) -> dict:
        position = self._object_state()
        return {
            "object_position": position,
            "object_rise": float(position[2] - self.scene.object_rest_z),
            "finger_contacts": self._finger_contacts()[0],
            "object": self.scene.episode.spec,
            "table_top": self.scene.table_top,
        }

    # ------------------------------------------------------------------ reward

    def _reward(self, values, elapsed: float, done: bool):
        p, client, w = self._p, self._client, self.weights
        body = self.scene.object_body
        x, y, z = p.getBasePositionAndOrientation(body, physicsClientId=client)[0]
        distance = 0.0
        for state in p.getLinkStates(self._hand, self._tip_links, physicsClientId=client):
            tip_x, tip_y, tip_z = state[4]
            distance += ((tip_x - x) ** 2 + (tip_y - y) ** 2 + (tip_z - z) ** 2) ** 0.5
        distance /= 3.0
        fingers, held = self._touching_fingers()
        lowest = p.getAABB(body, -1, physicsClientId=client)[0][2]
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

    def _safety_stop_reward(self) -> float:
        return -self.weights.safety_stop

    def _camera(self):
        from bh8_gym.rendering import Camera

        # Fixed on the object's start, wide enough to watch the 10 cm lift.
        return Camera(target=(0.0, 0.0, self.scene.table_top + 0.07), distance=0.5, yaw=40.0, pitch=-18.0)
