"""benchmarks/bench_hold.py --mode loop: the LOOP grasp a host drives (LCV 100, gain 255 on every finger,
the spread held at 0) holds still when it stops driving each finger once that finger has stalled.

Manual §9.3.1 and App. B A1: a finger that has stalled on an object "develops full force against the
object until no motion is detected, at which point the motor current may be removed since the finger
joints become mechanically locked". A finger driven on at full torque after it stalled keeps its links
working against the object, and a pinched object creeps about the pinch.
"""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_hold.py"


@pytest.fixture(scope="module")
def bench_hold():
    spec = importlib.util.spec_from_file_location("bench_hold", BENCH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop(spec.name, None)


def test_a_loop_grasp_that_stops_driving_stalled_fingers_holds_the_pinched_cylinder(bench_hold):
    """The 8 cm, 265 g cylinder at friction 0.42 of the benchmark's placement 18 (seed 0): F2 misses it
    and F1 and F3 pinch it. Driven on at LCV 100 through the 5 s hold it pivots about the pinch out of
    the hand; with LCV 0 for each finger once its LFAP has stood still (10 counts in 30 ms) it stays
    within 2 mm and 5°."""
    trial = bench_hold.trials(["cylinder"], placements=8, shake=False, seed=0, mode="loop")[18]
    assert trial.size == 0.08 and trial.lock_stalled
    held = bench_hold.run_trial(trial)
    assert held["closed"] and held["kept"]
    assert held["slip_mm"] < 2.0 and held["rotation_deg"] < 5.0
    driven_on = bench_hold.run_trial(bench_hold.Trial(**{**trial.__dict__, "lock_stalled": False}))
    assert not driven_on["kept"] or driven_on["slip_mm"] > 10.0


def test_pads_contact_patches_keep_a_pinched_capsule_from_pivoting(bench_hold):
    """A 4 cm, 240 g capsule at friction 1.15 (placement 1 of `--shapes capsule`, seed 0) pinched
    by two fingers (the third misses it): with point contacts (the default) it turns about the line
    through the two contacts under its weight through the 5 s hold; with 4 mm pads' contact patches
    (`finger_pad_radius`, a turn about the contact normal resisted up to (2/3)·mu·N·a) it stays."""
    from bh8_gym.plant import PlantParameters

    trial = bench_hold.trials(["capsule"], placements=15, shake=False, seed=0, mode="loop")[1]
    assert trial.size == 0.04 and trial.lock_stalled
    patches = bench_hold.run_trial(trial, PlantParameters(finger_pad_radius=0.004))
    assert patches["closed"] and patches["kept"] and not patches["all_three"]
    assert patches["slip_mm"] < 1.0 and patches["rotation_deg"] < 3.0
    points = bench_hold.run_trial(trial)
    assert points["closed"] and points["kept"] and not points["all_three"]
    assert points["slip_mm"] > 1.5 and points["rotation_deg"] > 5.0
