"""Objects in the hand's world: what an object is (`ObjectSpec`), how it is written on a command line
or in a config, how it is checked, and how it becomes a PyBullet body in a plant's world.

ONE size convention: every size is a FULL extent in metres (never a radius, never a half extent).

    box       (x, y, z)
    cylinder  (diameter, height), its axis along z
    sphere    (diameter,)
    capsule   (diameter, total length including both caps), its axis along z
    urdf      a URDF file loaded with a global `scale` (its own masses unless `mass` is given)
    mesh      an OBJ/STL file scaled by `scale` (file units to metres), with a `mass`

Two string forms build an `ObjectSpec`:

- `--object SPEC` (`bh8 serve`, `bh8 render`; `parse_object_spec`): `box:XxYxZ` (`box:X`, a cube),
  `sphere:dD`, `cylinder:dDxH`, `capsule:dDxL`, `FILE.urdf[:SCALE]`, `FILE.obj|stl[:SCALE]`;
  optionally `@X,Y,Z` (position, m) and `;mass=M;friction=F;scale=S`, e.g.
  `cylinder:d0.06x0.10@0,0,0.1;mass=0.2`. A round object's width is written with its letter: `d`
  for the diameter, or `r` for a radius (`sphere:r0.03` is `sphere:d0.06`). A bare number there
  (`sphere:0.03`) is refused: it was a radius in earlier versions, and is not silently read as a
  diameter now.
- object files (env kwarg `object_files`, `bh8 eval --object-files`; `parse_object_file`):
  `PATH.urdf[:SCALE]` or `PATH.obj|stl:SCALE:MASS_KG[:FRICTION]`.

Every object stays within our bounds (OBJECT_*, below). A mesh is read by `bh8_gym.meshes` and a
URDF by `bh8_gym.urdfs`; PyBullet is given only the clean OBJ and URDF files we write from them
(`bh8_gym.pybullet_files`), never a byte of the user's (its readers crash on bad input). A bad spec
or file raises an `ObjectError` (a ValueError) naming it, before any physics runs.

Loading: `ObjectLoader` (the environments) caches collision and visual shapes by
`ObjectSpec.shape_key`, so an object seen before costs one `createMultiBody` (about 0.2 ms) instead
of a file load (1-8 ms); PyBullet never frees a shape, so `shapes_created` counts them (the
environments build a fresh world past `envs.base.WORLD_SHAPE_LIMIT`). `ObjectLoader.create` is the
one way a body is made; `add_object` uses it to place one object in a plant's world by hand
(`--object`, tests, benchmarks): it may be fixed, its friction
defaults to the plant's `object_friction`, and each link gets rolling and spinning friction so a
ball on the palm comes to rest. The environments' loader keeps PyBullet's defaults there, as their
trained policies and recorded trajectories have always had them.
"""
from __future__ import annotations

import math
import os
import re
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple, Sequence

import numpy as np
import pybullet as p

from bh8_gym import pybullet_files
from bh8_gym.meshes import MESH_SUFFIXES, Mesh, MeshError, read_mesh
from bh8_gym.plant import HandPlant, PlantError
from bh8_gym.urdfs import UrdfError, UrdfModel, read_urdf

PRIMITIVE_KINDS = ("box", "cylinder", "sphere", "capsule")
FILE_KINDS = ("urdf", "mesh")
OBJECT_KINDS = PRIMITIVE_KINDS + FILE_KINDS
# Our bounds on an object (SI units), checked before PyBullet sees it: far outside them its solver
# fails (a sphere of 1e308 m turned the world to NaN; a 100 kg cube of 1 mm on the palm kept HI
# from ending). Each full extent: a 1 mm bead to a 2 m shelf, far more than the hand (fingers
# 120 mm, App. A) closes around.
OBJECT_EXTENT_RANGE_M = (0.001, 2.0)
# Mass: 1 g to 10 kg, past the 2 kg per fingertip payload (App. A), so an object can be too heavy.
OBJECT_MASS_RANGE_KG = (0.001, 10.0)
OBJECT_FRICTION_MAX = 10.0  # Coulomb coefficient; rubber on rubber is about 1-2
OBJECT_POSITION_LIMIT_M = 10.0  # each coordinate: the world around the hand
# `add_object`'s rolling and spinning friction (see the module docstring).
PLACED_ROLLING_FRICTION = 1e-4
PLACED_SPINNING_FRICTION = 1e-3
# `--object` in `bh8 serve --help` and `bh8 render --help` (the syntax of `parse_object_spec`).
OBJECT_SPEC_HELP = (
    "box:XxYxZ (or box:X, a cube), sphere:dD, cylinder:dDxH, capsule:dDxL: full extents in metres, a round "
    "object's diameter written dD (or its radius rR; a bare number is refused), L the capsule's whole length; "
    "or FILE.urdf[:SCALE], FILE.obj|stl[:SCALE]; optionally @X,Y,Z (position, m) and ;mass=M;friction=F "
    "(e.g. cylinder:d0.06x0.10;mass=0.2)"
)
_SIZE_COUNTS = {"box": 3, "cylinder": 2, "sphere": 1, "capsule": 2}
_ROUND_KINDS = ("cylinder", "sphere", "capsule")


class ObjectError(PlantError):
    """A bad object spec, size, mass, friction, pose or file (names the offending value)."""


@dataclass(frozen=True)
class ObjectSpec:
    """One object. Sizes are FULL extents in metres (module docstring).

    `mass` / `friction` None: a URDF's own values (`ObjectLoader`), or the plant's
    `object_friction` (`add_object`)."""

    kind: str
    size: tuple[float, ...] = ()
    mass: float | None = 0.1
    friction: float | None = 0.8
    path: str | None = None
    scale: float = 1.0
    name: str = ""
    rgba: tuple[float, float, float, float] = (0.85, 0.45, 0.15, 1.0)

    def __post_init__(self):
        if self.kind not in OBJECT_KINDS:
            raise ObjectError(f"object kind must be one of {OBJECT_KINDS}, got {self.kind!r}")
        expected = _SIZE_COUNTS.get(self.kind)
        if expected is not None:
            if len(self.size) != expected or not all(np.isfinite(s) and s > 0 for s in self.size):
                raise ObjectError(f"a {self.kind} needs {expected} positive numbers (full extents, m), got {self.size!r}")
            if self.kind == "capsule" and self.size[1] < self.size[0]:
                raise ObjectError(f"a capsule's length must be at least its diameter, got {self.size!r}")
            check_object_extents([float(s) for s in self.size], f"a {self.kind} of size {self.size!r}")
        else:
            if not self.path:
                raise ObjectError(f"a {self.kind} object needs a file path")
            if not (np.isfinite(self.scale) and self.scale > 0):
                raise ObjectError(f"object scale must be positive, got {self.scale!r}")
        low, high = OBJECT_MASS_RANGE_KG
        if self.mass is not None and not (np.isfinite(self.mass) and low <= self.mass <= high):
            raise ObjectError(f"object mass must be {low:g} to {high:g} kg, got {self.mass!r}")
        if self.kind != "urdf" and self.mass is None:  # only a URDF carries its own
            raise ObjectError(f"a {self.kind} object needs a mass (kg)")
        if self.friction is not None and not (np.isfinite(self.friction) and 0 <= self.friction <= OBJECT_FRICTION_MAX):
            raise ObjectError(f"object friction must be 0 to {OBJECT_FRICTION_MAX:g}, got {self.friction!r}")

    @property
    def shape_key(self) -> tuple:
        """What determines the collision shape (mass and friction do not)."""
        return (self.kind, tuple(round(s, 6) for s in self.size), self.path, round(self.scale, 6))


# ---------------------------------------------------------------------------- string forms

class ObjectPlacement(NamedTuple):
    """A `--object` SPEC: the object and its position (None: the caller places it)."""

    spec: ObjectSpec
    position: tuple[float, float, float] | None


def parse_object_spec(text: str) -> ObjectPlacement:
    """An `--object` SPEC (module docstring), checked; ObjectError names what is wrong."""
    if not isinstance(text, str) or not text.strip():
        raise ObjectError(f"object spec must be a non-empty string, got {text!r}")
    body, *options = text.strip().split(";")
    position = None
    if "@" in body:
        body, where = body.rsplit("@", 1)
        try:
            position = tuple(float(v) for v in where.split(","))
        except ValueError:
            raise ObjectError(f"bad position in object spec {text!r}") from None
        if len(position) != 3:
            raise ObjectError(f"object position needs x,y,z in {text!r}")
    head, _, argument = body.partition(":")
    lowered = head.lower()
    fields: dict = {"friction": None}
    try:
        if lowered in PRIMITIVE_KINDS:
            fields.update(kind=lowered, size=_primitive_size(lowered, argument, text))
        elif lowered.endswith(".urdf"):  # its own masses unless ;mass= is given
            fields.update(kind="urdf", path=head, scale=float(argument) if argument else 1.0, mass=None)
        elif lowered.endswith(tuple(MESH_SUFFIXES)):
            fields.update(kind="mesh", path=head, scale=float(argument) if argument else 1.0)
        else:
            raise ObjectError(f"unknown object kind in spec {text!r}: expected box, sphere, cylinder, capsule, "
                              "*.urdf or *.obj/*.stl")
        for option in options:
            name, _, value = option.partition("=")
            if name not in ("mass", "friction", "scale"):
                raise ObjectError(f"unknown object option {name!r} in spec {text!r}")
            fields[name] = float(value)
    except ObjectError:
        raise
    except ValueError:
        raise ObjectError(f"bad number in object spec {text!r}") from None
    return ObjectPlacement(ObjectSpec(**fields), position)


def _primitive_size(kind: str, argument: str, text: str) -> tuple[float, ...]:
    """The full extents of `KIND:SIZES`: a box's XxYxZ (or X), a round object's dD or rR first."""
    parts = argument.lower().split("x") if argument else []
    if kind == "box":
        numbers = [float(v) for v in parts]
        return tuple(numbers * 3 if len(numbers) == 1 else numbers)
    if not parts or parts[0][:1] not in ("d", "r"):
        example = {"sphere": "sphere:d0.06", "cylinder": "cylinder:d0.06x0.10", "capsule": "capsule:d0.04x0.10"}[kind]
        raise ObjectError(f"object spec {text!r}: write a {kind}'s width as d<diameter> or r<radius> in metres, "
                          f"e.g. {example} (sizes are full extents; a bare number was a radius in earlier versions)")
    width = float(parts[0][1:])
    diameter = 2.0 * width if parts[0][0] == "r" else width
    return (diameter, *(float(v) for v in parts[1:]))


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
        raise ObjectError(f"object file spec {text!r}: expected PATH[:SCALE[:MASS[:FRICTION]]] numbers") from None
    if not Path(path).is_file():
        raise ObjectError(f"object file {path!r} does not exist")
    suffix = Path(path).suffix.lower()
    if suffix == ".urdf":
        if len(numbers) > 1:
            raise ObjectError(f"object file spec {text!r}: a URDF takes at most a scale")
        spec = ObjectSpec(kind="urdf", path=str(Path(path).resolve()), scale=numbers[0] if numbers else 1.0,
                          mass=None, friction=None, name=Path(path).stem)
        check_urdf_object(spec.path, spec.scale)
        return spec
    if suffix in MESH_SUFFIXES:
        if len(numbers) not in (2, 3):
            raise ObjectError(f"mesh spec {text!r} needs PATH:SCALE:MASS_KG[:FRICTION]")
        spec = ObjectSpec(kind="mesh", path=str(Path(path).resolve()), scale=numbers[0], mass=numbers[1],
                          friction=numbers[2] if len(numbers) == 3 else 0.8, name=Path(path).stem)
        check_mesh_file(spec.path, spec.scale)
        return spec
    raise ObjectError(f"object file {path!r}: expected .urdf or a mesh ({', '.join(MESH_SUFFIXES)})")


# ---------------------------------------------------------------------------- checks

def check_object_extents(extents, what: str) -> None:
    """ObjectError unless every full extent (m) of the object `what` is within OBJECT_EXTENT_RANGE_M."""
    low, high = OBJECT_EXTENT_RANGE_M
    if not all(math.isfinite(v) and low <= v <= high for v in extents):
        shown = ", ".join(f"{v:.3g}" for v in extents)
        raise ObjectError(f"{what} measures {shown} m: each extent must be {low:g} to {high:g} m")


def check_mesh_file(path, scale: float) -> Mesh:
    """The checked mesh of the OBJ/STL file `path` (`bh8_gym.meshes`), or an ObjectError; its size
    at `scale` must be within OBJECT_EXTENT_RANGE_M."""
    try:
        mesh = read_mesh(path)
    except MeshError as error:
        raise ObjectError(str(error)) from None
    low, high = mesh.bounds
    check_object_extents([float(v) for v in (high - low) * scale], f"mesh {str(path)!r} at scale {scale:g}")
    return mesh


def check_urdf_file(path) -> UrdfModel:
    """The checked model of the URDF `path` and its meshes (`bh8_gym.urdfs`), or an ObjectError.
    Its size is checked on the loaded body (`check_loaded_object`)."""
    try:
        return read_urdf(path)
    except UrdfError as error:
        raise ObjectError(str(error)) from None


def check_urdf_object(path, scale: float) -> None:
    """`check_urdf_file`, then the URDF we write from it loaded at `scale` into a scratch PyBullet
    world and checked by `check_loaded_object`: an ObjectError before any world of ours holds it."""
    model = check_urdf_file(path)
    client = p.connect(p.DIRECT)
    try:
        with pybullet_files.written(model.files()) as paths, file_errors_named("urdf", path):
            body = p.loadURDF(paths[-1], globalScaling=float(scale), physicsClientId=client)
        check_loaded_object(client, body, f"URDF {str(path)!r} at scale {scale:g}")
    finally:
        p.disconnect(client)


def check_loaded_object(client: int, body: int, what: str) -> None:
    """ObjectError unless every link of a loaded `body` has a finite size and mass within the
    upper bounds (a URDF's links may be small, massless helpers)."""
    for link in range(-1, p.getNumJoints(body, physicsClientId=client)):
        low, high = p.getAABB(body, link, physicsClientId=client)
        extents = [h - l for l, h in zip(low, high)]
        if not all(math.isfinite(v) and v <= OBJECT_EXTENT_RANGE_M[1] for v in extents):
            check_object_extents(extents, what)
        mass = p.getDynamicsInfo(body, link, physicsClientId=client)[0]
        if not (math.isfinite(mass) and 0.0 <= mass <= OBJECT_MASS_RANGE_KG[1]):
            raise ObjectError(f"{what}: a link's mass is {mass!r} kg; at most {OBJECT_MASS_RANGE_KG[1]:g} kg")


def check_pose(position, orientation) -> tuple[list[float], list[float]]:
    """(position, orientation) as floats, or an ObjectError: x, y, z within ±OBJECT_POSITION_LIMIT_M
    and a non-zero quaternion x, y, z, w."""
    position = [float(v) for v in position]
    if len(position) != 3 or not all(math.isfinite(v) and abs(v) <= OBJECT_POSITION_LIMIT_M for v in position):
        raise ObjectError(f"object position must be x, y, z within ±{OBJECT_POSITION_LIMIT_M:g} m, got {position!r}")
    orientation = [float(v) for v in orientation]
    if len(orientation) != 4 or not all(math.isfinite(v) for v in orientation) or math.hypot(*orientation) < 1e-6:
        raise ObjectError(f"object orientation must be a quaternion x, y, z, w, got {orientation!r}")
    return position, orientation


@contextmanager
def file_errors_named(kind: str, path) -> Iterator[None]:
    """PyBullet's bare "Cannot load URDF file" / "createCollisionShape failed" as an ObjectError (a
    ValueError) naming the file `kind` ("urdf" or "mesh") `path`."""
    try:
        yield
    except p.error as error:
        raise ObjectError(f"PyBullet cannot load the {kind} file {str(path)!r} ({error}): not a valid "
                          f"{'URDF' if kind == 'urdf' else 'OBJ/STL mesh'}?") from None


def _existing_file(spec: ObjectSpec) -> None:
    if not Path(spec.path).expanduser().is_file():
        raise ObjectError(f"object file not found: {spec.path!r}")


# ---------------------------------------------------------------------------- loading

class ObjectLoader:
    """Creates object bodies in one PyBullet client, caching shapes by `ObjectSpec.shape_key`.

    `shapes_created` counts the shapes made: PyBullet keeps each until its client disconnects."""

    def __init__(self, client: int, visuals: bool = True):
        self.client = client
        self.visuals = visuals
        self._shapes: dict[tuple, tuple[int, int]] = {}
        self.shapes_created = 0

    def _shapes_for(self, spec: ObjectSpec) -> tuple[int, int]:
        cached = self._shapes.get(spec.shape_key)
        if cached is not None:
            return cached
        mesh = check_mesh_file(spec.path, spec.scale) if spec.kind == "mesh" else None
        if spec.kind == "box":
            geometry = dict(shapeType=p.GEOM_BOX, halfExtents=[s / 2 for s in spec.size])
        elif spec.kind == "cylinder":
            geometry = dict(shapeType=p.GEOM_CYLINDER, radius=spec.size[0] / 2, height=spec.size[1])
        elif spec.kind == "sphere":
            geometry = dict(shapeType=p.GEOM_SPHERE, radius=spec.size[0] / 2)
        elif spec.kind == "capsule":
            geometry = dict(shapeType=p.GEOM_CAPSULE, radius=spec.size[0] / 2, height=spec.size[1] - spec.size[0])
        else:
            geometry = dict(shapeType=p.GEOM_MESH, meshScale=[spec.scale] * 3)
        # A mesh reaches PyBullet as the OBJ we write from it (bh8_gym.meshes), never the user's file.
        files = [(mesh.obj_bytes, ".obj")] if mesh is not None else []
        with pybullet_files.written(files) as paths:
            if paths:
                geometry["fileName"] = paths[0]
            with file_errors_named(spec.kind, spec.path):
                collision = p.createCollisionShape(physicsClientId=self.client, **geometry)
            if collision < 0:
                raise ObjectError(f"PyBullet could not build a collision shape for {spec!r}")
            visual = -1
            if self.visuals:
                visual_geometry = dict(geometry)
                if spec.kind == "cylinder" or spec.kind == "capsule":  # createVisualShape's `length` is the `height`
                    visual_geometry["length"] = visual_geometry.pop("height")
                visual = p.createVisualShape(rgbaColor=spec.rgba, physicsClientId=self.client, **visual_geometry)
        self._shapes[spec.shape_key] = (collision, visual)
        self.shapes_created += 1
        return collision, visual

    def _load_urdf(self, spec: ObjectSpec, position, orientation, fixed: bool = False) -> int:
        model = check_urdf_file(spec.path)
        # PyBullet reads the URDF and meshes we write from the checked model, never the user's files.
        with pybullet_files.written(model.files()) as paths, file_errors_named(spec.kind, spec.path):
            body = p.loadURDF(paths[-1], position, orientation, globalScaling=spec.scale, useFixedBase=fixed,
                              physicsClientId=self.client)
        self.shapes_created += 1  # its own shapes, kept by PyBullet as ours are
        try:
            check_loaded_object(self.client, body, f"URDF {spec.path!r} at scale {spec.scale:g}")
        except ValueError:
            p.removeBody(body, physicsClientId=self.client)
            raise
        return body

    def create(self, spec: ObjectSpec, position: Sequence[float], orientation: Sequence[float],
               fixed: bool = False) -> int:
        """A body for `spec` at a pose (base frame = the shape's centre for primitives and meshes):
        the one way an object enters a world. `fixed` makes it immovable (mass 0, a URDF's base
        fixed). A URDF gets `spec.mass` on its base if given; `spec.friction`, if given, is the
        base's lateral friction."""
        if spec.kind == "urdf":
            body = self._load_urdf(spec, position, orientation, fixed=fixed)
        else:
            collision, visual = self._shapes_for(spec)
            body = p.createMultiBody(0.0 if fixed else spec.mass, collision, visual, position, orientation,
                                     physicsClientId=self.client)
        dynamics = {}
        if spec.mass is not None and spec.kind == "urdf":
            dynamics["mass"] = spec.mass
        if spec.friction is not None:
            dynamics["lateralFriction"] = spec.friction
        if dynamics:
            p.changeDynamics(body, -1, physicsClientId=self.client, **dynamics)
        return body

    def remove(self, body: int) -> None:
        p.removeBody(body, physicsClientId=self.client)


def add_object(plant: HandPlant, spec: ObjectSpec, position=(0.0, 0.0, 0.1), orientation=(0.0, 0.0, 0.0, 1.0),
               fixed: bool = False) -> int:
    """Place `spec` in `plant`'s world by hand (module docstring); returns its PyBullet body id.

    `fixed` makes it immovable (mass 0). A URDF keeps its own masses unless `spec.mass` is given
    (then its base gets it, as `ObjectLoader.create` does). ObjectError for a bad pose or file, before
    PyBullet sees it."""
    position, orientation = check_pose(position, orientation)
    if spec.kind in FILE_KINDS:
        _existing_file(spec)
    body = ObjectLoader(plant.client).create(spec, position, orientation, fixed=fixed)
    friction = plant.params.object_friction if spec.friction is None else spec.friction
    for link in range(-1, p.getNumJoints(body, physicsClientId=plant.client)):
        p.changeDynamics(body, link, lateralFriction=friction, rollingFriction=PLACED_ROLLING_FRICTION,
                         spinningFriction=PLACED_SPINNING_FRICTION, physicsClientId=plant.client)
    return body


def add_object_from_spec(plant: HandPlant, text: str) -> int:
    """`add_object` for an `--object` SPEC string (its position, else 0, 0, 0.1)."""
    spec, position = parse_object_spec(text)
    return add_object(plant, spec, position if position is not None else (0.0, 0.0, 0.1))


def remove_object(plant: HandPlant, body: int) -> None:
    """Remove a body `add_object` placed."""
    p.removeBody(body, physicsClientId=plant.client)
