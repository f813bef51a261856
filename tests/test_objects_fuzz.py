"""Fuzzing the ways an object enters a simulation (issue 19): `--object` specs (bh8 serve, bh8
render), `ObjectSpec`s (the environments) and mesh files (object_files, URDF meshes).

The property: bad input is a ValueError naming it, never a crash (PyBullet's OBJ reader segfaulted
on a face index past its vertices), a NaN world (a sphere of 1e308 m) or a hang; whatever is
accepted loads and simulates with finite state. Bounds: bh8_gym.plant's OBJECT_* constants.
"""
from __future__ import annotations

import math
import os
import struct
import sys

import numpy as np
import pybullet
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bh8_gym.meshes import Mesh, MeshError, read_mesh
from bh8_gym.objects import ObjectError, ObjectLoader, ObjectSpec, add_object, parse_object_spec, remove_object
from bh8_gym.plant import HandPlant, PlantParameters

FUZZ = settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

# Numbers as a clumsy or hostile user types them: sensible ones, extremes, non-numbers.
numbers = st.one_of(
    st.floats(min_value=0.005, max_value=0.2).map(lambda v: f"{v:.4g}"),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["0", "-0.05", "1e308", "1e-300", "nan", "inf", "-inf", "", "x", "1e999", "0x10", "1_0"]),
)


@st.composite
def object_specs(draw) -> str:
    kind = draw(st.sampled_from(["box", "sphere", "cylinder", "capsule", "cone", "BOX", ""]))
    sizes = draw(st.sampled_from(["", "d", "r"])) + "x".join(draw(st.lists(numbers, min_size=0, max_size=4)))
    spec = f"{kind}:{sizes}" if draw(st.booleans()) or sizes else kind
    if draw(st.booleans()):
        spec += "@" + ",".join(draw(st.lists(numbers, min_size=2, max_size=4)))
    for _ in range(draw(st.integers(0, 3))):
        spec += f";{draw(st.sampled_from(['mass', 'friction', 'scale', 'colour', '']))}={draw(numbers)}"
    return draw(st.one_of(st.just(spec), st.text(max_size=30)))


@pytest.fixture(scope="module")
def palm_up_plant():
    """The scene `bh8 serve --object` builds: palm up, no table."""
    plant = HandPlant(params=PlantParameters(table=False, wrist_position=(0.0, 0.0, 0.0),
                                             wrist_orientation=(0.0, 0.0, 0.0, 1.0)), seed=0)
    yield plant
    plant.close()


def _finite_after_steps(plant: HandPlant, body: int, steps: int = 25) -> None:
    for _ in range(steps):
        plant.step()
    low, high = pybullet.getAABB(body, -1, physicsClientId=plant.client)
    assert all(math.isfinite(v) for v in (*low, *high)), (low, high)
    assert np.all(np.isfinite(plant.motor_positions()))


@FUZZ
@given(spec=object_specs())
def test_any_object_spec_is_refused_or_simulates_finitely(palm_up_plant, spec):
    """`--object SPEC` (parse_object_spec, then add_object): an ObjectError (a ValueError) naming the
    problem, or an object whose world stays finite."""
    try:
        placement = parse_object_spec(spec)
        body = add_object(palm_up_plant, placement.spec, placement.position or (0.0, 0.0, 0.1))
    except ObjectError:
        return
    try:
        _finite_after_steps(palm_up_plant, body)
    finally:
        remove_object(palm_up_plant, body)


@pytest.fixture(scope="module")
def loader_client():
    client = pybullet.connect(pybullet.DIRECT)
    yield client
    pybullet.disconnect(client)


floats = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(min_value=0.0005, max_value=3.0))


@FUZZ
@given(kind=st.sampled_from(["box", "cylinder", "sphere", "capsule"]), size=st.lists(floats, min_size=0, max_size=4),
       mass=st.one_of(st.none(), floats), friction=st.one_of(st.none(), floats))
def test_any_object_spec_of_the_envs_is_refused_or_loads_finitely(loader_client, kind, size, mass, friction):
    """The environments' ObjectSpec: a ValueError, or a body with a finite, bounded size."""
    try:
        spec = ObjectSpec(kind, tuple(size), mass=mass, friction=friction)
    except ValueError:
        return
    loader = ObjectLoader(loader_client, visuals=False)
    body = loader.create(spec, (0.0, 0.0, 1.0), (0.0, 0.0, 0.0, 1.0))
    try:
        low, high = pybullet.getAABB(body, -1, physicsClientId=loader_client)
        assert all(math.isfinite(v) for v in (*low, *high))
        assert max(h - l for l, h in zip(low, high)) <= 2.0 + 0.01  # OBJECT_EXTENT_RANGE_M, plus PyBullet's margin
    finally:
        loader.remove(body)


# OBJ lines as an exporter, a clumsy user and an attacker write them.
index_tokens = st.one_of(
    st.integers(-12, 12).map(str),
    st.sampled_from(["999999", "99999999999999", "-2147483649", "a", "", "1/2/3", "2//1", "3/1", "1/", "/1", "1/2/3/4",
                     "1/0", "3//0", "3/0/1", "3/1/0", "1/2/", "2//", "1/-0", "1/00"]),
    st.tuples(st.integers(-6, 6), st.integers(-6, 6)).map(lambda t: f"{t[0]}/{t[1]}"),
)
coordinate_tokens = st.one_of(
    st.floats(min_value=-1.0, max_value=1.0).map(lambda v: f"{v:.5f}"),
    st.sampled_from(["nan", "inf", "-inf", "1e39", "1e308", "", "x", "0x1p3", "1_0", "+.5", "-5."]),
)
obj_lines = st.one_of(
    st.lists(coordinate_tokens, min_size=0, max_size=4).map(lambda c: "v " + " ".join(c)),
    st.lists(index_tokens, min_size=0, max_size=5).map(lambda i: "f " + " ".join(i)),
    st.sampled_from(["# comment", "", "vn 0 0 1", "vt 0.5 0.5", "g part", "o thing", "usemtl red", "s off",
                     "v\t0\t0\t0", "f\t1\t2\t3", "  v 1 1 1", "f 1 2 3\r", "v 0 0 0\0 junk", "F 1 2 3", "x" * 1100,
                     "mtllib evil.mtl", "usemtl " + "m" * 5000]),
    st.text(max_size=20).filter(lambda t: "\n" not in t),
)


good_vertices = st.tuples(*[st.floats(min_value=-1.0, max_value=1.0)] * 3).map(lambda v: "v %.4f %.4f %.4f" % v)


@st.composite
def obj_texts(draw) -> str:
    """Mostly well-formed OBJ (vertices, then faces that mostly name them) with hostile lines
    mixed in anywhere, so that both the reader's refusals and PyBullet's loading get exercised."""
    vertices = draw(st.lists(good_vertices, min_size=draw(st.sampled_from([0, 3, 3, 3])), max_size=6))
    n = len(vertices)
    valid = st.one_of(st.integers(1, max(n, 1)).map(str), st.integers(-max(n, 1), -1).map(str),
                      st.integers(1, max(n, 1)).map(lambda i: f"{i}/1/{i}"))
    entry = st.one_of(valid, valid, valid, valid, st.integers(-n - 1, n + 1).map(str), index_tokens)
    faces = st.lists(entry, min_size=3, max_size=5).map(lambda i: "f " + " ".join(i))
    lines = vertices + draw(st.lists(st.one_of(faces, faces, faces, obj_lines), min_size=1, max_size=6))
    if draw(st.booleans()):
        lines.insert(draw(st.integers(0, len(lines))), draw(obj_lines))
    return "\n".join(lines)


def _loads_in_a_child(path: str) -> int:
    """PyBullet builds a collision and a visual shape from `path` in a forked child; its wait
    status (a crash must not take the test runner with it)."""
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        code = 0
        try:
            client = pybullet.connect(pybullet.DIRECT)
            try:
                pybullet.createCollisionShape(pybullet.GEOM_MESH, fileName=path, meshScale=[0.05] * 3,
                                              physicsClientId=client)
                pybullet.createVisualShape(pybullet.GEOM_MESH, fileName=path, meshScale=[0.05] * 3,
                                           physicsClientId=client)
            except pybullet.error:
                code = 3
        except BaseException:
            code = 4
        os._exit(code)
    _, status = os.waitpid(pid, 0)
    return status


def _clean_obj_loads(mesh: Mesh, tmp_path) -> None:
    """The OBJ we write from `mesh` holds only our lines, and PyBullet loads it (in a child)."""
    text = mesh.obj_bytes.decode("ascii")
    assert all(line[:2] in ("v ", "f ", "o ") or line.startswith("# written by") for line in text.splitlines())
    path = tmp_path / "clean.obj"
    path.write_bytes(mesh.obj_bytes)
    status = _loads_in_a_child(str(path))
    assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0, status


TRIANGLE = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\n"


@pytest.mark.parametrize("face, refused", [
    ("f 1 1 1/0", False), ("f 3//0 1 2", False), ("f 3/0/1 1 2", False), ("f 1/-0 2 3", False), ("f 1/99 2 3", False),
    ("f 1/1 2/1 3/1", False), ("f 1/1/1 2/1/1 3/1/1", False), ("f 1//1 2//1 3//1", False), ("f 1//-7 2 3", False),
    ("f 1 2 3/", True), ("f 1 2 3/1/", True), ("f 1 2 /3", True), ("f 1/2/3/4 2 3", True),
])
def test_texture_and_normal_numbers_are_not_used_and_a_malformed_entry_is_refused(tmp_path, face, refused):
    """Issue 31: a texture or normal number of 0 passed the reader and then PyBullet's reader
    refused the file. PyBullet is now given our own OBJ, without texture or normal numbers, so
    any such number is accepted (it is not used); an entry that is none of i, i/j, i/j/k and i//k
    is refused naming the line."""
    path = tmp_path / "face.obj"
    path.write_text(TRIANGLE + face + "\n")
    if refused:
        with pytest.raises(MeshError, match=r"line 6: .*is not a face vertex"):
            read_mesh(path)
        return
    mesh = read_mesh(path)
    low, high = mesh.bounds
    assert list(high - low) == ([1.0, 1.0, 0.0] if face != "f 1 1 1/0" else [0.0, 0.0, 0.0])
    assert b"/" not in mesh.obj_bytes and b"vt" not in mesh.obj_bytes


@pytest.mark.skipif(not hasattr(os, "fork"), reason="forks a child for PyBullet")
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=obj_texts())
def test_any_obj_is_refused_or_rewritten_into_a_file_pybullet_loads(tmp_path_factory, text):
    """Any text is refused (a MeshError, a ValueError) or read into a mesh with finite bounds, whose
    clean OBJ holds only our lines and loads in PyBullet without crashing (checked in a child)."""
    path = tmp_path_factory.mktemp("obj") / "fuzz.obj"
    path.write_text(text, encoding="latin-1", errors="replace")
    try:
        mesh = read_mesh(path)
    except MeshError:
        return
    low, high = mesh.bounds
    assert np.all(np.isfinite(low)) and np.all(np.isfinite(high))
    _clean_obj_loads(mesh, path.parent)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(triangles=st.lists(st.lists(st.floats(allow_nan=True, allow_infinity=True, width=32), min_size=9, max_size=9),
                          max_size=4),
       count_offset=st.sampled_from([0, 0, 0, 1, -1, 2**31]), tail=st.binary(max_size=3))
def test_any_binary_stl_is_refused_or_rewritten_into_a_file_pybullet_loads(tmp_path_factory, triangles, count_offset,
                                                                            tail):
    """Binary STL: a wrong triangle count, stray bytes or non-finite vertices are refused; an
    accepted file becomes a clean OBJ that PyBullet loads (in a child process)."""
    body = b"".join(struct.pack("<12fH", 0, 0, 1, *t, 0) for t in triangles)
    count = (len(triangles) + count_offset) % 2**32
    path = tmp_path_factory.mktemp("stl") / "fuzz.stl"
    path.write_bytes(b"\0" * 80 + struct.pack("<I", count) + body + tail)
    try:
        mesh = read_mesh(path)
    except MeshError:
        return
    low, high = mesh.bounds
    assert np.all(np.isfinite(low)) and np.all(np.isfinite(high))
    if sys.platform.startswith("linux"):
        _clean_obj_loads(mesh, path.parent)
