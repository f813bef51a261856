"""A user's URDF read in Python (`read_urdf`) and re-emitted with only what we support, every mesh
rewritten (`bh8_gym.meshes`), so no byte of the user's URDF or its meshes reaches PyBullet's readers.

Why: PyBullet's URDF reader (TinyXML2) read files Python's parser refused and found meshes by rules
a check had to copy; it also loads `<deformable>` meshes, textures and COLLADA through readers that
crash on bad input. Checking a file and then letting PyBullet read the same file leaves each
missed case to crash it. So the URDF is parsed here and PyBullet is given a URDF this package
wrote (`UrdfModel.files`, written by `bh8_gym.pybullet_files`): our own names (`object`, `link0`,
`joint0`, ...), numbers written by us, and absolute paths to clean OBJ files.

What is read (a `UrdfError`, a ValueError naming the file and the reason, for anything else):

- the file: a regular file of at most URDF_FILE_LIMIT_BYTES (`bh8_gym.safe_files`), UTF-8,
  well-formed XML without a document type declaration, at most URDF_ELEMENT_LIMIT elements nested
  at most URDF_DEPTH_LIMIT deep, its root `robot`;
- `link` (at most URDF_LINK_LIMIT): `inertial` (`origin`, `mass`, `inertia`), `visual` and
  `collision` (`origin`, `geometry`; a visual's `material` colour, by name or inline), `contact`
  (PyBullet's friction, restitution, stiffness, damping, cfm/erp and inertia scaling values);
- `joint`: fixed, revolute, continuous or prismatic, with `parent`, `child`, `origin`, `axis`,
  `limit` and `dynamics`; the links form one tree (one root, each other link the child of one joint);
- `geometry`: `box`, `cylinder`, `sphere`, `capsule` or `mesh` (an OBJ or binary STL file and a
  positive `scale`);
- every number decimal and finite, within its bound (NUMBER_BOUNDS).

Anything else is left out (`gazebo`, `transmission`, `deformable`, textures, ...). A mesh name is
found as PyBullet found it, without looking in the working directory: a leading `file://`, then
`package://` or `model://`, dropped; an absolute path as it is; a relative one under the URDF's
folder, then under each folder above it, the innermost first.
"""
from __future__ import annotations

import math
import os
import re
import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass, field

from bh8_gym import pybullet_files
from bh8_gym.meshes import MESH_SUFFIXES, MESH_TRIANGLE_LIMIT, Mesh, MeshError, read_mesh
from bh8_gym.safe_files import read_bounded

# Our bounds: an object's URDF is a few KB (a robot's a few hundred), with a few links and meshes.
URDF_FILE_LIMIT_BYTES = 4 << 20
URDF_DEPTH_LIMIT = 100
URDF_ELEMENT_LIMIT = 20_000
URDF_LINK_LIMIT = 128
URDF_MESH_LIMIT = 64  # distinct mesh files
JOINT_TYPES = ("fixed", "revolute", "continuous", "prismatic")
# (low, high) of each kind of number: lengths in metres, angles in radians, SI units otherwise.
NUMBER_BOUNDS = {
    "xyz": (-100.0, 100.0), "rpy": (-100.0, 100.0), "axis": (-1e3, 1e3), "size": (0.0, 100.0),
    "scale": (1e-6, 1e4), "mass": (0.0, 1e3), "inertia": (-1e3, 1e3), "rgba": (0.0, 1.0),
    "limit": (-1e6, 1e6), "dynamics": (0.0, 1e6),
}
CONTACT_BOUNDS = {
    "lateral_friction": (0.0, 10.0), "rolling_friction": (0.0, 10.0), "spinning_friction": (0.0, 10.0),
    "restitution": (0.0, 1.0), "stiffness": (0.0, 1e9), "damping": (0.0, 1e9), "contact_cfm": (0.0, 1.0),
    "contact_erp": (0.0, 1.0), "inertia_scaling": (0.0, 1e3),
}
_NUMBER = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]{1,3})?")


class UrdfError(ValueError):
    """A URDF that is refused (the message names the file and the reason)."""


@dataclass
class Geometry:
    kind: str  # box, cylinder, sphere, capsule, mesh
    attributes: dict[str, str]  # as we write them
    mesh: Mesh | None = None
    path: str | None = None  # the mesh file it was read from


@dataclass
class Shape:
    origin: dict[str, str]
    geometry: Geometry
    rgba: str | None = None  # visuals only


@dataclass
class Link:
    inertial: list[tuple[str, dict[str, str]]] | None = None  # (tag, attributes) in order
    visuals: list[Shape] = field(default_factory=list)
    collisions: list[Shape] = field(default_factory=list)
    contact: dict[str, str] = field(default_factory=dict)


@dataclass
class Joint:
    type: str
    parent: int
    child: int
    children: list[tuple[str, dict[str, str]]]  # origin, axis, limit, dynamics as we write them


@dataclass
class UrdfModel:
    """A checked URDF: its links and joints, with our own names."""

    links: list[Link]
    joints: list[Joint]

    def files(self) -> list[tuple[bytes, str]]:
        """What `pybullet_files.written` takes: each clean mesh as an OBJ, then the URDF (last)."""
        meshes: dict[int, bytes] = {}
        for link in self.links:
            for shape in link.visuals + link.collisions:
                if shape.geometry.mesh is not None:
                    meshes.setdefault(id(shape.geometry.mesh), shape.geometry.mesh.obj_bytes)
        paths = {key: pybullet_files.path_for(data, ".obj") for key, data in meshes.items()}
        return [(data, ".obj") for data in meshes.values()] + [(self._text(paths), ".urdf")]

    def _text(self, mesh_paths: dict[int, str]) -> bytes:
        robot = ElementTree.Element("robot", name="object")
        for number, link in enumerate(self.links):
            element = ElementTree.SubElement(robot, "link", name=f"link{number}")
            if link.contact:
                contact = ElementTree.SubElement(element, "contact")
                for tag, value in link.contact.items():
                    ElementTree.SubElement(contact, tag, value=value)
            if link.inertial is not None:
                inertial = ElementTree.SubElement(element, "inertial")
                for tag, attributes in link.inertial:
                    ElementTree.SubElement(inertial, tag, attributes)
            for kind, shapes in (("visual", link.visuals), ("collision", link.collisions)):
                for index, shape in enumerate(shapes):
                    self._shape(ElementTree.SubElement(element, kind), shape, mesh_paths, f"material{number}_{index}")
        for number, joint in enumerate(self.joints):
            element = ElementTree.SubElement(robot, "joint", name=f"joint{number}", type=joint.type)
            ElementTree.SubElement(element, "parent", link=f"link{joint.parent}")
            ElementTree.SubElement(element, "child", link=f"link{joint.child}")
            for tag, attributes in joint.children:
                ElementTree.SubElement(element, tag, attributes)
        return ElementTree.tostring(robot, encoding="utf-8", xml_declaration=True)

    @staticmethod
    def _shape(element, shape: Shape, mesh_paths: dict[int, str], material: str) -> None:
        ElementTree.SubElement(element, "origin", shape.origin)
        geometry = ElementTree.SubElement(element, "geometry")
        attributes = dict(shape.geometry.attributes)
        if shape.geometry.mesh is not None:
            attributes["filename"] = mesh_paths[id(shape.geometry.mesh)]
        ElementTree.SubElement(geometry, shape.geometry.kind, attributes)
        if shape.rgba is not None:
            ElementTree.SubElement(ElementTree.SubElement(element, "material", name=material), "color", rgba=shape.rgba)


def read_urdf(path: str | os.PathLike) -> UrdfModel:
    """The checked model of the URDF file `path` (module docstring), or a UrdfError."""
    path = os.fspath(path)
    root = _parse(path, read_bounded(path, URDF_FILE_LIMIT_BYTES, "URDF", UrdfError))
    return _Reader(path, root).model()


class _Reader:
    """Reads the elements we support from a parsed URDF, checking every number and name."""

    def __init__(self, path: str, root: ElementTree.Element):
        self.path, self.root = path, root
        self.found: dict[str, Mesh] = {}  # mesh file -> its checked mesh (each read once)
        self.triangles = 0

    def fail(self, message: str) -> UrdfError:
        return UrdfError(f"URDF {self.path!r}: {message}")

    def model(self) -> UrdfModel:
        if _local(self.root.tag) != "robot":
            raise self.fail(f"the root element is <{_local(self.root.tag)}>, not <robot>")
        materials = {}
        for element in _children(self.root, "material"):
            color = _child(element, "color")
            if element.get("name") is not None and color is not None:
                materials[element.get("name")] = self.numbers(color, "rgba", 4, "rgba")
        link_elements = _children(self.root, "link")
        if not link_elements:
            raise self.fail("it has no <link>")
        if len(link_elements) > URDF_LINK_LIMIT:
            raise self.fail(f"it has more than {URDF_LINK_LIMIT} links")
        names = [element.get("name") for element in link_elements]
        if None in names or len(set(names)) != len(names):
            raise self.fail("every <link> needs a name of its own")
        index = {name: number for number, name in enumerate(names)}
        links = [self.link(element, materials) for element in link_elements]
        joints = [self.joint(element, index) for element in _children(self.root, "joint")]
        self.check_tree(joints, len(links))
        return UrdfModel(links, joints)

    def link(self, element, materials: dict[str, str]) -> Link:
        link = Link()
        inertial = _child(element, "inertial")
        if inertial is not None:
            link.inertial = [("origin", self.origin(inertial))]
            mass = _child(inertial, "mass")
            if mass is not None:
                link.inertial.append(("mass", {"value": self.numbers(mass, "value", 1, "mass")}))
            inertia = _child(inertial, "inertia")
            if inertia is not None:
                link.inertial.append(("inertia", {key: self.numbers(inertia, key, 1, "inertia", default="0")
                                                  for key in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")}))
        for visual in _children(element, "visual"):
            shape = self.shape(visual)
            material = _child(visual, "material")
            if material is not None:
                color = _child(material, "color")
                shape.rgba = (self.numbers(color, "rgba", 4, "rgba") if color is not None
                              else materials.get(material.get("name", "")))
            link.visuals.append(shape)
        link.collisions = [self.shape(collision) for collision in _children(element, "collision")]
        contact = _child(element, "contact")
        if contact is not None:
            for tag, bounds in CONTACT_BOUNDS.items():
                value = _child(contact, tag)
                if value is not None:
                    link.contact[tag] = self.numbers(value, "value", 1, tag, bounds=bounds)
        return link

    def shape(self, element) -> Shape:
        geometry = _child(element, "geometry")
        if geometry is None:
            raise self.fail(f"a <{_local(element.tag)}> has no <geometry>")
        kinds = [child for child in geometry if _local(child.tag) in ("box", "cylinder", "sphere", "capsule", "mesh")]
        if len(kinds) != 1:
            raise self.fail("a <geometry> needs exactly one box, cylinder, sphere, capsule or mesh")
        shape, kind = kinds[0], _local(kinds[0].tag)
        if kind == "box":
            return Shape(self.origin(element), Geometry(kind, {"size": self.numbers(shape, "size", 3, "size")}))
        if kind == "sphere":
            return Shape(self.origin(element), Geometry(kind, {"radius": self.numbers(shape, "radius", 1, "size")}))
        if kind in ("cylinder", "capsule"):
            return Shape(self.origin(element), Geometry(kind, {key: self.numbers(shape, key, 1, "size")
                                                               for key in ("radius", "length")}))
        scale = self.numbers(shape, "scale", 3, "scale", default="1 1 1")
        path, mesh = self.mesh(shape.get("filename"))
        return Shape(self.origin(element), Geometry("mesh", {"scale": scale}, mesh, path))

    def mesh(self, name: str | None) -> tuple[str, Mesh]:
        if not name or len(name) > 4096:
            raise self.fail(f"a <mesh> needs a filename, got {name!r:.100}")
        if not name.lower().endswith(MESH_SUFFIXES):
            raise self.fail(f"mesh {name!r:.200}: a mesh must be an {' or '.join(MESH_SUFFIXES)} file "
                            "(COLLADA and other kinds are not read)")
        candidates = mesh_candidates(self.path, name)
        found = next((candidate for candidate in candidates if os.path.lexists(candidate)), None)
        if found is None:
            raise self.fail(f"mesh {name!r:.200} not found (looked for {candidates[0]!r} and under the folders "
                            "above the URDF)")
        if found not in self.found:
            if len(self.found) >= URDF_MESH_LIMIT:
                raise self.fail(f"it names more than {URDF_MESH_LIMIT} mesh files")
            try:
                mesh = read_mesh(found)
            except MeshError as error:
                raise self.fail(str(error)) from None
            self.triangles += sum(len(part) for part in mesh.parts)
            if self.triangles > MESH_TRIANGLE_LIMIT:
                raise self.fail(f"its meshes have more than {MESH_TRIANGLE_LIMIT} triangles")
            self.found[found] = mesh
        return found, self.found[found]

    def joint(self, element, index: dict[str, int]) -> Joint:
        kind = element.get("type")
        if kind not in JOINT_TYPES:
            raise self.fail(f"joint type {kind!r:.40}: one of {', '.join(JOINT_TYPES)} is supported")
        ends = []
        for tag in ("parent", "child"):
            end = _child(element, tag)
            name = end.get("link") if end is not None else None
            if name not in index:
                raise self.fail(f"a joint's <{tag}> names no link of the URDF ({name!r:.80})")
            ends.append(index[name])
        children = [("origin", self.origin(element))]
        axis = _child(element, "axis")
        if axis is not None:
            xyz = self.numbers(axis, "xyz", 3, "axis", default="1 0 0")
            if all(float(v) == 0.0 for v in xyz.split()):
                raise self.fail("a joint's axis is 0 0 0")
            children.append(("axis", {"xyz": xyz}))
        limit = _child(element, "limit")
        if limit is not None:
            children.append(("limit", {key: self.numbers(limit, key, 1, "limit", default="0")
                                       for key in ("lower", "upper", "effort", "velocity")}))
        dynamics = _child(element, "dynamics")
        if dynamics is not None:
            children.append(("dynamics", {key: self.numbers(dynamics, key, 1, "dynamics", default="0")
                                          for key in ("damping", "friction")}))
        return Joint(kind, ends[0], ends[1], children)

    def check_tree(self, joints: list[Joint], count: int) -> None:
        parents: dict[int, int] = {}
        for joint in joints:
            if joint.child in parents or joint.child == joint.parent:
                raise self.fail(f"link {joint.child} is the child of more than one joint, or of itself")
            parents[joint.child] = joint.parent
        roots = [link for link in range(count) if link not in parents]
        if len(roots) != 1:
            raise self.fail(f"its links must form one tree (it has {len(roots)} roots)")
        for link in range(count):  # each link reaches the root within `count` steps: no cycle
            for _ in range(count):
                if link not in parents:
                    break
                link = parents[link]
            else:
                raise self.fail("its joints form a cycle")

    def origin(self, element) -> dict[str, str]:
        origin = _child(element, "origin")
        if origin is None:
            return {"xyz": "0 0 0", "rpy": "0 0 0"}
        return {key: self.numbers(origin, key, 3, key, default="0 0 0") for key in ("xyz", "rpy")}

    def numbers(self, element, attribute: str, count: int, kind: str, default: str | None = None,
                bounds: tuple[float, float] | None = None) -> str:
        """The attribute's `count` numbers, checked against their bounds, as we write them."""
        text = element.get(attribute, default)
        fields = text.split() if isinstance(text, str) else []
        low, high = bounds or NUMBER_BOUNDS[kind]
        if len(fields) != count or not all(_NUMBER.fullmatch(value) for value in fields):
            raise self.fail(f"<{_local(element.tag)} {attribute}> needs {count} decimal number(s), "
                            f"got {text!r:.80}")
        values = [float(value) for value in fields]
        if not all(math.isfinite(value) and low <= value <= high for value in values):
            raise self.fail(f"<{_local(element.tag)} {attribute}> {text!r:.80}: each must be {low:g} to {high:g}")
        return " ".join(repr(value) for value in values)


def mesh_candidates(urdf_path: str, name: str) -> list[str]:
    """The files tried, in order, for the mesh `name` of the URDF `urdf_path` (module docstring)."""
    name = name.removeprefix("file://")
    for scheme in ("package://", "model://"):
        if name.startswith(scheme):
            name = name[len(scheme):]
            break
    if os.path.isabs(name):
        return [name]
    folder = os.path.dirname(os.path.abspath(urdf_path))
    candidates = []
    while True:
        candidates.append(os.path.join(folder, name))
        parent = os.path.dirname(folder)
        if parent == folder:
            return candidates
        folder = parent


def _local(tag) -> str:
    return tag.rpartition("}")[2] if isinstance(tag, str) else ""


def _children(element, tag: str) -> list:
    return [child for child in element if _local(child.tag) == tag]


def _child(element, tag: str):
    found = _children(element, tag)
    return found[0] if found else None


class _Builder(ElementTree.TreeBuilder):
    """Builds the tree, refusing a DTD, deep nesting and too many elements as soon as they start."""

    def __init__(self, path: str):
        super().__init__()
        self.path, self.depth, self.count = path, 0, 0

    def doctype(self, name, pubid, system):
        raise UrdfError(f"URDF {self.path!r} has a document type declaration (<!DOCTYPE>); remove it")

    def start(self, tag, attrs):
        self.depth += 1
        self.count += 1
        if self.depth > URDF_DEPTH_LIMIT:
            raise UrdfError(f"URDF {self.path!r} nests elements more than {URDF_DEPTH_LIMIT} deep")
        if self.count > URDF_ELEMENT_LIMIT:
            raise UrdfError(f"URDF {self.path!r} has more than {URDF_ELEMENT_LIMIT} elements")
        return super().start(tag, attrs)

    def end(self, tag):
        self.depth -= 1
        return super().end(tag)


def _parse(path: str, data: bytes) -> ElementTree.Element:
    try:
        data.decode("utf-8")
    except UnicodeDecodeError as error:
        raise UrdfError(f"URDF {path!r} is not UTF-8 text (byte {error.start})") from None
    parser = ElementTree.XMLParser(target=_Builder(path), encoding="utf-8")
    try:
        parser.feed(data)
        return parser.close()
    except ElementTree.ParseError as error:
        raise UrdfError(f"URDF {path!r} is not well-formed XML ({error})") from None
