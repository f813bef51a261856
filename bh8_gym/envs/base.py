"""The common core of the BH8 environments: one step is one RealTime (LOOP) cycle through the firmware.

An environment is three parts (panda-gym's robot/task/sim split):

- the host's side, `LoopInterface` (bh8_gym/loop_interface.py): block layout, setup script, baud,
  action and observation spaces, the observation builder and the host's clock. `bh8 deploy` uses
  the same object with a real hand;
- the simulated hand, `simulator.LoopSimulation`: plant and firmware, the setup script run, LOOP
  entered, and the snapshot every reset restores;
- the task (tasks.py): its scene, its reward and its simulator-only observations.

A step encodes the action as a control block, writes it to the emulated firmware, runs the
firmware until it waits for the next block and decodes the feedback block it sent, exactly as
`bh8 deploy` does over a serial cable to a real BH8-262. Each step costs the simulated time SPEC.md
§6 charges: (control + feedback bytes) × 10 / BAUD + the firmware's processing time, nominally
1 ms (`cycle_seconds`); with randomize=True each reset draws the processing time
(RandomizationRanges.processing_time), and `elapsed()`, the host's clock in the observation,
follows the drawn latency.

Reset runs nothing but a `Firmware.restore` of the snapshot (once the scene has made
`WORLD_SHAPE_LIMIT` object shapes, which PyBullet never frees, reset first builds that world and
snapshot afresh), then draws the randomisation (plant parameters, then processing time), places
the episode's scene (`prepare_episode`, which `bh8 serve --env` runs on LOOP entry) and asks for
one feedback block with an "A" header (no control data), which gives the first observation, as
deploy does.

Only things a host knows on real hardware are in the observation. `privileged=True` appends
simulator state (the task's) and puts it in info["privileged"]; `bh8 deploy` refuses such policies.

Safety (`bh8_gym.safety.SafetyEnvelope`, kwarg `safety`): the limits `bh8 deploy` enforces. LCV
actions lie within ±max_velocity, and a step whose feedback shows a finger's strain above
max_strain ends the episode as deploy would stop the hand: terminated, no success,
info["safety_stop"] naming the reading, plus the task's `safety_stop_reward`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from bh8_gym.hand_file import hand_parameters_from
from bh8_gym.envs.randomization import (
    PlantRandomizer,
    RandomizationRanges,
    calibrated_ranges,
    physics_generator,
    sample_plant_parameters,
    sample_processing_time,
)
from bh8_gym.loop_interface import LoopInterface, check_switch
from bh8_gym.plant import PlantParameters
from bh8_gym.rendering import check_image_size, render_frame
from bh8_gym.settings import dataclass_from
from bh8_gym.simulator import LoopSimulation

# PyBullet never frees a collision shape (it refuses to remove one a body has used), and a random
# primitive's shape never repeats, so each such episode kept ~2.5 KB for the life of the world.
# After this many new object shapes, reset builds a fresh world instead of restoring the old one
# (the same trajectories: a seed replays exactly whatever the env ran before). Memory stays bounded.
WORLD_SHAPE_LIMIT = 1024


@dataclass(frozen=True)
class EnvSnapshot:
    """The whole state of one episode at a step: firmware and plant (`FirmwareSnapshot`), the
    task's scene (the arm's clock and wrist), and the env's host-side bookkeeping (clock, previous
    action, haptic history, generators). Opaque: give it back to `BH8LoopEnv.restore`."""

    firmware: Any
    scene: Any
    host: dict


class _FromInterface:
    """An attribute of the env's `LoopInterface`, read through the env (`env.layout`, ...)."""

    def __set_name__(self, owner, name):
        self.name = name

    def __get__(self, env, owner=None):
        return self if env is None else getattr(env.interface, self.name)


class BH8LoopEnv(gym.Env):
    """Base class: a `LoopInterface`, a task and the simulated hand they drive."""

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 30}
    env_id = ""

    # The host's side, read through the env (the names users and `bh8 serve --env` know).
    layout = _FromInterface()
    motors = _FromInterface()
    baud = _FromInterface()
    firmware_profile = _FromInterface()
    coefficients = _FromInterface()
    safety = _FromInterface()
    privileged = _FromInterface()
    episode_seconds = _FromInterface()
    setup_commands = _FromInterface()
    baud_command = _FromInterface()
    loop_command = _FromInterface()
    observation_fields = _FromInterface()
    host_observation_size = _FromInterface()
    cycle_seconds = _FromInterface()
    nominal_processing_time = _FromInterface()
    observation_from_feedback = _FromInterface()
    next_elapsed = _FromInterface()
    nominal_episode_steps = _FromInterface()

    def __init__(
        self,
        *,
        interface: LoopInterface,
        task,
        randomize: bool,
        randomization: RandomizationRanges | None,
        plant_parameters,
        render_mode: str | None,
        render_size: tuple[int, int],
        hand_parameters=None,
    ):
        if render_mode not in (None, "rgb_array", "human"):
            raise ValueError(f"render_mode must be None, 'rgb_array' or 'human', got {render_mode!r}")
        check_switch("randomize", randomize)
        self.interface = interface
        self.task = task
        self.action_space = interface.action_space
        self.observation_space = interface.observation_space
        self.render_mode = render_mode
        self.render_size = tuple(render_size)
        if len(self.render_size) != 2:
            raise ValueError(f"render_size must be (width, height) in pixels, got {render_size!r}")
        try:
            check_image_size(*self.render_size)  # here rather than at the first render()
        except ValueError as error:
            raise ValueError(f"render_size {render_size!r}: {error}") from None
        self.randomize = bool(randomize)
        self.randomization = dataclass_from(RandomizationRanges, randomization, "randomization")
        # One frame per step plays in real time (gymnasium's RecordVideo reads this).
        self.metadata = {**self.metadata, "render_fps": round(1.0 / interface.cycle_seconds)}
        self._obs = np.zeros(len(interface.observation_fields), dtype=np.float32)
        self._n_host = interface.host_observation_size

        base = PlantParameters() if plant_parameters is None else PlantParameters.from_overrides(plant_parameters)
        self.hand_parameters = hand_parameters_from(hand_parameters)
        if self.hand_parameters is not None:
            # A calibrated hand (`bh8 calibrate fit`): its measured values, and randomisation about them.
            overridden = sorted(set(self.hand_parameters.values) & set(plant_parameters or {}))
            if overridden:
                raise ValueError(f"plant_parameters sets {', '.join(overridden)}, which hand_parameters "
                                 f"({self.hand_parameters.source}) sets too: give each once")
            base = self.hand_parameters.plant_parameters(base)
            self.randomization = calibrated_ranges(self.randomization, self.hand_parameters.values,
                                                   self.hand_parameters.uncertainty)
        self._base_parameters = task.plant_parameters(base)
        self._build_world()

        self._prev_action: list[int] = [0] * len(interface.layout.control_fields)
        self._elapsed = 0.0
        self._processing_time = interface.nominal_processing_time
        self._physics_rng: np.random.Generator | None = None
        self._episode_started = False
        self._cycles = 0
        self._last_values: tuple[int, ...] = ()
        self._history = interface.new_history()

    def _build_world(self) -> None:
        """The simulated hand in LOOP, the task's scene, the snapshot every reset restores."""
        self.simulation = LoopSimulation(self.interface, self._base_parameters, self.task.build_scene,
                                         gui=self.render_mode == "human")
        self.plant, self.firmware, self.scene = self.simulation.plant, self.simulation.firmware, self.simulation.scene
        self._randomizer = PlantRandomizer(self.plant, self.firmware)

    def _renew_world_if_full(self) -> None:
        """A fresh world once the scene has made WORLD_SHAPE_LIMIT object shapes (not under the
        GUI, whose window it would replace; not from `prepare_episode`, whose firmware `bh8 serve
        --env` holds)."""
        if self.render_mode != "human" and getattr(self.scene, "shapes_created", 0) >= WORLD_SHAPE_LIMIT:
            self.simulation.close()
            self._build_world()

    # ------------------------------------------------------------------ helpers

    def _cycle(self, block: bytes) -> tuple[int, ...]:
        if self.firmware is None:
            raise self._closed_error()
        self._feedback_block = self.simulation.cycle(block)
        self._cycles += 1
        self.task.new_cycle()
        return self.interface.layout.decode_feedback(self._feedback_block)

    def __getstate__(self):
        raise TypeError(f"{type(self).__name__} holds a PyBullet simulation and cannot be pickled or copied; "
                        "give vector envs a factory instead (e.g. lambda: gym.make(...))")

    def elapsed(self) -> float:
        """Seconds of the host's clock since its first block of this episode (the reset's "A" block).

        The clock the firmware charges (SPEC.md §6): each cycle's block bytes at BAUD plus the
        firmware's processing time, so it follows a randomised latency. It is summed from 0 at
        the reset's "A" block by `next_elapsed`, in the firmware's order of additions, so a host
        that knows the latency (`bh8 deploy --clock cycles`, nominal latency) gets the same bits.
        """
        return self._elapsed

    def longest_episode_steps(self) -> int:
        """The most steps an episode can take: on the fastest randomised latency (nominal without
        randomisation). A TimeLimit shorter than this cuts episodes before their end."""
        fastest = self.interface.nominal_processing_time
        if self.randomize:
            fastest = min(fastest, self.randomization.processing_time[0])
        return self.interface.episode_steps(fastest)

    def _observation(self, values) -> np.ndarray:
        obs = self._obs
        self.interface.fill_host_observation(obs, values, self._prev_action, self._elapsed, self._history)
        if self.interface.privileged:
            self.task.fill_privileged(obs[self._n_host:])
        return obs.copy()

    # ------------------------------------------------------------------ gymnasium API

    def prepare_episode(self, seed: int | None = None, keep_io: bool = False) -> None:
        """Everything `reset` does before its "A" block: seed `np_random` (as gym.Env.reset), remove
        the object, restore the post-LOOP snapshot, randomise the plant and the firmware's
        processing time (with randomize=False the restore puts back the firmware's default), then
        draw and place the episode's scene.

        `bh8 serve --env` calls this when a client enters LOOP, so the served hand is the state
        this env's reset gives; the client's first block then plays the part of the "A" block.
        `keep_io=True` keeps the firmware's pending serial bytes across the restore (the served
        LOOP's "*" and any control block that came with the LOOP command).
        """
        if self.firmware is None:
            raise self._closed_error()
        super().reset(seed=seed)
        if seed is not None or self._physics_rng is None:
            self._physics_rng = physics_generator(self.np_random)  # a seed's scenes do not depend on randomize
        self.scene.remove_object()
        self.firmware.restore(self.simulation.snapshot, keep_io=keep_io)
        if self.randomize:
            params = sample_plant_parameters(self._base_parameters, self._physics_rng, self.randomization)
            self._randomizer.apply(params, sample_processing_time(self._physics_rng, self.randomization))
        self.task.begin_episode(self.np_random)
        self._processing_time = self.firmware.processing_time
        self._elapsed = 0.0
        self._prev_action = [0] * len(self._prev_action)
        if self._history is not None:
            self._history.reset()
        self._cycles = 0
        self._episode_started = True

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        if self.firmware is not None:
            self._renew_world_if_full()
        self.prepare_episode(seed)
        start = self.interface.start_block
        values = self._cycle(start)
        self._elapsed = self.interface.next_elapsed(0.0, len(start), self._processing_time)
        self._last_values = values
        info = {"control_block": start, "feedback_block": self._feedback_block}
        if self.interface.privileged:
            info["privileged"] = self.task.privileged_info()
        return self._observation(values), info

    def step(self, action):
        if not self._episode_started:
            raise gym.error.ResetNeeded("call reset() before step()") if self.firmware is not None else self._closed_error()
        interface = self.interface
        control = interface.validate_action(action)
        block = interface.encode_action(control)
        values = self._cycle(block)
        self._prev_action = control
        self._last_values = values
        elapsed = self._elapsed = interface.next_elapsed(self._elapsed, interface.control_block_size, self._processing_time)
        truncated = interface.episode_over(elapsed)
        reward, terms, success, terminated = self.task.reward(values, elapsed, truncated)
        info = {
            "control_block": block,
            "feedback_block": self._feedback_block,
            "is_success": success,
            "reward_terms": terms,
            "time": elapsed,
        }
        stop = interface.strain_violation(values)
        if stop is not None:  # bh8 deploy would stop the hand here: the episode ends, unsuccessful
            terms = {**terms, "safety": self.task.safety_stop_reward()}
            if "success" in terms:
                terms["success"] = 0.0
            reward = sum(terms.values())
            terminated, info["is_success"], info["reward_terms"], info["safety_stop"] = True, False, terms, stop
        if interface.privileged:
            info["privileged"] = self.task.privileged_info()
        if self.render_mode == "human":
            self.render()
        return self._observation(values), reward, terminated, truncated and not terminated, info

    # ------------------------------------------------------------------ snapshot and branch

    def snapshot(self) -> EnvSnapshot:
        """The episode's state after the last step, to branch from: `restore` it, step one
        continuation, `restore` it again, step another. Every branch starts from the same
        state, whatever the others did (the plant renews its contact pairs on restore, as reset
        does), so a continuation's outcome does not depend on the branches run before it.
        Call `release` when done with it (PyBullet keeps a saved state until removed)."""
        if not self._episode_started:
            raise gym.error.ResetNeeded("snapshot() needs an episode: call reset() first")
        host = {
            "prev_action": list(self._prev_action), "elapsed": self._elapsed, "processing_time": self._processing_time,
            "cycles": self._cycles, "last_values": self._last_values, "feedback_block": self._feedback_block,
            "history": None if self._history is None else self._history.copy(),
            "np_random": self.np_random.bit_generator.state,
            "physics_rng": None if self._physics_rng is None else self._physics_rng.bit_generator.state,
        }
        return EnvSnapshot(self.firmware.snapshot(), self.scene.snapshot_state(), host)

    def restore(self, snapshot: EnvSnapshot) -> None:
        """Return the episode to `snapshot` (taken by this env in this episode's world)."""
        if not isinstance(snapshot, EnvSnapshot):
            raise TypeError(f"restore() needs an EnvSnapshot, got {type(snapshot).__name__}")
        if self.firmware is None:
            raise self._closed_error()
        host = snapshot.host
        self.firmware.restore(snapshot.firmware)
        self.scene.restore_state(snapshot.scene)
        self._prev_action = list(host["prev_action"])
        self._elapsed, self._processing_time = host["elapsed"], host["processing_time"]
        self._cycles, self._last_values = host["cycles"], host["last_values"]
        self._feedback_block = host["feedback_block"]
        self._history = None if host["history"] is None else host["history"].copy()
        self.np_random.bit_generator.state = host["np_random"]
        if host["physics_rng"] is not None:
            self._physics_rng.bit_generator.state = host["physics_rng"]
        self._episode_started = True

    def release(self, snapshot: EnvSnapshot) -> None:
        """Free the PyBullet state `snapshot` holds (it cannot be restored after)."""
        self.plant.remove_state(snapshot.firmware.plant_state)

    def render(self):
        if self.firmware is None:
            raise self._closed_error()
        if self.render_mode == "rgb_array":
            return render_frame(self.plant, *self.render_size, camera=self.task.camera())
        return None

    def _closed_error(self) -> gym.error.ClosedEnvironmentError:
        return gym.error.ClosedEnvironmentError(f"{type(self).__name__} is closed; make a new env")

    def close(self):
        if getattr(self, "firmware", None) is not None:
            self.simulation.close()
            self.firmware = None
