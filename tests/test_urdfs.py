"""URDF objects (bh8_gym/urdfs.py; issue 32, item 1; issue 39).

Issue 32: the URDF check read the file with Python's XML parser while PyBullet read it with its
own (TinyXML2) and found meshes by other rules (`file://`, `model://`, the working directory
first, every directory above the URDF), so it loaded a mesh that was never checked and died of
SIGSEGV on its face `f 1 2 999999` (`bh8 serve --object`, `bh8 render --object`, `bh8 eval
--object-files`: exit 139). Issue 39: PyBullet now reads only the URDF and meshes we write from
the checked model, so a disagreement between readers can no longer reach it. Each crafted URDF
below is loaded the two ways the package loads one (`parse_object_file`, the environments' and
`bh8 eval`'s, and `ObjectLoader`, which `--object` uses) in a forked child, so a crash fails the
test instead of killing it. Hostile ones must be refused (a ValueError); the benign ones must
still load.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pybullet
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bh8_gym.objects import ObjectLoader, ObjectSpec, parse_object_file

BAD_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 999999\n"  # PyBullet's OBJ reader reads past its vertices
GOOD_OBJ = "v 0 0 0\nv 0.05 0 0\nv 0 0.05 0\nv 0 0 0.05\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"
BAD_DAE = """<?xml version="1.0"?>
<COLLADA xmlns="http://www.collada.org/2005/11/COLLADASchema" version="1.4.1"><library_geometries>
<geometry id="g"><mesh><source id="p"><float_array id="pa" count="9">0 0 0 1 0 0 0 1 0</float_array>
<technique_common><accessor source="#pa" count="3" stride="3"><param name="X" type="float"/>
<param name="Y" type="float"/><param name="Z" type="float"/></accessor></technique_common></source>
<vertices id="v"><input semantic="POSITION" source="#p"/></vertices><triangles count="1">
<input semantic="VERTEX" source="#v" offset="0"/><p>0 1 999999</p></triangles></mesh></geometry>
</library_geometries><library_visual_scenes><visual_scene id="s"><node><instance_geometry url="#g"/>
</node></visual_scene></library_visual_scenes><scene><instance_visual_scene url="#s"/></scene></COLLADA>
"""


def robot(filename: str, extra: str = "", head: str = "", tail: str = "") -> str:
    return (f'{head}<robot name="part"{extra}><link name="base"><inertial><mass value="0.1"/>'
            '<inertia ixx="1e-4" ixy="0" ixz="0" iyy="1e-4" iyz="0" izz="1e-4"/></inertial>'
            f'<collision><geometry><mesh filename="{filename}"/></geometry></collision></link></robot>{tail}')


@pytest.fixture
def layout(tmp_path):
    """objects/urdf/ holds the URDFs and meshes good and bad; objects/ a bad mesh one level up;
    cwd/ (the child's working directory) a bad mesh under the name of a good one beside the URDFs."""
    urdf_dir, cwd = tmp_path / "objects" / "urdf", tmp_path / "cwd"
    for folder in (urdf_dir / "sub", urdf_dir / "meshes", cwd / "meshes"):
        folder.mkdir(parents=True)
    files = {urdf_dir / "good.obj": GOOD_OBJ, urdf_dir / "badface.obj": BAD_OBJ,
             urdf_dir / "sub" / "badface.obj": BAD_OBJ, urdf_dir / "BADFACE.OBJ": BAD_OBJ, urdf_dir / "meshes" / "part.obj": GOOD_OBJ,
             cwd / "meshes" / "part.obj": BAD_OBJ, tmp_path / "objects" / "up.obj": BAD_OBJ,
             urdf_dir / "bad\tface.obj": BAD_OBJ, urdf_dir / "bad\nface.obj": BAD_OBJ,
             urdf_dir / "good&e;.obj": BAD_OBJ, urdf_dir / "bad.dae": BAD_DAE}
    for path, text in files.items():
        path.write_text(text)
    return urdf_dir, cwd


def _load_in_a_child(urdf: Path, cwd: Path) -> int:
    """Exit status 0 if both ways of loading `urdf` succeed in a forked child working in `cwd`, 2 if
    either refuses it with a ValueError, 4 for another exception; or the signal that killed it."""
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        code = 0
        try:
            os.chdir(cwd)
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, 1)
            os.dup2(null, 2)
            client = pybullet.connect(pybullet.DIRECT)
            ObjectLoader(client, visuals=False).create(ObjectSpec("urdf", path=str(urdf), mass=None, friction=None),
                                                      (0.0, 0.0, 0.5), (0.0, 0.0, 0.0, 1.0))
            parse_object_file(str(urdf))
        except ValueError:
            code = 2
        except BaseException:
            code = 4
        os._exit(code)
    _, status = os.waitpid(pid, 0)
    return os.WEXITSTATUS(status) if os.WIFEXITED(status) else -os.WTERMSIG(status)


# name: the URDF's text given the absolute URDF directory (each of these crashed PyBullet, or
# would have, unchecked)
HOSTILE = {
    "an undefined entity": lambda d: robot("badface.obj", extra=' extra="a&bogus;"'),
    "a bare ampersand": lambda d: robot("badface.obj", extra=' extra="a & b"'),
    "< in an attribute": lambda d: robot("badface.obj", extra=' extra="a<b"'),
    "an element after the root": lambda d: robot("badface.obj", tail="<x/>"),
    "a NUL byte": lambda d: robot("badface.obj").replace("<link", "\0<link"),
    "-- in a comment": lambda d: robot("badface.obj", head="<!-- a -- b -->"),
    "a bogus encoding": lambda d: robot("badface.obj", head='<?xml version="1.0" encoding="bogus-enc"?>'),
    "a latin-1 declaration": lambda d: robot("badface.obj", head='<?xml version="1.0" encoding="ISO-8859-1"?>'),
    "a default namespace": lambda d: robot("badface.obj", extra=' xmlns="http://example.com/urdf"'),
    "an entity that hides the name": lambda d: robot("good&e;.obj", head='<!DOCTYPE robot [<!ENTITY e "">]>'),
    "a doctype without entities": lambda d: robot("badface.obj", head="<!DOCTYPE robot>"),
    "a tab in the name": lambda d: robot("bad\tface.obj"),
    "a line break in the name": lambda d: robot("bad\nface.obj"),
    "file://": lambda d: robot("file://badface.obj"),
    "file:/// and an absolute path": lambda d: robot(f"file://{d}/badface.obj"),
    "model://": lambda d: robot("model://badface.obj"),
    "file://package://": lambda d: robot("file://package://badface.obj"),
    "package:// and the URDF's folder": lambda d: robot("package://urdf/badface.obj"),
    "a mesh in the folder above": lambda d: robot("up.obj"),
    "an absolute path": lambda d: robot(f"{d}/sub/badface.obj"),
    "upper-case extension": lambda d: robot("BADFACE.OBJ"),
    "a visual mesh only": lambda d: robot("good.obj").replace(
        "</link>", '<visual><geometry><mesh filename="badface.obj"/></geometry></visual></link>'),
    "a second mesh in one geometry": lambda d: robot("good.obj").replace(
        "<geometry>", '<geometry><mesh filename="badface.obj"/>'),
    "a byte-order mark": lambda d: "\ufeff" + robot("badface.obj"),
    "a COLLADA mesh": lambda d: robot("bad.dae"),
    "nesting 100k deep": lambda d: robot("good.obj").replace("<link", "<a>" * 100_000 + "</a>" * 100_000 + "<link"),
    "a NaN origin": lambda d: robot("good.obj").replace("<geometry>", '<origin xyz="nan 0 0"/><geometry>'),
    "a mass of 1e300": lambda d: robot("good.obj").replace('<mass value="0.1"/>', '<mass value="1e300"/>'),
    "a joint cycle": lambda d: robot("good.obj").replace("</robot>", '<link name="b"/><joint name="j" type="fixed">'
                                                         '<parent link="b"/><child link="b"/></joint></robot>'),
    "two roots": lambda d: robot("good.obj").replace("</robot>", '<link name="b"/></robot>'),
    "a joint to no link": lambda d: robot("good.obj").replace("</robot>", '<joint name="j" type="fixed">'
                                                              '<parent link="base"/><child link="x"/></joint></robot>'),
    "100k elements": lambda d: robot("good.obj").replace("<link", "<a/>" * 100_000 + "<link"),
}
BENIGN = {
    # PyBullet took cwd/meshes/part.obj (bad) first; the working directory is not searched now
    "a mesh name also found in the working directory": lambda d: robot("meshes/part.obj"),
    "a plain mesh name": lambda d: robot("good.obj"),
    "package://": lambda d: robot("package://good.obj"),
    "file://": lambda d: robot("file://good.obj"),
    "a sub-folder": lambda d: robot("meshes/part.obj").replace("meshes/", "./meshes/../meshes/"),
    "an XML declaration and a comment": lambda d: robot("good.obj",
                                                        head='<?xml version="1.0" encoding="UTF-8"?><!-- x -->'),
    "a character reference": lambda d: robot("good&#46;obj"),
}


@pytest.mark.skipif(not hasattr(os, "fork"), reason="forks a child for PyBullet")
@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_a_hostile_urdf_is_refused_not_a_crash(layout, case):
    urdf_dir, cwd = layout
    urdf = urdf_dir / "part.urdf"
    urdf.write_bytes(HOSTILE[case](urdf_dir).encode())
    assert _load_in_a_child(urdf, cwd) == 2  # refused; -11 was SIGSEGV


@pytest.mark.skipif(not hasattr(os, "fork"), reason="forks a child for PyBullet")
@pytest.mark.parametrize("case", sorted(BENIGN))
def test_an_ordinary_urdf_still_loads(layout, case):
    urdf_dir, _ = layout
    urdf = urdf_dir / "part.urdf"
    urdf.write_bytes(BENIGN[case](urdf_dir).encode())
    assert _load_in_a_child(urdf, urdf_dir) == 0


names = st.sampled_from(["good.obj", "badface.obj", "up.obj", "sub/badface.obj", "BADFACE.OBJ", "meshes/part.obj",
                         "bad\tface.obj", "good&e;.obj", "bad.dae", "missing.obj", "x", ".obj", "good.obj "])
prefixes = st.sampled_from(["", "", "file://", "package://", "model://", "file://package://", "package://file://",
                            "./", "../urdf/", "package://urdf/", "file://../"])
extras = st.sampled_from(["", "", ' extra="a&bogus;"', ' a="&amp;"', ' xmlns="http://x"', ' x="a\tb"', ' a="<"',
                          ' a="&#0;"', ' a="&#x41;"'])
heads = st.sampled_from(["", "", '<?xml version="1.0"?>', '<?xml version="1.0" encoding="bogus"?>', "\ufeff",
                         '<!DOCTYPE robot [<!ENTITY e "">]>', "<!-- -- -->", "\0"])
tails = st.sampled_from(["", "", "junk", "<x/>", "<!-- c -->", "\0", "<?pi x?>"])


@pytest.mark.skipif(not hasattr(os, "fork"), reason="forks a child for PyBullet")
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(prefix=prefixes, name=names, extra=extras, head=heads, tail=tails, visual=st.booleans())
def test_any_urdf_is_refused_or_loads_without_crashing(layout, prefix, name, extra, head, tail, visual):
    """URDFs built from the pieces above (file names as PyBullet resolves them, text Python's and
    PyBullet's XML readers disagree on): each is refused or loads; none crashes the process."""
    urdf_dir, cwd = layout
    text = robot(prefix + name, extra=extra, head=head, tail=tail)
    if visual:
        text = text.replace("collision>", "visual>")
    urdf = urdf_dir / "fuzz.urdf"
    urdf.write_bytes(text.encode())
    assert _load_in_a_child(urdf, cwd) in (0, 2), text


@pytest.mark.parametrize("command", ["serve", "render", "eval"])
def test_the_commands_refuse_a_hostile_urdf_with_one_line(layout, tmp_path, command):
    """`bh8 serve --object`, `bh8 render --object` and `bh8 eval --object-files` died with exit 139
    on a URDF naming `file://badface.obj`; now exit 2 and a one-line message naming the mesh."""
    urdf_dir, _ = layout
    urdf = urdf_dir / "part.urdf"
    urdf.write_text(robot("file://badface.obj"))
    argv = {"serve": ["serve", "--object", str(urdf), "--state", str(tmp_path / "store")],
            "render": ["render", "--object", str(urdf), "-o", str(tmp_path / "x.png")],
            "eval": ["eval", "--baseline", "loop", "--object-files", str(urdf), "--episodes", "1", "--no-progress",
                     "--gif-episodes", "0"]}[command]
    result = subprocess.run([sys.executable, "-m", "bh8_gym.cli", *argv], capture_output=True, text=True, timeout=300)
    assert result.returncode == 2, (result.returncode, result.stderr[-800:])
    errors = [line for line in result.stderr.splitlines() if line.startswith(f"bh8 {command}: ")]
    assert len(errors) == 1 and "face vertex 999999 is not one of the 3 vertices" in errors[0]
    assert "Traceback" not in result.stderr
