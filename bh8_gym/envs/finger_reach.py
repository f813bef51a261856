"""BH8FingerReach-v0: drive each LOOP motor to a target encoder position with LOOP velocities.

Small and quick to learn (minutes of PPO): the hand alone, no object, no arm. Each episode draws
a target per motor (scenes.ReachRanges); the host knows them, so they are in the observation
(target / full range, and the remaining error (target − LFAP) / full range). Set them for
deployment with `env.unwrapped.set_targets(counts)`.

LOOP configuration: motors 1-4, LCV on, LCPG OFF: the firmware then uses the motor's FPG as the
LOOP gain (firmware.py: "a motor whose LCPG flag is 0 keeps FPG as its gain"), so the setup
script sets `FPG loop_gain`. Default 40: U = 40/4 × velocity error saturates at full duty for
an error of 12.7 counts per sample, so the motor follows the commanded velocity briskly without
the action having to carry a gain byte; the factory FPG 10 leaves the fingers sluggish.
Feedback: LFAP only. At 38400 baud a step is 4.65 ms (5 + 9 bytes + 1 ms); a 1 s episode is 215 steps.

Reward: "error" = −mean |target − position| / full range per step; "success" = +bonus when every
motor is within its tolerance, which ends the episode (terminated).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from bh8_gym.envs.base import FULL_RANGE_COUNTS, BH8LoopEnv
from bh8_gym.envs.randomization import RandomizationRanges
from bh8_gym.envs.scenes import ReachEpisode, ReachRanges, ReachScene
from bh8_gym.plant import dataclass_from
from bh8_gym.realtime_codec import MotorFlags


@dataclass(frozen=True)
class ReachTolerance:
    """Success tolerance, encoder counts: 2° of the inner link (fingers), 3° of spread."""

    finger: int = 250
    spread: int = 52


class BH8FingerReachEnv(BH8LoopEnv):
    """Reach encoder targets; see the module docstring."""

    env_id = "BH8FingerReach-v0"

    def __init__(
        self,
        *,
        baud: int = 38400,
        motors: Sequence[int] = (1, 2, 3, 4),
        lcpg: bool = False,
        loop_gain: int = 40,
        lcvc: int = 1,
        lft: bool = False,
        firmware_profile: str = "4.3",
        episode_seconds: float = 1.0,
        targets: ReachRanges | None = None,
        tolerance: ReachTolerance | None = None,
        success_bonus: float = 1.0,
        randomize: bool = True,
        randomization: RandomizationRanges | None = None,
        plant_parameters=None,
        privileged: bool = False,
        render_mode: str | None = None,
        render_size: tuple[int, int] = (320, 240),
        safety=None,
    ):
        if not (isinstance(loop_gain, (int, np.integer)) and 0 <= loop_gain <= 255):
            raise ValueError(f"loop_gain (FPG) must be an integer 0..255, got {loop_gain!r}")
        self.ranges = dataclass_from(ReachRanges, targets, "targets")
        self.tolerance = dataclass_from(ReachTolerance, tolerance, "tolerance")
        self.success_bonus = float(success_bonus)
        self.loop_gain = int(loop_gain)
        motors = tuple(sorted(set(int(m) for m in motors)))
        super().__init__(
            motors=motors,
            flags=MotorFlags(LCV=True, LCPG=lcpg, LFV=False, LFS=False, LFAP=True, LFDP=False),
            lft=lft, lcvc=lcvc, lfvc=1, lfdpc=1, lfdpd=False, baud=baud,
            firmware_profile=firmware_profile,
            extra_motor_settings="" if lcpg else f"FPG {self.loop_gain}",
            episode_seconds=episode_seconds, randomize=randomize, randomization=randomization,
            plant_parameters=plant_parameters, privileged=privileged, render_mode=render_mode,
            render_size=render_size, safety=safety,
        )
        fields = self.layout.feedback_fields
        # Plain lists: a handful of values per step, cheaper in Python than in numpy.
        self._lfap_index = [fields.index((m, "LFAP")) for m in self.motors]
        self._full_range = [float(FULL_RANGE_COUNTS[m]) for m in self.motors]
        self._tolerances = [self.tolerance.spread if m == 4 else self.tolerance.finger for m in self.motors]
        self._targets = [0.0] * len(self.motors)

    def _plant_parameters(self, params):
        # No table: the hand reaches in free space (and PyBullet has one body fewer to collide).
        return replace(params, table=False)

    def _build_scene(self) -> ReachScene:
        return ReachScene(self.plant, self.motors, self.ranges)

    def _begin_episode(self, rng: np.random.Generator) -> None:
        episode = self.scene.sample_episode(rng)
        self.scene.begin_episode(episode)
        self._targets = [float(t) for t in episode.targets]

    @property
    def targets(self) -> np.ndarray:
        """This episode's target encoder counts, one per LOOP motor (a copy; see `set_targets`)."""
        return np.array(self._targets)

    def set_targets(self, counts: Sequence[int]) -> None:
        """Set the targets (encoder counts, one per LOOP motor), e.g. for deployment."""
        counts = np.asarray(counts, dtype=np.float64)
        if counts.shape != (len(self.motors),) or not np.all(np.isfinite(counts)):
            raise ValueError(f"targets must be {len(self.motors)} finite encoder counts, got {counts!r}")
        self.scene.begin_episode(ReachEpisode(tuple(int(c) for c in counts)))
        self._targets = counts.tolist()

    def _extra_observation_names(self) -> list[str]:
        return [f"target{m}" for m in self.motors] + [f"error{m}" for m in self.motors]

    def _extra_observation(self, values, elapsed: float) -> list[float]:
        targets, full_range = self._targets, self._full_range
        return [t / r for t, r in zip(targets, full_range)] + [
            (t - values[i]) / r for t, i, r in zip(targets, self._lfap_index, full_range)]

    def _privileged_info(self) -> dict:
        return {"motor_positions": self.plant.motor_positions(), "joint_angles": self.plant.joint_angles()}

    def _reward(self, values, elapsed: float, done: bool):
        errors = [abs(t - values[i]) for t, i in zip(self._targets, self._lfap_index)]
        success = all(e <= tolerance for e, tolerance in zip(errors, self._tolerances))
        terms = {
            "error": -(sum(e / r for e, r in zip(errors, self._full_range)) / len(errors)),
            "success": self.success_bonus if success else 0.0,
        }
        return terms["error"] + terms["success"], terms, success, success
