"""The compiled per-step modules (setup.py, Cython) against their own sources: the same trajectories
bit for bit, BH8_GYM_PURE_PYTHON=1 imports every one from source, and a source edited after the
build runs from source rather than as the stale compiled code (bh8_gym/compilation.py)."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time

import pytest

from bh8_gym import compilation
from bh8_gym.compilation import PURE_PYTHON_VARIABLE, SourceFinder, compiled_files, sources_to_import

# Prints the compiled modules, then a digest of whole episodes: every observation, reward, feedback
# block and the plant's joint states and temperature, for grasp (randomised and not) and reach.
_TRAJECTORY_DIGEST = textwrap.dedent("""
    import hashlib
    import gymnasium as gym
    import numpy as np
    import bh8_gym
    from bh8_gym.compilation import compiled_modules

    digest = hashlib.sha256()
    for env_id, kwargs in (("BH8Grasp-v0", {}), ("BH8Grasp-v0", {"randomize": False}), ("BH8FingerReach-v0", {})):
        env = gym.make(env_id, **kwargs)
        rng = np.random.default_rng(7)
        for episode in range(2):
            obs, info = env.reset(seed=100 + episode)
            digest.update(obs.tobytes() + info["feedback_block"])
            done = False
            while not done:
                action = rng.integers(env.action_space.low, env.action_space.high, endpoint=True)
                obs, reward, terminated, truncated, info = env.step(action)
                done = terminated or truncated
                state = env.unwrapped.plant._state
                digest.update(obs.tobytes() + np.float64(reward).tobytes() + info["feedback_block"])
                digest.update(np.array(state.positions + state.velocities + state.torques + (state.temperature,)).tobytes())
        env.close()
    print("modules=" + ",".join(compiled_modules()))
    print("digest=" + digest.hexdigest())
""")


def _run_digest(pure_python: bool) -> tuple[list[str], str]:
    environment = {key: value for key, value in os.environ.items() if key != PURE_PYTHON_VARIABLE}
    if pure_python:
        environment[PURE_PYTHON_VARIABLE] = "1"
    result = subprocess.run([sys.executable, "-c", _TRAJECTORY_DIGEST], capture_output=True, text=True,
                            env=environment, timeout=240)
    assert result.returncode == 0, result.stderr
    lines = dict(line.split("=", 1) for line in result.stdout.splitlines() if "=" in line)
    return [name for name in lines["modules"].split(",") if name], lines["digest"]


def test_compiled_modules_give_the_sources_trajectories_bit_for_bit():
    compiled, compiled_digest = _run_digest(pure_python=False)
    if not compiled:
        pytest.skip("nothing compiled here (built without a C compiler): the package runs from source")
    assert {"bh8_gym.plant", "bh8_gym.firmware", "bh8_gym.motion_control", "bh8_gym.envs.base"} <= set(compiled)
    from_source, source_digest = _run_digest(pure_python=True)
    assert from_source == []
    assert compiled_digest == source_digest


def _fake_build(tmp_path, source_age_s: float):
    """A package with one module and a 'compiled' file beside it; the source `source_age_s` older."""
    package = tmp_path / "pkg"
    (package / "sub").mkdir(parents=True)
    source = package / "sub" / "mod.py"
    source.write_text("VALUE = 'from source'\n")
    compiled = package / "sub" / f"mod{compilation._EXTENSION_SUFFIXES[0]}"
    compiled.write_bytes(b"\x7fELF")
    now = time.time()
    os.utime(compiled, (now, now))
    os.utime(source, (now - source_age_s, now - source_age_s))
    return package, source


def test_a_source_edited_after_the_build_is_imported_from_source_in_a_source_tree(tmp_path):
    package, source = _fake_build(tmp_path, source_age_s=-60.0)  # edited a minute after the build
    pairs = compiled_files(package)
    assert list(pairs) == ["pkg.sub.mod"]
    assert sources_to_import(pairs, pure_python=False, source_tree=True) == {"pkg.sub.mod": source}
    # An installed wheel is never edited: its file times say nothing.
    assert sources_to_import(pairs, pure_python=False, source_tree=False) == {}


def test_an_up_to_date_build_runs_compiled_unless_pure_python_is_asked_for(tmp_path):
    package, source = _fake_build(tmp_path, source_age_s=60.0)
    pairs = compiled_files(package)
    assert sources_to_import(pairs, pure_python=False, source_tree=True) == {}
    assert sources_to_import(pairs, pure_python=True, source_tree=False) == {"pkg.sub.mod": source}


def test_the_source_finder_loads_the_module_from_its_source(tmp_path, monkeypatch):
    package, source = _fake_build(tmp_path, source_age_s=-60.0)
    (package / "__init__.py").write_text("")
    (package / "sub" / "__init__.py").write_text("")
    monkeypatch.syspath_prepend(str(tmp_path))
    finder = SourceFinder({"pkg.sub.mod": source})
    monkeypatch.setattr(sys, "meta_path", [finder, *sys.meta_path])
    for name in ("pkg", "pkg.sub", "pkg.sub.mod"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    import pkg.sub.mod  # the fake compiled file would fail to load

    assert pkg.sub.mod.VALUE == "from source" and pkg.sub.mod.__file__ == str(source)
