"""What the grasp choice decides from: the features of the fingers' feedback up to the decision point.

Built by the host from the decoded feedback blocks alone (LFS strain and LFAP position per motor),
so `bh8 deploy` computes them from a real hand's blocks exactly as the env's episodes do:

- the haptic history (`bh8_gym.haptic_history.HapticHistory`: per finger the strain's rise and
  peak, contact, where and how long ago it touched, how far it moved lately, how its strain changed;
  the spread's motion);
- the fingers' strain rise (over the episode's first block), their positions and the spread's, now
  and `LAGS` blocks ago: how the grasp built up, not only where it is (a box stops the fingers
  dead and their strain climbs; a ball keeps them moving as it rolls);
- the host's clock (the episode's fraction), the time since this attempt began and the attempt's
  number (a retried grasp starts again from an object the first one moved);
- which fingers the probe counts as touching (its contact rule, `SqueezeBaseline`'s).

Entries are scaled to about [-1, 1] like the rest of the observation (loop_interface.py).
"""
from __future__ import annotations

from collections import deque
from typing import Iterable, Sequence

import numpy as np

from bh8_gym.haptic_history import POSITION_SCALE, STRAIN_SCALE, HapticHistory
from bh8_gym.protocol import FINGER_MOTORS, SPREAD_MOTOR

LAGS = (0, 3, 6, 12, 24)  # blocks back (~0, 20, 40, 80, 155 ms at 38400 baud)
SPREAD_SCALE = 400.0  # counts: the spread's drift under a grasp is a few hundred at most


class ChoiceFeatures:
    """The features of one episode's feedback so far (module docstring). `reset()` at the episode's
    start, `observe(values, elapsed)` once per decoded block in order, `vector(contacts)` at a decision."""

    def __init__(self, feedback_fields: Sequence[tuple[int, str]], episode_seconds: float):
        fields = list(feedback_fields)
        missing = [(m, name) for m in FINGER_MOTORS for name in ("LFS", "LFAP") if (m, name) not in fields]
        if missing or (SPREAD_MOTOR, "LFAP") not in fields:
            raise ValueError(f"the grasp choice needs LFS and LFAP of every finger and the spread's LFAP; "
                             f"the feedback has {fields}")
        self.history = HapticHistory(fields, episode_seconds)
        self._strain = [fields.index((m, "LFS")) for m in FINGER_MOTORS]
        self._position = [fields.index((m, "LFAP")) for m in FINGER_MOTORS]
        self._spread = fields.index((SPREAD_MOTOR, "LFAP"))
        self.episode_seconds = float(episode_seconds)
        names = list(self.history.names)
        for lag in LAGS:
            names += [f"rise{m}_lag{lag}" for m in FINGER_MOTORS] + [f"position{m}_lag{lag}" for m in FINGER_MOTORS]
            names.append(f"spread_lag{lag}")
        names += ["elapsed", "attempt_elapsed", "attempt"] + [f"probe_contact{m}" for m in FINGER_MOTORS]
        self.names: tuple[str, ...] = tuple(names)
        self.reset()

    def reset(self) -> None:
        self.history.reset()
        self._blocks: deque = deque(maxlen=max(LAGS) + 1)
        self._zero: list[int] | None = None
        self.elapsed = 0.0
        self._attempt_start = 0.0
        self.attempt = 0

    def new_attempt(self) -> None:
        """A retry begins (the hand has reopened): its clock starts now."""
        self.attempt += 1
        self._attempt_start = self.elapsed

    def observe(self, values: Sequence[int], elapsed: float) -> None:
        self.history.observe(values, elapsed)
        strains = [values[i] for i in self._strain]
        if self._zero is None:
            self._zero = strains
        self._blocks.append((strains, [values[i] for i in self._position], values[self._spread]))
        self.elapsed = float(elapsed)

    def vector(self, contacts: Iterable[bool]) -> np.ndarray:
        """The features after the last block observed (`names` gives each entry's meaning)."""
        if not self._blocks:
            raise ValueError("ChoiceFeatures.vector() before the first observe()")
        out = list(self.history.values())
        newest = len(self._blocks) - 1
        for lag in LAGS:
            strains, positions, spread = self._blocks[max(newest - lag, 0)]
            out += [(s - z) / STRAIN_SCALE for s, z in zip(strains, self._zero)]
            out += [p / POSITION_SCALE * 2.0 for p in positions]
            out.append(spread / SPREAD_SCALE)
        out += [self.elapsed / self.episode_seconds, (self.elapsed - self._attempt_start) / self.episode_seconds,
                float(self.attempt)]
        out += [1.0 if c else 0.0 for c in contacts]
        return np.asarray(out, dtype=np.float64)
