"""PyBullet parses only files this package wrote (issue 39, finding 2 and its class).

PyBullet's OBJ, MTL, STL, texture and URDF readers trust their input. Through files that passed our
checks: an MTL naming a texture of 1500 characters aborted the process (exit 134, the stack
overwritten), a truncated HDR texture hung stb_image for ever (CVE-2021-42715), a 420 KB PNG took
0.9 GB, and a bad-face OBJ named by a `<deformable>` element segfaulted (exit 139). Now a user's
mesh is read by `bh8_gym.meshes`, a URDF by `bh8_gym.urdfs`, and PyBullet is given only files
`bh8_gym.pybullet_files` wrote from them: these tests watch every call that makes PyBullet open a
file, re-run the reproducers in a child process, and check that the collision shape PyBullet builds
from our file is the one it built from the original (pybullet_data's own models).
"""
from __future__ import annotations

import ast
import hashlib
import os
import struct
import subprocess
import sys
import xml.etree.ElementTree as ElementTree
import zlib
from pathlib import Path

import numpy as np
import pybullet
import pybullet_data
import pytest

from bh8_gym import pybullet_files
from bh8_gym.envs.objects import random_urdf_spec
from bh8_gym.meshes import read_mesh
from bh8_gym.objects import ObjectLoader, ObjectSpec
from bh8_gym.plant import HandPlant, PlantParameters

REPOSITORY = Path(__file__).resolve().parent.parent
# The pybullet calls that make it open a file, and the keyword arguments that name one.
FILE_CALLS = ("loadURDF", "loadSDF", "loadMJCF", "loadSoftBody", "loadTexture", "loadBullet", "loadPlugin",
              "createCollisionShape", "createVisualShape", "createCollisionShapeArray", "createVisualShapeArray")
FILE_KEYWORDS = ("fileName", "fileNames", "simFileName", "bulletFileName", "textureFilename")
TETRA = "v 0 0 0\nv 0.05 0 0\nv 0 0.05 0\nv 0 0 0.05\nvt 0 0\nvn 0 0 1\n" \
        "f 1/1/1 2/1/1 3/1/1\nf 1/1/1 2/1/1 4/1/1\nf 1/1/1 3/1/1 4/1/1\nf 2/1/1 3/1/1 4/1/1\n"
OUR_URDF_TAGS = {"robot", "link", "joint", "parent", "child", "origin", "axis", "limit", "dynamics", "inertial",
                 "mass", "inertia", "visual", "collision", "geometry", "box", "cylinder", "sphere", "capsule", "mesh",
                 "material", "color", "contact", *("lateral_friction", "rolling_friction", "spinning_friction",
                                                   "restitution", "stiffness", "damping", "contact_cfm",
                                                   "contact_erp", "inertia_scaling")}


def _png(width: int, height: int) -> bytes:
    """An RGB PNG of zeros: a few hundred KB that decode to width x height x 3 bytes."""
    compressor = zlib.compressobj(9)
    row = b"\0" * (1 + 3 * width)
    data = b"".join(compressor.compress(row) for _ in range(height)) + compressor.flush()

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", data) + chunk(b"IEND", b"")


@pytest.fixture(scope="module")
def attack_files(tmp_path_factory) -> dict[str, Path]:
    """The issue's reproducers: OBJ files whose MTL names a hostile texture, and URDFs that name
    them, a `<deformable>` with a bad-face OBJ, and a texture material."""
    folder = tmp_path_factory.mktemp("attack")
    (folder / "trunc.hdr").write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 4 +X 16\n\x02\x02\x00\x10")
    (folder / "big.png").write_bytes(_png(12000, 12000))
    (folder / "badface.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 999999\n")
    textures = {"long_texture": "A" * 1500 + ".png", "truncated_hdr": "trunc.hdr", "huge_png": "big.png"}
    files = {}
    for name, texture in textures.items():
        (folder / f"{name}.mtl").write_text(f"newmtl m\nmap_Kd {texture}\n")
        (folder / f"{name}.obj").write_text(f"mtllib {name}.mtl\nusemtl m\n{TETRA}")
        files[f"{name}.obj"] = folder / f"{name}.obj"
        files[f"{name}.urdf"] = folder / f"{name}.urdf"
        files[f"{name}.urdf"].write_text(_robot(f'<visual><geometry><mesh filename="{name}.obj"/></geometry></visual>'
                                                f'<collision><geometry><mesh filename="{name}.obj"/></geometry>'
                                                '</collision>'))
    (folder / "good.obj").write_text(TETRA)
    files["deformable.urdf"] = folder / "deformable.urdf"
    files["deformable.urdf"].write_text(_robot(
        '<collision><geometry><mesh filename="good.obj"/></geometry></collision>',
        after='<deformable name="d"><inertial><mass value="1"/><inertia ixx="0" ixy="0" ixz="0" iyy="0" iyz="0" '
              'izz="0"/></inertial><collision_margin value="0.006"/><neohookean mu="60" lambda="200" '
              'damping="0.01"/><visual filename="badface.obj"/></deformable>'))
    files["texture_material.urdf"] = folder / "texture_material.urdf"
    files["texture_material.urdf"].write_text(_robot(
        '<visual><geometry><mesh filename="good.obj"/></geometry><material name="t"><texture filename="trunc.hdr"/>'
        '</material></visual><collision><geometry><box size="0.05 0.05 0.05"/></geometry></collision>'))
    return files


def _robot(shapes: str, after: str = "") -> str:
    return ('<robot name="attack"><link name="base"><inertial><mass value="0.1"/><inertia ixx="1e-4" ixy="0" '
            f'ixz="0" iyy="1e-4" iyz="0" izz="1e-4"/></inertial>{shapes}</link>{after}</robot>')


def _spec(path: Path) -> ObjectSpec:
    if path.suffix == ".urdf":
        return ObjectSpec("urdf", path=str(path), mass=None, friction=None)
    return ObjectSpec("mesh", path=str(path), scale=1.0)


@pytest.fixture
def opened_by_pybullet(monkeypatch) -> list[tuple[str, str, bytes]]:
    """(call, path, the file's bytes at the call) of every file handed to a PyBullet call."""
    seen = []
    for name in FILE_CALLS:
        real = getattr(pybullet, name)

        def spy(*args, _real=real, _name=name, **kwargs):
            named = [value for key, value in kwargs.items() if key in FILE_KEYWORDS]
            if _name.startswith("load") and args and isinstance(args[0], str):
                named.append(args[0])
            for value in named:
                for path in [value] if isinstance(value, str) else value:
                    seen.append((_name, path, Path(path).read_bytes()))
            return _real(*args, **kwargs)

        monkeypatch.setattr(pybullet, name, spy)
    return seen


def _assert_written_by_us(seen: list[tuple[str, str, bytes]]) -> None:
    folder = pybullet_files.private_folder()
    for call, path, data in seen:
        assert os.path.dirname(path) == folder, (call, path)
        if path.endswith(".obj"):
            lines = data.decode("ascii").splitlines()
            assert lines[0] == "# written by bh8_gym.meshes from a checked mesh", path
            assert all(line.split(" ", 1)[0] in ("v", "o", "f") for line in lines[1:]), path
        else:
            assert path.endswith(".urdf"), (call, path)
            root = ElementTree.fromstring(data)
            assert {element.tag for element in root.iter()} <= OUR_URDF_TAGS, path
            for mesh in root.iter("mesh"):
                assert os.path.dirname(mesh.get("filename")) == folder, mesh.get("filename")


def test_pybullet_is_given_only_files_we_wrote(attack_files, opened_by_pybullet):
    """The hand, a user's meshes and URDFs (the attack files above) and pybullet_data's models:
    every file any PyBullet call is given lies in our private folder and holds only
    what we write (an OBJ of vertex, object and face lines; a URDF of our elements)."""
    plant = HandPlant(PlantParameters())
    try:
        loader = ObjectLoader(plant.client)
        for name in ("long_texture.obj", "long_texture.urdf", "deformable.urdf", "texture_material.urdf"):
            loader.create(_spec(attack_files[name]), (0.3, 0.0, 0.1), (0.0, 0.0, 0.0, 1.0))
        loader.create(random_urdf_spec("000", np.random.default_rng(0)), (0.5, 0.0, 0.1), (0.0, 0.0, 0.0, 1.0))
    finally:
        plant.close()
    calls = {call for call, _, _ in opened_by_pybullet}
    assert {"loadURDF", "createCollisionShape", "createVisualShape"} <= calls
    _assert_written_by_us(opened_by_pybullet)
    for _, path, data in opened_by_pybullet:  # named by their content
        assert os.path.basename(path).split(".")[0] == hashlib.sha256(data).hexdigest()
    assert not os.stat(pybullet_files.private_folder()).st_mode & 0o077  # no one else may write there


def test_only_the_loaders_hand_pybullet_a_file():
    """Every call in the package that can make PyBullet open a file is in the two places the test
    above exercises (objects.ObjectLoader and the plant's hand): a new one must go through
    bh8_gym.pybullet_files and be added there."""
    callers = set()
    for path in [*(REPOSITORY / "bh8_gym").rglob("*.py"), *(REPOSITORY / "agents").rglob("*.py")]:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not isinstance(node, ast.Call):
                continue
            name = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
            keywords = {keyword.arg for keyword in node.keywords}
            if name.startswith("load") and name in FILE_CALLS or keywords & set(FILE_KEYWORDS) or \
                    (name in FILE_CALLS and "**" in ast.unparse(node)):
                callers.add(str(path.relative_to(REPOSITORY)))
    assert callers == {"bh8_gym/objects.py", "bh8_gym/plant/hand.py"}


CHILD = """
import json, sys
import pybullet
from bh8_gym.objects import ObjectLoader, ObjectSpec
results = {}
for path in sys.argv[1:]:
    client = pybullet.connect(pybullet.DIRECT)
    spec = (ObjectSpec("urdf", path=path, mass=None, friction=None) if path.endswith(".urdf")
            else ObjectSpec("mesh", path=path, scale=1.0))
    try:
        ObjectLoader(client).create(spec, (0, 0, 0.1), (0, 0, 0, 1))
        pybullet.getCameraImage(32, 32, physicsClientId=client)  # the renderer decodes visual textures
        results[path] = "loaded"
    except ValueError as error:
        results[path] = "refused: " + str(error)
    pybullet.disconnect(client)
# this process's own peak (VmHWM: ru_maxrss would count the pytest process it was forked from)
results["maxrss"] = int(next(line.split()[1] for line in open("/proc/self/status") if line.startswith("VmHWM")))
print(json.dumps(results))
"""


def test_the_issues_hostile_meshes_and_urdfs_neither_crash_hang_nor_run_away(attack_files):
    """Each reproducer of finding 2 loaded and rendered in one fresh process: before, it aborted
    (exit 134), segfaulted (139), hung (killed at the timeout) or took 0.9 GB. Now each loads
    (PyBullet never opens the MTL, texture or deformable mesh) or is refused with a ValueError."""
    paths = [str(attack_files[name]) for name in sorted(attack_files)]
    process = subprocess.Popen([sys.executable, "-c", CHILD, *paths], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    try:
        stdout, stderr = process.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        process.kill()
        process.communicate()
        pytest.fail("a hostile file hung the loader")
    assert process.returncode == 0, (process.returncode, stderr[-2000:])
    results = __import__("json").loads(stdout.splitlines()[-1])
    assert results.pop("maxrss") < 600_000  # KB, the child's own peak; the PNG alone took 905 MB
    assert set(results) == set(paths)
    assert results[str(attack_files["deformable.urdf"])] == "loaded"  # the deformable element is left out
    assert results[str(attack_files["long_texture.obj"])] == "loaded"


def test_our_obj_gives_pybullet_the_collision_shape_of_the_original(tmp_path):
    """The clean OBJ keeps what PyBullet builds a collision shape from: one convex hull per o/g
    group, of the face vertices in order (polygons as its reader's triangle fan, negative indices,
    texture and normal numbers dropped). Compared with the original file loaded directly (our own
    crafted file, and pybullet_data's models: trusted files): the same bounding box, inertia and a
    dropped body's every position, bit for bit."""
    crafted = tmp_path / "crafted.obj"
    crafted.write_text("# polygons, groups, negative indices, vt/vn, a material\nmtllib none.mtl\n"
                       "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0.5 0.5 0.8\nvt 0 0\nvn 0 0 1\n"
                       "o first\nusemtl m\nf 1/1/1 2/1/1 3/1/1 4/1/1\nf -1 1 2\nf 5 2 3\nf 5 3 4\nf 5//1 4//1 1//1\n"
                       "g second\nv 2 0 0\nv 3 0 0\nv 2 1 0\nv 2.5 0.3 1\nf -4 -3 -2\nf -4 -3 -1\nf -3 -2 -1 -4\n"
                       "o empty\n")
    root = Path(pybullet_data.getDataPath()) / "random_urdfs"
    originals = [crafted, *(root / name / f"{name}.obj" for name in ("000", "105", "333", "999"))]
    client = pybullet.connect(pybullet.DIRECT)
    try:
        pybullet.setGravity(0, 0, -9.81, physicsClientId=client)
        pybullet.createMultiBody(0, pybullet.createCollisionShape(pybullet.GEOM_PLANE, physicsClientId=client),
                                 physicsClientId=client)
        for original in originals:
            with pybullet_files.written([(read_mesh(original).obj_bytes, ".obj")]) as (ours,):
                runs = [_drop(client, str(path), 0.02) for path in (original, ours)]
            assert runs[0] == runs[1], original
    finally:
        pybullet.disconnect(client)


def _drop(client: int, path: str, scale: float) -> list:
    shape = pybullet.createCollisionShape(pybullet.GEOM_MESH, fileName=path, meshScale=[scale] * 3,
                                          physicsClientId=client)
    body = pybullet.createMultiBody(0.1, shape, basePosition=(0, 0, 0.2), baseOrientation=(0.3, 0.2, 0.1, 0.9),
                                    physicsClientId=client)
    states = [pybullet.getAABB(body, physicsClientId=client), pybullet.getDynamicsInfo(body, -1, physicsClientId=client)]
    for _ in range(120):
        pybullet.stepSimulation(physicsClientId=client)
        states.append(pybullet.getBasePositionAndOrientation(body, physicsClientId=client))
    pybullet.removeBody(body, physicsClientId=client)
    return states
