"""Time PyBullet's own calls made while the timer is active (shared by the benchmarks).

`pybullet.stepSimulation` is timed on its own; every other PyBullet function (joint reads, motor
commands, contact and pose queries) together. The bare C calls are what PyBullet itself costs; wall
time over them is what our Python adds, measured on the very states the code under test produced.
Each timed call pays about 0.2 µs for the timer itself (counted in neither total).
"""
from __future__ import annotations

import time
import types

import pybullet as p


class PhysicsTimer:
    """Accumulates seconds and counts of `stepSimulation` calls (`seconds`, `calls`) and of all other
    PyBullet calls (`other_seconds`, `other_calls`); the functions are patched on the module while active."""

    def __init__(self):
        self.seconds, self.calls = 0.0, 0
        self.other_seconds, self.other_calls = 0.0, 0
        self._originals = {name: f for name, f in vars(p).items() if isinstance(f, types.BuiltinFunctionType)}

    def __enter__(self) -> "PhysicsTimer":
        clock = time.perf_counter

        def timed_step(original):
            def call(*args, **kwargs):
                start = clock()
                result = original(*args, **kwargs)
                self.seconds += clock() - start
                self.calls += 1
                return result
            return call

        def timed_other(original):
            def call(*args, **kwargs):
                start = clock()
                result = original(*args, **kwargs)
                self.other_seconds += clock() - start
                self.other_calls += 1
                return result
            return call

        for name, original in self._originals.items():
            setattr(p, name, timed_step(original) if name == "stepSimulation" else timed_other(original))
        return self

    def __exit__(self, *exc) -> None:
        for name, original in self._originals.items():
            setattr(p, name, original)
