"""The host side of each environment: its `LoopInterface` from its keyword arguments, without PyBullet.

`grasp_interface` and `reach_interface` take the keyword arguments of BH8Grasp-v0 and
BH8FingerReach-v0 that shape the loop (LOOP flags, coefficients, baud, the arm's schedule or the
reach's gain, the safety envelope) with their defaults; the environments build their interface
with them, and `interface_for(env_id, env_kwargs)` builds the same one for `bh8 deploy` from a
policy file's metadata, on a computer that has only the hand. The simulator's keyword arguments
(scene, reward, randomisation, rendering) are set apart in `SIMULATOR_OPTIONS`.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Any, Mapping, Sequence

import gymnasium as gym
import numpy as np

from bh8_gym.envs import register_envs
from bh8_gym.envs.arm import ArmSchedule
from bh8_gym.loop_interface import FULL_RANGE_COUNTS, LoopInterface, check_switch, loop_layout
from bh8_gym.realtime_codec import LoopLayout, MotorFlags
from bh8_gym.safety import SafetyEnvelope
from bh8_gym.settings import dataclass_from

SHAKE_AMPLITUDE = 0.01  # metres; `shake=True` shakes the wrist ±1 cm at 2 Hz during hold
# Privileged (simulation-only) entries of the grasp observation, in order (`tasks.GraspTask` fills them).
GRASP_PRIVILEGED_NAMES = ("object_dx", "object_dy", "object_dz", "object_rise", "contact_f1", "contact_f2", "contact_f3",
                          "object_box", "object_capsule", "object_cylinder", "object_sphere", "object_mesh",
                          "object_width_x", "object_width_y", "object_height", "object_mass", "object_friction")


class ArmPhaseObservation:
    """The grasp's task entries: a one-hot of the arm's phase and the fraction of that phase elapsed."""

    privileged_names = GRASP_PRIVILEGED_NAMES

    def __init__(self, arm: ArmSchedule):
        self.arm = arm
        self.names = tuple(f"phase_{name}" for name in ArmSchedule.PHASES) + ("phase_fraction",)
        self._n_phases = len(ArmSchedule.PHASES)
        self._durations = arm.durations

    def values(self, feedback, elapsed: float) -> list[float]:
        index, in_phase = self.arm.phase(elapsed)
        phases = [0.0] * self._n_phases
        phases[index] = 1.0
        phases.append(min(in_phase / self._durations[index], 1.0))
        return phases


class ReachTargetObservation:
    """The reach's task entries: each motor's target / full range, then (target − LFAP) / full range.

    The host knows the targets (`set`, e.g. for deployment); zeros until the first are set."""

    privileged_names = ()

    def __init__(self, layout: LoopLayout):
        self.motors = layout.motors
        self.names = tuple(f"target{m}" for m in self.motors) + tuple(f"error{m}" for m in self.motors)
        fields = layout.feedback_fields
        # Plain lists: a handful of values per step, cheaper in Python than in numpy.
        self.lfap_index = [fields.index((m, "LFAP")) for m in self.motors]
        self.full_range = [float(FULL_RANGE_COUNTS[m]) for m in self.motors]
        self.targets = [0.0] * len(self.motors)

    def set(self, counts: Sequence[float]) -> None:
        self.targets = [float(c) for c in counts]

    def values(self, feedback, elapsed: float) -> list[float]:
        targets, full_range = self.targets, self.full_range
        return [t / r for t, r in zip(targets, full_range)] + [
            (t - feedback[i]) / r for t, i, r in zip(targets, self.lfap_index, full_range)]


def grasp_arm(arm: ArmSchedule | Mapping | None = None, shake: bool = False) -> ArmSchedule:
    """The grasp's arm schedule: `arm` (or the default), shaking during hold if `shake` and it does not."""
    check_switch("shake", shake)
    arm = dataclass_from(ArmSchedule, arm, "arm")
    if shake and arm.shake_amplitude == 0.0:
        arm = replace(arm, shake_amplitude=SHAKE_AMPLITUDE)
    return arm


def grasp_interface(
    *,
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
    arm: ArmSchedule | Mapping | None = None,
    shake: bool = False,
    safety: SafetyEnvelope | Mapping | None = None,
    privileged: bool = False,
    history: bool = False,
) -> LoopInterface:
    """BH8Grasp-v0's loop (the lead's design): motors 1-4 with LCV and LCPG, feedback LFS and LFAP;
    the episode is the arm's schedule; `history` adds the haptic history (haptic_history.py)."""
    arm = grasp_arm(arm, shake)
    flags = MotorFlags(LCV=lcv, LCPG=lcpg, LFV=lfv, LFS=lfs, LFAP=lfap, LFDP=lfdp)
    return LoopInterface(
        layout=loop_layout(motors, flags, lft, firmware_profile), flags=flags, lcvc=lcvc, lfvc=lfvc,
        lfdpc=lfdpc, lfdpd=lfdpd, baud=baud, extra_motor_settings="", episode_seconds=arm.total_seconds,
        task=ArmPhaseObservation(arm), safety=dataclass_from(SafetyEnvelope, safety, "safety"),
        privileged=privileged, history=history,
    )


def reach_interface(
    *,
    baud: int = 38400,
    motors: Sequence[int] = (1, 2, 3, 4),
    lcpg: bool = False,
    loop_gain: int = 40,
    lcvc: int = 1,
    lft: bool = False,
    firmware_profile: str = "4.3",
    episode_seconds: float = 1.0,
    safety: SafetyEnvelope | Mapping | None = None,
    privileged: bool = False,
) -> LoopInterface:
    """BH8FingerReach-v0's loop: LCV (and LCPG only if `lcpg`; else the setup sets FPG `loop_gain`,
    the LOOP gain of a motor without LCPG), feedback LFAP."""
    if not (isinstance(loop_gain, (int, np.integer)) and 0 <= loop_gain <= 255):
        raise ValueError(f"loop_gain (FPG) must be an integer 0..255, got {loop_gain!r}")
    flags = MotorFlags(LCV=True, LCPG=lcpg, LFV=False, LFS=False, LFAP=True, LFDP=False)
    layout = loop_layout(tuple(sorted(set(int(m) for m in motors))), flags, lft, firmware_profile)
    return LoopInterface(
        layout=layout, flags=flags, lcvc=lcvc, lfvc=1, lfdpc=1, lfdpd=False, baud=baud,
        extra_motor_settings="" if lcpg else f"FPG {int(loop_gain)}", episode_seconds=episode_seconds,
        task=ReachTargetObservation(layout), safety=dataclass_from(SafetyEnvelope, safety, "safety"),
        privileged=privileged,
    )


HOST_INTERFACES = {"BH8Grasp-v0": grasp_interface, "BH8FingerReach-v0": reach_interface}
# The environments' keyword arguments that only the simulator uses (scene, reward, randomisation, rendering).
SIMULATOR_OPTIONS = {
    "BH8Grasp-v0": frozenset({"object_set", "object_files", "placement", "success_height", "reward_weights",
                              "randomize", "randomization", "plant_parameters", "hand_parameters", "render_mode",
                              "render_size"}),
    "BH8FingerReach-v0": frozenset({"targets", "tolerance", "success_bonus", "randomize", "randomization",
                                    "plant_parameters", "hand_parameters", "render_mode", "render_size"}),
}


def host_options(env_id: str, env_kwargs: Mapping[str, Any] | None) -> dict:
    """The keyword arguments of `env_kwargs` that shape the host's side (everything but
    SIMULATOR_OPTIONS): an env built for another object set or physics must share them to run
    the same policy."""
    simulator = SIMULATOR_OPTIONS.get(env_id, frozenset())
    return {k: v for k, v in (env_kwargs or {}).items() if k not in simulator}


def interface_for(env_id: str, env_kwargs: Mapping[str, Any] | None = None) -> LoopInterface:
    """The LoopInterface of `gym.make(env_id, **env_kwargs)` (its registered keyword arguments
    included), built without the simulator. ValueError for an unknown id or keyword."""
    register_envs()
    try:
        spec = gym.spec(env_id)
    except gym.error.Error as error:
        raise ValueError(f"unknown environment {env_id!r} ({error}); bh8-gym has {', '.join(HOST_INTERFACES)}") from None
    if spec.id not in HOST_INTERFACES:
        raise ValueError(f"{env_id!r} is not a bh8-gym RealTime environment")
    kwargs = {**spec.kwargs, **(env_kwargs or {})}
    simulator = SIMULATOR_OPTIONS[spec.id]
    try:
        return HOST_INTERFACES[spec.id](**{k: v for k, v in kwargs.items() if k not in simulator})
    except TypeError as error:
        raise ValueError(f"{env_id}: {error}") from None
