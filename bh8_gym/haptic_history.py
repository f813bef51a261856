"""What a host remembers of an episode's feedback: the haptic history a grasp policy needs to tell a
ball from a box.

One feedback block says where the fingers are and how hard they press now; it cannot say when each
finger first touched, how far it had closed then, or whether it is still moving under load. Those
tell objects apart after the first contacts (a box stops the fingers dead where a ball rolls
away from them), so a policy that picks its grasp per object needs them. This history is built by
the host from the blocks alone (`LoopInterface` with `history=True`), so `bh8 deploy` builds it
from a real hand's blocks exactly as the environment does from the simulator's.

Per finger (F1-F3), from its strain LFS and position LFAP:
- the strain's rise over its reading in the episode's first block (the gauges' offsets differ per
  finger and per hand, SPEC.md §1, so the rise is what a contact changes), and its peak so far;
- contact: the rise has reached `CONTACT_RISE` counts in two blocks running (one block's reading
  swings ±13 counts as a finger starts); the position at which it did, and the time since;
- the position's change over the last `SHORT_LAG` and `LONG_LAG` blocks (a finger stalled on a
  hard face moves nothing; one rolling an object keeps moving);
- the strain's change over the last `SHORT_LAG` blocks;
and for the spread, its position's change over `SHORT_LAG` blocks (a grasp back-drives it).
Entries are scaled to about [-1, 1] like the rest of the observation (loop_interface.py).
"""
from __future__ import annotations

import copy
from collections import deque
from typing import Sequence

from bh8_gym.protocol import FINGER_MOTORS, SPREAD_MOTOR

CONTACT_RISE = 10  # strain counts over the first block's reading, two blocks running
SHORT_LAG = 6  # blocks (~40 ms at 38400 baud)
LONG_LAG = 24  # blocks (~155 ms)
STRAIN_SCALE = 128.0  # counts, as the observation's LFS entries
POSITION_SCALE = 17_500.0  # finger counts over the full range (SPEC.md §1), as the LFAP entries
# Position changes are small against the full range: a finger at full speed (~14 counts per
# 256 µs sample, ~25 samples per block) moves ~350 counts a block; scaled so SHORT_LAG blocks of
# full speed read about 1.
DELTA_SCALE = 2_000.0
SPREAD_DELTA_SCALE = 400.0


class HapticHistory:
    """The history of one episode's feedback blocks for one LOOP layout (see the module docstring).

    `reset()` at the episode's start; `observe(values)` once per decoded feedback block, in order;
    `values()` the entries after the last block observed. `elapsed` is the host's clock (seconds)
    and `episode_seconds` scales the time since contact.
    """

    def __init__(self, feedback_fields: Sequence[tuple[int, str]], episode_seconds: float):
        self.fingers = [m for m in FINGER_MOTORS if (m, "LFS") in feedback_fields and (m, "LFAP") in feedback_fields]
        if not self.fingers:
            raise ValueError("a haptic history needs LFS and LFAP feedback of at least one finger")
        self._strain = [feedback_fields.index((m, "LFS")) for m in self.fingers]
        self._position = [feedback_fields.index((m, "LFAP")) for m in self.fingers]
        self._spread = feedback_fields.index((SPREAD_MOTOR, "LFAP")) if (SPREAD_MOTOR, "LFAP") in feedback_fields else None
        self.episode_seconds = float(episode_seconds)
        names = []
        for m in self.fingers:
            names += [f"rise{m}", f"peak_rise{m}", f"contact{m}", f"contact_position{m}", f"since_contact{m}",
                      f"moved{m}_short", f"moved{m}_long", f"strain_change{m}"]
        if self._spread is not None:
            names.append(f"moved{SPREAD_MOTOR}_short")
        self.names: tuple[str, ...] = tuple(names)
        self.reset()

    def reset(self) -> None:
        n = len(self.fingers)
        self._zero: list[int] | None = None
        self._peak = [0] * n
        self._rising = [0] * n
        self._contact_position: list[float | None] = [None] * n
        self._contact_time: list[float | None] = [None] * n
        self._blocks: deque = deque(maxlen=LONG_LAG + 1)  # (strains, positions, spread)
        self._elapsed = 0.0

    def copy(self) -> "HapticHistory":
        """An independent copy (a snapshot of the episode; `BH8LoopEnv.snapshot`). The blocks kept are
        never changed once observed, so they are shared."""
        twin = copy.copy(self)
        twin._peak, twin._rising = self._peak.copy(), self._rising.copy()
        twin._contact_position, twin._contact_time = self._contact_position.copy(), self._contact_time.copy()
        twin._blocks = self._blocks.copy()
        return twin

    def observe(self, values: Sequence[int], elapsed: float) -> None:
        """Take one decoded feedback block, received at the host's clock `elapsed`."""
        strains = [values[i] for i in self._strain]
        positions = [values[i] for i in self._position]
        spread = values[self._spread] if self._spread is not None else 0
        if self._zero is None:
            self._zero = strains
        for k, (strain, zero) in enumerate(zip(strains, self._zero)):
            rise = strain - zero
            self._peak[k] = max(self._peak[k], rise)
            self._rising[k] = self._rising[k] + 1 if rise >= CONTACT_RISE else 0
            if self._contact_position[k] is None and self._rising[k] >= 2:
                self._contact_position[k] = positions[k]
                self._contact_time[k] = elapsed
        self._blocks.append((strains, positions, spread))
        self._elapsed = elapsed

    def values(self) -> list[float]:
        if not self._blocks:
            raise ValueError("HapticHistory.values() before the first observe()")
        strains, positions, spread = self._blocks[-1]
        short = self._blocks[max(len(self._blocks) - 1 - SHORT_LAG, 0)]
        long = self._blocks[0]
        out = []
        for k in range(len(self.fingers)):
            touched = self._contact_position[k] is not None
            out += [
                (strains[k] - self._zero[k]) / STRAIN_SCALE,
                self._peak[k] / STRAIN_SCALE,
                1.0 if touched else 0.0,
                self._contact_position[k] / POSITION_SCALE if touched else 0.0,
                (self._elapsed - self._contact_time[k]) / self.episode_seconds if touched else 0.0,
                (positions[k] - short[1][k]) / DELTA_SCALE,
                (positions[k] - long[1][k]) / DELTA_SCALE,
                (strains[k] - short[0][k]) / STRAIN_SCALE,
            ]
        if self._spread is not None:
            out.append((spread - short[2]) / SPREAD_DELTA_SCALE)
        return out
