"""Snapshots of a `Firmware` and its plant, so every environment episode starts from the same
post-LOOP state without replaying the setup script."""
from __future__ import annotations

import copy

from bh8_gym.motion_control import MotorChannel
from bh8_gym.protocol import MOTORS

_IMMUTABLE = frozenset((int, float, bool, str, bytes, type(None)))


def _frozen(value) -> bool:
    """Whether nothing can change `value` in place (numbers, strings, tuples of those)."""
    kind = type(value)
    return kind in _IMMUTABLE or (kind is tuple and all(_frozen(v) for v in value))


def _copier(value):
    """How to copy one firmware attribute so that no later step changes the copy through the
    original: None for a frozen value (shared), else a function chosen once, at snapshot time, for
    the shapes the firmware holds (lists and dicts of frozen values, dicts of those, bytearrays,
    MotorChannels of frozen fields); anything else is deep-copied. A restore then costs a few
    container copies instead of a `copy.deepcopy` of the whole state (~6x faster)."""
    kind = type(value)
    if _frozen(value):
        return None
    if kind is bytearray:
        return bytearray
    if kind is list and all(_frozen(v) for v in value):
        return list.copy
    if kind is dict and all(_frozen(v) for v in value.values()):
        return dict.copy
    if kind is dict and all(type(v) is dict and all(_frozen(x) for x in v.values()) for v in value.values()):
        return lambda table: {k: inner.copy() for k, inner in table.items()}
    if kind is dict and all(type(v) is MotorChannel and _channel_frozen(v) for v in value.values()):
        return lambda channels: {k: copy.copy(channel) for k, channel in channels.items()}
    return copy.deepcopy


def _channel_frozen(channel: MotorChannel) -> bool:
    return all(_frozen(getattr(channel, name)) for name in MotorChannel.__slots__ if hasattr(channel, name))


# Attributes a snapshot does not copy: the plant, the store, hooks, the running task and constants.
_NOT_SNAPSHOT = frozenset(
    ("plant", "store", "cycle_hook", "loop_entry_hook", "other_profile_hook", "_task", "_motor_table", "_global_table",
     "_owns_plant", "_channel_list")
)
_SHARED_STATE = ("_loop_layout",)  # immutable after construction; shared, not copied


class FirmwareSnapshot:
    """Opaque state of a `Firmware` and its plant; give it back to `Firmware.restore`."""

    __slots__ = ("plant_state", "state", "shared", "copied")

    def __init__(self, plant_state, state: dict, shared: dict):
        self.plant_state = plant_state
        self.state = state
        # frozen values are restored as they are; the others through the copier chosen for them
        self.shared = {**shared, **{k: v for k, v in state.items() if _copier(v) is None}}
        self.copied = [(k, copier) for k, v in state.items() if (copier := _copier(v)) is not None]


class Snapshots:
    """`snapshot` / `restore` of `Firmware`: its whole state is its instance dictionary, minus what
    `_NOT_SNAPSHOT` names."""

    def snapshot(self) -> FirmwareSnapshot:
        """Firmware and plant state, for `restore` (only between commands: no motion running)."""
        if self._task is not None:
            raise RuntimeError("snapshot() needs the firmware between commands (a motion or RealTime cycle is running)")
        shared = {name: self.__dict__[name] for name in _SHARED_STATE}
        state = {k: v for k, v in self.__dict__.items() if k not in _NOT_SNAPSHOT and k not in _SHARED_STATE}
        return FirmwareSnapshot(self.plant.save_state(), {k: copy.deepcopy(v) for k, v in state.items()}, shared)

    def restore(self, snapshot: FirmwareSnapshot, keep_io: bool = False) -> None:
        """Return firmware and plant to `snapshot`; later bytes equal those of the original run.

        `keep_io=True` keeps the serial bytes not yet processed (input) and not yet read (output),
        as a live serial line would (used from `loop_entry_hook`)."""
        if not isinstance(snapshot, FirmwareSnapshot):
            raise TypeError(f"restore() needs a FirmwareSnapshot, got {type(snapshot).__name__}")
        pending = (self._input, self._output) if keep_io else None
        self.plant.restore_state(snapshot.plant_state)
        state, attributes = snapshot.state, self.__dict__
        attributes.update(snapshot.shared)
        for name, copier in snapshot.copied:
            attributes[name] = copier(state[name])
        self._task = None
        self._channel_list = [self._channels[m] for m in MOTORS]
        self._refresh_plant_state()
        if pending is not None:
            self._input, self._output = pending
