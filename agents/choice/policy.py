"""The grasp choice as a policy: probe, decide, grasp; and, if told, check, reopen and try again.

`GraspChoicePolicy` is host-side, like the scripts it runs (`agents/grasps.py`): it reads only the
feedback blocks, so `bh8 eval` runs it on the simulated hand and `bh8 deploy` on a real one, with
the same bytes for the same blocks.

1. **Probe.** From the episode's first block the `probe` grasp closes the fingers (by default
   `loop-v70`, the best single script of the ceiling family: probing costs nothing when the choice
   keeps it). Every candidate grasp is fed each block too, so the one chosen continues from the
   state it would have reached.
2. **Decide.** At `decision_seconds` on the host's clock (cycles × the nominal cycle time) the
   selector (`model.SuccessModel`) scores every candidate from the features
   (`features.ChoiceFeatures`) and the best one drives the fingers from then on: a discrete choice.
3. **Second chance** (`retries` > 0). At `check_seconds` the failure predictor scores the chosen
   grasp again from the longer history; below `retry_threshold` the fingers reopen to
   `reopen_fraction` of where they were and the attempt starts over: probe, decide. The arm must
   then give the hand the longer grasp phase the env's `arm.grasp_seconds` sets.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from bh8_gym.action_bytes import bytes_to_unit
from bh8_gym.agents.choice.features import ChoiceFeatures
from bh8_gym.agents.choice.model import SuccessModel
from bh8_gym.agents.grasps import CONTINUATIONS, FAMILY, SqueezeBaseline, _LoopScript, clamp, host_side, make_script
from bh8_gym.protocol import FINGER_MOTORS, SPREAD_MOTOR

FORMAT = "bh8-grasp-choice/1"
MAX_GRASPS = 16
MAX_RETRIES = 3


def known_grasp(name: str) -> bool:
    return name in FAMILY or name in CONTINUATIONS


@dataclass(frozen=True)
class ChoiceSettings:
    """What the choice does and when (module docstring); checked on construction."""

    probe: str = "loop-v70"
    grasps: tuple[str, ...] = ("loop-v70", "squeeze", "squeeze-t225", "loop")
    decision_seconds: float = 0.65  # host clock from the episode's (or a retry's) first block
    retries: int = 0
    check_seconds: float = 0.75  # host clock from the attempt's first block
    retry_threshold: float = 0.3
    reopen_fraction: float = 0.5  # of each finger's position when the reopen starts
    reopen_velocity: int = 100  # LCV bytes

    def __post_init__(self):
        object.__setattr__(self, "grasps", tuple(self.grasps))
        if not isinstance(self.probe, str) or not known_grasp(self.probe) or self.probe in CONTINUATIONS:
            raise ValueError(f"probe must name a grasp of the family ({', '.join(FAMILY)}), got {self.probe!r}")
        if not 1 <= len(self.grasps) <= MAX_GRASPS or len(set(self.grasps)) != len(self.grasps):
            raise ValueError(f"grasps must be 1 to {MAX_GRASPS} different names, got {list(self.grasps)!r}")
        for name in self.grasps:
            if not isinstance(name, str) or not known_grasp(name):
                raise ValueError(f"unknown grasp {name!r} (the family: {', '.join(FAMILY)}; continuations: "
                                 f"{', '.join(CONTINUATIONS)})")
        for name in ("decision_seconds", "check_seconds"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and not isinstance(value, bool) and 0.0 < value <= 10.0):
                raise ValueError(f"{name} must be in (0, 10] seconds, got {value!r}")
        if not (isinstance(self.retries, int) and not isinstance(self.retries, bool) and 0 <= self.retries <= MAX_RETRIES):
            raise ValueError(f"retries must be an integer 0..{MAX_RETRIES}, got {self.retries!r}")
        if self.retries and not self.check_seconds > self.decision_seconds:
            raise ValueError(f"check_seconds ({self.check_seconds}) must come after decision_seconds "
                             f"({self.decision_seconds})")
        for name in ("retry_threshold", "reopen_fraction"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and not isinstance(value, bool) and 0.0 <= value <= 1.0):
                raise ValueError(f"{name} must be in [0, 1], got {value!r}")
        if not (isinstance(self.reopen_velocity, int) and 1 <= self.reopen_velocity <= 127):
            raise ValueError(f"reopen_velocity must be an LCV byte 1..127, got {self.reopen_velocity!r}")


class Reopen(_LoopScript):
    """Open every finger (LCV −velocity, gain 255) to `fraction` of where it was when the reopen began,
    the spread held: the start of a second attempt."""

    def __init__(self, host, velocity: int, fraction: float, spread_gain: float = 0.1):
        super().__init__(host)
        fields = self.layout.feedback_fields
        self._positions = [fields.index((m, "LFAP")) for m in FINGER_MOTORS]
        self._spread = fields.index((SPREAD_MOTOR, "LFAP"))
        self.velocity, self.fraction, self.spread_gain = velocity, fraction, spread_gain
        self.start: list[int] | None = None

    def act(self, values) -> np.ndarray:
        if self.start is None:
            self.start = [values[i] for i in self._positions]
        for index, (motor, name) in enumerate(self._control_fields):
            if motor == SPREAD_MOTOR:
                self._bytes[index] = (int(clamp(-self.spread_gain * values[self._spread], -127, 127))
                                      if name == "LCV" else 255)
            else:
                finger = FINGER_MOTORS.index(motor)
                opening = values[self._positions[finger]] > self.fraction * self.start[finger]
                self._bytes[index] = (-self.velocity if opening else 0) if name == "LCV" else 255
        return self._action()

    def done(self, values) -> bool:
        return self.start is not None and all(values[i] <= self.fraction * s + 1 for i, s in zip(self._positions, self.start))


class GraspChoicePolicy:
    """Probe, decide, grasp (module docstring). Runs like the scripts: `reset(env)` at each episode,
    `act(observation, info)` each cycle with `info["feedback_block"]`; `needs_feedback` tells
    `bh8 eval` and `bh8 deploy` so. `decisions` lists what it did this episode."""

    needs_feedback = True
    privileged = False

    def __init__(self, settings: ChoiceSettings, selector: SuccessModel, predictor: SuccessModel | None = None,
                 metadata: dict | None = None):
        self.settings = settings
        if selector.outputs != len(settings.grasps):
            raise ValueError(f"the selector scores {selector.outputs} grasps, the settings name {len(settings.grasps)}")
        if predictor is not None and (predictor.outputs != len(settings.grasps) or predictor.inputs != selector.inputs):
            raise ValueError("the failure predictor must score the same grasps from the same features as the selector")
        if settings.retries and predictor is None:
            raise ValueError("retries need a failure predictor")
        self.selector, self.predictor = selector, predictor
        self.metadata = dict(metadata or {})
        self._host = None

    # ------------------------------------------------------------------ running
    def bind(self, env) -> None:
        """Build the scripts and features for `env` (an env or its LoopInterface)."""
        host = host_side(env)
        self._host = host
        self.layout = host.layout
        self.features = ChoiceFeatures(self.layout.feedback_fields, host.episode_seconds)
        if len(self.features.names) != self.selector.inputs:
            raise ValueError(f"the selector takes {self.selector.inputs} features; this env's feedback gives "
                             f"{len(self.features.names)}")
        self.cycle_seconds = float(host.cycle_seconds)
        self.observation_dim = host.host_observation_size
        self.action_dim = len(self.layout.control_fields)
        self.reset()

    def reset(self, env=None) -> None:
        """A new episode (binding to `env` first if it is not the one bound)."""
        if env is not None and host_side(env) is not self._host:
            self.bind(env)
            return
        if self._host is None:
            raise RuntimeError("GraspChoicePolicy.reset() before bind(env)")
        self.features.reset()
        self.cycles = 0
        self.decisions: list[dict] = []
        self._begin_attempt()

    def _begin_attempt(self) -> None:
        settings, host = self.settings, self._host
        self.phase = "probe"
        self.attempt_cycles = 0
        self.grasps = [make_script(name, host) for name in settings.grasps]
        self.probe = (self.grasps[settings.grasps.index(settings.probe)] if settings.probe in settings.grasps
                      else make_script(settings.probe, host))
        self.touch = SqueezeBaseline(host)  # its contact rule: which fingers touch
        self.chosen: int | None = None
        self.reopen: Reopen | None = None

    @property
    def elapsed(self) -> float:
        return self.cycles * self.cycle_seconds

    def act(self, observation, info) -> np.ndarray:
        values = self.layout.decode_feedback(info["feedback_block"])
        self.cycles += 1
        self.features.observe(values, self.elapsed)
        if self.phase == "reopen":
            if not self.reopen.done(values):
                return self.reopen.act(values)
            self.features.new_attempt()
            self._begin_attempt()
        self.attempt_cycles += 1
        attempt_elapsed = self.attempt_cycles * self.cycle_seconds
        if self.phase == "probe":
            self.touch.act(observation, info)
            actions = self.last_actions = [grasp.act(observation, info) for grasp in self.grasps]
            probe = (actions[self.settings.grasps.index(self.settings.probe)] if self.settings.probe in self.settings.grasps
                     else self.probe.act(observation, info))
            if attempt_elapsed < self.settings.decision_seconds:
                return probe
            self.decided_features = self.decision_features()
            scores = self.selector(self.decided_features)
            self.chosen = int(np.argmax(scores))
            self.phase = "grasp"
            self.decisions.append({"at": self.elapsed, "grasp": self.settings.grasps[self.chosen],
                                   "scores": [round(float(s), 4) for s in scores]})
            return actions[self.chosen]
        settings = self.settings
        if (self.phase == "grasp" and self.features.attempt < settings.retries
                and attempt_elapsed >= settings.check_seconds):
            self.phase = "held"  # checked once per attempt
            chance = float(self.predictor(self.decision_features())[self.chosen])
            self.decisions.append({"at": self.elapsed, "check": self.settings.grasps[self.chosen], "chance": round(chance, 4)})
            if chance < settings.retry_threshold:
                self.phase = "reopen"
                self.reopen = Reopen(self._host, settings.reopen_velocity, settings.reopen_fraction)
                return self.reopen.act(values)
        return self.grasps[self.chosen].act(observation, info)

    def decision_features(self) -> np.ndarray:
        return self.features.vector(self.touch.contact.values())

    def predict(self, observation, state=None, episode_start=None, deterministic: bool = True):
        raise TypeError("a grasp-choice policy acts on feedback blocks: call act(observation, info) "
                        "(bh8 eval and bh8 deploy do)")

    def stop_action(self) -> np.ndarray:
        """Zero velocity and gain in the float action space (what a test run of the policy can send)."""
        space = self._host.action_space
        return bytes_to_unit(np.zeros(space.shape), space.low.astype(float), space.high.astype(float))

    # ------------------------------------------------------------------ the file
    def arrays(self) -> dict[str, np.ndarray]:
        metadata = {**self.metadata, "settings": asdict(self.settings),
                    "selector_layers": len(self.selector.weights),
                    "predictor_layers": 0 if self.predictor is None else len(self.predictor.weights),
                    "privileged": False}
        out = {"format": np.array(FORMAT), "metadata": np.array(json.dumps(metadata))}
        out.update(self.selector.arrays("selector"))
        if self.predictor is not None:
            out.update(self.predictor.arrays("predictor"))
        return out

    @classmethod
    def from_arrays(cls, arrays: dict, where: str = "the policy file") -> "GraspChoicePolicy":
        """A policy from a file's arrays (ValueError naming what is wrong)."""
        metadata = json.loads(str(arrays["metadata"]))
        if not isinstance(metadata, dict) or not isinstance(metadata.get("settings"), dict):
            raise ValueError(f"{where}: its metadata is not a JSON object with settings")
        settings = metadata["settings"]
        unknown = set(settings) - set(ChoiceSettings.__dataclass_fields__)
        if unknown:
            raise ValueError(f"{where}: unknown settings {sorted(unknown)}")
        if not isinstance(settings.get("grasps", []), list):
            raise ValueError(f"{where}: grasps must be a list of names")
        choice = ChoiceSettings(**settings)
        selector = SuccessModel.from_arrays(arrays, "selector", metadata.get("selector_layers"))
        layers = metadata.get("predictor_layers", 0)
        if not (isinstance(layers, int) and not isinstance(layers, bool) and layers >= 0):
            raise ValueError(f"{where}: predictor_layers must be a count of layers (0: no predictor), got {layers!r}")
        predictor = SuccessModel.from_arrays(arrays, "predictor", layers) if layers else None
        return cls(choice, selector, predictor, {k: v for k, v in metadata.items()
                                                 if k not in ("settings", "selector_layers", "predictor_layers")})

    def save(self, path) -> Path:
        from bh8_gym.atomic_files import atomic_write_npz

        path = Path(path)
        atomic_write_npz(path, self.arrays())
        return path


def probe_policy(settings: ChoiceSettings, features: int) -> GraspChoicePolicy:
    """A policy that always keeps the probe (the selector scores it 1, the rest 0): the labelling run's
    stand-in before any selector exists, and the reference a trained selector must beat."""
    keep = np.array([1.0 if name == settings.probe else 0.0 for name in settings.grasps])
    selector = SuccessModel(np.zeros(features), np.ones(features), [np.zeros((features, len(keep)))], [keep])
    return GraspChoicePolicy(settings, selector)

