"""The environments' object SETS and their SPLITS: procedural primitives, pybullet_data's random
URDFs, user files. What one object is, its spec strings, checks and loading are `bh8_gym.objects`
(sizes are full extents everywhere).

An `ObjectSet` samples the `ObjectSpec` of each episode with the environment's `np_random`; the
scene loads it with `bh8_gym.objects.ObjectLoader`. Bodies are not cached: the environments reset
with PyBullet `restoreState`, which needs exactly the bodies that existed at `saveState`, so each
episode's object is created after the restore and removed before the next one.

Sizes are graspable by the BH8-262 (manual App. A: fingers 70 + 50 mm long; the palm spans the
knuckles 50 mm apart): 3-9 cm. Masses 50-400 g stay well inside the 2 kg-per-fingertip payload
(App. A) so a grasp fails for lack of a good grasp, not for lack of strength.

Object sets (kwarg `object_set` of the environments), each object in exactly one of three splits:
train (learning), validation (model selection, early stopping, tuning) and test (reported only).

- ``"train"`` / ``"validation"`` / ``"test"``: pybullet_data's ``random_urdfs`` models (1000
  random convex-decomposed blobs), each scaled so its largest bounding-box extent is a fixed
  per-model size in `RandomUrdfRanges.extent` (flat ones scaled up to `min_height`, within
  `max_extent`). Test is the models whose folder name ends in 0 (100 models), validation those
  ending in 5 (100), train the other 799 (168 has a broken mesh). Fixed by name, never by seed.
- ``"primitives-train"`` / ``"primitives-validation"`` / ``"primitives-test"``: procedural boxes,
  cylinders, spheres and capsules. Sizes are split by cell: each full extent in 5 mm cells, so a
  size cell is a (kind, cells) tuple; per kind, a fixed hash order of its cells puts 10 % of them
  (at least one) in test and 10 % in validation (`primitive_size_cells`). An episode draws a kind,
  a cell of the split, a size within the cell, and a mass and friction (`PrimitiveRanges`).
- ``"mixed"`` / ``"mixed-validation"`` / ``"mixed-test"``: the primitives and the random_urdfs of a
  split, half the episodes each.
- ``"primitives"`` (every cell) and ``"all"`` (every object): demonstrations, not evaluation.

`object_family(spec)` names an object's family for reports: "random_urdf", the primitive's kind,
or "file".

User objects: `ObjectSet.from_files` takes URDF files (optionally with a global scale) and meshes
(OBJ/STL with a scale and a mass), `bh8_gym.objects.parse_object_file`.
"""
from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

import numpy as np
import pybullet_data

from bh8_gym.envs.resting import resting_pose
from bh8_gym.meshes import mesh_bounds
from bh8_gym.objects import PRIMITIVE_KINDS, ObjectSpec, parse_object_file
from bh8_gym.urdfs import read_urdf

SPLITS = ("train", "validation", "test")
OBJECT_SETS = ("train", "validation", "test", "primitives-train", "primitives-validation", "primitives-test",
               "mixed", "mixed-validation", "mixed-test", "primitives", "all")
# Size cells of the procedural primitives (metres), and the share of each kind's cells held out.
PRIMITIVE_CELL = 0.005
HELD_OUT_SHARE = {"test": 0.10, "validation": 0.10}


@dataclass(frozen=True)
class PrimitiveRanges:
    """Ranges of the procedural primitives (uniform). Why: graspable by the 262 (module docstring)."""

    extent: tuple[float, float] = (0.03, 0.09)  # metres, every full extent
    mass: tuple[float, float] = (0.05, 0.40)  # kg
    # Coulomb friction: 0.4 (smooth plastic on rubber pads) .. 1.2 (rubber on rubber); typical
    # tabletop objects against the BarrettHand's rubber-padded fingers.
    friction: tuple[float, float] = (0.4, 1.2)
    kinds: tuple[str, ...] = PRIMITIVE_KINDS
    capsule_max_diameter: float = 0.06  # metres: a thicker capsule is too round to lie still


@dataclass(frozen=True)
class RandomUrdfRanges:
    """How pybullet_data's random URDFs are resized; mass and friction drawn per episode."""

    extent: tuple[float, float] = (0.05, 0.08)  # metres: largest bbox extent, fixed per model
    # Many models lie flat (under 3 cm high at rest at that size): a palm-down hand whose
    # fingertips must stay off the table cannot reach them (scenes.PlacementRanges), so flat
    # models are scaled up to this height, as long as their largest extent stays under max_extent.
    min_height: float = 0.04
    max_extent: float = 0.10
    mass: tuple[float, float] = (0.05, 0.40)
    friction: tuple[float, float] = (0.4, 1.2)


def random_urdf_root() -> Path:
    return Path(pybullet_data.getDataPath()) / "random_urdfs"


# Models whose mesh cannot be loaded: 168.obj has NaN vertices (pybullet_data 3.2.7).
BROKEN_RANDOM_URDFS = frozenset({"168"})


def random_urdf_split(name: str) -> str:
    """The split of random_urdfs model `name`: "test" if its name ends in 0, "validation" in 5,
    else "train"."""
    return {"0": "test", "5": "validation"}.get(name[-1:], "train")


def random_urdf_names(split: str) -> tuple[str, ...]:
    """Model folder names of a split (`random_urdf_split`, without BROKEN_RANDOM_URDFS)."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    root = random_urdf_root()
    names = sorted(p.name for p in root.iterdir() if (p / f"{p.name}.urdf").is_file()) if root.is_dir() else []
    return tuple(n for n in names if random_urdf_split(n) == split and n not in BROKEN_RANDOM_URDFS)


def _urdf_single_mesh(urdf_path: Path) -> tuple[Path, np.ndarray]:
    """The collision mesh file and its scale of a one-link URDF such as the random_urdfs (read by
    `bh8_gym.urdfs`, as a user's URDF is)."""
    link = read_urdf(urdf_path).links[0]
    geometry = link.collisions[0].geometry if link.collisions else None
    if geometry is None or geometry.mesh is None:
        raise ValueError(f"{urdf_path} has no collision mesh")
    return Path(geometry.path), np.array([float(v) for v in geometry.attributes["scale"].split()])


def obj_vertex_bounds(obj_path: Path | str) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds (min, max) of the vertices the faces of a mesh file use; a ValueError
    (bh8_gym.meshes.MeshError) for a file that is refused."""
    return mesh_bounds(obj_path)


def _unit_hash(text: str) -> float:
    """A number in [0, 1) fixed by `text` (stable across processes, unlike hash())."""
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "big") / 2.0**64


def random_urdf_spec(name: str, rng: np.random.Generator, ranges: RandomUrdfRanges = RandomUrdfRanges()) -> ObjectSpec:
    """The mesh spec of random_urdfs model `name`: fixed per-model scale, episode mass/friction."""
    urdf = random_urdf_root() / name / f"{name}.urdf"
    mesh_path, mesh_scale = _urdf_single_mesh(urdf)
    low, high = obj_vertex_bounds(mesh_path)
    extents = (high - low) * mesh_scale
    # its height lying at rest on the table, as the scene sets it down (resting.py), not as loaded
    lying = resting_pose(ObjectSpec(kind="mesh", path=str(mesh_path), scale=float(mesh_scale[0]))).extents
    largest, height = float(np.max(extents)), float(lying[2] * mesh_scale[2])
    if not (np.isfinite(largest) and largest > 0 and height > 0):
        raise ValueError(f"random_urdfs model {name!r} has a degenerate mesh {str(mesh_path)!r}")
    extent = ranges.extent[0] + (ranges.extent[1] - ranges.extent[0]) * _unit_hash(name)
    factor = min(max(extent / largest, ranges.min_height / height), ranges.max_extent / largest)
    return ObjectSpec(
        kind="mesh",
        path=str(mesh_path),
        scale=float(mesh_scale[0]) * factor,
        mass=float(rng.uniform(*ranges.mass)),
        friction=float(rng.uniform(*ranges.friction)),
        name=f"random_urdf/{name}",
        rgba=(0.2, 0.45 + 0.4 * _unit_hash(name + "g"), 0.85, 1.0),
    )


def _cell_edges(low: float, high: float) -> np.ndarray:
    """Edges of the 5 mm size cells covering [low, high] (the last cell may be shorter)."""
    count = max(1, int(np.ceil((high - low) / PRIMITIVE_CELL - 1e-9)))
    return np.minimum(low + PRIMITIVE_CELL * np.arange(count + 1), high)


def _size_dimensions(kind: str, ranges: "PrimitiveRanges") -> list[tuple[float, float]]:
    """(low, high) of each full extent a primitive of `kind` draws."""
    lo, hi = ranges.extent
    if kind == "box":
        return [(lo, hi)] * 3
    if kind == "cylinder":
        return [(lo, hi)] * 2
    if kind == "sphere":
        return [(lo, hi)]
    return [(lo, min(hi, ranges.capsule_max_diameter)), (lo, hi)]  # capsule: diameter, length


def primitive_size_cells(kind: str, split: str | None, ranges: "PrimitiveRanges" = None) -> tuple[tuple[int, ...], ...]:
    """The size cells (one cell index per extent) of `kind` in `split` (None: every cell). Per kind,
    the cells in the order of a fixed hash of their indices: the first HELD_OUT_SHARE["test"] of
    them (at least one) are test, the next share validation, the rest train."""
    ranges = ranges or PrimitiveRanges()
    counts = [len(_cell_edges(*bounds)) - 1 for bounds in _size_dimensions(kind, ranges)]
    cells = [tuple(int(i) for i in index) for index in np.ndindex(*counts)]
    if kind == "capsule":  # its length (caps included) is at least its diameter
        cells = [cell for cell in cells if cell[1] >= cell[0]]
    if split is None:
        return tuple(cells)
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    cells.sort(key=lambda cell: _unit_hash(f"{kind}/{cell}"))
    n_test = max(1, int(round(HELD_OUT_SHARE["test"] * len(cells))))
    n_validation = max(1, int(round(HELD_OUT_SHARE["validation"] * len(cells))))
    bounds = {"test": (0, n_test), "validation": (n_test, n_test + n_validation),
              "train": (n_test + n_validation, len(cells))}[split]
    return tuple(sorted(cells[bounds[0]:bounds[1]]))


def primitive_split(spec: ObjectSpec, ranges: "PrimitiveRanges" = None) -> str:
    """The split whose size cells hold primitive `spec`'s size."""
    ranges = ranges or PrimitiveRanges()
    cell = tuple(int(np.clip(np.searchsorted(_cell_edges(*bounds), size, side="right") - 1, 0,
                             len(_cell_edges(*bounds)) - 2))
                 for size, bounds in zip(spec.size, _size_dimensions(spec.kind, ranges)))
    for split in SPLITS:
        if cell in primitive_size_cells(spec.kind, split, ranges):
            return split
    raise ValueError(f"{spec!r} lies outside the primitive ranges")


def sample_primitive(rng: np.random.Generator, ranges: PrimitiveRanges = PrimitiveRanges(),
                     split: str | None = None) -> ObjectSpec:
    """A random box, cylinder, sphere or capsule of `split`'s size cells (None: any size in `ranges`)."""
    kind = ranges.kinds[int(rng.integers(len(ranges.kinds)))]
    cells = _split_cells(kind, split, ranges)
    cell = cells[int(rng.integers(len(cells)))]
    size = []
    for index, bounds in zip(cell, _size_dimensions(kind, ranges)):
        edges = _cell_edges(*bounds)
        low = max(edges[index], size[0]) if kind == "capsule" and size else edges[index]  # length >= diameter
        size.append(float(rng.uniform(low, edges[index + 1])))
    colour = tuple(float(c) for c in rng.uniform(0.3, 0.95, 3)) + (1.0,)
    return ObjectSpec(
        kind=kind,
        size=tuple(size),
        mass=float(rng.uniform(*ranges.mass)),
        friction=float(rng.uniform(*ranges.friction)),
        name=kind,
        rgba=colour,
    )


_CELL_CACHE: dict = {}


def _split_cells(kind: str, split: str | None, ranges: PrimitiveRanges) -> tuple[tuple[int, ...], ...]:
    key = (kind, split, ranges.extent, ranges.capsule_max_diameter)
    if key not in _CELL_CACHE:
        _CELL_CACHE[key] = primitive_size_cells(kind, split, ranges)
    return _CELL_CACHE[key]


def object_family(spec: ObjectSpec | None) -> str:
    """An object's family for reports: "random_urdf", the primitive's kind, "file" (a user's object)."""
    if spec is None:
        return "(none)"
    if spec.name.startswith("random_urdf/"):
        return "random_urdf"
    if spec.kind in PRIMITIVE_KINDS:
        return spec.kind
    return "file"


@dataclass
class ObjectSet:
    """Samples the object of an episode. Build with `ObjectSet.named(...)` or `ObjectSet.from_files(...)`."""

    primitive_weight: float = 1.0
    urdf_names: tuple[str, ...] = ()
    files: tuple[ObjectSpec, ...] = ()
    primitive_ranges: PrimitiveRanges = field(default_factory=PrimitiveRanges)
    urdf_ranges: RandomUrdfRanges = field(default_factory=RandomUrdfRanges)
    name: str = ""
    primitive_split: str | None = None  # the primitives' size cells (None: all)

    @classmethod
    def named(cls, name: str) -> "ObjectSet":
        if name in SPLITS:
            return cls(primitive_weight=0.0, urdf_names=random_urdf_names(name), name=name)
        if name.startswith("primitives-") and name[len("primitives-"):] in SPLITS:
            return cls(primitive_weight=1.0, name=name, primitive_split=name[len("primitives-"):])
        if name == "mixed" or (name.startswith("mixed-") and name[len("mixed-"):] in ("validation", "test")):
            split = name[len("mixed-"):] if "-" in name else "train"
            return cls(primitive_weight=0.5, urdf_names=random_urdf_names(split), name=name, primitive_split=split)
        if name == "primitives":
            return cls(primitive_weight=1.0, name=name)
        if name == "all":
            names = sum((random_urdf_names(split) for split in SPLITS), ())
            return cls(primitive_weight=0.5, urdf_names=tuple(sorted(names)), name=name)
        raise ValueError(f"object_set must be one of {OBJECT_SETS}, got {name!r}")

    @classmethod
    def from_files(cls, files: Iterable[str | os.PathLike | ObjectSpec] | str | os.PathLike | ObjectSpec) -> "ObjectSet":
        if isinstance(files, (str, os.PathLike, ObjectSpec)):  # one file, not its characters
            files = (files,)
        specs = tuple(parse_object_file(f) for f in files)
        if not specs:
            raise ValueError("object_files is empty")
        return cls(primitive_weight=0.0, files=specs, name="files")

    def __post_init__(self):
        if not self.urdf_names and not self.files and self.primitive_weight <= 0:
            raise ValueError(f"object set {self.name!r} is empty (is pybullet_data installed?)")

    def sample(self, rng: np.random.Generator) -> ObjectSpec:
        if self.files:
            return self.files[int(rng.integers(len(self.files)))]
        if not self.urdf_names or rng.random() < self.primitive_weight:
            return sample_primitive(rng, self.primitive_ranges, self.primitive_split)
        return random_urdf_spec(self.urdf_names[int(rng.integers(len(self.urdf_names)))], rng, self.urdf_ranges)
