"""What the fit minimises: the differences between the recorded hand's signals and a replay's,
each scaled to one unit of its own kind (`ResidualModel`).

- finger positions: LFAP of each finger in the sweeps' lift phases (a weak drive lifting the finger
  against its weight), in % of the motor's range (loop_interface.FULL_RANGE_COUNTS);
- spread positions: LFAP of the spread in the sweeps' lift phases (where the fingers move smoothly;
  not in `CLEAR_SEGMENT`, excitation.py), % of its range;
- strains (reported, not fitted by the replays): each finger's mean gauge reading over each
  squeeze's hold, in counts (a finger pressing an object jitters by a few counts from cycle to cycle);
- timing: how long each supervisory motion took, in 10 ms (a log of a real hand only: the
  simulated hand's clock stands still while the host waits, so its times say nothing).

The fingers' returns (stiff, helped by their weight) are not compared: there the simulated finger
lurches from cycle to cycle (its overrun brake), and the replay sets every motor to the recorded
positions when the next phase starts (replay.py).

The gauges enter linearly: reading = offset + gain x load (the torque about the outer joint, §9.4).
Each replay runs with `REPLAY_OFFSETS` and the default gain; the offsets that fit best are read off
the rest phases (fingers still, nothing pressing: the median of the recorded reading minus the
replay's load reading), the gain off the squeezes (`strain_gain`: the recorded readings above their
offsets against the replays' loads, a line through the origin, with how far the recorded hand's
landings on the object may put it off).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bh8_gym.calibration.excitation import CLEAR_SEGMENT, PHASE_HOLD, PHASE_LIFT, PHASE_RETURN, REST_PHASES
from bh8_gym.calibration.replay import Signals
from bh8_gym.loop_interface import FULL_RANGE_COUNTS
from bh8_gym.protocol import FINGER_MOTORS, SPREAD_MOTOR

REPLAY_OFFSETS = (120, 120, 120)  # gauge offsets every replay runs with (mid-range: nothing clips)
REPLAY_GAIN = 100.0  # and its gain: PlantParameters' default, counts per N·m
GAIN_LOAD_SPAN = 0.03  # N·m: squeezes whose loads span less than this tell no gain
TIMING_SCALE_S = 0.01
MOVED_COUNTS = 300  # a motor that moved less than this in the phases that tell its parameters did not move
STRAIN_EVIDENCE_COUNTS = 3  # a squeeze whose gauges moved less than this from rest tells nothing of their gain


def _through_origin(load: np.ndarray, reading: np.ndarray, keep: np.ndarray) -> float:
    """The slope of the line through the origin that fits `reading` against `load` where `keep`."""
    return float(load[keep] @ reading[keep] / (load[keep] @ load[keep]))


def _phase(name: str) -> str:
    return name.rsplit(".", 1)[-1] if "." in name else ""


@dataclass
class Evidence:
    """What the log holds for each group of parameters, and which motors never moved."""

    lifts: bool
    spread: bool
    squeezes: bool
    timing: bool
    still_motors: tuple


class ResidualModel:
    """Residual vectors of replays against one recorded hand (module docstring)."""

    def __init__(self, observed: Signals, hand_clock: str | None):
        self.observed = observed
        # CLEAR_SEGMENT's phases are not compared (an object pushed about: excitation.py)
        phases = np.array(["" if name.split(".")[0] == CLEAR_SEGMENT else _phase(name) for name in observed.segments])
        self.squeeze_of = [name.rsplit(".", 1)[0] for name in observed.segments]
        columns = {m: i for i, m in enumerate(observed.motors)}
        self.finger_columns = [columns[m] for m in FINGER_MOTORS if m in columns]
        self.spread_column = columns.get(SPREAD_MOTOR)
        self.lift = phases == PHASE_LIFT
        self.sweep = self.lift | (phases == PHASE_RETURN)
        # The spread is compared where the fingers lift (smoothly) only: while they return (lurching,
        # see above) a billionth of a change anywhere in the hand moves a spread near its stall
        # duty by a hundred counts, and the fit would chase that scatter.
        self.spread_compared = self.lift
        self.rest = np.isin(phases, REST_PHASES)
        self.hold = phases == PHASE_HOLD
        self.holds = sorted({self.squeeze_of[i] for i in np.flatnonzero(self.hold)})
        self.timing = hand_clock == "wall" and len(observed.durations) > 0
        self.ranges = np.array([FULL_RANGE_COUNTS[m] for m in observed.motors], dtype=float)
        self.evidence = self._evidence()
        # A motor that did not move where the excitation moves it (a fault, an obstacle, a stuck
        # spread) is left out: what it did is no motion the simulated motor can be fitted to.
        still = self.evidence.still_motors
        self.finger_columns = [c for c, m in zip(range(len(observed.motors)), observed.motors)
                               if m in FINGER_MOTORS and m not in still]
        if SPREAD_MOTOR in still:
            self.spread_column = None

    def _moved(self, column: int, mask: np.ndarray) -> bool:
        values = self.observed.positions[mask, column]
        return values.size > 0 and float(values.max() - values.min()) >= MOVED_COUNTS

    def _evidence(self) -> Evidence:
        still = []
        for motor, column in zip(self.observed.motors, range(len(self.observed.motors))):
            mask = self.lift if motor != SPREAD_MOTOR else self.sweep
            if not self._moved(column, mask):
                still.append(motor)
        lifts = any(self._moved(c, self.lift) for c in self.finger_columns)
        spread = self.spread_column is not None and self._moved(self.spread_column, self.sweep)
        squeezes = False
        if self.holds and self.rest.any():
            rest = np.nanmedian(self.observed.strains[self.rest], axis=0)
            for name in self.holds:
                held = np.nanmedian(self.observed.strains[self._hold_mask(name)], axis=0)
                squeezes = squeezes or bool(np.nanmax(np.abs(held - rest)) >= STRAIN_EVIDENCE_COUNTS)
        return Evidence(lifts, spread, squeezes, self.timing, tuple(still))

    def _hold_mask(self, name: str) -> np.ndarray:
        return self.hold & np.array([squeeze == name for squeeze in self.squeeze_of])

    # -- offsets -----------------------------------------------------------------------------

    def offsets(self, replayed: Signals) -> tuple[int, int, int]:
        """The gauge offsets that make the replay's rest readings the recorded ones."""
        rest = self.rest if self.rest.any() else np.ones(len(self.rest), dtype=bool)
        recorded = np.nanmedian(self.observed.strains[rest], axis=0)
        loads = np.nanmedian(replayed.strains[rest], axis=0) - np.array(REPLAY_OFFSETS)
        offsets = np.round(recorded - loads)
        return tuple(int(min(255, max(0, value))) if np.isfinite(value) else 120 for value in offsets)

    def offset_uncertainty(self, replayed: Signals) -> tuple[float, float, float]:
        rest = self.rest if self.rest.any() else np.ones(len(self.rest), dtype=bool)
        spread = np.nanstd(self.observed.strains[rest] - replayed.strains[rest], axis=0)
        return tuple(float(max(0.5, value)) for value in spread)  # rounded to counts: half a count at best

    # -- residuals ---------------------------------------------------------------------------

    def strain_gain(self, replayed: Signals, others: tuple = ()) -> tuple[float, float] | None:
        """The gauges' gain (counts per N·m) and its standard deviation read off the squeezes'
        holds: each finger's mean recorded reading above its offset against the replay's mean load
        (its reading above REPLAY_OFFSETS over REPLAY_GAIN), a line through the origin; None without
        squeezes whose loads span GAIN_LOAD_SPAN.

        Where a fingertip lands on the object, and so how the squeeze's torque splits between the
        links, differs from one run to the next: a replay a billionth away (`others`) puts loads on
        the gauges a few % apart, and the recorded run is one such landing. So the loads are
        averaged over `replayed` and `others`, and the standard deviation is the largest of three
        estimates of what the recorded landings do to the gain: the points' scatter about the line;
        the squeezes' (a squeeze's fingers land together: a standard error robust to that, by
        squeeze); and the replays' (the gain read against each replay's loads alone)."""
        if not self.holds:
            return None
        offsets = np.array(self.offsets(replayed), dtype=float)
        replays = (replayed, *others)
        loads, readings = [], []
        for name in self.holds:
            mask = self._hold_mask(name)
            recorded = self.observed.strains[mask]
            usable = np.all((recorded > 0) & (recorded < 255), axis=1)  # a clipped reading says nothing
            if not usable.any():
                continue
            held = np.array([np.nanmean(r.strains[mask][usable], axis=0) for r in replays])
            loads.append((held - np.array(REPLAY_OFFSETS)) / REPLAY_GAIN)
            readings.append(np.nanmean(recorded[usable], axis=0) - offsets)
        if not loads:
            return None
        each = np.stack(loads, axis=1)  # (replays, squeezes, fingers)
        load, reading = each.mean(axis=0), np.array(readings)
        keep = np.all(np.isfinite(each), axis=0) & np.isfinite(reading)
        if keep.sum() < 3 or np.ptp(load[keep]) < GAIN_LOAD_SPAN:
            return None
        gain = _through_origin(load, reading, keep)
        weight = np.where(keep, load, 0.0)
        residual = np.where(keep, reading - gain * load, 0.0)
        norm = float(np.sum(weight ** 2))
        estimates = [float(np.sqrt(np.sum(residual ** 2) / (keep.sum() - 1) / norm))]
        squeezes = int(np.sum(keep.any(axis=1)))
        if squeezes > 1:
            by_squeeze = np.sum(weight * residual, axis=1)
            estimates.append(float(np.sqrt(squeezes / (squeezes - 1) * np.sum(by_squeeze ** 2)) / norm))
        if len(replays) > 1:
            each_gain = [_through_origin(one, reading, keep) for one in each]
            estimates.append(float(np.std(each_gain, ddof=1) * np.sqrt(1 + 1 / len(replays))))
        return gain, max(estimates)

    def groups(self, replayed: Signals, gain: float = REPLAY_GAIN) -> dict[str, np.ndarray]:
        """The scaled residuals of one replay, by signal (module docstring); the squeezes' readings
        as a gauge of `gain` would give them."""
        recorded = self.observed
        if replayed.positions.shape != recorded.positions.shape:
            raise ValueError(f"the replay gave {replayed.positions.shape[0]} blocks, the log has "
                             f"{recorded.positions.shape[0]}")
        difference = (replayed.positions - recorded.positions) / (0.01 * self.ranges)
        groups = {}
        if self.finger_columns:
            groups["finger positions"] = difference[self.lift][:, self.finger_columns].ravel()
        if self.spread_column is not None:
            groups["spread positions"] = difference[self.spread_compared][:, self.spread_column]
        if self.holds:
            offsets = np.array(self.offsets(replayed))
            means = []
            for name in self.holds:
                mask = self._hold_mask(name)
                load = (np.nanmean(replayed.strains[mask], axis=0) - np.array(REPLAY_OFFSETS)) / REPLAY_GAIN
                means.append(offsets + gain * load - np.nanmean(recorded.strains[mask], axis=0))
            groups["strains"] = np.nan_to_num(np.concatenate(means))
        if self.timing and len(replayed.durations) == len(recorded.durations):
            groups["timing"] = (replayed.durations - recorded.durations) / TIMING_SCALE_S
        return groups

    def vector(self, replayed: Signals, groups=None) -> np.ndarray:
        """The residuals of `groups` (default: all) in one vector."""
        found = self.groups(replayed)
        return np.concatenate([found[name] for name in (groups or found) if name in found])

    def summary(self, replayed: Signals, gain: float = REPLAY_GAIN) -> dict[str, float]:
        """RMS of each signal in its own unit: position % of range per motor, strain counts, timing s."""
        recorded = self.observed
        out = {}
        difference = (replayed.positions - recorded.positions) / (0.01 * self.ranges)
        for motor, column in zip(recorded.motors, range(len(recorded.motors))):
            mask = self.sweep if motor == SPREAD_MOTOR else self.lift
            if mask.any() and column in (*self.finger_columns, self.spread_column):
                out[f"motor {motor} position, % of range"] = float(np.sqrt(np.mean(difference[mask, column] ** 2)))
        groups = self.groups(replayed, gain)
        if "strains" in groups:
            out["strain in the squeezes, counts"] = float(np.sqrt(np.mean(groups["strains"] ** 2)))
        if "timing" in groups:
            out["motion times, s"] = float(np.sqrt(np.mean((groups["timing"] * TIMING_SCALE_S) ** 2)))
        return out

    def position_rms(self, replayed: Signals) -> float:
        """The replay's position RMS over every motor's compared phases, % of the motor's range."""
        values = [value for name, value in self.summary(replayed).items() if name.endswith("% of range")]
        return float(np.sqrt(np.mean(np.square(values)))) if values else float("nan")
