"""What is in an environment's world, where it goes each episode, and what the arm does each cycle.

Shared by the environments and `scene_for_seed` (the env's world for a seed without the env;
`bh8 serve --env ID --seed N` serves the env itself): `build_scene(env_id, plant)` makes the static
world, `scene.sample_episode(rng)` draws an episode (the SAME draws in the same order as the
environment's reset), `scene.begin_episode(episode)` places it, and `scene.cycle_hook` (set as
`Firmware.cycle_hook`) moves the arm once per RealTime cycle. The arm's clock starts at the first
RealTime cycle after `begin_episode`, as a host's clock would start at its first control block.

Geometry: the hand hangs palm-down at the plant's initial wrist pose (PlantParameters.wrist_position);
the plant's TABLE moves under it per episode (placing a static box is a reset, moving the hand would need physics steps).
Position and yaw errors of the "arm's" placement are applied to the object, which is equivalent
(only the hand-object relation matters on an unbounded table) and keeps the hand's pose fixed.

The arm's approach is a top-down pick pipeline's (`PlacementRanges`): it sees the object lying at
rest (`resting.resting_orientation`: a mesh is set down in the pose it settles into), centres the
palm on the object's footprint, turns the hand so that the fingers close across the footprint's
narrowest width (F3 opposite F1 and F2 along the hand's y axis, the object's longest side along
F1-F2), and stops the palm above the object's estimated top; each with the pipeline's error.
It chooses the arm's behaviour from the object's height at rest: an object lower than
`PlacementRanges.table_contact_below` gets the table-contact grasp (the palm starts with the open
fingertips just over the table and the arm holds `ArmSchedule.press_force` down through the grasp,
so the closing fingertips lift the hand and slide along the table to the object's base); a taller
one the rigid approach, whose fingers' sweep clears the table.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from math import cos, pi, radians, sin

import numpy as np
import pybullet
from gymnasium.utils import seeding

from bh8_gym.envs.arm import ArmSchedule
from bh8_gym.envs.objects import ObjectSet
from bh8_gym.envs.randomization import (
    PlantRandomizer,
    RandomizationRanges,
    physics_generator,
    sample_plant_parameters,
    sample_processing_time,
)
from bh8_gym.envs.resting import IDENTITY, resting_orientation
from bh8_gym.hand_urdf import FINGER_SWEEP_DEPTH, KNUCKLE_HEIGHT, PALM_TOP
from bh8_gym.objects import ObjectLoader, ObjectSpec

# Quaternion (x, y, z, w) turning the wrist frame's z axis (out through the palm, §9.5) to world -z.
WRIST_PALM_DOWN = (1.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class PlacementRanges:
    """Where the arm puts the hand relative to the object (uniform draws): what a vision-guided pick
    pipeline does. It sees the object from above, centres the palm over it (with `position_error`
    and `yaw_error`), estimates the object's top (with `top_error`) and stops the palm there: the
    knuckle housings (KNUCKLE_HEIGHT proud of the palm face) `clearance` above the estimated top,
    but never so low that a closing finger would reach the table (FINGER_SWEEP_DEPTH plus
    `fingertip_margin`): a short object is met by the fingertips' sweep just above the table."""

    # A calibrated RGB-D pipeline on a tabletop: ±2 cm, ±15° in the plane (lead's design), ±5 mm
    # on the object's top (depth noise of a structured-light camera at about 0.5 m).
    position_error: float = 0.02  # metres, each of x and y
    yaw_error: float = radians(15.0)
    top_error: float = 0.005  # metres
    # The knuckle housings above the estimated top, metres: at least top_error, so they never
    # start inside the object.
    clearance: tuple[float, float] = (0.005, 0.02)
    # Above the table, the deepest point of the closing fingers' sweep: metres.
    fingertip_margin: float = 0.005
    # Objects lower than this at rest (metres, as the pipeline estimates it) get the table-contact
    # grasp; 0, the default, turns it off, so the env and every figure measured on it stay as they
    # were. 0.03 is the measured setting (docs/envs.md): below 3 cm the rigid approach meets the
    # object only near its top or not at all (the fingers' sweep clears the table).
    table_contact_below: float = 0.0
    # In the table-contact grasp the palm starts with the open hand's lowest point this far above
    # the table (metres): the arm's guarded move covers it in the first cycles.
    table_contact_margin: float = 0.003

    def __post_init__(self):
        if not (self.position_error >= 0 and self.yaw_error >= 0 and self.top_error >= 0
                and self.fingertip_margin >= 0 and self.table_contact_below >= 0
                and self.table_contact_margin >= 0):
            raise ValueError(f"PlacementRanges errors and margins must be >= 0, got {self!r}")
        if not (len(self.clearance) == 2 and self.top_error <= self.clearance[0] <= self.clearance[1]):
            raise ValueError(f"PlacementRanges.clearance must be (low, high) with top_error <= low <= high, "
                             f"got {self.clearance!r} with top_error {self.top_error!r}")

    @property
    def min_palm_above_table(self) -> float:
        """The lowest the palm face goes above the table (fingertips clear of it by the margin)."""
        return FINGER_SWEEP_DEPTH + self.fingertip_margin


# Yaws (degrees) the pipeline tries for a mesh's grasp axis (`GraspScene.grasp_yaw`).
GRASP_YAW_STEP_DEG = 5


@dataclass(frozen=True)
class GraspEpisode:
    """Everything drawn for one grasp episode (the environment and `bh8 serve --env` share it)."""

    spec: ObjectSpec
    object_xy: tuple[float, float]  # footprint centre in the hand's horizontal frame, metres
    object_yaw: float  # radians: the pipeline's yaw error (the object turned from its grasp yaw)
    clearance: float
    top_error: float = 0.0  # metres: the pipeline's estimate of the object's top minus the truth

    def table_contact(self, height: float, placement: PlacementRanges) -> bool:
        """Whether the pipeline gives an object `height` metres tall at rest the table-contact grasp."""
        return height + self.top_error < placement.table_contact_below


class GraspScene:
    """Table, object and a palm-down hand on a lifting arm."""

    def __init__(
        self,
        plant,
        object_set: ObjectSet,
        placement: PlacementRanges = PlacementRanges(),
        arm: ArmSchedule = ArmSchedule(),
        visuals: bool = True,
    ):
        self._p = pybullet
        self.plant = plant
        self.client = plant.client
        self.object_set = object_set
        self.placement = placement
        self.arm = arm
        self.loader = ObjectLoader(self.client, visuals=visuals)
        if plant.table_id is None:
            raise ValueError("the grasp scene needs the plant's table (PlantParameters.table=True)")
        self.table = plant.table_id
        self._table_half_height = -pybullet.getBasePositionAndOrientation(self.table, physicsClientId=self.client)[0][2]
        self.wrist_start = np.array(plant.params.wrist_position, dtype=float)
        #: World height of the palm face (the wrist hangs palm-down, the palm face PALM_TOP below it).
        self.palm_height = float(self.wrist_start[2] - PALM_TOP)
        self._wrist_target = self.wrist_start.copy()
        self.table_top = 0.0
        self.object_body: int | None = None
        self.object_rest_z = 0.0
        self.object_extents = (0.0, 0.0, 0.0)
        self._grasp_yaws: dict[tuple, float] = {}
        self.episode: GraspEpisode | None = None
        self.start_time: float | None = None
        #: Whether this episode's arm does the table-contact grasp, and its wrist's height over the
        #: planned start (metres) and the least it may take (the knuckles clear of the object's top).
        self.table_contact = False
        self.press_rise = 0.0
        self._lowest_rise = 0.0
        self._hand_links = range(-1, pybullet.getNumJoints(plant.hand_id, physicsClientId=self.client))
        plant.set_wrist_pose(self.wrist_start, WRIST_PALM_DOWN, teleport=True)

    @property
    def shapes_created(self) -> int:
        """Object shapes made in this world (PyBullet keeps each; the env renews the world)."""
        return self.loader.shapes_created

    def _table_position(self, top: float) -> tuple[float, float, float]:
        return (0.0, 0.0, top - self._table_half_height)

    def sample_episode(self, rng: np.random.Generator) -> GraspEpisode:
        spec = self.object_set.sample(rng)
        pl = self.placement
        error = rng.uniform(-pl.position_error, pl.position_error, 2)
        yaw = float(rng.uniform(-pl.yaw_error, pl.yaw_error))
        clearance = float(rng.uniform(*pl.clearance))
        top_error = float(rng.uniform(-pl.top_error, pl.top_error))
        # The arm's error puts the hand at +error/+yaw from the object; seen from the hand, the
        # object sits at -error rotated by -yaw.
        return GraspEpisode(spec, (float(-error[0]), float(-error[1])), -yaw, clearance, top_error)

    def remove_object(self) -> None:
        """Remove the episode's object (before a PyBullet restoreState, which needs the saved bodies)."""
        if self.object_body is not None:
            self.loader.remove(self.object_body)
            self.object_body = None

    def grasp_yaw(self, spec: ObjectSpec, body: int) -> float:
        """The object's yaw (radians) at which its footprint is narrowest along the hand's closing
        axis (y): a box turns its shorter side across, a round object needs no turn, a mesh lying at
        rest is measured at every GRASP_YAW_STEP_DEG (cached per shape)."""
        if spec.kind == "box":
            return 0.0 if spec.size[1] <= spec.size[0] else pi / 2.0
        if spec.kind in ("cylinder", "sphere", "capsule"):
            return 0.0
        key = spec.shape_key
        if key not in self._grasp_yaws:
            p, client = self._p, self.client
            widths, rest = [], resting_orientation(spec)
            for degrees in range(0, 180, GRASP_YAW_STEP_DEG):
                p.resetBasePositionAndOrientation(body, (0.0, 0.0, -5.0), _turned(radians(degrees), rest),
                                                  physicsClientId=client)
                low, high = p.getAABB(body, -1, physicsClientId=client)
                widths.append((round(high[1] - low[1], 4), degrees))  # 0.1 mm: ties go to the smaller yaw
            self._grasp_yaws[key] = radians(min(widths)[1])
        return self._grasp_yaws[key]

    def begin_episode(self, episode: GraspEpisode) -> None:
        """Place the table and the object for `episode`; the arm starts at the next cycle."""
        p, client = self._p, self.client
        self.remove_object()
        body = self.loader.create(episode.spec, (0.0, 0.0, -5.0), (0.0, 0.0, 0.0, 1.0))
        orientation = _turned(self.grasp_yaw(episode.spec, body) + episode.object_yaw,
                              resting_orientation(episode.spec))
        p.resetBasePositionAndOrientation(body, (0.0, 0.0, -5.0), orientation, physicsClientId=client)
        low, high = p.getAABB(body, -1, physicsClientId=client)
        height = high[2] - low[2]
        #: The object's extents as placed (x, y across the fingers, height), metres.
        self.object_extents = (high[0] - low[0], high[1] - low[1], height)
        bottom_offset = -5.0 - low[2]
        centre_x, centre_y = (low[0] + high[0]) / 2.0, (low[1] + high[1]) / 2.0  # the footprint's centre
        wrap = height + episode.top_error + KNUCKLE_HEIGHT + episode.clearance
        self.table_contact = episode.table_contact(height, self.placement)
        if self.table_contact:
            # Down to the open hand's lowest point just over the table; never the knuckles into the object.
            palm_above_table = max(wrap, self._hand_depth() + self.placement.table_contact_margin)
            self._lowest_rise = wrap - palm_above_table
        else:
            palm_above_table = max(wrap, self.placement.min_palm_above_table)
            self._lowest_rise = 0.0
        self.press_rise = 0.0
        self.plant.step_hook = None  # the arm's clock starts at the next cycle (an episode cut short left it set)
        self.table_top = self.palm_height - palm_above_table
        p.resetBasePositionAndOrientation(self.table, self._table_position(self.table_top), (0, 0, 0, 1),
                                          physicsClientId=client)
        self.object_rest_z = self.table_top + bottom_offset + 1e-4
        p.resetBasePositionAndOrientation(body, (episode.object_xy[0] - centre_x, episode.object_xy[1] - centre_y,
                                                 self.object_rest_z), orientation, physicsClientId=client)
        self.object_body = body
        self.episode = episode
        self.start_time = None
        self._wrist_target[:] = self.wrist_start
        self.plant.set_wrist_pose(self._wrist_target, WRIST_PALM_DOWN)

    def snapshot_state(self) -> tuple:
        """What moves in an episode besides PyBullet's bodies: the arm's clock and wrist target."""
        return (self.start_time, self.press_rise, self._wrist_target.copy(), self.plant.step_hook)

    def restore_state(self, state: tuple) -> None:
        """Back to `snapshot_state`'s state (the same episode's object must still be in the world)."""
        self.start_time, self.press_rise, wrist, self.plant.step_hook = state
        self._wrist_target[:] = wrist

    def _press(self) -> None:
        """Before each physics step of a table-contact grasp: the arm's admittance in z."""
        plant = self.plant
        self.press_rise = self.arm.press_rise(self.press_rise, plant.contact_lift(), plant.dt, self._lowest_rise)
        self._wrist_target[2] = self.wrist_start[2] + self.press_rise
        plant.set_wrist_pose(self._wrist_target, WRIST_PALM_DOWN)

    def _hand_depth(self) -> float:
        """How far the hand's lowest point is below its palm face now (metres)."""
        p, client, hand = self._p, self.client, self.plant.hand_id
        lowest = min(p.getAABB(hand, link, physicsClientId=client)[0][2] for link in self._hand_links)
        return self.palm_height - lowest

    def cycle_hook(self, firmware) -> None:
        """Once per RealTime cycle: start the arm's clock, move the wrist along the schedule (in a
        table-contact grasp, pressing on what the hand touches until the lift)."""
        if self.start_time is None:
            self.start_time = firmware.time
        elapsed = firmware.time - self.start_time
        pressing = self.table_contact and elapsed < self.arm.grasp_seconds
        self.plant.step_hook = self._press if pressing else None  # the lift starts from where the press left it
        if pressing:
            return
        dx, dz = self.arm.wrist_offset(elapsed)
        dz += self.press_rise
        if dx or dz:
            self._wrist_target[0] = self.wrist_start[0] + dx
            self._wrist_target[2] = self.wrist_start[2] + dz
            self.plant.set_wrist_pose(self._wrist_target, WRIST_PALM_DOWN)


def _turned(yaw: float, orientation) -> tuple[float, float, float, float]:
    """`orientation` turned by `yaw` radians about the world's vertical."""
    half = yaw / 2.0
    if orientation == IDENTITY:  # a primitive: exactly the plain yaw quaternion
        return (0.0, 0.0, sin(half), cos(half))
    return tuple(pybullet.multiplyTransforms((0.0, 0.0, 0.0), (0.0, 0.0, sin(half), cos(half)),
                                             (0.0, 0.0, 0.0), orientation)[1])


@dataclass(frozen=True)
class ReachEpisode:
    targets: tuple[int, ...]  # encoder counts per LOOP motor


@dataclass(frozen=True)
class ReachRanges:
    """Targets of BH8FingerReach-v0, encoder counts (BH8-262 scale, SPEC.md §1)."""

    # Fingers up to 10,000 counts (inner link 80°): fingers closed further at zero spread meet each
    # other, and a reach task should not depend on finger-finger collisions.
    finger: tuple[int, int] = (0, 10_000)
    spread: tuple[int, int] = (0, 3_150)  # the whole spread range (0-180°)


class ReachScene:
    """The hand alone, palm up, in free space; targets are the host's business (no arm)."""

    cycle_hook = None

    def __init__(self, plant, motors: tuple[int, ...], ranges: ReachRanges = ReachRanges()):
        self.plant = plant
        self.motors = motors
        self.ranges = ranges
        low = [ranges.spread[0] if m == 4 else ranges.finger[0] for m in motors]
        high = [ranges.spread[1] if m == 4 else ranges.finger[1] for m in motors]
        self._low = np.array(low)
        self._high = np.array(high)

    def sample_episode(self, rng: np.random.Generator) -> ReachEpisode:
        return ReachEpisode(tuple(int(v) for v in rng.integers(self._low, self._high + 1)))

    def begin_episode(self, episode: ReachEpisode) -> None:
        self.episode = episode

    def remove_object(self) -> None:
        """Nothing to remove: the reach scene has no per-episode bodies."""

    def snapshot_state(self):
        """The reach scene holds nothing that moves within an episode."""
        return None

    def restore_state(self, state) -> None:
        """Nothing to restore (`snapshot_state`)."""


@dataclass
class SceneOptions:
    """Keyword options `build_scene` accepts (the environments pass their own)."""

    object_set: str | ObjectSet = "primitives"
    placement: PlacementRanges = field(default_factory=PlacementRanges)
    arm: ArmSchedule = field(default_factory=ArmSchedule)
    motors: tuple[int, ...] = (1, 2, 3, 4)
    reach: ReachRanges = field(default_factory=ReachRanges)
    visuals: bool = True


def build_scene(env_id: str, plant, options: SceneOptions | None = None):
    """The static scene of environment `env_id` in `plant` (for `bh8 serve --env`)."""
    options = options or SceneOptions()
    if env_id.startswith("BH8Grasp"):
        object_set = options.object_set
        if isinstance(object_set, str):
            object_set = ObjectSet.named(object_set)
        return GraspScene(plant, object_set, options.placement, options.arm, options.visuals)
    if env_id.startswith("BH8FingerReach"):
        return ReachScene(plant, tuple(options.motors), options.reach)
    raise ValueError(f"no scene for environment {env_id!r}; expected BH8Grasp-v0 or BH8FingerReach-v0")


def episode_object(env) -> ObjectSpec | None:
    """The ObjectSpec of `env`'s current episode (None for a scene without objects)."""
    return getattr(getattr(env.unwrapped.scene, "episode", None), "spec", None)


def scene_for_seed(
    env_id: str,
    plant,
    seed: int,
    randomize: bool = True,
    options: SceneOptions | None = None,
    firmware=None,
    ranges=None,
):
    """The scene `env_id`'s `reset(seed=seed)` builds, in `plant`, without building the env.

    Draws exactly what the environment's first reset after `seed` draws, from the same generators:
    with `randomize`, the plant parameters and then the RealTime processing time from
    `physics_generator` (the processing time applied to `firmware` when given), and the episode
    from gymnasium's seeded generator; it applies them and places the scene.
    `ranges`: the env's RandomizationRanges (default: the defaults). Set
    `firmware.cycle_hook = scene.cycle_hook`; the arm's clock starts at the first RealTime cycle.
    The plant should be freshly built with the environment's base PlantParameters.

    This gives the env's world, not its firmware state: `bh8 serve --env ID --seed N` serves the
    env's own firmware instead (`BH8LoopEnv.prepare_episode` on LOOP entry), which is byte-exact.
    """
    ranges = ranges or RandomizationRanges()
    rng, _ = seeding.np_random(seed)
    scene = build_scene(env_id, plant, options)
    if randomize:
        physics_rng = physics_generator(rng)
        params = sample_plant_parameters(plant.params, physics_rng, ranges)
        processing_time = sample_processing_time(physics_rng, ranges)
        PlantRandomizer(plant, firmware).apply(params, processing_time if firmware is not None else None)
    scene.begin_episode(scene.sample_episode(rng))
    return scene
