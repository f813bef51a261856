"""Graspable objects for the environments: procedural primitives, pybullet_data's random URDFs, user files.

An `ObjectSpec` describes one object (shape, size, mass, friction); an `ObjectSet` samples specs with
the environment's `np_random`; an `ObjectLoader` turns a spec into a PyBullet body, caching the
collision and visual shapes so that an object seen before costs one `createMultiBody` (about 0.2 ms)
instead of a file load (1-8 ms). Bodies themselves are not cached: the environments reset with
PyBullet `restoreState`, which needs exactly the bodies that existed at `saveState`, so each
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

User objects: `parse_object_file` / `ObjectSet.from_files` take URDF files (optionally with a
global scale) and meshes (OBJ/STL with a scale and a mass); see `parse_object_file`. Every object
stays within the plant's bounds (`bh8_gym.plant.OBJECT_EXTENT_RANGE_M`, `OBJECT_MASS_RANGE_KG`,
`OBJECT_FRICTION_MAX`), and every mesh is read by `bh8_gym.meshes` before PyBullet sees it (a bad
face index crashes PyBullet's reader): a bad spec or file raises a ValueError naming it, at
`parse_object_file` for user files and again before loading.

PyBullet never frees a collision shape (it refuses to remove one a body has used), so each new
shape stays in memory for the life of the PyBullet client; `ObjectLoader.shapes_created` counts
them, and the environments build a fresh world when it passes `envs.base.WORLD_SHAPE_LIMIT`.
"""
from __future__ import annotations

import hashlib
import os
import re
import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from bh8_gym.meshes import MESH_SUFFIXES, mesh_bounds
from bh8_gym.plant import (
    OBJECT_FRICTION_MAX,
    OBJECT_MASS_RANGE_KG,
    check_loaded_object,
    check_mesh_file,
    check_object_extents,
    check_urdf_file,
    check_urdf_object,
    file_errors_named,
)

PRIMITIVE_KINDS = ("box", "cylinder", "sphere", "capsule")
FILE_KINDS = ("urdf", "mesh")
SPLITS = ("train", "validation", "test")
OBJECT_SETS = ("train", "validation", "test", "primitives-train", "primitives-validation", "primitives-test",
               "mixed", "mixed-validation", "mixed-test", "primitives", "all")
# Size cells of the procedural primitives (metres), and the share of each kind's cells held out.
PRIMITIVE_CELL = 0.005
HELD_OUT_SHARE = {"test": 0.10, "validation": 0.10}


@dataclass(frozen=True)
class ObjectSpec:
    """One object. Sizes are FULL extents in metres (not half extents).

    kind "box": size = (x, y, z); "cylinder": (diameter, height); "sphere": (diameter,);
    "capsule": (diameter, total length) lying along z; "urdf": `path` loaded with `scale`
    (mass/friction None keep the file's values); "mesh": `path` scaled by `scale`, with `mass`.
    """

    kind: str
    size: tuple[float, ...] = ()
    mass: float | None = 0.1
    friction: float | None = 0.8
    path: str | None = None
    scale: float = 1.0
    name: str = ""
    rgba: tuple[float, float, float, float] = (0.85, 0.45, 0.15, 1.0)

    def __post_init__(self):
        if self.kind not in PRIMITIVE_KINDS + FILE_KINDS:
            raise ValueError(f"object kind must be one of {PRIMITIVE_KINDS + FILE_KINDS}, got {self.kind!r}")
        expected = {"box": 3, "cylinder": 2, "sphere": 1, "capsule": 2}.get(self.kind)
        if expected is not None:
            if len(self.size) != expected or not all(np.isfinite(s) and s > 0 for s in self.size):
                raise ValueError(f"a {self.kind} needs {expected} positive finite sizes, got {self.size!r}")
            if self.kind == "capsule" and self.size[1] < self.size[0]:
                raise ValueError(f"a capsule's length must be at least its diameter, got {self.size!r}")
            check_object_extents([float(s) for s in self.size], f"a {self.kind} of size {self.size!r}")
        else:
            if not self.path:
                raise ValueError(f"a {self.kind} object needs a file path")
            if not (np.isfinite(self.scale) and self.scale > 0):
                raise ValueError(f"object scale must be positive, got {self.scale!r}")
        low, high = OBJECT_MASS_RANGE_KG
        if self.mass is not None and not (np.isfinite(self.mass) and low <= self.mass <= high):
            raise ValueError(f"object mass must be {low:g} to {high:g} kg, got {self.mass!r}")
        if self.kind != "urdf" and self.mass is None:  # only a URDF carries its own
            raise ValueError(f"a {self.kind} object needs a mass (kg)")
        if self.friction is not None and not (np.isfinite(self.friction) and 0 <= self.friction <= OBJECT_FRICTION_MAX):
            raise ValueError(f"object friction must be 0 to {OBJECT_FRICTION_MAX:g}, got {self.friction!r}")

    @property
    def shape_key(self) -> tuple:
        """What determines the collision shape (mass and friction do not)."""
        return (self.kind, tuple(round(s, 6) for s in self.size), self.path, round(self.scale, 6))


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
    # A third of the models are flat (height under 3 cm at that size): a palm-down hand whose
    # fingertips must stay off the table cannot reach them (scenes.PlacementRanges), so flat
    # models are scaled up to this height, as long as their largest extent stays under max_extent.
    min_height: float = 0.04
    max_extent: float = 0.10
    mass: tuple[float, float] = (0.05, 0.40)
    friction: tuple[float, float] = (0.4, 1.2)


def random_urdf_root() -> Path:
    import pybullet_data

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


_MESH_SCALE = re.compile(r"\s+")


def _urdf_single_mesh(urdf_path: Path) -> tuple[Path, np.ndarray]:
    """The collision mesh file and its scale of a one-link URDF such as the random_urdfs."""
    root = ElementTree.parse(urdf_path).getroot()
    mesh = root.find("./link/collision/geometry/mesh")
    if mesh is None:
        raise ValueError(f"{urdf_path} has no collision mesh")
    scale = np.array([float(v) for v in _MESH_SCALE.split(mesh.get("scale", "1 1 1").strip())])
    return urdf_path.parent / mesh.get("filename"), scale


def obj_vertex_bounds(obj_path: Path | str) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds (min, max) of the vertices the faces of a mesh file use; a ValueError
    (bh8_gym.meshes.MeshError) for a file PyBullet could not read safely."""
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
    largest, height = float(np.max(extents)), float(extents[2])
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


def parse_object_file(text: str | os.PathLike | ObjectSpec) -> ObjectSpec:
    """A user object: an `ObjectSpec`, or "PATH.urdf[:SCALE]" or "PATH.obj:SCALE:MASS_KG[:FRICTION]".

    Meshes need a scale (file units to metres) and a mass (kg); URDFs carry their own mass.
    """
    if isinstance(text, ObjectSpec):
        return text
    text = os.fspath(text)
    path, _, rest = text.partition(":") if not re.match(r"^[A-Za-z]:[\\/]", text) else (text, "", "")
    fields_ = [f for f in rest.split(":") if f] if rest else []
    try:
        numbers = [float(f) for f in fields_]
    except ValueError:
        raise ValueError(f"object file spec {text!r}: expected PATH[:SCALE[:MASS[:FRICTION]]] numbers") from None
    if not Path(path).is_file():
        raise ValueError(f"object file {path!r} does not exist")
    suffix = Path(path).suffix.lower()
    if suffix == ".urdf":
        if len(numbers) > 1:
            raise ValueError(f"object file spec {text!r}: a URDF takes at most a scale")
        spec = ObjectSpec(kind="urdf", path=str(Path(path).resolve()), scale=numbers[0] if numbers else 1.0,
                          mass=None, friction=None, name=Path(path).stem)
        check_urdf_object(spec.path, spec.scale)
        return spec
    if suffix in MESH_SUFFIXES:
        if len(numbers) not in (2, 3):
            raise ValueError(f"mesh spec {text!r} needs PATH:SCALE:MASS_KG[:FRICTION]")
        spec = ObjectSpec(kind="mesh", path=str(Path(path).resolve()), scale=numbers[0], mass=numbers[1],
                          friction=numbers[2] if len(numbers) == 3 else 0.8, name=Path(path).stem)
        check_mesh_file(spec.path, spec.scale)
        return spec
    raise ValueError(f"object file {path!r}: expected .urdf or a mesh ({', '.join(MESH_SUFFIXES)})")


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


class ObjectLoader:
    """Creates object bodies in one PyBullet client, caching shapes by `ObjectSpec.shape_key`.

    `shapes_created` counts the shapes made: PyBullet keeps each until its client disconnects."""

    def __init__(self, client: int, visuals: bool = True):
        import pybullet

        self._p = pybullet
        self.client = client
        self.visuals = visuals
        self._shapes: dict[tuple, tuple[int, int]] = {}
        self.shapes_created = 0

    def _shapes_for(self, spec: ObjectSpec) -> tuple[int, int]:
        cached = self._shapes.get(spec.shape_key)
        if cached is not None:
            return cached
        p = self._p
        if spec.kind == "mesh":
            check_mesh_file(spec.path, spec.scale)  # PyBullet's reader crashes on a bad face index
        if spec.kind == "box":
            geometry = dict(shapeType=p.GEOM_BOX, halfExtents=[s / 2 for s in spec.size])
        elif spec.kind == "cylinder":
            geometry = dict(shapeType=p.GEOM_CYLINDER, radius=spec.size[0] / 2, height=spec.size[1])
        elif spec.kind == "sphere":
            geometry = dict(shapeType=p.GEOM_SPHERE, radius=spec.size[0] / 2)
        elif spec.kind == "capsule":
            geometry = dict(shapeType=p.GEOM_CAPSULE, radius=spec.size[0] / 2, height=spec.size[1] - spec.size[0])
        else:
            geometry = dict(shapeType=p.GEOM_MESH, fileName=spec.path, meshScale=[spec.scale] * 3)
        with file_errors_named(spec.kind, spec.path):
            collision = p.createCollisionShape(physicsClientId=self.client, **geometry)
        if collision < 0:
            raise ValueError(f"PyBullet could not build a collision shape for {spec!r}")
        visual = -1
        if self.visuals:
            visual_geometry = dict(geometry)
            if spec.kind == "cylinder" or spec.kind == "capsule":
                visual_geometry["length"] = visual_geometry.pop("height")
            visual = p.createVisualShape(rgbaColor=spec.rgba, physicsClientId=self.client, **visual_geometry)
        self._shapes[spec.shape_key] = (collision, visual)
        self.shapes_created += 1
        return collision, visual

    def create(self, spec: ObjectSpec, position: Sequence[float], orientation: Sequence[float]) -> int:
        """A body for `spec` at a pose (base frame = the shape's centre for primitives and meshes)."""
        p = self._p
        if spec.kind == "urdf":
            check_urdf_file(spec.path)
            with file_errors_named(spec.kind, spec.path):
                body = p.loadURDF(spec.path, position, orientation, globalScaling=spec.scale, physicsClientId=self.client)
            self.shapes_created += 1  # its own shapes, kept by PyBullet as ours are
            try:
                check_loaded_object(self.client, body, f"URDF {spec.path!r} at scale {spec.scale:g}")
            except ValueError:
                p.removeBody(body, physicsClientId=self.client)
                raise
        else:
            collision, visual = self._shapes_for(spec)
            body = p.createMultiBody(spec.mass, collision, visual, position, orientation, physicsClientId=self.client)
        dynamics = {}
        if spec.mass is not None and spec.kind == "urdf":
            dynamics["mass"] = spec.mass
        if spec.friction is not None:
            dynamics["lateralFriction"] = spec.friction
        if dynamics:
            p.changeDynamics(body, -1, physicsClientId=self.client, **dynamics)
        return body

    def remove(self, body: int) -> None:
        self._p.removeBody(body, physicsClientId=self.client)
