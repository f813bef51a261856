"""Plant speed: simulated seconds per wall second with 4 motors driven and one object in contact,
against raw PyBullet stepping of the same scene (no drive-train logic; the joint motors keep the
plant's last command), and physics steps per second. The same steps are run again with the plant's
PyBullet calls timed: plant wall / its `p.stepSimulation` time is the drive-train overhead measured
on the plant's very states, and its other PyBullet calls (joint reads, motor commands) are the part
of that overhead no Python code can remove.

Run: /work/venv/bin/python benchmarks/bench_plant.py [--seconds 5]
"""
from __future__ import annotations

import argparse
import time

import pybullet as p

from bh8_gym.objects import ObjectSpec, add_object
from bh8_gym.plant import HandPlant

from physics_timer import PhysicsTimer


def scene() -> tuple[HandPlant, int]:
    plant = HandPlant(seed=0)
    plant.set_wrist_pose((0.0, 0.0, 0.225), (1.0, 0.0, 0.0, 0.0), teleport=True)
    cylinder = add_object(plant, ObjectSpec("cylinder", (0.06, 0.13), mass=0.2, friction=None), position=(0.0, 0.0, 0.065))
    plant.set_drives([24_414.0] * 3 + [2_000.0], [1.0, 1.0, 1.0, 0.5])
    for _ in range(500):  # close onto the box so the timed part is in contact
        plant.step()
    return plant, cylinder


def run_plant(plant: HandPlant, steps: int) -> float:
    """Wall seconds of `steps` plant steps, the drives alternating so the fingers keep working."""
    start = time.perf_counter()
    for k in range(steps):
        if k % 250 == 0:
            direction = 1.0 if (k // 250) % 2 == 0 else -0.2
            plant.set_drives([24_414.0 * direction] * 3 + [2_000.0 * direction], [1.0, 1.0, 1.0, 0.5])
        plant.step()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=5.0,
                        help="simulated seconds per measurement (default: %(default)s)")
    args = parser.parse_args()
    plant, cylinder = scene()
    steps = int(args.seconds / plant.dt)
    start_state = plant.save_state()
    plant_wall = run_plant(plant, steps)
    contacts = len(plant.contacts(cylinder, plant.hand_id))
    client = plant.client
    start = time.perf_counter()
    for _ in range(steps):  # from where the plant's run ended, its last joint motor command kept
        p.stepSimulation(physicsClientId=client)
    raw_wall = time.perf_counter() - start
    plant.restore_state(start_state)  # the plant's steps again, PyBullet's calls timed (deterministic)
    with PhysicsTimer() as physics:
        timed_wall = run_plant(plant, steps)
    plant.close()
    print(f"physics step {plant.dt * 1000:.1f} ms; {steps} steps; hand-object contacts at the end: {contacts}")
    print(f"plant:   {steps / plant_wall:8.0f} steps/s  {args.seconds / plant_wall:6.1f} simulated s per wall s")
    print(f"raw:     {steps / raw_wall:8.0f} steps/s  {args.seconds / raw_wall:6.1f} simulated s per wall s")
    print(f"plant overhead over raw stepping: {plant_wall / raw_wall:.2f}x; over its own physics calls "
          f"({1e6 * physics.seconds / physics.calls:.0f} us each): {timed_wall / physics.seconds:.2f}x; its other "
          f"PyBullet calls (joint reads, motor commands, {1e6 * physics.other_seconds / physics.calls:.1f} us per step) "
          f"alone would make that {(physics.seconds + physics.other_seconds) / physics.seconds:.2f}x")


if __name__ == "__main__":
    main()
