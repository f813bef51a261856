"""Mesh files checked before PyBullet reads them: a small validating reader of OBJ and binary STL.

PyBullet's readers trust their input. Its OBJ reader (Bullet's fork of tinyobjloader) indexes the
vertex array with a face's numbers unchecked, so `f 1 2 999999`, a face before any vertex, or an
index past a C int kills the whole process (SIGSEGV); a NaN vertex loads and turns the physics to
NaN. Its STL reader takes binary STL only. So an object file is read here first, by the rules that
reader follows, and refused with a `MeshError` naming the file, the line and the reason, unless
PyBullet can read it safely:

- OBJ: lines of at most `OBJ_LINE_LIMIT` characters (the reader's buffer splits longer ones, which
  could smuggle a line past a check); `v x y z [...]` with finite numbers within float32; faces
  `f` of at least two vertices (two make no triangle and are skipped), each `i`, `i/j`, `i/j/k`
  or `i//k`, whose vertex number `i` names a vertex defined above it (1..n, or -n..-1 counted
  back; 0 is no vertex). The texture and normal numbers `j` and `k` must be written and not 0:
  the reader bounds-checks them itself, but it refuses a 0 (`createCollisionShape failed`), and
  it reads a missing one (`i/`, `i/j/`) as 0, or as the next entry's number when a space follows
  (measured on pybullet 3.2.7). Other lines (`vn`, `vt`, `g`, `o`, `usemtl`, comments, ...) are
  left to it.
- STL: binary, `84 + 50 × n` bytes for its n ≥ 1 triangles, every vertex finite.
- Either: a regular file of at most `MESH_FILE_LIMIT_BYTES`, with at least one face.

`mesh_bounds` returns the axis-aligned bounds of the vertices the faces use (what PyBullet's
collision shape is built from), so callers can check an object's size before loading it.
"""
from __future__ import annotations

import functools
import os
import re
import stat
from pathlib import Path

import numpy as np

MESH_SUFFIXES = (".obj", ".stl")
# Our bound: a graspable object's mesh is KBs to a few MB; a bigger file is refused unread.
MESH_FILE_LIMIT_BYTES = 64 << 20
# Bullet's OBJ reader reads a line into a 1024-byte buffer (1023 characters and the terminator).
OBJ_LINE_LIMIT = 1023
FLOAT32_MAX = float(np.finfo(np.float32).max)
# A C int's digits: the reader converts indices with atoi, which has no defined result past them.
_INDEX_DIGITS = 9
_FLOAT = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
# i, i/j, i/j/k or i//k: the groups are i, then j of i/j, j and k of i/j/k, or k of i//k.
_FACE_VERTEX = re.compile(r"(-?[0-9]+)(?:/(-?[0-9]+)|/(-?[0-9]+)/(-?[0-9]+)|//(-?[0-9]+))?")
_SPACES = re.compile(r"[ \t]+")
_STL_HEADER_BYTES = 84
_STL_TRIANGLE = np.dtype([("normal", "<f4", 3), ("vertices", "<f4", (3, 3)), ("attribute", "<u2")])


class MeshError(ValueError):
    """A mesh file PyBullet cannot read safely (the message names the file and the reason)."""


def mesh_bounds(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """(min, max) of the vertices the faces of the OBJ or binary STL file `path` use, in file
    units; MeshError if PyBullet could not read the file safely (module docstring)."""
    path = Path(path)
    try:
        info = path.stat()
    except OSError as error:
        raise MeshError(f"mesh {str(path)!r} cannot be read: {error.strerror or error}") from None
    low, high = _checked_bounds(str(path), info.st_size, info.st_mtime_ns, info.st_ino)
    return np.array(low), np.array(high)


@functools.lru_cache(maxsize=256)
def _checked_bounds(path: str, size: int, mtime_ns: int, inode: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Checked once per file version (the environments load the same meshes episode after episode)."""
    suffix = Path(path).suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise MeshError(f"mesh {path!r}: PyBullet builds collision shapes from {' and '.join(MESH_SUFFIXES)} files only")
    data = read_regular_file(path, MESH_FILE_LIMIT_BYTES, "mesh", MeshError)
    vertices = _obj_vertices(path, data) if suffix == ".obj" else _stl_vertices(path, data)
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    return tuple(float(v) for v in low), tuple(float(v) for v in high)


def read_regular_file(path: str, limit: int, what: str, error_type: type[ValueError]) -> bytes:
    """The bytes of `path`, a regular file of at most `limit` bytes (a FIFO or device is refused
    unread), or an `error_type` naming it as `what` ("mesh", "URDF")."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))  # a FIFO must not block the open
    except (OSError, ValueError) as error:  # ValueError: a NUL in the name
        raise error_type(f"{what} {path!r} cannot be read: {getattr(error, 'strerror', None) or error}") from None
    with os.fdopen(fd, "rb") as handle:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise error_type(f"{what} {path!r} is not a regular file")
        data = handle.read(limit + 1)
    if len(data) > limit:
        raise error_type(f"{what} {path!r} is larger than {limit >> 20} MB")
    return data


def _obj_vertices(path: str, data: bytes) -> np.ndarray:
    """The vertices the faces of an OBJ file use, as an (n, 3) array; MeshError on a bad line."""
    vertices: list[tuple[float, float, float]] = []
    used: set[int] = set()
    # The reader ends a line at LF; a NUL or CR ends what it parses of it.
    for number, raw in enumerate(data.split(b"\n"), start=1):
        if len(raw) > OBJ_LINE_LIMIT:
            raise MeshError(f"mesh {path!r} line {number}: longer than {OBJ_LINE_LIMIT} characters")
        line = raw.decode("latin-1").split("\0", 1)[0].split("\r", 1)[0].lstrip(" \t")
        if len(line) < 2 or line[1] not in " \t" or line[0] not in "vf":
            continue  # comments, vn, vt, g, o, usemtl, ...: nothing the reader indexes unchecked
        fields = _SPACES.split(line[2:].strip(" \t"))
        if line[0] == "v":
            vertices.append(_obj_vertex(path, number, fields))
            continue
        if len(fields) < 2 or not fields[0]:  # the reader reads two entries of every face
            raise MeshError(f"mesh {path!r} line {number}: a face needs at least 3 vertices, got {line!r:.80}")
        face = [_obj_face_vertex(path, number, field, len(vertices)) for field in fields]
        if len(face) >= 3:  # two make no triangle (the reader skips such a line segment)
            used.update(face)
    if not used:
        raise MeshError(f"mesh {path!r} has no faces")
    return np.array([vertices[i] for i in sorted(used)], dtype=float)


def _obj_vertex(path: str, number: int, fields: list[str]) -> tuple[float, float, float]:
    if len(fields) < 3 or not all(_FLOAT.fullmatch(field) for field in fields[:3]):
        raise MeshError(f"mesh {path!r} line {number}: a vertex needs 3 decimal numbers, got {' '.join(fields)!r:.80}")
    xyz = tuple(float(field) for field in fields[:3])
    if not all(abs(value) <= FLOAT32_MAX for value in xyz):
        raise MeshError(f"mesh {path!r} line {number}: vertex {xyz} is beyond float32")
    return xyz


def _obj_face_vertex(path: str, number: int, field: str, defined: int) -> int:
    """The 0-based vertex of one face entry; it must be one of the `defined` vertices above it."""
    found = _FACE_VERTEX.fullmatch(field)
    if found is None or any(part and len(part.lstrip("-")) > _INDEX_DIGITS for part in found.groups()):
        raise MeshError(f"mesh {path!r} line {number}: {field!r:.40} is not a face vertex (i, i/j, i/j/k or i//k)")
    if any(part is not None and int(part) == 0 for part in found.groups()[1:]):
        raise MeshError(f"mesh {path!r} line {number}: face vertex {field!r:.40} has a texture or normal number "
                        "of 0, which PyBullet refuses (they count from 1, or back from -1)")
    index = int(found.group(1))
    resolved = index - 1 if index > 0 else defined + index
    if index == 0 or not 0 <= resolved < defined:
        raise MeshError(f"mesh {path!r} line {number}: face vertex {index} is not one of the {defined} vertices "
                        "defined above it")
    return resolved


def _stl_vertices(path: str, data: bytes) -> np.ndarray:
    count = int.from_bytes(data[80:84], "little") if len(data) >= _STL_HEADER_BYTES else 0
    if count < 1 or len(data) != _STL_HEADER_BYTES + _STL_TRIANGLE.itemsize * count:
        raise MeshError(f"mesh {path!r}: not a binary STL with at least one triangle (PyBullet reads binary STL "
                        f"only: 84 + 50 x n bytes, n in bytes 80-83)")
    triangles = np.frombuffer(data, dtype=_STL_TRIANGLE, offset=_STL_HEADER_BYTES, count=count)
    vertices = triangles["vertices"].reshape(-1, 3).astype(float)
    if not np.all(np.isfinite(vertices)):
        raise MeshError(f"mesh {path!r}: a vertex is not a finite number")
    return vertices
