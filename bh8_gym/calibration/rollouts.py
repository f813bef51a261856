"""Replays of one log under many parameter sets at once: a process pool on this machine, or Ray
tasks on a cluster (`bh8 calibrate fit --address`).

Each worker reads the log once (its bytes are sent once: the pool's initializer, or one object in
Ray's store) and then replays it for every parameter set it is given. The local pool starts its
processes with "spawn": a forked copy of a process holding a PyBullet client is not safe.
"""
from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor

from bh8_gym.calibration.log_format import parse_log
from bh8_gym.calibration.replay import replay

_WORKER_LOG = None


def _load(data: bytes, name: str) -> None:
    global _WORKER_LOG
    _WORKER_LOG = parse_log(data, name)


def _replay_here(hand: dict):
    return replay(_WORKER_LOG, hand)


class LocalRollouts:
    """`jobs` worker processes (default: the CPUs this process may use)."""

    def __init__(self, data: bytes, name: str, jobs: int | None = None):
        if jobs is None:
            jobs = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        self.jobs = jobs
        if self.jobs == 1:
            _load(data, name)
            self._pool = None
        else:
            self._pool = ProcessPoolExecutor(self.jobs, mp_context=multiprocessing.get_context("spawn"),
                                             initializer=_load, initargs=(data, name))

    def map(self, hands: list[dict]) -> list:
        if self._pool is None:
            return [_replay_here(hand) for hand in hands]
        return list(self._pool.map(_replay_here, hands))

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)

    @property
    def where(self) -> str:
        return f"{self.jobs} local process{'es' if self.jobs != 1 else ''}"


class RayRollouts:
    """Ray tasks on the cluster at `address` (checked reachable by the caller), one per replay."""

    def __init__(self, data: bytes, name: str, address: str):
        import ray

        self._ray = ray
        self._started = not ray.is_initialized()
        if self._started:
            ray.init(address=address, log_to_driver=False)
        self._log = ray.put((data, name))

        @ray.remote
        def replay_remote(log_data, hand):
            from bh8_gym.calibration.log_format import parse_log as parse
            from bh8_gym.calibration.replay import replay as run

            return run(parse(*log_data), hand)

        self._remote = replay_remote
        self.address = address

    def map(self, hands: list[dict]) -> list:
        return self._ray.get([self._remote.remote(self._log, hand) for hand in hands])

    def close(self) -> None:
        if self._started:
            self._ray.shutdown()

    @property
    def where(self) -> str:
        return f"the Ray cluster at {self.address}"
