"""Assembling the simulated hand: a plant, the firmware on it, and for the environments the
post-LOOP snapshot every episode starts from.

One place builds what the environments, `bh8 serve` and the in-process `bh8sim://` port serve, so
they all serve the same hand:

- `build_plant(seed, objects, gui, hand, palm_up)`: the plant's default scene, or with `--object`
  SPEC strings the palm-up scene with each object placed in the hand; `hand`: the PlantParameters
  fields of a hand-parameters file (`--hand-parameters`, bh8_gym/hand_file.py);
- `build_firmware(state_dir, profile, seed, objects, gui, hand)`: the firmware on `build_plant`'s
  plant (`bh8 serve`, `bh8sim://`); `shutdown_firmware` persists its counters and closes the plant;
- `LoopSimulation`: the environments' plant and firmware (a store in memory), their task's scene,
  the interface's setup script run and LOOP entered, and the snapshot each reset restores.
"""
from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path
from typing import Mapping, Sequence

import pybullet

from bh8_gym.firmware import Firmware
from bh8_gym.hand_urdf import KNUCKLE_HEIGHT, PALM_TOP
from bh8_gym.loop_interface import LoopInterface
from bh8_gym.objects import add_object, parse_object_spec
from bh8_gym.plant import HandPlant, PlantParameters
from bh8_gym.protocol import FIRMWARE_PROFILES, LINE_END, PROMPT

# The scene `--object` builds (the plant's defaults hold the hand palm-down over a table, as the
# grasp environments use it): the wrist at the world origin with the palm facing up and no table,
# so world coordinates are hand coordinates (z out of the palm, metres) and an object rests on the
# palm, where a GC closes on it.
OBJECT_SCENE_WRIST_POSITION = (0.0, 0.0, 0.0)
OBJECT_SCENE_WRIST_ORIENTATION = (0.0, 0.0, 0.0, 1.0)
# Gap between the top of the knuckle housings (hand_urdf.KNUCKLE_HEIGHT proud of the palm face,
# hand_urdf.PALM_TOP from the wrist) and an object placed without @X,Y,Z: one narrower than the
# gap between the housings drops the rest onto the palm face (15 mm, 55 ms) and settles at once.
PALM_CLEARANCE_M = 0.002


class FirmwareProtocolError(RuntimeError):
    """The emulated firmware answered something other than the expected block or prompt."""


def build_plant(seed: int = 0, objects: Sequence[str] = (), gui: bool = False, hand: Mapping | None = None,
                palm_up: bool | None = None) -> HandPlant:
    """The plant `bh8 serve` drives: the plant's default scene, or with `objects` (`--object`
    SPEC strings) the palm-up scene above with each object placed. `hand`: PlantParameters fields
    of the hand itself (a hand-parameters file's, `bh8 serve --hand-parameters`); `palm_up`: the
    palm-up scene even without objects (None: palm up when there are objects). Raises ValueError
    naming a bad spec (before any physics starts)."""
    placements = []
    for text in objects:
        try:
            placements.append((text, parse_object_spec(text)))
        except ValueError as error:
            raise ValueError(f"object {text!r}: {error}") from None
    params = PlantParameters(**dict(hand or {}))
    if placements if palm_up is None else palm_up:
        params = replace(params, table=False, wrist_position=OBJECT_SCENE_WRIST_POSITION,
                         wrist_orientation=OBJECT_SCENE_WRIST_ORIENTATION)
    plant = HandPlant(params=params, seed=seed, gui=gui)
    try:
        for text, (spec, position) in placements:
            try:
                body = add_object(plant, spec, **({} if position is None else {"position": position}))
            except ValueError as error:
                raise ValueError(f"object {text!r}: {error}") from None
            if position is None:
                _rest_on_palm(plant, body)
    except BaseException:
        plant.close()
        raise
    return plant


def _rest_on_palm(plant: HandPlant, body: int) -> None:
    """Move `body` so its bounding box sits centred over the palm, PALM_CLEARANCE_M above the
    knuckle housings (it cannot start inside them)."""
    cid = plant.client
    lows, highs = [], []
    for link in range(-1, pybullet.getNumJoints(body, physicsClientId=cid)):
        low, high = pybullet.getAABB(body, link, physicsClientId=cid)
        lows.append(low)
        highs.append(high)
    low = [min(v[i] for v in lows) for i in range(3)]
    high = [max(v[i] for v in highs) for i in range(3)]
    position, orientation = pybullet.getBasePositionAndOrientation(body, physicsClientId=cid)
    shift = (-(low[0] + high[0]) / 2.0, -(low[1] + high[1]) / 2.0, PALM_TOP + KNUCKLE_HEIGHT + PALM_CLEARANCE_M - low[2])
    pybullet.resetBasePositionAndOrientation(
        body, [c + d for c, d in zip(position, shift)], orientation, physicsClientId=cid
    )


def build_firmware(
    state_dir: str | os.PathLike | None,
    profile: str = "4.3",
    seed: int = 0,
    objects: Sequence[str] = (),
    gui: bool = False,
    hand: Mapping | None = None,
) -> Firmware:
    """The firmware on `build_plant(seed, objects, gui)`, its store in `state_dir`.

    Shared by `bh8 serve` and the bh8sim:// URL handler so both serve the same hand. Without
    objects the plant is the one `Firmware(store_dir=..., seed=...)` builds itself, so the pty and
    in-process give identical bytes (Contract 2). `bh8 serve --env` serves an env's firmware
    instead (`commands.serve.build_env_firmware`).
    """
    if profile not in FIRMWARE_PROFILES:
        raise ValueError(f"firmware profile must be one of {FIRMWARE_PROFILES}, got {profile!r}")
    plant = build_plant(seed, objects, gui, hand)
    try:
        firmware = Firmware(plant=plant, store_dir=None if state_dir is None else Path(state_dir), profile=profile, seed=seed)
    except BaseException:
        plant.close()
        raise
    return firmware


def shutdown_firmware(firmware: Firmware) -> None:
    """Persist the firmware's counters and close its plant (Firmware.shutdown closes only a plant
    it built itself; build_firmware builds the plant)."""
    try:
        firmware.shutdown()
    finally:
        firmware.plant.close()


class LoopSimulation:
    """An environment's simulated hand: plant, firmware and the task's scene, in LOOP after the
    interface's setup script, with the snapshot every reset restores.

    `build_scene(plant)` makes the task's static scene; its `cycle_hook` (the arm) runs once per
    RealTime cycle. The firmware's store is in memory: an env saves nothing between processes
    (no files, nothing a killed worker leaves)."""

    def __init__(self, interface: LoopInterface, params: PlantParameters, build_scene, gui: bool = False):
        self.interface = interface
        self.plant = HandPlant(params=params, seed=0, gui=gui)
        self.firmware = Firmware(plant=self.plant, store_dir=None, profile=interface.firmware_profile, seed=0)
        self.scene = build_scene(self.plant)
        # The baud rate last: the host switches its own port rate right after it.
        for line in (*interface.setup_commands, interface.baud_command):
            self.supervisory(line)
        loop = interface.loop_command.encode()
        echo = self.firmware.transact(loop + b"\r")
        if echo != loop + b"*":
            raise FirmwareProtocolError(f"{interface.loop_command!r} answered {echo!r}")
        self.firmware.cycle_hook = self.scene.cycle_hook
        self.snapshot = self.firmware.snapshot()

    def supervisory(self, line: str) -> bytes:
        """Send one supervisory command; FirmwareProtocolError unless it answers with its echo and a prompt."""
        reply = self.firmware.transact(line.encode("ascii") + b"\r")
        if not reply.startswith(line.encode("ascii") + LINE_END) or not reply.endswith(PROMPT) or b"ERR" in reply:
            raise FirmwareProtocolError(f"setup command {line!r} answered {reply!r}")
        return reply

    def cycle(self, block: bytes) -> bytes:
        """One RealTime cycle: write the control block, run the firmware until it waits, read its
        feedback block (FirmwareProtocolError unless it is one)."""
        firmware = self.firmware
        firmware.write(block)
        firmware.run_until_idle()
        feedback = firmware.read()
        if len(feedback) != self.interface.feedback_block_size or feedback[0] != 0x2A:
            raise FirmwareProtocolError(f"control block {block!r} answered {feedback!r}")
        return feedback

    def close(self) -> None:
        self.plant.close()
