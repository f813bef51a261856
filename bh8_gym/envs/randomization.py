"""Domain randomisation of the simulated hand (PlantParameters), drawn each reset from a generator
spawned from the env's seed (`physics_generator`), apart from the scene's draws.

On by default (`randomize=True`); evaluation turns it off. Every range says why it is as wide as
it is: the constants the manual gives vary from unit to unit and with temperature; the ones we
estimated (SPEC.md §8 open points) get wider ranges, because a policy must not depend on our guess.

Object mass and friction are drawn with the object (objects.py); placement errors in scenes.py.
The RealTime processing time per cycle (the cycle latency, SPEC.md §6 and §8) is a per-firmware
setting drawn by `sample_processing_time` and applied with `PlantRandomizer(plant, firmware)`.
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

def physics_generator(np_random: np.random.Generator) -> np.random.Generator:
    """The generator of the plant and latency draws, spawned from `np_random`'s seed sequence.

    It takes no draw from `np_random`, so the scenes drawn from it (objects, placement) are the
    same for a seed whether or not the physics is randomised.
    """
    return np.random.default_rng(np_random.bit_generator.seed_seq.spawn(1)[0])


# PlantParameters fields multiplied by a uniform factor (low, high), in draw order.
SCALED_FIELDS = (
    "motor_peak_torque",
    "motor_no_load_speed",
    "finger_drive_efficiency",
    "breakaway_base_torque",
    "breakaway_preload_slope",
    "rotor_impact_gain",
    "strain_gain",
    "link_mass_scale",
)
# PlantParameters fields drawn uniformly in (low, high), in draw order.
ABSOLUTE_FIELDS = ("finger_friction", "palm_friction", "table_friction")


@dataclass(frozen=True)
class RandomizationRanges:
    """Ranges; a factor range (1.0, 1.0) or an equal (low, high) switches that knob off."""

    # Table 7's peak torque is nominal; motors differ by about ±10 % and lose torque when hot.
    motor_peak_torque: tuple[float, float] = (0.85, 1.15)
    # No-load speed varies with supply voltage and brush wear.
    motor_no_load_speed: tuple[float, float] = (0.9, 1.1)
    # Our estimate (worm + cable); worm efficiency depends on lubrication and load.
    finger_drive_efficiency: tuple[float, float] = (0.8, 1.2)
    # TorqueSwitch breakaway vs preload is an image in the manual (SPEC.md §8): wide ranges.
    breakaway_base_torque: tuple[float, float] = (0.7, 1.3)
    breakaway_preload_slope: tuple[float, float] = (0.7, 1.3)
    rotor_impact_gain: tuple[float, float] = (0.7, 1.3)
    # Strain-gauge slope is an open point (SPEC.md §8); no-load offsets 100-140 per finger (SPEC §1).
    strain_gain: tuple[float, float] = (0.85, 1.15)
    strain_offsets: tuple[int, int] = (100, 140)
    # Link masses from CAD-like estimates (hand_urdf): ±10 %.
    link_mass_scale: tuple[float, float] = (0.9, 1.1)
    # Pads get dusty or worn; tables differ.
    finger_friction: tuple[float, float] = (0.5, 1.1)
    palm_friction: tuple[float, float] = (0.4, 0.8)
    table_friction: tuple[float, float] = (0.3, 0.8)
    # Seconds of firmware processing per RealTime cycle (absolute): our 1 ms is an estimate (SPEC.md §8),
    # so a policy must tolerate a 68HC811 somewhat faster or slower than we guessed.
    processing_time: tuple[float, float] = (0.7e-3, 1.5e-3)
    # A calibrated hand (its gauges' offsets measured, `calibrated_ranges`): each finger's offset is
    # drawn within ± this many counts of its own instead of from `strain_offsets`. None: not calibrated.
    strain_offset_jitter: int | None = None

    def __post_init__(self):
        for item in fields(self):
            if item.name == "strain_offset_jitter":
                jitter = self.strain_offset_jitter
                if jitter is not None and (isinstance(jitter, bool) or not isinstance(jitter, int) or not 0 <= jitter <= 40):
                    raise ValueError(f"strain_offset_jitter must be None or an integer 0..40, got {jitter!r}")
                continue
            low, high = getattr(self, item.name)
            if not (np.isfinite(low) and np.isfinite(high) and 0 <= low <= high):
                raise ValueError(f"randomisation range {item.name} must be 0 <= low <= high, got {(low, high)!r}")


def sample_plant_parameters(base, rng: np.random.Generator, ranges: RandomizationRanges = RandomizationRanges()):
    """A copy of `base` (PlantParameters) with the randomised fields drawn from `rng` (fixed order)."""
    values = {}
    for name in SCALED_FIELDS:
        low, high = getattr(ranges, name)
        values[name] = getattr(base, name) * float(rng.uniform(low, high))
    for name in ABSOLUTE_FIELDS:
        values[name] = float(rng.uniform(*getattr(ranges, name)))
    if ranges.strain_offset_jitter is not None and base.strain_offsets is not None:
        jitter = ranges.strain_offset_jitter
        draws = rng.integers(-jitter, jitter + 1, size=3)  # one draw of three, as below: the order stays
        values["strain_offsets"] = tuple(int(min(255, max(0, o + d))) for o, d in zip(base.strain_offsets, draws))
    else:
        low, high = ranges.strain_offsets
        values["strain_offsets"] = tuple(int(v) for v in rng.integers(int(low), int(high) + 1, size=3))
    return replace(base, **values)


# Randomisation about a calibrated hand (`bh8 calibrate fit`'s hand file): a fitted field's factor
# range is ± CALIBRATED_SIGMAS of its uncertainty, at least ± CALIBRATED_MIN_SPREAD (the model's own
# error: the fit replays its log to a fraction of a percent, not exactly), never wider than before.
CALIBRATED_SIGMAS = 3.0
CALIBRATED_MIN_SPREAD = 0.03


def calibrated_ranges(ranges: RandomizationRanges, values: dict, uncertainty: dict) -> RandomizationRanges:
    """`ranges` narrowed about a calibrated hand: its PlantParameters `values` become the base (the
    factors' centre) and each field with an `uncertainty` (one standard deviation) gets a range from
    it; the gauges' offsets are drawn about the measured ones."""
    narrowed = {}
    for name in SCALED_FIELDS:
        sigma, value = uncertainty.get(name), values.get(name)
        if sigma is None or not value:
            continue
        low, high = getattr(ranges, name)
        spread = max(CALIBRATED_MIN_SPREAD, CALIBRATED_SIGMAS * float(sigma) / abs(float(value)))
        narrowed[name] = (max(low, 1.0 - spread), min(high, 1.0 + spread)) if low <= 1.0 <= high else (low, high)
    if "strain_offsets" in values:
        sigmas = uncertainty.get("strain_offsets") or (0.5, 0.5, 0.5)
        narrowed["strain_offset_jitter"] = int(min(40, max(1, np.ceil(CALIBRATED_SIGMAS * max(sigmas)))))
    return replace(ranges, **narrowed)


def sample_processing_time(rng: np.random.Generator, ranges: RandomizationRanges = RandomizationRanges()) -> float:
    """Firmware processing seconds per RealTime cycle, drawn from `rng` (one draw; call it after
    `sample_plant_parameters` so the plant draws stay as they were)."""
    return float(rng.uniform(*ranges.processing_time))


class PlantRandomizer:
    """Applies sampled PlantParameters to a live HandPlant between episodes (after a state restore),
    and, given the firmware, a sampled RealTime processing time."""

    def __init__(self, plant, firmware=None):
        self.plant = plant
        self.firmware = firmware

    def apply(self, params, processing_time: float | None = None) -> None:
        self.plant.set_parameters(params)
        if processing_time is not None:
            if self.firmware is None:
                raise ValueError(f"processing_time {processing_time!r} needs PlantRandomizer(plant, firmware)")
            if not 0.0 <= processing_time < 1.0:
                raise ValueError(f"processing_time must be in [0, 1) seconds, got {processing_time!r}")
            self.firmware.processing_time = float(processing_time)
