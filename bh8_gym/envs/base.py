"""The common core of the BH8 environments: one step is one RealTime (LOOP) cycle through the firmware.

A step encodes the action as a control block with `realtime_codec.LoopLayout`, writes it to the
emulated firmware, runs the firmware until it waits for the next block and decodes the feedback
block it sent, exactly as `bh8 deploy` does over a serial cable to a real BH8-262. Each step costs
the simulated time SPEC.md §6 charges: (control + feedback bytes) × 10 / BAUD + the firmware's
processing time, nominally 1 ms (`cycle_seconds` is that nominal figure); with randomize=True each
reset draws the processing time (RandomizationRanges.processing_time), and `elapsed()`, the
host's clock in the observation, follows the drawn latency.

Reset runs nothing but a `Firmware.restore` of a snapshot taken once at construction, after the
supervisory setup script (`setup_commands` then `loop_command`: the very lines `bh8 deploy` sends
to a real hand) has run (once the scene has made `WORLD_SHAPE_LIMIT` object shapes, which PyBullet
never frees, reset first builds that world and snapshot afresh), then draws the randomisation (plant parameters, then processing time),
places the episode's scene (`prepare_episode`, which `bh8 serve --env` runs on LOOP entry) and asks
for one feedback block with an "A" header (no control data), which gives the first observation,
as deploy does.

Observation (float32, `observation_fields` names every entry):

- the decoded feedback fields the LOOP flags enable, coefficients applied, scaled to about
  [-1, 1]: LFV × LFVC / 16 (counts per sample, full speed ≈ 14), (LFS − 128) / 128, LFAP / full
  range (17,500 fingers, 3,150 spread: SPEC.md §1), LFDP × LFDPC / 128 (counts; with LFDPC > 1
  up to ±LFDPC), LFT / 1000 (tenths °C; 4.4: /100);
- the previous action, each datum mapped to [-1, 1] (`wrappers.bytes_to_unit`);
- the fraction of the episode's time elapsed (the host's clock since its first block), then what
  the subclass adds (the arm's phase for grasping, the targets for reaching).

Only things a host knows on real hardware are in it. `privileged=True` appends simulator state
(object pose, contacts) and puts it in info["privileged"]; `bh8 deploy` refuses such policies.

Safety (`bh8_gym.safety.SafetyEnvelope`, kwarg `safety`): the limits `bh8 deploy` enforces. LCV
actions lie within ±max_velocity, and a step whose feedback shows a finger's strain above
max_strain ends the episode as deploy would stop the hand: terminated, no success,
info["safety_stop"] naming the reading, plus the subclass's `_safety_stop_reward`.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Any, Sequence

import gymnasium as gym
import numpy as np

from bh8_gym.envs.randomization import (
    PlantRandomizer,
    RandomizationRanges,
    physics_generator,
    sample_plant_parameters,
    sample_processing_time,
)
from bh8_gym.protocol import BAUD_RATES, BITS_PER_BYTE, SPREAD_MOTOR
from bh8_gym.realtime_codec import HEADER_CONTROL_FEEDBACK, HEADER_FEEDBACK, LoopLayout, MotorFlags
from bh8_gym.safety import SafetyEnvelope

FULL_RANGE_COUNTS = {1: 17_500.0, 2: 17_500.0, 3: 17_500.0, 4: 3_150.0}  # SPEC.md §1, BH8-262
VELOCITY_FULL_SCALE = 16.0  # counts per sample: no-load motor speed ≈ 14 counts per 256 µs sample
STRAIN_CENTRE = 128.0
DELTA_FULL_SCALE = 128.0
TEMPERATURE_SCALE = {"4.3": 1000.0, "4.4": 100.0}  # LFT: tenths of °C on 4.3, whole °C on 4.4
# An episode ends when the host's clock reaches episode_seconds less this (float rounding slack).
END_TOLERANCE_S = 1e-9
# PyBullet never frees a collision shape (it refuses to remove one a body has used), and a random
# primitive's shape never repeats, so each such episode kept ~2.5 KB for the life of the world.
# After this many new object shapes, reset builds a fresh world instead of restoring the old one
# (the same trajectories: a seed replays exactly whatever the env ran before). Memory stays bounded.
WORLD_SHAPE_LIMIT = 1024


class FirmwareProtocolError(RuntimeError):
    """The emulated firmware answered something other than the expected block or prompt."""


def check_switch(name: str, value) -> None:
    """An on/off keyword must be a bool (or 0/1): a string such as "false" would otherwise count as on."""
    if not (isinstance(value, (bool, np.bool_)) or (isinstance(value, (int, np.integer)) and value in (0, 1))):
        raise ValueError(f"{name} must be True or False, got {value!r}")


class BH8LoopEnv(gym.Env):
    """Base class; subclasses define the scene, the extra observation entries and the reward."""

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 30}
    env_id = ""

    def __init__(
        self,
        *,
        motors: Sequence[int],
        flags: MotorFlags,
        lft: bool,
        lcvc: int,
        lfvc: int,
        lfdpc: int,
        lfdpd: bool,
        baud: int,
        firmware_profile: str,
        extra_motor_settings: str,
        episode_seconds: float,
        randomize: bool,
        randomization: RandomizationRanges | None,
        plant_parameters,
        privileged: bool,
        render_mode: str | None,
        render_size: tuple[int, int],
        safety: SafetyEnvelope | dict | None = None,
    ):
        if baud not in BAUD_RATES:
            raise ValueError(f"baud must be one of {BAUD_RATES} (manual §5.4.1 BAUD), got {baud!r}")
        if render_mode not in (None, "rgb_array", "human"):
            raise ValueError(f"render_mode must be None, 'rgb_array' or 'human', got {render_mode!r}")
        for name, value in (("lcvc", lcvc), ("lfvc", lfvc), ("lfdpc", lfdpc)):
            if not (isinstance(value, (int, np.integer)) and 1 <= value <= 255):
                raise ValueError(f"{name} must be an integer 1..255 (Table 4), got {value!r}")
        if not episode_seconds > 0:
            raise ValueError(f"episode_seconds must be > 0, got {episode_seconds!r}")
        switches = {"randomize": randomize, "privileged": privileged, "lft": lft, "lfdpd": lfdpd,
                    **{name.lower(): getattr(flags, name) for name in ("LCV", "LCPG", "LFV", "LFS", "LFAP", "LFDP")}}
        for name, value in switches.items():
            check_switch(name, value)
        # The spread has no strain gauge: its LFS would read 255 every cycle (§5.3.2), a byte of the
        # feedback block (and of the cycle time) that tells the policy nothing, so it is not asked for.
        motors = LoopLayout(motors, flags, lft=lft, firmware=firmware_profile).motors  # checked, sorted
        self._spread_lfs_off = bool(flags.LFS) and SPREAD_MOTOR in motors
        spread_flags = replace(flags, LFS=False)
        self.layout = LoopLayout(motors, {m: spread_flags if m == SPREAD_MOTOR else flags for m in motors},
                                 lft=lft, firmware=firmware_profile)
        if not self.layout.control_fields:
            raise ValueError("the LOOP configuration sends no control data (enable LCV or LCPG)")
        if not self.layout.feedback_fields:
            raise ValueError("the LOOP configuration returns no feedback (enable LFV, LFS, LFAP, LFDP or LFT)")
        self.motors = self.layout.motors
        self.baud = int(baud)
        self.firmware_profile = firmware_profile
        self.privileged = bool(privileged)
        self.render_mode = render_mode
        self.render_size = tuple(render_size)
        from bh8_gym.plant import dataclass_from
        from bh8_gym.rendering import check_image_size

        if len(self.render_size) != 2:
            raise ValueError(f"render_size must be (width, height) in pixels, got {render_size!r}")
        try:
            check_image_size(*self.render_size)  # here rather than at the first render()
        except ValueError as error:
            raise ValueError(f"render_size {render_size!r}: {error}") from None
        self.randomize = bool(randomize)
        self.randomization = dataclass_from(RandomizationRanges, randomization, "randomization")
        self.safety = dataclass_from(SafetyEnvelope, safety, "safety")
        self.episode_seconds = float(episode_seconds)
        self.coefficients = {"LCVC": int(lcvc), "LFVC": int(lfvc), "LFDPC": int(lfdpc)}

        prefix = "".join(str(m) for m in self.motors)
        f = flags
        settings = (
            f"LCV {int(f.LCV)} LCVC {lcvc} LCPG {int(f.LCPG)} LFV {int(f.LFV)} LFVC {lfvc} "
            f"LFS {int(f.LFS)} LFAP {int(f.LFAP)} LFDP {int(f.LFDP)} LFDPC {lfdpc}"
        )
        if extra_motor_settings:
            settings += " " + extra_motor_settings
        #: The supervisory script `bh8 deploy` sends to a real hand before `loop_command`.
        #: HI first (it uses the stored gains and velocities), then the LOOP configuration, then
        #: the baud rate last (the host switches its own port rate right after it).
        self.setup_commands: tuple[str, ...] = (
            "HI",
            f"{prefix}FSET {settings}",
            *((f"{SPREAD_MOTOR}FSET LFS 0",) if self._spread_lfs_off else ()),
            f"PSET LFT {int(lft)} LFDPD {int(lfdpd)}",
            f"PSET BAUD {self.baud // 100}",
        )
        self.loop_command = f"{prefix}LOOP"

        control_bytes = self._control_block_size = self.layout.control_block_size(HEADER_CONTROL_FEEDBACK)
        #: Simulated seconds per step (SPEC.md §6): both blocks' bytes at BAUD plus processing.
        from bh8_gym.firmware import REALTIME_PROCESSING_S

        self.cycle_seconds = (control_bytes + self.layout.feedback_size) * BITS_PER_BYTE / self.baud + REALTIME_PROCESSING_S
        # One frame per step plays in real time (gymnasium's RecordVideo reads this).
        self.metadata = {**self.metadata, "render_fps": round(1.0 / self.cycle_seconds)}
        #: The firmware's processing seconds per cycle without randomisation: what a host assumes.
        self.nominal_processing_time = REALTIME_PROCESSING_S
        # The host clock's terms, as the firmware computes a cycle's time (SPEC.md §6).
        self._seconds_per_byte = BITS_PER_BYTE / self.baud
        self._feedback_seconds = self.layout.feedback_size * self._seconds_per_byte

        # Action space: the control data of one block, in control_fields order; LCV inside the envelope.
        velocity_low, velocity_high = self.safety.velocity_bounds
        low = [velocity_low if name == "LCV" else 0 for _, name in self.layout.control_fields]
        high = [velocity_high if name == "LCV" else 255 for _, name in self.layout.control_fields]
        if any(name == "LCT" for _, name in self.layout.control_fields):
            raise ValueError("LCT (firmware 4.4 torque control) is not supported by the environments")
        self.action_space = gym.spaces.Box(np.array(low, np.int16), np.array(high, np.int16), dtype=np.int16)
        self._action_low = self.action_space.low.astype(np.int64)
        self._action_high = self.action_space.high.astype(np.int64)
        self._action_low_f = self._action_low.astype(np.float64)
        self._action_shape = self.action_space.shape
        self._low_list = self._action_low.tolist()
        self._high_list = self._action_high.tolist()
        self._action_high_f = self._action_high.astype(np.float64)

        # Observation layout, precomputed: obs_feedback = (values - offset) * scale.
        offsets, scales, names = [], [], []
        for motor, name in self.layout.feedback_fields:
            names.append(f"{name}{motor}" if motor else name)
            if name == "LFV":
                offsets.append(0.0), scales.append(lfvc / VELOCITY_FULL_SCALE)
            elif name == "LFS":
                offsets.append(STRAIN_CENTRE), scales.append(1.0 / STRAIN_CENTRE)
            elif name == "LFAP":
                offsets.append(0.0), scales.append(1.0 / FULL_RANGE_COUNTS[motor])
            elif name == "LFDP":
                offsets.append(0.0), scales.append(lfdpc / DELTA_FULL_SCALE)
            else:  # LFT
                offsets.append(0.0), scales.append(1.0 / TEMPERATURE_SCALE[firmware_profile])
        self._fb_offset = np.array(offsets)
        self._fb_scale = np.array(scales)
        # Plain-float copies for the per-step observation (see _fill_host).
        self._fb_offset_list, self._fb_scale_list = self._fb_offset.tolist(), self._fb_scale.tolist()
        self._action_centres = ((self._action_low_f + self._action_high_f) / 2.0).tolist()
        self._action_halves = ((self._action_high_f - self._action_low_f) / 2.0).tolist()
        names += [f"prev_{name}{motor}" for motor, name in self.layout.control_fields]
        names.append("episode_fraction")
        names += self._extra_observation_names()
        self._n_host = len(names)
        if self.privileged:
            names += self._privileged_observation_names()
        #: Name of every observation entry, in order.
        self.observation_fields: tuple[str, ...] = tuple(names)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(len(names),), dtype=np.float32)
        self._n_fb = len(self.layout.feedback_fields)
        # (motor, index in the decoded feedback) of each finger's strain: the envelope's check.
        self._strain_fields = [(motor, index) for index, (motor, name) in enumerate(self.layout.feedback_fields)
                               if name == "LFS" and motor != SPREAD_MOTOR]
        self._n_act = len(self.layout.control_fields)
        self._obs = np.zeros(len(names), dtype=np.float32)

        from bh8_gym.plant import PlantParameters

        self._base_parameters = self._plant_parameters(
            PlantParameters() if plant_parameters is None else PlantParameters.from_overrides(plant_parameters))
        self._build_world()

        self._prev_action: list[int] = [0] * self._n_act
        self._feedback_block_size = self.layout.feedback_size
        self._a_block = self.layout.encode_control((), HEADER_FEEDBACK)
        self._elapsed = 0.0
        self._processing_time = self.nominal_processing_time
        self._physics_rng: np.random.Generator | None = None
        self._episode_started = False
        self._cycles = 0
        self._last_values: tuple[int, ...] = ()

    def _build_world(self) -> None:
        """The world, the firmware, the setup script, and the snapshot every reset restores."""
        from bh8_gym.firmware import Firmware
        from bh8_gym.plant import HandPlant

        self.plant = HandPlant(params=self._base_parameters, seed=0, gui=self.render_mode == "human")
        # The store in memory: an env saves nothing between processes (no files, nothing a killed worker leaves).
        self.firmware = Firmware(plant=self.plant, store_dir=None, profile=self.firmware_profile, seed=0)
        self.scene = self._build_scene()
        for line in self.setup_commands:
            self._supervisory(line)
        echo = self.firmware.transact(self.loop_command.encode() + b"\r")
        if echo != self.loop_command.encode() + b"*":
            raise FirmwareProtocolError(f"{self.loop_command!r} answered {echo!r}")
        self.firmware.cycle_hook = self.scene.cycle_hook
        self._snapshot = self.firmware.snapshot()
        self._randomizer = PlantRandomizer(self.plant, self.firmware)
        self._world_built()

    def _renew_world_if_full(self) -> None:
        """A fresh world once the scene has made WORLD_SHAPE_LIMIT object shapes (not under the
        GUI, whose window it would replace; not from `prepare_episode`, whose firmware `bh8 serve
        --env` holds)."""
        if self.render_mode != "human" and getattr(self.scene, "shapes_created", 0) >= WORLD_SHAPE_LIMIT:
            self.plant.close()
            self._build_world()

    # ------------------------------------------------------------------ subclass interface

    def _build_scene(self):
        raise NotImplementedError

    def _world_built(self) -> None:
        """Called after each (re)build of the world: look up PyBullet ids of the new plant here."""

    def _plant_parameters(self, params):
        """The PlantParameters this env builds its plant with (subclasses adapt the world)."""
        return params

    def _extra_observation_names(self) -> list[str]:
        return []

    def _privileged_observation_names(self) -> list[str]:
        return []

    def _extra_observation(self, values: Sequence[int], elapsed: float) -> list[float]:
        """The subclass's host-side observation entries (plain floats), from the decoded feedback
        `values` and the host's clock."""
        return []

    def _fill_privileged(self, out: np.ndarray) -> None:
        """Write privileged entries into `out` (only with privileged=True)."""

    def _privileged_info(self) -> dict:
        return {}

    def _reward(self, values: tuple[int, ...], elapsed: float, done: bool) -> tuple[float, dict, bool, bool]:
        """(reward, reward terms, is_success, terminated) after a step."""
        raise NotImplementedError

    def _safety_stop_reward(self) -> float:
        """The reward term "safety" of a step that ends the episode with a safety stop."""
        return 0.0

    def _begin_episode(self, rng: np.random.Generator) -> None:
        """Draw and place the episode's scene (after the snapshot was restored)."""
        episode = self.scene.sample_episode(rng)
        self.scene.begin_episode(episode)

    # ------------------------------------------------------------------ helpers

    def _supervisory(self, line: str) -> bytes:
        reply = self.firmware.transact(line.encode("ascii") + b"\r")
        expected_start = line.encode("ascii") + b"\n\r"
        if not reply.startswith(expected_start) or not reply.endswith(b"=> ") or b"ERR" in reply:
            raise FirmwareProtocolError(f"setup command {line!r} answered {reply!r}")
        return reply

    def _cycle(self, block: bytes) -> tuple[int, ...]:
        firmware = self.firmware
        if firmware is None:
            raise self._closed_error()
        firmware.write(block)
        firmware.run_until_idle()
        feedback = firmware.read()
        if len(feedback) != self._feedback_block_size or feedback[0] != 0x2A:
            raise FirmwareProtocolError(f"control block {block!r} answered {feedback!r}")
        self._feedback_block = feedback
        self._cycles += 1
        return self.layout.decode_feedback(feedback)

    def _validate_action(self, action) -> list[int]:
        array = np.asarray(action)
        if array.shape != self._action_shape:
            raise ValueError(f"action must have shape {self._action_shape}, got {array.shape}: {action!r}")
        if array.dtype.kind not in "iu":
            if array.dtype.kind not in "fb" or not np.all(np.isfinite(array)):
                raise ValueError(f"action must be integers, got {action!r}")
            if not np.all(array == np.round(array)):
                raise ValueError(f"action must be whole numbers (LOOP bytes), got {action!r}")
            array = array.astype(np.int64)
        values = array.tolist()
        # Plain-Python comparison: a handful of values, cheaper than numpy's per-call overhead.
        for value, low, high in zip(values, self._low_list, self._high_list):
            if value < low or value > high:
                raise ValueError(
                    f"action {action!r} out of range: each datum must lie in {self._low_list}..{self._high_list} "
                    f"({[f'{n}{m}' for m, n in self.layout.control_fields]})"
                )
        return values

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

    def next_elapsed(self, elapsed: float, control_block_size: int, processing_time: float) -> float:
        """The host's clock after one more cycle: `elapsed` + the control block's transfer time +
        `processing_time` + the feedback block's transfer time, added in the order the firmware
        advances its clock (float addition is not associative; phase boundaries depend on it)."""
        return elapsed + control_block_size * self._seconds_per_byte + processing_time + self._feedback_seconds

    def nominal_episode_steps(self) -> int:
        """Steps after reset until the episode's end on the nominal latency (`bh8 deploy`'s default cycles)."""
        return self._episode_steps(self.nominal_processing_time)

    def _episode_steps(self, processing_time: float) -> int:
        elapsed = self.next_elapsed(0.0, len(self._a_block), processing_time)
        steps = 0
        while not elapsed >= self.episode_seconds - END_TOLERANCE_S:
            elapsed = self.next_elapsed(elapsed, self._control_block_size, processing_time)
            steps += 1
        return steps

    def longest_episode_steps(self) -> int:
        """The most steps an episode can take: on the fastest randomised latency (nominal without
        randomisation). A TimeLimit shorter than this cuts episodes before their end."""
        fastest = self.nominal_processing_time
        if self.randomize:
            fastest = min(fastest, self.randomization.processing_time[0])
        return self._episode_steps(fastest)

    # ------------------------------------------------------------------ public observation builder

    @property
    def host_observation_size(self) -> int:
        """How many leading observation entries a host has on real hardware (all, unless privileged)."""
        return self._n_host

    def observation_from_feedback(
        self, values: Sequence[int], previous_action: Sequence[int], elapsed: float
    ) -> np.ndarray:
        """The observation a host builds from a decoded feedback block (host-side entries only).

        `values`: `layout.decode_feedback(block)`; `previous_action`: the control values last sent
        (zeros before the first); `elapsed`: seconds since the episode's first block. This is what
        `bh8 deploy` calls with the real hand's blocks; privileged entries are never included.
        """
        out = np.zeros(self._n_host, dtype=np.float32)
        self._fill_host(out, values, np.asarray(previous_action, dtype=np.float64).tolist(), elapsed)
        return out

    def _fill_host(self, out: np.ndarray, values, previous_action: list, elapsed: float) -> None:
        # One store of plain floats (cheaper than numpy expressions on ~20 entries); the arithmetic is
        # numpy's float64, term for term, so the float32 observation is bit-identical.
        host = [(v - offset) * scale for v, offset, scale in zip(values, self._fb_offset_list, self._fb_scale_list)]
        host += [(value - centre) / half  # wrappers.bytes_to_unit
                 for value, centre, half in zip(previous_action, self._action_centres, self._action_halves)]
        host.append(min(elapsed / self.episode_seconds, 1.0))
        host += self._extra_observation(values, elapsed)
        out[:self._n_host] = host

    def _observation(self, values) -> np.ndarray:
        obs = self._obs
        self._fill_host(obs, values, self._prev_action, self.elapsed())
        if self.privileged:
            self._fill_privileged(obs[self._n_host:])
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
        self.firmware.restore(self._snapshot, keep_io=keep_io)
        if self.randomize:
            params = sample_plant_parameters(self._base_parameters, self._physics_rng, self.randomization)
            self._randomizer.apply(params, sample_processing_time(self._physics_rng, self.randomization))
        self._begin_episode(self.np_random)
        self._processing_time = self.firmware.processing_time
        self._elapsed = 0.0
        self._prev_action = [0] * self._n_act
        self._cycles = 0
        self._episode_started = True

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        if self.firmware is not None:
            self._renew_world_if_full()
        self.prepare_episode(seed)
        values = self._cycle(self._a_block)
        self._elapsed = self.next_elapsed(0.0, len(self._a_block), self._processing_time)
        self._last_values = values
        info = {"control_block": self._a_block, "feedback_block": self._feedback_block}
        if self.privileged:
            info["privileged"] = self._privileged_info()
        return self._observation(values), info

    def step(self, action):
        if not self._episode_started:
            raise gym.error.ResetNeeded("call reset() before step()") if self.firmware is not None else self._closed_error()
        control = self._validate_action(action)
        block = self.layout.encode_control(control, HEADER_CONTROL_FEEDBACK)
        values = self._cycle(block)
        self._prev_action = control
        self._last_values = values
        elapsed = self._elapsed = self.next_elapsed(self._elapsed, self._control_block_size, self._processing_time)
        truncated = elapsed >= self.episode_seconds - END_TOLERANCE_S
        reward, terms, success, terminated = self._reward(values, elapsed, truncated)
        info = {
            "control_block": block,
            "feedback_block": self._feedback_block,
            "is_success": success,
            "reward_terms": terms,
            "time": elapsed,
        }
        stop = self.safety.strain_violation([(motor, values[index]) for motor, index in self._strain_fields])
        if stop is not None:  # bh8 deploy would stop the hand here: the episode ends, unsuccessful
            terms = {**terms, "safety": self._safety_stop_reward()}
            if "success" in terms:
                terms["success"] = 0.0
            reward = sum(terms.values())
            terminated, info["is_success"], info["reward_terms"], info["safety_stop"] = True, False, terms, stop
        if self.privileged:
            info["privileged"] = self._privileged_info()
        if self.render_mode == "human":
            self.render()
        return self._observation(values), reward, terminated, truncated and not terminated, info

    def render(self):
        if self.firmware is None:
            raise self._closed_error()
        if self.render_mode == "rgb_array":
            from bh8_gym.rendering import render_frame

            return render_frame(self.plant, *self.render_size, camera=self._camera())
        return None

    def _camera(self):
        return None

    def _closed_error(self) -> gym.error.ClosedEnvironmentError:
        return gym.error.ClosedEnvironmentError(f"{type(self).__name__} is closed; make a new env")

    def close(self):
        if getattr(self, "firmware", None) is not None:
            self.plant.close()
            self.firmware = None
