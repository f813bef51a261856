"""Snapshots of a `Firmware` and its plant, so every environment episode starts from the same
post-LOOP state without replaying the setup script."""
from __future__ import annotations

import copy

from bh8_gym.protocol import MOTORS

# Attributes a snapshot does not copy: the plant, the store, hooks, the running task and constants.
_NOT_SNAPSHOT = frozenset(
    ("plant", "store", "cycle_hook", "loop_entry_hook", "other_profile_hook", "_task", "_motor_table", "_global_table",
     "_owns_plant", "_channel_list")
)
_SHARED_STATE = ("_loop_layout",)  # immutable after construction; shared, not copied


class FirmwareSnapshot:
    """Opaque state of a `Firmware` and its plant; give it back to `Firmware.restore`."""

    __slots__ = ("plant_state", "state", "shared")

    def __init__(self, plant_state, state: dict, shared: dict):
        self.plant_state = plant_state
        self.state = state
        self.shared = shared


class Snapshots:
    """`snapshot` / `restore` of `Firmware`: its whole state is its instance dictionary, minus what
    `_NOT_SNAPSHOT` names."""

    def snapshot(self) -> FirmwareSnapshot:
        """Firmware and plant state, for `restore` (only between commands: no motion running)."""
        if self._task is not None:
            raise RuntimeError("snapshot() needs the firmware between commands (a motion or RealTime cycle is running)")
        shared = {name: self.__dict__[name] for name in _SHARED_STATE}
        state = {k: v for k, v in self.__dict__.items() if k not in _NOT_SNAPSHOT and k not in _SHARED_STATE}
        return FirmwareSnapshot(self.plant.save_state(), copy.deepcopy(state), shared)

    def restore(self, snapshot: FirmwareSnapshot, keep_io: bool = False) -> None:
        """Return firmware and plant to `snapshot`; later bytes equal those of the original run.

        `keep_io=True` keeps the serial bytes not yet processed (input) and not yet read (output),
        as a live serial line would (used from `loop_entry_hook`)."""
        if not isinstance(snapshot, FirmwareSnapshot):
            raise TypeError(f"restore() needs a FirmwareSnapshot, got {type(snapshot).__name__}")
        pending = (self._input, self._output) if keep_io else None
        self.plant.restore_state(snapshot.plant_state)
        self.__dict__.update(copy.deepcopy(snapshot.state))
        self.__dict__.update(snapshot.shared)
        self._task = None
        self._channel_list = [self._channels[m] for m in MOTORS]
        self._refresh_plant_state()
        if pending is not None:
            self._input, self._output = pending
