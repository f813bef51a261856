"""The mapping between a policy's actions and a LOOP control block's bytes, a fact of the host side.

A Gaussian policy (PPO, SAC) gives floats in [-1, 1]; the hand takes integer control data (LCV
-128..127, LCPG 0..255, within the safety envelope's bounds: `LoopInterface.action_space`). The
same mapping serves the environments' `ContinuousActions` wrapper, the previous action in the
host's observation (`LoopInterface`) and `bh8 deploy`, so a trained policy drives a real hand with
exactly the bytes it produced in simulation. numpy only: nothing here loads PyBullet.
"""
from __future__ import annotations

import numpy as np


def centres_and_halves(low, high) -> tuple[list[float], list[float]]:
    """The centre and half-range of each datum's integer range, as plain floats (the per-step
    mappings take lists: on a handful of values numpy's call costs dominate)."""
    low, high = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
    return ((low + high) / 2.0).tolist(), ((high - low) / 2.0).tolist()


def unit_to_bytes(unit: np.ndarray, low: np.ndarray, high: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Map floats in [-1, 1] (clipped) linearly onto the integer range low..high, rounding to nearest.

    LCV (-128..127): -1 -> -128, 0 -> 0, +1 -> 127. LCPG (0..255): -1 -> 0, +1 -> 255.
    """
    units, centres, halves = np.broadcast_arrays(np.asarray(unit, dtype=np.float64), (low + high) / 2.0, (high - low) / 2.0)
    values = np.array(unit_to_byte_list(units.ravel().tolist(), centres.ravel().tolist(), halves.ravel().tolist()),
                      dtype=np.int64).reshape(units.shape)
    if out is None:
        return values.astype(np.int16)
    out[...] = values
    return out


def unit_to_byte_list(units: list[float], centres: list[float], halves: list[float]) -> list[int]:
    """`unit_to_bytes` on plain floats, element by element: round(centre + half x clip(u, -1, 1)),
    halves to even as np.rint. The per-step path: on a handful of values numpy's call costs dominate."""
    return [round(centre + half * (-1.0 if u < -1.0 else (1.0 if u > 1.0 else u)))
            for u, centre, half in zip(units, centres, halves)]


def byte_list_to_unit(values: list[int], centres: list[float], halves: list[float]) -> list[float]:
    """`bytes_to_unit` on plain numbers (cast to float32 for the same action): the scripts' per-cycle path."""
    return [(value - centre) / half for value, centre, half in zip(values, centres, halves)]


def bytes_to_unit(values: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """Inverse of `unit_to_bytes` (up to rounding): integer control values -> floats in [-1, 1]."""
    centre = (low + high) / 2.0
    half = (high - low) / 2.0
    return ((np.asarray(values, dtype=np.float64) - centre) / half).astype(np.float32)

