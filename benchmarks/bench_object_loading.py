"""What loading an object costs now that PyBullet reads only files we write (bh8_gym.meshes, urdfs,
pybullet_files): pybullet_data's random_urdfs models, each loaded once into a fresh world.

Per model, the median of each way:
- `pybullet alone`: createCollisionShape + createVisualShape on the original OBJ (what PyBullet
  itself costs, unchecked: the package no longer does this);
- `ours, first load`: read_mesh (read, parse, check) with an empty cache, write the clean OBJ,
  PyBullet on it: what an env worker pays the first time it meets a model;
- `ours, cached`: the same with the parsed mesh cached (every later world of the same process);
- the same three for the model's URDF (loadURDF against ObjectLoader's URDF path).

Run: python benchmarks/bench_object_loading.py [--models 200]
(With PYTHONPATH set to a checkout of main at 5acafd1 it measures the path before: the validating
reader, then PyBullet on the user's own file.)
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import pybullet
import pybullet_data

from bh8_gym import meshes
from bh8_gym.objects import ObjectLoader, ObjectSpec


def _clear_mesh_cache() -> None:
    if hasattr(meshes, "_cache"):
        meshes._cache.clear()
    else:  # main before issue 39
        meshes._checked_bounds.cache_clear()


def _timed(function) -> float:
    start = time.perf_counter()
    function()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", type=int, default=200, help="random_urdfs models, the first N (default: %(default)s)")
    models = parser.parse_args().models
    root = Path(pybullet_data.getDataPath()) / "random_urdfs"
    names = sorted(path.name for path in root.iterdir() if (path / f"{path.name}.obj").is_file())
    names = [name for name in names if name != "168"][:models]  # 168 has NaN vertices
    times: dict[str, list[float]] = {key: [] for key in ("mesh: pybullet alone", "mesh: ours, first load",
                                                         "mesh: ours, cached", "urdf: pybullet alone",
                                                         "urdf: ours, first load", "urdf: ours, cached")}
    client = pybullet.connect(pybullet.DIRECT)
    for name in names:
        obj, urdf = str(root / name / f"{name}.obj"), str(root / name / f"{name}.urdf")

        def direct():
            pybullet.createCollisionShape(pybullet.GEOM_MESH, fileName=obj, meshScale=[0.01] * 3,
                                          physicsClientId=client)
            pybullet.createVisualShape(pybullet.GEOM_MESH, fileName=obj, meshScale=[0.01] * 3, physicsClientId=client)

        def ours():
            ObjectLoader(client).create(ObjectSpec("mesh", path=obj, scale=0.01), (0, 0, 1), (0, 0, 0, 1))

        def direct_urdf():
            pybullet.loadURDF(urdf, physicsClientId=client)

        def ours_urdf():
            ObjectLoader(client).create(ObjectSpec("urdf", path=urdf, mass=None, friction=None), (0, 0, 1),
                                        (0, 0, 0, 1))

        times["mesh: pybullet alone"].append(_timed(direct))
        _clear_mesh_cache()
        times["mesh: ours, first load"].append(_timed(ours))
        times["mesh: ours, cached"].append(_timed(ours))
        times["urdf: pybullet alone"].append(_timed(direct_urdf))
        _clear_mesh_cache()
        times["urdf: ours, first load"].append(_timed(ours_urdf))
        times["urdf: ours, cached"].append(_timed(ours_urdf))
        pybullet.resetSimulation(physicsClientId=client)
    pybullet.disconnect(client)
    print(f"{len(names)} random_urdfs models, median ms per load (mean in brackets)")
    for key, values in times.items():
        print(f"{key:24s} {1e3 * statistics.median(values):7.2f} ({1e3 * statistics.fmean(values):.2f})")


if __name__ == "__main__":
    main()
