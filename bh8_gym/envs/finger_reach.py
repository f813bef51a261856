"""BH8FingerReach-v0: drive each LOOP motor to a target encoder position with LOOP velocities."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from bh8_gym.envs.base import BH8LoopEnv
from bh8_gym.envs.interfaces import reach_interface
from bh8_gym.envs.randomization import RandomizationRanges
from bh8_gym.envs.scenes import ReachRanges
from bh8_gym.envs.tasks import ReachTask, ReachTolerance
from bh8_gym.settings import dataclass_from


class BH8FingerReachEnv(BH8LoopEnv):
    """Reach encoder targets: small and quick to learn (minutes of PPO), the hand alone, no object, no arm.

    LOOP configuration: motors 1-4, LCV on, LCPG OFF: the firmware then uses the motor's FPG as the
    LOOP gain (a motor whose LCPG flag is 0 keeps FPG as its gain), so the setup script sets
    `FPG loop_gain`. Default 40: U = 40/4 × velocity error saturates at full duty for an error of
    12.7 counts per sample, so the motor follows the commanded velocity briskly without the action
    having to carry a gain byte; the factory FPG 10 leaves the fingers sluggish. Feedback: LFAP
    only. At 38400 baud a step is 4.65 ms (5 + 9 bytes + 1 ms); a 1 s episode is 215 steps.

    ## Action Space
    ``Box(int16)``: one LCV byte per LOOP motor (with ``lcpg=True`` an LCPG byte after each),
    within the safety envelope.

    ## Observation Space
    ``Box(float32)``, named by `env.observation_fields`: LFAP of each motor / full range, the
    previous action in [-1, 1], the elapsed fraction, then per motor target / full range and
    (target − LFAP) / full range. The host knows the targets: set them for deployment with
    `env.unwrapped.set_targets(counts)`.

    ## Rewards
    "error" = −mean |target − position| / full range per step; "success" = +bonus when every
    motor is within its tolerance (ReachTolerance: 2° of the inner link, 3° of spread).

    ## Starting State
    The hand after HI, palm up in free space (no table), targets drawn per motor from
    scenes.ReachRanges; plant parameters and latency drawn when `randomize`.

    ## Episode End
    Terminated on success; truncated when the host's clock reaches ``episode_seconds``; terminated
    on a safety stop.

    ## Arguments
    - ``baud`` (38400), ``motors``, ``lcpg`` (False), ``loop_gain`` (40), ``lcvc``, ``lft``,
      ``firmware_profile``, ``episode_seconds`` (1.0), ``safety``, ``privileged``: the loop
      (envs.interfaces.reach_interface has the defaults);
    - ``targets`` (ReachRanges), ``tolerance`` (ReachTolerance), ``success_bonus`` (1.0);
    - ``randomize`` (True), ``randomization``, ``plant_parameters``, ``hand_parameters`` (a hand file
      from `bh8 calibrate fit`, as BH8Grasp-v0's), ``render_mode``, ``render_size``.
    """

    env_id = "BH8FingerReach-v0"

    def __init__(
        self,
        *,
        targets: ReachRanges | None = None,
        tolerance: ReachTolerance | None = None,
        success_bonus: float = 1.0,
        randomize: bool = True,
        randomization: RandomizationRanges | None = None,
        plant_parameters=None,
        hand_parameters=None,
        render_mode: str | None = None,
        render_size: tuple[int, int] = (320, 240),
        **loop_options,
    ):
        interface = reach_interface(**loop_options)
        self.ranges = dataclass_from(ReachRanges, targets, "targets")
        self.tolerance = dataclass_from(ReachTolerance, tolerance, "tolerance")
        self.success_bonus = float(success_bonus)
        task = ReachTask(interface.task, self.ranges, self.tolerance, self.success_bonus)
        super().__init__(interface=interface, task=task, randomize=randomize, randomization=randomization,
                         plant_parameters=plant_parameters, render_mode=render_mode, render_size=render_size,
                         hand_parameters=hand_parameters)

    @property
    def targets(self) -> np.ndarray:
        """This episode's target encoder counts, one per LOOP motor (a copy; see `set_targets`)."""
        return np.array(self.interface.task.targets)

    def set_targets(self, counts: Sequence[int]) -> None:
        """Set the targets (encoder counts, one per LOOP motor), e.g. for deployment."""
        counts = np.asarray(counts, dtype=np.float64)
        if counts.shape != (len(self.motors),) or not np.all(np.isfinite(counts)):
            raise ValueError(f"targets must be {len(self.motors)} finite encoder counts, got {counts!r}")
        self.task.set_targets(counts.tolist())
