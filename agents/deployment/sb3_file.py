"""An SB3 `.zip` read as a policy, with nothing unpickled unless the caller trusts the file.

Its `data` JSON stores every setting that is not plain JSON
(policy class, spaces, schedules, buffer classes) as a cloudpickle, and SB3's loader unpickles
them, which runs whatever code the file carries. `SB3Policy` therefore never lets SB3 unpickle
anything unless the caller trusts the file (`trust=True`, the commands' `--trust-file`): each
pickled entry is replaced by a stand-in rebuilt from the plain JSON SB3 writes beside it
(`SB3_STAND_INS`: the policy class and torch classes from an allowlist, Box spaces from their
bounds, schedules by constants, which prediction does not use), and a file carrying any other
pickled entry is refused. The weights are read by torch with `weights_only=True` either way.

Imports numpy and gymnasium at import time; torch and SB3 only when a model is loaded.
"""
from __future__ import annotations

import io
import json
import math
import pickle
import re
import zipfile
import zlib
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from bh8_gym.agents.policy_io import MAX_LAYERS, PolicyFileError, find_run_metadata, read_policy_bytes

SB3_DATA_LIMIT_BYTES = 16 << 20  # the `data` JSON of an SB3 .zip
# What an SB3 .zip may make SB3 build when it is loaded (bh8-gym's networks have about 20 k
# parameters, two layers of 128; its buffers about 10 M numbers); _check_sb3_sizes.
SB3_LAYER_WIDTH_LIMIT = 4096
SB3_PARAMETER_LIMIT = 1 << 25  # 128 MB of float32 weights
SB3_BUFFER_VALUE_LIMIT = 1 << 28  # numbers in the rollout or replay buffer (1 GB of float32)
SB3_SPACE_LIMIT = 1 << 16  # entries of an observation or action


_CLASS_REPR = re.compile(r"<class '([\w.]+)'>")
_INIT_OF = re.compile(r"<function (\w+)\.__init__ ")
# Pickled entries of an SB3 `data` JSON that prediction does not use: a constant stands in.
_SCHEDULE_KEYS = ("learning_rate", "lr_schedule", "clip_range", "clip_range_vf")
# Pickled entries SB3 replaces with its default when None (the buffer classes), converts
# (train_freq), or keeps only for training: the last observations, episode buffers, action noise.
_DEFAULTED_KEYS = {"rollout_buffer_class": None, "replay_buffer_class": None, "train_freq": (1, "step"),
                   "_last_obs": None, "_last_episode_starts": None, "_last_original_obs": None,
                   "ep_info_buffer": None, "ep_success_buffer": None, "action_noise": None}
SB3_STAND_INS = ("policy_class", "policy_kwargs", "observation_space", "action_space", *_SCHEDULE_KEYS, *_DEFAULTED_KEYS)


def _allowed_classes() -> dict[str, type]:
    """Classes a policy's settings may name (module.qualname as SB3's JSON prints them)."""
    import torch
    from stable_baselines3.common.policies import ActorCriticPolicy
    from stable_baselines3.common.torch_layers import FlattenExtractor
    from stable_baselines3.sac.policies import SACPolicy

    from bh8_gym.agents.asymmetric import AsymmetricActorCriticPolicy

    classes = [ActorCriticPolicy, SACPolicy, AsymmetricActorCriticPolicy, FlattenExtractor, torch.nn.Tanh,
               torch.nn.ReLU, torch.nn.ELU, torch.nn.LeakyReLU, torch.nn.SiLU, torch.nn.GELU, torch.optim.Adam,
               torch.optim.AdamW, torch.optim.RMSprop, torch.optim.SGD]
    return {f"{cls.__module__}.{cls.__qualname__}": cls for cls in classes}


# What reading a damaged member can raise: BadZipFile and EOFError (cut short or a bad CRC), zlib.error,
# lzma/bz2's OSError and EOFError (a bad stream), NotImplementedError (an unknown method),
# RuntimeError (an encrypted member), MemoryError (a stream past what it says).
ZIP_ERRORS = (zipfile.BadZipFile, EOFError, OSError, zlib.error, NotImplementedError, RuntimeError, MemoryError,
              ValueError, RecursionError)


def _sb3_data(raw: bytes, path: Path) -> tuple[dict | None, dict[str, int]]:
    """An SB3 .zip's `data` JSON (None if it has none: not an SB3 model, SB3's own error says so)
    and the unpacked size of each of its members, read without unpickling."""
    try:
        with zipfile.ZipFile(io.BytesIO(raw)) as archive:
            sizes = {member.filename: member.file_size for member in archive.infolist()}
            if "data" not in sizes:
                return None, sizes
            with archive.open("data") as member:
                text = member.read(SB3_DATA_LIMIT_BYTES + 1)
        if len(text) > SB3_DATA_LIMIT_BYTES:
            raise PolicyFileError(f"{str(path)!r}: its data is larger than {SB3_DATA_LIMIT_BYTES >> 20} MB")
        data = json.loads(text)
    except PolicyFileError:
        raise
    except ZIP_ERRORS as error:
        raise PolicyFileError(f"cannot read SB3 model {str(path)!r}: {str(error)[:200] or type(error).__name__}") from None
    if not isinstance(data, dict):
        raise PolicyFileError(f"cannot read SB3 model {str(path)!r}: its data is not a JSON object")
    return data, sizes


def _check_sb3_sizes(data: dict, member_sizes: dict[str, int], path: Path) -> None:
    """PolicyFileError unless what SB3 builds when it loads the model `data` describes is bounded,
    checked before it builds anything (a 20 KB .zip asking for net_arch [12000, 12000] took minutes
    and 3 GB; n_steps 1e12 was an allocation error): the spaces, the buffer SB3 allocates (rollout:
    n_steps x n_envs transitions; replay: buffer_size), every layer's width and the network's depth,
    and the parameters, which must fit in the weights the file stores (4 bytes each at least)."""
    def bad(what: str) -> PolicyFileError:
        return PolicyFileError(f"{str(path)!r}: {what}; not a model bh8-gym loads")

    weights_bytes = member_sizes.get("policy.pth", 0)

    def count(where: dict, key: str, default: int, limit: int) -> int:
        value = where.get(key, default)
        if not (isinstance(value, int) and not isinstance(value, bool) and 1 <= value <= limit):
            raise bad(f"{key} must be a whole number from 1 to {limit}, got {value!r:.40}")
        return value

    def space_size(key: str) -> int:
        shape = (data.get(key) or {}).get("_shape") if isinstance(data.get(key), dict) else None
        if not (isinstance(shape, list) and all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in shape)
                and math.prod(shape) <= SB3_SPACE_LIMIT):
            raise bad(f"its {key} must have a shape of at most {SB3_SPACE_LIMIT} entries, got {shape!r:.60}")
        return math.prod(shape)

    observations, actions = space_size("observation_space"), space_size("action_space")
    off_policy = "buffer_size" in data  # SAC; PPO has n_steps
    if off_policy:
        transitions = count(data, "buffer_size", 1, SB3_BUFFER_VALUE_LIMIT)
    else:
        transitions = count(data, "n_steps", 1, SB3_BUFFER_VALUE_LIMIT) * count(data, "n_envs", 1, SB3_BUFFER_VALUE_LIMIT)
    if transitions * (observations + actions) > SB3_BUFFER_VALUE_LIMIT:
        raise bad(f"its {'replay' if off_policy else 'rollout'} buffer would hold {transitions} transitions of "
                  f"{observations + actions} numbers, more than {SB3_BUFFER_VALUE_LIMIT}")
    kwargs = data.get("policy_kwargs") if isinstance(data.get("policy_kwargs"), dict) else {}
    net_arch = kwargs.get("net_arch")
    nets = net_arch if isinstance(net_arch, dict) else {"pi": net_arch, ("qf" if off_policy else "vf"): net_arch}
    parameters = 0
    for name, widths in nets.items():
        if widths is None:
            widths = [256, 256] if off_policy else [64, 64]  # SB3's defaults
        if not (isinstance(widths, list) and len(widths) <= MAX_LAYERS and all(
                isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= SB3_LAYER_WIDTH_LIMIT for v in widths)):
            raise bad(f"its net_arch must list at most {MAX_LAYERS} layer widths from 1 to {SB3_LAYER_WIDTH_LIMIT}, "
                      f"got {widths!r:.60}")
        inputs, outputs, copies = {"pi": (observations, actions, 1), "vf": (observations, 1, 1),
                                   # SAC: n_critics Q-networks and their target copies
                                   "qf": (observations + actions, 1, 2 * count(kwargs, "n_critics", 2, 64))}.get(
                                      name, (observations, 1, 1))
        sizes = [inputs, *widths, outputs]
        parameters += copies * sum((a + 1) * b for a, b in zip(sizes, sizes[1:]))
    if parameters > SB3_PARAMETER_LIMIT or 4 * parameters > weights_bytes:
        raise bad(f"its net_arch makes a network of {parameters} parameters, but the file stores "
                  f"{weights_bytes} bytes of weights (and bh8-gym loads at most {SB3_PARAMETER_LIMIT})")
    # Each member holds at most the network's tensors (the optimiser: two more per parameter) in
    # float64 and torch's framing: a 1 MB .zip unpacking a 0.96 GB tensor is refused unread.
    allowed = 3 * 8 * parameters + (1 << 20)
    oversized = sorted(name for name, size in member_sizes.items() if name != "data" and size > allowed)
    if oversized:
        raise bad(f"its {', '.join(oversized)} unpack to more than a network of {parameters} parameters needs "
                  f"({allowed} bytes)")


def _stand_ins(data: dict, path: Path) -> dict[str, Any]:
    """For an SB3 .zip's `data` JSON: a stand-in for every pickled entry, so that SB3 unpickles
    nothing (`custom_objects`). PolicyFileError for an entry that has none."""
    pickled = {key: value for key, value in data.items() if isinstance(value, dict) and ":serialized:" in value}
    unknown = sorted(set(pickled) - set(SB3_STAND_INS))
    if unknown:
        raise PolicyFileError(_untrusted(path, f"pickled Python objects in {unknown}, which only unpickling can rebuild"))
    classes = _allowed_classes()
    stand_ins: dict[str, Any] = {}
    for key, entry in pickled.items():
        if key in _SCHEDULE_KEYS:
            from stable_baselines3.common.utils import FloatSchedule

            stand_ins[key] = FloatSchedule(0.0)
        elif key in _DEFAULTED_KEYS:
            stand_ins[key] = _DEFAULTED_KEYS[key]
        elif key == "policy_class":
            found = _INIT_OF.match(str(entry.get("__init__", "")))
            name = f"{entry.get('__module__')}.{found.group(1) if found else '?'}"
            if name not in classes:
                raise PolicyFileError(_untrusted(path, f"the policy class {name}, which is not one bh8-gym trains"))
            stand_ins[key] = classes[name]
        elif key == "policy_kwargs":
            stand_ins[key] = {name: _plain_setting(value, classes, path) for name, value in entry.items()
                              if not name.startswith(":")}
        else:  # observation_space, action_space
            stand_ins[key] = _box_from_json(key, entry, path)
    return stand_ins


def _plain_setting(value, classes: dict[str, type], path: Path):
    """A policy_kwargs item as SB3's JSON shows it: JSON as is; "<class 'x.Y'>" from the allowlist."""
    if isinstance(value, str):
        found = _CLASS_REPR.fullmatch(value)
        if found:
            if found.group(1) not in classes:
                raise PolicyFileError(_untrusted(path, f"the class {found.group(1)} in its policy_kwargs"))
            return classes[found.group(1)]
    return value


def _box_from_json(key: str, entry: dict, path: Path):
    """A gymnasium Box from the plain fields SB3 writes beside a pickled one (dtype, shape, bounds)."""
    def numbers(text) -> np.ndarray:
        if not isinstance(text, str) or "..." in text:
            raise ValueError
        return np.array([float(v) for v in text.replace("[", " ").replace("]", " ").split()])

    try:
        if entry.get(":type:") != "<class 'gymnasium.spaces.box.Box'>":
            raise ValueError
        shape = tuple(int(v) for v in entry["_shape"])
        dtype = np.dtype(entry["dtype"])
        low, high = numbers(entry["low"]).reshape(shape), numbers(entry["high"]).reshape(shape)
        if dtype.kind == "f":  # float32 bounds for a float32 space: Box warns about float64 ones
            low, high = low.astype(dtype), high.astype(dtype)
        return gym.spaces.Box(low, high, shape=shape, dtype=dtype)
    except (KeyError, TypeError, ValueError):
        raise PolicyFileError(_untrusted(path, f"an {key} that is not a Box bh8-gym can rebuild")) from None


def _untrusted(path: Path, what: str) -> str:
    return (f"{str(path)!r} carries {what}. Unpickling runs whatever code the file holds: pass --trust-file "
            "(trust=True) only for a file you made or trust, or deploy its pickle-free export (bh8 export)")


class SB3Policy:
    """An SB3 model with the same `predict` and `metadata` as `NumpyPolicy` (needs torch).

    Unless `trust`, SB3 unpickles nothing from the file (module docstring: stand-ins)."""

    def __init__(self, path: Path, device: str = "cpu", trust: bool = False):
        from stable_baselines3 import PPO, SAC

        algorithms = {"PPO": PPO, "SAC": SAC}
        self.path = path
        self.metadata = find_run_metadata(path)
        name = self.metadata.get("algorithm")
        if name is not None and name not in algorithms:
            raise PolicyFileError(f"{str(path)!r}: unsupported algorithm {name!r}")
        candidates = [algorithms[name]] if name else [PPO, SAC]
        raw = read_policy_bytes(Path(path))
        data, sizes = _sb3_data(raw, Path(path))
        if data is not None:
            _check_sb3_sizes(data, sizes, Path(path))
        custom_objects = None if trust or data is None else _stand_ins(data, Path(path))
        errors = []
        for algorithm in candidates:
            try:
                self.model = algorithm.load(io.BytesIO(raw), device=device, custom_objects=custom_objects)
                break
            except pickle.UnpicklingError:
                # torch's weights-only loader refused a pickled object among the weights; its message
                # advises loading with weights_only=False, which would run it: not said here
                raise PolicyFileError(f"{str(path)!r}: its weights hold pickled Python objects besides tensors, "
                                      "which bh8-gym never unpickles (not even with --trust-file); not a model "
                                      "bh8-gym saved") from None
            # AssertionError: SB3's "No data found in the saved file" (a zip that is not an SB3 model);
            # AttributeError: a zip without its policy.pth
            except (AssertionError, AttributeError, KeyError, IndexError, TypeError, *ZIP_ERRORS) as exc:
                errors.append(f"{algorithm.__name__}: {str(exc)[:200] or type(exc).__name__}")
        else:
            raise PolicyFileError(f"cannot load SB3 model {str(path)!r}: {'; '.join(errors)}")
        self.metadata.setdefault("algorithm", type(self.model).__name__)
        from bh8_gym.agents.asymmetric import HostObservationModel, host_observation_count

        host_observations = host_observation_count(self.model)
        # An asymmetric model's actor takes host observations; its critic's extra inputs are not needed.
        self._predictor = HostObservationModel(self.model) if host_observations else self.model
        self.observation_dim = host_observations or int(np.prod(self.model.observation_space.shape or (0,)))
        self.action_dim = int(np.prod(self.model.action_space.shape or (0,)))

    @property
    def privileged(self) -> bool:
        return bool(self.metadata.get("privileged", False))

    def predict(self, observation, state=None, episode_start=None, deterministic: bool = True):
        return self._predictor.predict(observation, deterministic=deterministic)

    def reset_noise(self) -> None:
        """Draw new exploration noise for `deterministic=False`. Needed once per episode with gSDE
        (use_sde): SB3 draws its exploration matrix only here, so without a new draw every
        stochastic episode repeats one fixed perturbation of the policy."""
        if getattr(self.model, "use_sde", False):
            self.model.policy.reset_noise()
