"""A user's mesh read in Python (`read_mesh`): OBJ and binary STL, checked, and rewritten as a clean
OBJ for PyBullet (`Mesh.obj_bytes`), so no byte of the user's file reaches PyBullet's readers.

Why: PyBullet's readers trust their input. Its OBJ reader (Bullet's fork of tinyobjloader) indexes
its vertex array with a face's numbers unchecked (`f 1 2 999999` killed the process with SIGSEGV),
follows `mtllib` to an MTL file whose texture name overran a stack buffer, and its renderer decodes
the texture with stb_image (a truncated HDR looped forever; a 560 KB PNG took 2 GB). Checking a file
and then letting PyBullet read the same file keeps all of that one missed case away. So the file is
parsed here, and PyBullet is given an OBJ this package wrote (`bh8_gym.pybullet_files`): vertex
lines and triangle lines, nothing else (no MTL, no texture, no normals).

What is read (a `MeshError`, a ValueError naming the file, line and reason, for anything else):

- OBJ: text without NUL bytes. `v x y z [...]`: decimal numbers, finite within float32 (PyBullet
  stores float32). `f e1 e2 e3 ...`: each entry `i`, `i/j`, `i/j/k` or `i//k`,
  `i` a vertex defined above it (1..n, or -n..-1 counted back); `j` and `k` (texture and normal)
  are not used and so not checked. A face of fewer than 3 entries makes no triangle and is skipped
  (as PyBullet does). `o` and `g` start a new part. Everything else (`vn`, `vt`, `mtllib`,
  `usemtl`, `s`, comments, ...) is ignored: in particular no MTL or texture file is opened.
- STL: binary, `84 + 50 x n` bytes for its n >= 1 triangles, every vertex finite within float32.
- Either: a regular file of at most MESH_FILE_LIMIT_BYTES (`bh8_gym.safe_files`), with at least one
  triangle, at most MESH_PART_LIMIT parts and MESH_TRIANGLE_LIMIT triangles.

The collision shape PyBullet builds from the clean OBJ is the one it built from the user's file:
one convex hull per part (`o`/`g` group; an STL is one part), of the face vertices in the same
order: polygons are split into the triangle fan PyBullet's reader makes, and each vertex is kept as
the double the file's decimal reads as and written as the shortest decimal of that double, which
PyBullet's `atof` reads back to the same double (and so to the same float32).
"""
from __future__ import annotations

import functools
import hashlib
import os
import re
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bh8_gym.safe_files import read_bounded

MESH_SUFFIXES = (".obj", ".stl")
# Our bounds: a graspable object's mesh is KBs to a few MB (pybullet_data's random_urdfs: 14 KB on
# average, 100 KB at most); a convex decomposition has tens of parts.
MESH_FILE_LIMIT_BYTES = 32 << 20
MESH_PART_LIMIT = 1024
MESH_TRIANGLE_LIMIT = 2_000_000
FLOAT32_MAX = float(np.finfo(np.float32).max)
_INDEX_DIGITS = 9  # a vertex number past a C int's digits is refused, whatever it resolves to
_FLOAT = re.compile(rb"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]{1,4})?")
# i, i/j, i/j/k or i//k: group 1 is i; j and k are not used.
_FACE_VERTEX = re.compile(rb"(-?[0-9]{1,%d})(?:/-?[0-9]+|/-?[0-9]+/-?[0-9]+|//-?[0-9]+)?" % _INDEX_DIGITS)
_PLAIN_FACE = re.compile(rb"[ \t]*f(?:[ \t]+[0-9]{1,%d})+\s*" % _INDEX_DIGITS)  # positive numbers only
_STL_HEADER_BYTES = 84
_STL_TRIANGLE = np.dtype([("normal", "<f4", 3), ("vertices", "<f4", (3, 3)), ("attribute", "<u2")])
_CACHE_ENTRIES = 2048  # parsed meshes kept per process (the envs load the same meshes episode after episode)


class MeshError(ValueError):
    """A mesh file that is refused (the message names the file and the reason)."""


@dataclass(frozen=True, eq=False)
class Mesh:
    """A checked mesh: `vertices` (n, 3) float64 in file units, in the order faces first use them,
    and `parts`, one (m, 3) int32 array of triangles (indices into `vertices`) per convex part."""

    vertices: np.ndarray
    parts: tuple[np.ndarray, ...]

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) of the vertices (every vertex is used by a face), in file units."""
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    @functools.cached_property
    def obj_bytes(self) -> bytes:
        """The mesh as an OBJ written by us: vertex lines, then per part an `o` line and its triangles."""
        lines = [b"# written by bh8_gym.meshes from a checked mesh"]
        lines.extend(b"v %r %r %r" % tuple(float(v) for v in vertex) for vertex in self.vertices)
        for number, triangles in enumerate(self.parts):
            lines.append(b"o part%d" % number)
            lines.extend(b"f %d %d %d" % (a, b, c) for a, b, c in (triangles + 1).tolist())
        lines.append(b"")
        return b"\n".join(lines)


_cache: OrderedDict[tuple[str, bytes], Mesh] = OrderedDict()


def read_mesh(path: str | os.PathLike) -> Mesh:
    """The checked mesh of the OBJ or binary STL file `path` (module docstring), or a MeshError."""
    path = os.fspath(path)
    suffix = Path(path).suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise MeshError(f"mesh {path!r}: a mesh must be an {' or '.join(MESH_SUFFIXES)} file")
    data = read_bounded(path, MESH_FILE_LIMIT_BYTES, "mesh", MeshError)
    key = (suffix, hashlib.sha256(data).digest())
    mesh = _cache.get(key)
    if mesh is None:
        mesh = _obj_mesh(path, data) if suffix == ".obj" else _stl_mesh(path, data)
        _cache[key] = mesh
        if len(_cache) > _CACHE_ENTRIES:
            _cache.popitem(last=False)
    else:
        _cache.move_to_end(key)
    return mesh


def mesh_bounds(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """(min, max) of the vertices of the checked mesh `path`, in file units; MeshError if refused."""
    return read_mesh(path).bounds


def _obj_mesh(path: str, data: bytes) -> Mesh:
    if b"\0" in data:
        raise MeshError(f"mesh {path!r}: an OBJ file is text; this one holds a NUL byte (byte {data.index(0)})")
    defined: list[tuple[float, float, float]] = []
    parts: list[list[int]] = [[]]  # per part, the flat vertex numbers (0-based) of its triangles
    triangles = 0
    for number, raw in enumerate(data.split(b"\n"), start=1):
        fields = raw.split()
        if not fields:
            continue
        head = fields[0]
        if head == b"v":
            defined.append(_obj_vertex(path, number, fields[1:]))
        elif head == b"f":
            if _PLAIN_FACE.fullmatch(raw):  # the usual `f 1 2 3`: one check for the line
                face = [int(field) - 1 for field in fields[1:]]
                if face and (min(face) < 0 or max(face) >= len(defined)):
                    face = [_obj_face_vertex(path, number, field, len(defined)) for field in fields[1:]]  # names it
            else:
                face = [_obj_face_vertex(path, number, field, len(defined)) for field in fields[1:]]
            for second in range(1, len(face) - 1):  # the fan PyBullet's reader makes; < 3 entries: none
                parts[-1].extend((face[0], face[second], face[second + 1]))
            triangles += max(0, len(face) - 2)
            if triangles > MESH_TRIANGLE_LIMIT:
                raise MeshError(f"mesh {path!r} has more than {MESH_TRIANGLE_LIMIT} triangles")
        elif head in (b"o", b"g") and parts[-1]:
            if len(parts) >= MESH_PART_LIMIT:
                raise MeshError(f"mesh {path!r} has more than {MESH_PART_LIMIT} parts (o/g groups with faces)")
            parts.append([])
    parts = [part for part in parts if part]
    if not parts:
        raise MeshError(f"mesh {path!r} has no faces (a face needs 3 vertices)")
    used = np.concatenate([np.asarray(part, dtype=np.int64) for part in parts])
    order, first = np.unique(used, return_index=True)
    by_first_use = order[np.argsort(first)]
    renumber = np.empty(len(defined), dtype=np.int64)
    renumber[by_first_use] = np.arange(len(by_first_use))
    vertices = np.asarray(defined, dtype=np.float64)[by_first_use]
    return Mesh(vertices, tuple(renumber[np.asarray(part)].reshape(-1, 3).astype(np.int32) for part in parts))


def _obj_vertex(path: str, number: int, fields: list[bytes]) -> tuple[float, float, float]:
    if len(fields) < 3 or not all(_FLOAT.fullmatch(field) for field in fields[:3]):
        shown = b" ".join(fields).decode("latin-1")
        raise MeshError(f"mesh {path!r} line {number}: a vertex needs 3 decimal numbers, got {shown!r:.80}")
    xyz = (float(fields[0]), float(fields[1]), float(fields[2]))
    if not all(abs(value) <= FLOAT32_MAX for value in xyz):
        raise MeshError(f"mesh {path!r} line {number}: vertex {xyz} is beyond float32")
    return xyz


def _obj_face_vertex(path: str, number: int, field: bytes, defined: int) -> int:
    """The 0-based vertex of one face entry; it must be one of the `defined` vertices above it."""
    found = _FACE_VERTEX.fullmatch(field)
    if found is None:
        shown = field.decode("latin-1")
        raise MeshError(f"mesh {path!r} line {number}: {shown!r:.40} is not a face vertex (i, i/j, i/j/k or i//k)")
    index = int(found.group(1))
    resolved = index - 1 if index > 0 else defined + index
    if index == 0 or not 0 <= resolved < defined:
        raise MeshError(f"mesh {path!r} line {number}: face vertex {index} is not one of the {defined} vertices "
                        "defined above it")
    return resolved


def _stl_mesh(path: str, data: bytes) -> Mesh:
    count = int.from_bytes(data[80:84], "little") if len(data) >= _STL_HEADER_BYTES else 0
    if count < 1 or len(data) != _STL_HEADER_BYTES + _STL_TRIANGLE.itemsize * count:
        raise MeshError(f"mesh {path!r}: not a binary STL with at least one triangle (84 + 50 x n bytes, n in "
                        "bytes 80-83; ASCII STL is not read)")
    if count > MESH_TRIANGLE_LIMIT:
        raise MeshError(f"mesh {path!r} has more than {MESH_TRIANGLE_LIMIT} triangles")
    triangles = np.frombuffer(data, dtype=_STL_TRIANGLE, offset=_STL_HEADER_BYTES, count=count)
    vertices = triangles["vertices"].reshape(-1, 3)
    if not np.all(np.isfinite(vertices)):
        raise MeshError(f"mesh {path!r}: a vertex is not a finite number")
    # every corner of every triangle, in order: the points PyBullet's STL reader gives its hull
    return Mesh(vertices.astype(np.float64), (np.arange(3 * count, dtype=np.int32).reshape(-1, 3),))
