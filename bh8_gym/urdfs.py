"""URDF files checked before PyBullet reads them: the mesh files PyBullet would open, found as it finds them.

PyBullet reads a URDF with its own XML reader (TinyXML2) and looks for each mesh by its own rules,
then hands the mesh to readers that trust their input (bh8_gym.meshes). A check that reads the
URDF differently checks other files than PyBullet opens: a URDF Python's parser refused (an
undefined entity, a bare `&`, junk after the root, a NUL byte) or a mesh named
`file://badface.obj` was not checked, and PyBullet then died of SIGSEGV on the mesh's bad face.
So `urdf_mesh_files` reads a URDF as PyBullet reads it and refuses it with a `UrdfError` wherever
the two readers could disagree:

- a regular file of at most `URDF_FILE_LIMIT_BYTES`, UTF-8 text (TinyXML2 reads the bytes as
  UTF-8 whatever the XML declaration says), well-formed XML without a document type declaration
  (Python's parser expands a DTD's entities; TinyXML2 ignores them), nested at most
  `URDF_DEPTH_LIMIT` elements deep;
- every element named `mesh` (in any XML namespace: TinyXML2 knows none) with a `filename`
  attribute: the name has no space or control character (Python's parser reads a tab or line
  break in an attribute as a space, TinyXML2 keeps it, so the two would name different files);
  PyBullet takes a name of more than 4 characters ending (any case) in `.obj`, `.stl`, `.dae` or
  `.cdf`: OBJ and STL files must pass `bh8_gym.meshes`; COLLADA (`.dae`) and `.cdf` files are
  refused (PyBullet's COLLADA reader crashes on a bad index as well, and is not checked here);
- the file PyBullet opens for a name (`pybullet_mesh_candidates`, measured on pybullet 3.2.7 and
  as Bullet's `UrdfFindMeshFile` reads): a leading `file://` dropped, then a `package://` or
  `model://`; the name as it is (an absolute path, or relative to the working directory), then
  under each directory of the URDF's path, the innermost first, then under `.`, `..` and `../..`:
  the first that opens. A name that opens nowhere is PyBullet's clean "cannot find" error.
"""
from __future__ import annotations

import os
import xml.etree.ElementTree as ElementTree

from bh8_gym.meshes import MESH_SUFFIXES, read_regular_file

# Our bounds: an object's URDF is a few KB (a robot's a few hundred); elements nest 5 deep
# (robot, link, collision, geometry, mesh).
URDF_FILE_LIMIT_BYTES = 4 << 20
URDF_DEPTH_LIMIT = 100
# What PyBullet reads by the last 4 characters of a mesh name, and the readers not checked here.
PYBULLET_MESH_SUFFIXES = (".obj", ".stl", ".dae", ".cdf")
UNCHECKED_MESH_SUFFIXES = (".dae", ".cdf")


class UrdfError(ValueError):
    """A URDF PyBullet might read differently from this check, or whose meshes are not safe to load."""


def urdf_mesh_files(path: str | os.PathLike) -> list[str]:
    """The OBJ/STL files PyBullet opens when it loads the URDF `path` (the same string passed to
    `loadURDF`: the search depends on it), in document order; UrdfError for a URDF it could read
    differently or that names a mesh kind not checked here (module docstring)."""
    path = os.fspath(path)
    data = read_regular_file(path, URDF_FILE_LIMIT_BYTES, "URDF", UrdfError)
    found = []
    for name in _mesh_names(path, data):
        if len(name) <= 4 or name[-4:].lower() not in PYBULLET_MESH_SUFFIXES:
            continue  # PyBullet skips the name ("invalid mesh filename")
        if name[-4:].lower() in UNCHECKED_MESH_SUFFIXES:
            raise UrdfError(f"URDF {path!r}: mesh {name!r}: a URDF object's meshes must be "
                            f"{' or '.join(MESH_SUFFIXES)} files (PyBullet's reader of the others is not checked)")
        opened = next((candidate for candidate in pybullet_mesh_candidates(path, name) if _opens(candidate)), None)
        if opened is not None:
            found.append(opened)
    return found


def pybullet_mesh_candidates(urdf_path: str, name: str) -> list[str]:
    """The files PyBullet tries, in order, for the mesh `name` of the URDF `urdf_path` (module docstring)."""
    name = name.removeprefix("file://")
    for scheme in ("package://", "model://"):
        if name.startswith(scheme):
            name = name[len(scheme):]
            break
    directories = [urdf_path[:index] for index, char in enumerate(urdf_path) if char in "/\\"]
    return [name, *(f"{directory}/{name}" for directory in [*reversed(directories), ".", "..", "../.."])]


def _opens(candidate: str) -> bool:
    """Whether PyBullet's fopen(candidate, "rb") would succeed (a directory or FIFO does: the mesh
    check then refuses it)."""
    try:
        os.close(os.open(candidate, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0)))
    except (OSError, ValueError):  # ValueError: a NUL in the name
        return False
    return True


class _Builder(ElementTree.TreeBuilder):
    """Builds the tree, refusing a DTD and nesting deeper than URDF_DEPTH_LIMIT as soon as they start."""

    def __init__(self, path: str):
        super().__init__()
        self.path, self.depth = path, 0

    def doctype(self, name, pubid, system):
        raise UrdfError(f"URDF {self.path!r} has a document type declaration (<!DOCTYPE>), whose entities "
                        "PyBullet's XML reader does not read as Python's does; remove it")

    def start(self, tag, attrs):
        self.depth += 1
        if self.depth > URDF_DEPTH_LIMIT:
            raise UrdfError(f"URDF {self.path!r} nests elements more than {URDF_DEPTH_LIMIT} deep")
        return super().start(tag, attrs)

    def end(self, tag):
        self.depth -= 1
        return super().end(tag)


def _mesh_names(path: str, data: bytes) -> list[str]:
    """The `filename` of every `mesh` element, refusing what PyBullet's XML reader could read differently."""
    try:
        data.decode("utf-8")
    except UnicodeDecodeError as error:
        raise UrdfError(f"URDF {path!r} is not UTF-8 text (byte {error.start}), which PyBullet's XML reader "
                        "expects") from None
    parser = ElementTree.XMLParser(target=_Builder(path), encoding="utf-8")  # the declaration is not TinyXML2's
    try:
        parser.feed(data)
        root = parser.close()
    except ElementTree.ParseError as error:
        raise UrdfError(f"URDF {path!r} is not well-formed XML ({error})") from None
    names = []
    for element in root.iter():
        local_name = element.tag.rpartition("}")[2] if isinstance(element.tag, str) else ""  # not a comment or PI
        if local_name != "mesh" or "filename" not in element.attrib:
            continue
        name = element.attrib["filename"]
        if any(char.isspace() or ord(char) < 32 or ord(char) == 127 for char in name):
            raise UrdfError(f"URDF {path!r}: mesh filename {name!r} holds a space or control character; rename "
                            "the file (a space here may be a tab or line break in the file, which PyBullet's XML "
                            "reader keeps and Python's does not)")
        names.append(name)
    return names

