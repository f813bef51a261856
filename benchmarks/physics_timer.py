"""Time the `pybullet.stepSimulation` calls made while the timer is active (shared by the benchmarks).

The bare C call is what PyBullet itself costs; wall time over it is what our Python adds, measured
on the very states the code under test produced.
"""
from __future__ import annotations

import time

import pybullet as p


class PhysicsTimer:
    """Accumulates the seconds and count of `pybullet.stepSimulation` calls (patched on the module while active)."""

    def __init__(self):
        self.seconds, self.calls, self._original = 0.0, 0, p.stepSimulation

    def __enter__(self) -> "PhysicsTimer":
        original, clock = self._original, time.perf_counter

        def timed_step(*args, **kwargs):
            start = clock()
            original(*args, **kwargs)
            self.seconds += clock() - start
            self.calls += 1

        p.stepSimulation = timed_step
        return self

    def __exit__(self, *exc) -> None:
        p.stepSimulation = self._original
