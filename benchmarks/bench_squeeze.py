"""How robust the locked-worm squeeze is (manual §9.3.1, App. B FAQ A1: with the motor current
removed the grasp stays): GC with HOLD 0 on a standing 150 g cylinder (or, `--shape sphere`, a
150 g sphere on the table; `--shape post`, a post fixed to the world), then 0.5 s with the motors
off, over a grid of radii and sideways offsets. A grasp "keeps its squeeze" when every finger's
strain-gauge load stays above 15 and their sum above 70 % of the loads the stalled drives produced
(the criterion of tests/test_integration_grasp.py, which runs the grid's centre cell). Also per
cell: how far each finger was pushed open (encoder counts, from its furthest-closed position,
counted once it has closed 1000 counts) while its own motor was still driving it closed, which a
powered worm does not allow, how far the object moved, and how long the GC took.

Prints one line per cell and the counts: figures of the plant model's quality, not its speed.

Run: python benchmarks/bench_squeeze.py
"""
from __future__ import annotations

import argparse
import tempfile

import numpy as np

from bh8_gym.firmware import Firmware
from bh8_gym.plant import HandPlant, PlantParameters

PALM_DOWN = (1.0, 0.0, 0.0, 0.0)
GC_LIMIT_S = 60.0  # simulated seconds; a GC at the default MCV takes about 1 s in free air


def command(fw: Firmware, line: str) -> None:
    reply = fw.transact(line.encode() + b"\r")
    if b"ERR" in reply:
        raise RuntimeError(f"{line!r} answered {reply!r}")


def squeeze(params: PlantParameters, shape: str, radius: float, offset: float):
    """Per finger: stalled loads and loads with the motors off (strain-gauge units), counts pushed
    open while driving; the object's horizontal travel in metres; the GC's simulated seconds."""
    plant = HandPlant(params, seed=0)
    with tempfile.TemporaryDirectory() as store:
        fw = Firmware(plant=plant, store_dir=store, seed=0)
        try:
            plant.set_wrist_pose((0.0, 0.0, 0.225), PALM_DOWN, teleport=True)
            if shape == "cylinder":
                thing = plant.add_object("cylinder", (radius, 0.13), position=(offset, 0.0, 0.065), mass=0.15)
            elif shape == "sphere":
                thing = plant.add_object("sphere", (radius,), position=(offset, 0.0, radius), mass=0.15)
            command(fw, "HI")
            if shape == "post":  # fixed to the world: the lock's own behaviour, no object dynamics;
                # placed after HI, which it would keep from ending (the spread sweeps the fingers into it)
                thing = plant.add_object("box", (2 * radius, 2 * radius, 0.16), position=(offset, 0.0, 0.12), fixed=True)
            command(fw, "GFSET HOLD 0")
            zero = np.array(plant.strain_offsets)
            fw.write(b"GC\r")
            gc_start = fw.time
            start = np.array(plant.object_pose(thing)[0][:2])
            driving = [[], [], []]  # each finger's loads while its own motor drives
            first, furthest, pushed_open = list(plant.motor_positions()[:3]), [-np.inf] * 3, [0.0] * 3
            while not fw.idle:
                if fw.time - gc_start > GC_LIMIT_S:
                    raise RuntimeError(f"GC did not end within {GC_LIMIT_S} simulated seconds")
                fw.run_for(plant.dt)
                gauges = plant.strain_gauges()[:3] - zero
                positions = plant.motor_positions()
                for f in range(3):
                    if plant._state.drive_on[f]:
                        driving[f].append(gauges[f])
                        if positions[f] > first[f] + 1000.0:  # under way: not the start's own settling
                            furthest[f] = max(furthest[f], positions[f])
                            pushed_open[f] = max(pushed_open[f], furthest[f] - positions[f])
            fw.read()
            gc_seconds = fw.time - gc_start
            stalled = np.array([np.median(loads[-10:]) for loads in driving])
            off = []
            for _ in range(5):
                fw.run_for(0.1)
                off.append(plant.strain_gauges()[:3] - zero)
            travel = float(np.linalg.norm(np.array(plant.object_pose(thing)[0][:2]) - start))
            return stalled, np.array(off), pushed_open, travel, gc_seconds
        finally:
            fw.shutdown()
            plant.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    radii, offsets = [0.028, 0.029, 0.03, 0.031, 0.032], [-0.002, 0.0, 0.002]
    parser.add_argument("--radii", type=float, nargs="+", default=radii,
                        help=f"object radii in m (default: {' '.join(map(str, radii))})")
    parser.add_argument("--offsets", type=float, nargs="+", default=offsets,
                        help=f"sideways offsets of the object in m (default: {' '.join(map(str, offsets))})")
    parser.add_argument("--shape", choices=("cylinder", "sphere", "post"), default="cylinder",
                        help="a 13 cm cylinder standing on the table, a sphere on it (same mass), or a "
                             "square post (side 2 x radius) fixed to the world (default: %(default)s)")
    parser.add_argument("--solver-iterations", type=int, default=PlantParameters.solver_iterations,
                        help="PyBullet's constraint solver iterations per step (PlantParameters.solver_iterations; "
                             "default: %(default)s)")
    args = parser.parse_args()
    params = PlantParameters(solver_iterations=args.solver_iterations)
    kept = backdriven = 0
    cells = len(args.radii) * len(args.offsets)
    print("radius m  offset m  stalled loads    lowest loads, motors off  kept  pushed open while driving  object moved  GC took")
    for radius in args.radii:
        for offset in args.offsets:
            stalled, off, pushed_open, travel, gc_seconds = squeeze(params, args.shape, radius, offset)
            ok = bool(np.all(off > 15) and np.all(off.sum(axis=1) >= 0.7 * stalled.sum()))
            kept += ok
            backdriven += max(pushed_open) > 100
            print(f"{radius:8.3f}  {offset:+8.3f}  {np.array2string(stalled.astype(int)):15s}  "
                  f"{np.array2string(off.min(axis=0).astype(int)):24s}  {'yes' if ok else 'no ':4s}  "
                  f"{str([round(c) for c in pushed_open]):25s}  {travel * 100:5.1f} cm      {gc_seconds:5.2f} s", flush=True)
    print(f"{args.shape}, solver iterations {args.solver_iterations}: squeeze kept in {kept} of {cells} grasps; "
          f"a driving finger pushed open by over 100 counts in {backdriven}")


if __name__ == "__main__":
    main()
