"""BH8Grasp-v0: grasp an object on a table with LOOP velocity and gain bytes, then survive the lift."""
from __future__ import annotations

from typing import Sequence

from bh8_gym.envs.arm import ArmSchedule
from bh8_gym.envs.base import BH8LoopEnv
from bh8_gym.envs.interfaces import grasp_interface
from bh8_gym.envs.objects import ObjectSet
from bh8_gym.envs.randomization import RandomizationRanges
from bh8_gym.envs.scenes import PlacementRanges
from bh8_gym.envs.tasks import GraspRewardWeights, GraspTask
from bh8_gym.objects import ObjectSpec
from bh8_gym.settings import dataclass_from


class BH8GraspEnv(BH8LoopEnv):
    """Grasp an object on a table, then hold it while the arm lifts the hand.

    The hand hangs palm-down on an arm above a table with one object (objects.py); a pick pipeline
    placed it with a realistic error (scenes.PlacementRanges: ±2 cm, ±15°, the palm 0.5-2 cm above
    the object's estimated top). The arm's schedule (arm.ArmSchedule) runs on the host's clock:
    grasp 0.8 s (the policy drives the fingers, the arm is still), lift 0.7 s (the wrist rises
    10 cm), hold 0.5 s (optionally shaking). At 38400 baud one step is 6.47 ms (9-byte control
    block + 12-byte feedback block + 1 ms), so an episode is 309 steps.

    ## Action Space
    ``Box(int16)``, one datum per LOOP control field (`env.layout.control_fields`): per motor 1-4
    LCV (signed velocity byte, LCVC 1: 1/16 count per sample per unit; within the safety envelope,
    ±100 by default) and LCPG (gain byte 0..255: the grasp force, U = LCPG/4 × velocity error,
    §6.1). `wrappers.ContinuousActions` maps floats in [-1, 1] onto these bytes.

    ## Observation Space
    ``Box(float32)``, named by `env.observation_fields`: LFS of the fingers and LFAP of each motor
    (scaled, loop_interface.py), the previous action in [-1, 1], the episode's elapsed fraction,
    a one-hot of the arm's phase and the fraction of that phase elapsed. With `privileged=True`:
    the object's position from the wrist, its rise and per-finger contacts (simulation only).

    ## Rewards
    Each term in info["reward_terms"]: "reach" −w·mean fingertip-to-object distance / 10 cm;
    "contact" +w·(fingers touching)/3; "lift" +w·clip(object rise / lift height, 0, 1);
    "success" +bonus on the last step if successful; "safety" −penalty on a safety stop.
    Success: the object's lowest point is more than `success_height` above the table and it touches
    the hand (info["is_success"] every step; the last step's value is the episode's result).

    ## Starting State
    The snapshot taken after the setup script and LOOP entry (fingers open after HI), the plant's
    parameters and the firmware's latency drawn when `randomize`, an object drawn from the object
    set and placed under the palm.

    ## Episode End
    The end of the arm's schedule ends the episode as `terminated`: it is part of the task (the
    observation has the clock), so learners must not bootstrap a value past it. A finger's strain
    above the safety envelope's limit terminates it too (info["safety_stop"]).

    ## Arguments
    - ``object_set`` ("primitives"), ``object_files``: the objects (objects.ObjectSet.named,
      ObjectSet.from_files, which replaces the set);
    - ``baud`` (38400), ``motors``, ``lcv``, ``lcpg``, ``lfv``, ``lfs``, ``lfap``, ``lfdp``,
      ``lft``, ``lcvc``, ``lfvc``, ``lfdpc``, ``lfdpd``, ``firmware_profile`` ("4.3"): the LOOP
      configuration (envs.interfaces.grasp_interface has the defaults);
    - ``arm`` (ArmSchedule), ``shake`` (False: ±1 cm at 2 Hz during hold);
    - ``placement`` (PlacementRanges), ``success_height`` (0.03 m), ``reward_weights``
      (GraspRewardWeights);
    - ``randomize`` (True), ``randomization`` (RandomizationRanges), ``plant_parameters``,
      ``hand_parameters`` (a hand file from `bh8 calibrate fit`: the hand's measured parameters, and
      randomisation about them, randomization.calibrated_ranges);
    - ``privileged`` (False), ``safety`` (SafetyEnvelope), ``render_mode``, ``render_size``.
    """

    env_id = "BH8Grasp-v0"

    def __init__(
        self,
        *,
        object_set: str | ObjectSet = "primitives",
        object_files: Sequence[str | ObjectSpec] | None = None,
        placement: PlacementRanges | None = None,
        success_height: float = 0.03,
        reward_weights: GraspRewardWeights | None = None,
        randomize: bool = True,
        randomization: RandomizationRanges | None = None,
        plant_parameters=None,
        hand_parameters=None,
        render_mode: str | None = None,
        render_size: tuple[int, int] = (320, 240),
        **loop_options,
    ):
        if object_files is not None:  # replaces object_set; an empty list is an error, not primitives
            object_set = ObjectSet.from_files(object_files)
        elif not isinstance(object_set, ObjectSet):
            object_set = ObjectSet.named(object_set)
        self.object_set = object_set
        interface = grasp_interface(**loop_options)
        self.arm: ArmSchedule = interface.task.arm
        self.placement = dataclass_from(PlacementRanges, placement, "placement")
        self.success_height = float(success_height)
        self.weights = dataclass_from(GraspRewardWeights, reward_weights, "reward_weights")
        task = GraspTask(self.object_set, self.placement, self.arm, self.success_height, self.weights,
                         visuals=render_mode is not None)
        super().__init__(interface=interface, task=task, randomize=randomize, randomization=randomization,
                         plant_parameters=plant_parameters, render_mode=render_mode, render_size=render_size,
                         hand_parameters=hand_parameters)
