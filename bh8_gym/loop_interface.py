"""The host's side of a RealTime (LOOP) loop: what a computer driving a BH8-262 knows and does.

One `LoopInterface` holds, for one LOOP configuration: the block layout (`realtime_codec.LoopLayout`),
the supervisory setup script a host sends before LOOP, the baud rate, the action and observation
spaces, the observation built from a decoded feedback block, and the host's cycle clock. The
environments step their simulated firmware through it, `bh8 deploy` drives a real hand through it
and the scripted baselines read it, so a policy sees the same numbers on either side. Nothing here
loads PyBullet: `bh8 deploy` runs on a computer that has only the hand.

The task adds its own host-side entries to the observation (`TaskObservation`: the arm's phase for
grasping, the targets for reaching); everything else is common:

- the decoded feedback fields the LOOP flags enable, coefficients applied, scaled to about
  [-1, 1]: LFV × LFVC / 16 (counts per sample, full speed ≈ 14), (LFS − 128) / 128, LFAP / full
  range (17,500 fingers, 3,150 spread: SPEC.md §1), LFDP × LFDPC / 128 (counts; with LFDPC > 1
  up to ±LFDPC), LFT / 1000 (tenths °C; 4.4: /100);
- the previous action, each datum mapped to [-1, 1] (`action_bytes.bytes_to_unit`);
- the fraction of the episode's time elapsed (the host's clock since its first block), then the
  task's entries.

The clock (SPEC.md §6): a cycle costs its control block's bytes at the baud rate, the firmware's
processing time (nominally `REALTIME_PROCESSING_S`) and the feedback block's bytes, added in that
order, the order the firmware advances its own clock, so both agree to the bit.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Protocol, Sequence

import gymnasium as gym
import numpy as np

from bh8_gym.action_bytes import centres_and_halves
from bh8_gym.haptic_history import HapticHistory
from bh8_gym.protocol import BAUD_RATES, BITS_PER_BYTE, REALTIME_PROCESSING_S, SPREAD_MOTOR, seconds_per_byte
from bh8_gym.realtime_codec import HEADER_CONTROL_FEEDBACK, HEADER_FEEDBACK, LoopLayout, MotorFlags
from bh8_gym.safety import SafetyEnvelope

FULL_RANGE_COUNTS = {1: 17_500.0, 2: 17_500.0, 3: 17_500.0, 4: 3_150.0}  # SPEC.md §1, BH8-262
VELOCITY_FULL_SCALE = 16.0  # counts per sample: no-load motor speed ≈ 14 counts per 256 µs sample
STRAIN_CENTRE = 128.0
DELTA_FULL_SCALE = 128.0
TEMPERATURE_SCALE = {"4.3": 1000.0, "4.4": 100.0}  # LFT: tenths of °C on 4.3, whole °C on 4.4
MAX_EPISODE_SECONDS = 600.0  # our bound on one episode (the envs' are 2-3 s)
# An episode ends when the host's clock reaches episode_seconds less this (float rounding slack).
END_TOLERANCE_S = 1e-9


def check_switch(name: str, value) -> None:
    """An on/off keyword must be a bool (or 0/1): a string such as "false" would otherwise count as on."""
    if not (isinstance(value, (bool, np.bool_)) or (isinstance(value, (int, np.integer)) and value in (0, 1))):
        raise ValueError(f"{name} must be True or False, got {value!r}")


class TaskObservation(Protocol):
    """A task's host-side observation entries: what a host knows besides the feedback blocks."""

    names: tuple[str, ...]  # one per entry, in order
    privileged_names: tuple[str, ...]  # simulator-only entries the task appends with privileged=True

    def values(self, feedback: Sequence[int], elapsed: float) -> list[float]:
        """The entries (plain floats) from a decoded feedback block and the host's clock."""


def loop_layout(motors: Sequence[int], flags: MotorFlags, lft: bool, firmware_profile: str) -> LoopLayout:
    """The layout of the LOOP on `motors` with `flags`, less the spread's strain: the spread has no
    gauge, its LFS would read 255 every cycle (§5.3.2), a byte of the feedback block (and of the
    cycle time) that tells a policy nothing, so it is not asked for."""
    for name in ("LCV", "LCPG", "LFV", "LFS", "LFAP", "LFDP"):
        check_switch(name.lower(), getattr(flags, name))
    check_switch("lft", lft)
    motors = LoopLayout(motors, flags, lft=lft, firmware=firmware_profile).motors  # checked, sorted
    spread_flags = replace(flags, LFS=False)
    layout = LoopLayout(motors, {m: spread_flags if m == SPREAD_MOTOR else flags for m in motors},
                        lft=lft, firmware=firmware_profile)
    if not layout.control_fields:
        raise ValueError("the LOOP configuration sends no control data (enable LCV or LCPG)")
    if not layout.feedback_fields:
        raise ValueError("the LOOP configuration returns no feedback (enable LFV, LFS, LFAP, LFDP or LFT)")
    if any(name == "LCT" for _, name in layout.control_fields):
        raise ValueError("LCT (firmware 4.4 torque control) is not supported by the environments")
    return layout


class LoopInterface:
    """The host's side of one LOOP configuration; see the module docstring.

    `layout` comes from `loop_layout(motors, flags, lft, firmware_profile)`; `extra_motor_settings`
    are FSET pairs the setup script adds for the LOOP motors (e.g. "FPG 40").
    """

    def __init__(
        self,
        *,
        layout: LoopLayout,
        flags: MotorFlags,
        lcvc: int,
        lfvc: int,
        lfdpc: int,
        lfdpd: bool,
        baud: int,
        extra_motor_settings: str,
        episode_seconds: float,
        task: TaskObservation,
        safety: SafetyEnvelope,
        privileged: bool = False,
        history: bool = False,
    ):
        if baud not in BAUD_RATES:
            raise ValueError(f"baud must be one of {BAUD_RATES} (manual §5.4.1 BAUD), got {baud!r}")
        for name, value in (("lcvc", lcvc), ("lfvc", lfvc), ("lfdpc", lfdpc)):
            if not (isinstance(value, (int, np.integer)) and 1 <= value <= 255):
                raise ValueError(f"{name} must be an integer 1..255 (Table 4), got {value!r}")
        if (isinstance(episode_seconds, bool) or not isinstance(episode_seconds, (int, float))
                or not 0 < episode_seconds <= MAX_EPISODE_SECONDS):
            # bounded before `episode_steps` loops over it
            raise ValueError(f"episode_seconds must be in (0, {MAX_EPISODE_SECONDS:g}] s, got {episode_seconds!r:.40}")
        check_switch("lfdpd", lfdpd)
        check_switch("privileged", privileged)
        check_switch("history", history)
        self.layout = layout
        self.motors = layout.motors
        self.firmware_profile = layout.firmware
        self.baud = int(baud)
        self.coefficients = {"LCVC": int(lcvc), "LFVC": int(lfvc), "LFDPC": int(lfdpc)}
        self.episode_seconds = float(episode_seconds)
        self.task = task
        self.safety = safety
        self.privileged = bool(privileged)
        #: Whether the observation carries the episode's haptic history (haptic_history.py).
        self.history = bool(history)
        if self.history:  # checked here: a layout without finger strain and position has none to keep
            HapticHistory(layout.feedback_fields, self.episode_seconds)

        prefix = "".join(str(m) for m in self.motors)
        settings = (
            f"LCV {int(flags.LCV)} LCVC {lcvc} LCPG {int(flags.LCPG)} LFV {int(flags.LFV)} LFVC {lfvc} "
            f"LFS {int(flags.LFS)} LFAP {int(flags.LFAP)} LFDP {int(flags.LFDP)} LFDPC {lfdpc}"
        )
        if extra_motor_settings:
            settings += " " + extra_motor_settings
        spread_lfs_off = bool(flags.LFS) and SPREAD_MOTOR in self.motors
        #: The supervisory script a host sends before `loop_command`: HI first (it uses the stored
        #: gains and velocities), then the LOOP configuration, then `baud_command` last (the host
        #: switches its own port rate right after it: `BarrettHand.set_baud`).
        self.setup_commands: tuple[str, ...] = (
            "HI",
            f"{prefix}FSET {settings}",
            *((f"{SPREAD_MOTOR}FSET LFS 0",) if spread_lfs_off else ()),
            f"PSET LFT {int(layout.lft)} LFDPD {int(lfdpd)}",
        )
        self.baud_command = f"PSET BAUD {self.baud // 100}"
        self.loop_command = f"{prefix}LOOP"

        # The clock's terms, as the firmware computes a cycle's time (SPEC.md §6).
        self.control_block_size = layout.control_block_size(HEADER_CONTROL_FEEDBACK)
        self.feedback_block_size = layout.feedback_size
        self.start_block = layout.encode_control((), HEADER_FEEDBACK)  # the "A" block: no control data
        self._seconds_per_byte = seconds_per_byte(self.baud)
        self._feedback_seconds = self.feedback_block_size * self._seconds_per_byte
        #: The firmware's processing seconds per cycle without randomisation: what a host assumes.
        self.nominal_processing_time = REALTIME_PROCESSING_S
        #: Seconds per cycle at the nominal processing time: both blocks' bytes at BAUD plus processing.
        self.cycle_seconds = ((self.control_block_size + self.feedback_block_size) * BITS_PER_BYTE / self.baud
                              + REALTIME_PROCESSING_S)

        self._build_action_space()
        self._build_observation_space()
        # (motor, index in the decoded feedback) of each finger's strain: the envelope's check.
        self._strain_fields = [(motor, index) for index, (motor, name) in enumerate(layout.feedback_fields)
                               if name == "LFS" and motor != SPREAD_MOTOR]

    def _build_action_space(self) -> None:
        """The control data of one block, in control_fields order; LCV inside the safety envelope."""
        velocity_low, velocity_high = self.safety.velocity_bounds
        fields = self.layout.control_fields
        low = [velocity_low if name == "LCV" else 0 for _, name in fields]
        high = [velocity_high if name == "LCV" else 255 for _, name in fields]
        self.action_space = gym.spaces.Box(np.array(low, np.int16), np.array(high, np.int16), dtype=np.int16)
        self._action_shape = self.action_space.shape
        # Plain lists: a handful of values per step, cheaper in Python than in numpy.
        self._low_list, self._high_list = low, high
        self._action_centres, self._action_halves = centres_and_halves(low, high)

    def _build_observation_space(self) -> None:
        """Observation layout, precomputed: a feedback entry is (value - offset) * scale."""
        lfvc, lfdpc = self.coefficients["LFVC"], self.coefficients["LFDPC"]
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
                offsets.append(0.0), scales.append(1.0 / TEMPERATURE_SCALE[self.firmware_profile])
        # Plain floats for the per-step observation (see fill_host_observation).
        self._fb_offset_list, self._fb_scale_list = offsets, scales
        names += [f"prev_{name}{motor}" for motor, name in self.layout.control_fields]
        names.append("episode_fraction")
        names += self.task.names
        if self.history:
            names += HapticHistory(self.layout.feedback_fields, self.episode_seconds).names
        #: How many leading observation entries a host has on real hardware (all, unless privileged).
        self.host_observation_size = len(names)
        if self.privileged:
            names += self.task.privileged_names
        #: Name of every observation entry, in order.
        self.observation_fields: tuple[str, ...] = tuple(names)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(len(names),), dtype=np.float32)

    # ------------------------------------------------------------------ actions

    def validate_action(self, action) -> list[int]:
        """The action as a list of LOOP control values, or ValueError naming what is wrong with it."""
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

    def encode_action(self, values: Sequence[int]) -> bytes:
        """The "C" control block carrying `values` (a feedback block comes back)."""
        return self.layout.encode_control(values, HEADER_CONTROL_FEEDBACK)

    def strain_violation(self, feedback: Sequence[int]) -> str | None:
        """Why the safety envelope stops the hand after this decoded feedback block, or None."""
        return self.safety.strain_violation([(motor, feedback[index]) for motor, index in self._strain_fields])

    # ------------------------------------------------------------------ observation

    def new_history(self) -> HapticHistory | None:
        """A fresh haptic history for one stream of episodes (None when the observation has none):
        the env keeps one, `bh8 deploy` another; reset it at each episode's first block."""
        return HapticHistory(self.layout.feedback_fields, self.episode_seconds) if self.history else None

    def observation_from_feedback(
        self, values: Sequence[int], previous_action: Sequence[int], elapsed: float,
        history: HapticHistory | None = None,
    ) -> np.ndarray:
        """The observation a host builds from a decoded feedback block (host-side entries only).

        `values`: `layout.decode_feedback(block)`; `previous_action`: the control values last sent
        (zeros before the first); `elapsed`: seconds since the episode's first block; `history`:
        the episode's `new_history()` when the observation has one (this block is added to it).
        This is what `bh8 deploy` calls with the real hand's blocks; privileged entries are never
        included.
        """
        out = np.zeros(self.host_observation_size, dtype=np.float32)
        self.fill_host_observation(out, values, np.asarray(previous_action, dtype=np.float64).tolist(), elapsed,
                                   history)
        return out

    def fill_host_observation(self, out: np.ndarray, values, previous_action: list, elapsed: float,
                              history: HapticHistory | None = None) -> None:
        """Write the host-side entries into `out[:host_observation_size]` (adding this block to
        `history`, which an interface with `history=True` needs)."""
        # One store of plain floats (cheaper than numpy expressions on ~20 entries); the arithmetic is
        # numpy's float64, term for term, so the float32 observation is bit-identical.
        host = [(v - offset) * scale for v, offset, scale in zip(values, self._fb_offset_list, self._fb_scale_list)]
        host += [(value - centre) / half  # action_bytes.bytes_to_unit
                 for value, centre, half in zip(previous_action, self._action_centres, self._action_halves)]
        host.append(min(elapsed / self.episode_seconds, 1.0))
        host += self.task.values(values, elapsed)
        if self.history:
            if history is None:
                raise ValueError("this observation carries a haptic history: pass the episode's "
                                 "LoopInterface.new_history()")
            history.observe(values, elapsed)
            host += history.values()
        out[:self.host_observation_size] = host

    # ------------------------------------------------------------------ the host's clock

    def next_elapsed(self, elapsed: float, control_block_size: int, processing_time: float) -> float:
        """The host's clock after one more cycle: `elapsed` + the control block's transfer time +
        `processing_time` + the feedback block's transfer time, added in the order the firmware
        advances its clock (float addition is not associative; phase boundaries depend on it)."""
        return elapsed + control_block_size * self._seconds_per_byte + processing_time + self._feedback_seconds

    def episode_over(self, elapsed: float) -> bool:
        """Whether the host's clock has reached the episode's end."""
        return elapsed >= self.episode_seconds - END_TOLERANCE_S

    def episode_steps(self, processing_time: float) -> int:
        """Control blocks after the "A" block until the episode's end, at `processing_time` per cycle."""
        if not (isinstance(processing_time, (int, float)) and 0 <= processing_time <= MAX_EPISODE_SECONDS):
            raise ValueError(f"processing_time must be 0 to {MAX_EPISODE_SECONDS:g} s, got {processing_time!r:.40}")
        elapsed = self.next_elapsed(0.0, len(self.start_block), processing_time)
        steps = 0
        while not self.episode_over(elapsed):
            elapsed = self.next_elapsed(elapsed, self.control_block_size, processing_time)
            steps += 1
        return steps

    def nominal_episode_steps(self) -> int:
        """Steps after reset until the episode's end on the nominal latency (`bh8 deploy`'s default cycles)."""
        return self.episode_steps(self.nominal_processing_time)
