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
        self._step, self._other = [0.0, 0], [0.0, 0]  # [seconds, calls]
        self._originals = {name: f for name, f in vars(p).items() if isinstance(f, types.BuiltinFunctionType)}

    seconds = property(lambda self: self._step[0])
    calls = property(lambda self: self._step[1])
    other_seconds = property(lambda self: self._other[0])
    other_calls = property(lambda self: self._other[1])

    def __enter__(self) -> "PhysicsTimer":
        clock = time.perf_counter

        def timed(original, total):
            def call(*args, **kwargs):
                start = clock()
                result = original(*args, **kwargs)
                total[0] += clock() - start
                total[1] += 1
                return result
            return call

        for name, original in self._originals.items():
            setattr(p, name, timed(original, self._step if name == "stepSimulation" else self._other))
        return self

    def __exit__(self, *exc) -> None:
        for name, original in self._originals.items():
            setattr(p, name, original)
