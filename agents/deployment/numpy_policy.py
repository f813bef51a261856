"""The numpy-only policy file: `export_sb3_policy` writes a trained SB3 actor to .npz,
`NumpyPolicy` reads it back and runs it without torch.

An exported file holds the deterministic actor of a PPO or SAC `MlpPolicy` (Box observations and
actions): the weights of every linear layer, the hidden activation's name, the observation
normalisation of a `VecNormalize` used in training (identity when none was used), the action
space bounds and how the network's output becomes an action ("clip" for PPO's Gaussian mean,
"tanh" for SAC's squashed mean). Metadata (algorithm, env id and kwargs, whether the policy was
trained on privileged observations) is one JSON string, so `np.load(allow_pickle=False)` reads
every entry: the file carries no code.

This module imports numpy and gymnasium at import time; torch and SB3 only when exporting.
"""
from __future__ import annotations

import io
import json
import math
import os
import zipfile
import zlib
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from bh8_gym.agents.policy_io import (
    MAX_LAYERS,
    PolicyFileError,
    atomic_write_npz,
    check_metadata,
    read_policy_bytes,
)

FORMAT = "bh8-numpy-policy/1"
NPZ_MEMBER_LIMIT = 2 * MAX_LAYERS + 16  # an export's arrays: two per layer and eight others
NPZ_UNPACKED_LIMIT_BYTES = 64 << 20  # an export's arrays (bh8-gym's: about 200 KB)
NPZ_DTYPES = (np.dtype("<f8"), np.dtype("<f4"))
NPZ_TEXT_LIMIT_BYTES = 4 << 20  # the metadata JSON, as a numpy unicode string (4 bytes a character)

_ACTIVATIONS = {
    "tanh": np.tanh,
    "relu": lambda x: np.maximum(x, 0.0),
    "elu": lambda x: np.where(x > 0, x, np.expm1(np.minimum(x, 0.0))),
    # torch's default negative slope
    "leaky_relu": lambda x: np.where(x > 0, x, 0.01 * x),
    "silu": lambda x: x / (1.0 + np.exp(-x)),
}
# torch module class name -> our activation name
_TORCH_ACTIVATION_NAMES = {"Tanh": "tanh", "ReLU": "relu", "ELU": "elu", "LeakyReLU": "leaky_relu", "SiLU": "silu"}
OUTPUT_TRANSFORMS = ("clip", "tanh")


class NumpyPolicy:
    """A deterministic MLP actor read from an exported .npz; `predict(obs)` needs only numpy."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        arrays = read_npz(self.path)
        if "format" not in arrays or str(arrays["format"]) != FORMAT:
            raise PolicyFileError(f"{str(self.path)!r} is not a {FORMAT} file")
        try:
            self._read(arrays)
        except PolicyFileError:
            raise
        except (KeyError, ValueError, TypeError) as exc:  # json's errors are ValueErrors
            raise PolicyFileError(f"{str(self.path)!r} is damaged ({type(exc).__name__}: {exc}); export it again") from None
        except RecursionError:  # JSON nested past the interpreter's stack (an export's is one flat object)
            raise PolicyFileError(f"{str(self.path)!r} is damaged: its metadata is nested too deep; export it again") from None

    def _read(self, arrays: dict[str, np.ndarray]) -> None:
        self.metadata: dict[str, Any] = check_metadata(json.loads(str(arrays["metadata"])),
                                                        f"{str(self.path)!r}'s metadata")
        n_layers = self.metadata["n_layers"]
        if not (isinstance(n_layers, int) and not isinstance(n_layers, bool) and 1 <= n_layers <= MAX_LAYERS):
            raise PolicyFileError(f"{str(self.path)!r}: n_layers must be 1..{MAX_LAYERS}, got {n_layers!r}")
        self.weights = [arrays[f"layer{i}_weight"].astype(np.float64) for i in range(n_layers)]
        self.biases = [arrays[f"layer{i}_bias"].astype(np.float64) for i in range(n_layers)]
        activation = self.metadata["activation"]
        if activation not in _ACTIVATIONS:
            raise PolicyFileError(f"unknown activation {activation!r} in {str(self.path)!r}")
        self._activation = _ACTIVATIONS[activation]
        self.output_transform = self.metadata["output_transform"]
        if self.output_transform not in OUTPUT_TRANSFORMS:
            raise PolicyFileError(f"unknown output transform {self.output_transform!r} in {str(self.path)!r}")
        self.obs_mean = arrays["obs_mean"].astype(np.float64)
        with np.errstate(invalid="ignore"):  # a negative variance gives NaN here, refused by _check_shapes
            self.obs_std = np.sqrt(arrays["obs_var"].astype(np.float64) + float(arrays["obs_epsilon"]))
        self.obs_clip = float(arrays["obs_clip"])
        self.action_low = arrays["action_low"].astype(np.float64)
        self.action_high = arrays["action_high"].astype(np.float64)
        self._check_shapes()
        self.observation_dim = self.weights[0].shape[1]
        self.action_dim = self.weights[-1].shape[0]

    def _check_shapes(self) -> None:
        """The layers chain (each takes what the one before gives), the normalisation and action
        bounds fit the ends, and every number is finite: a file that fails here would fail (or
        act wildly) at its first prediction, after a deploy had already set up the hand."""
        def bad(what: str) -> PolicyFileError:
            return PolicyFileError(f"{str(self.path)!r} is damaged: {what}; export it again")

        width = None
        for index, (weight, bias) in enumerate(zip(self.weights, self.biases)):
            if weight.ndim != 2 or bias.shape != (weight.shape[0],) or 0 in weight.shape:
                raise bad(f"layer {index} has weights {weight.shape} and biases {bias.shape}")
            if width is not None and weight.shape[1] != width:
                raise bad(f"layer {index} takes {weight.shape[1]} inputs but layer {index - 1} gives {width}")
            width = weight.shape[0]
        inputs = self.weights[0].shape[1]
        for name, array, size in (("obs_mean", self.obs_mean, inputs), ("obs_var", self.obs_std, inputs),
                                  ("action_low", self.action_low, width), ("action_high", self.action_high, width)):
            if array.shape != (size,):
                raise bad(f"{name} has shape {array.shape}, the network's {'inputs' if size == inputs else 'outputs'} "
                          f"({size},)")
        numbers = (*self.weights, *self.biases, self.obs_mean, self.obs_std, self.action_low, self.action_high)
        if not all(np.all(np.isfinite(array)) for array in numbers) or not np.all(self.obs_std > 0.0):
            raise bad("a weight, bias, normalisation or bound is not a finite number (or a variance is not positive)")
        if not np.all(self.action_low <= self.action_high) or not self.obs_clip > 0.0:
            raise bad("action_low exceeds action_high, or obs_clip is not positive")

    @property
    def privileged(self) -> bool:
        """True when the policy was trained on observations a real hand cannot provide."""
        return bool(self.metadata.get("privileged", False))

    def predict(self, observation, state=None, episode_start=None, deterministic: bool = True):
        """The deterministic action for one observation (shape (obs_dim,)) or a batch (n, obs_dim).

        Returns (action, None) like SB3's `predict`, so evaluation code treats both alike. An
        exported file has no exploration noise: `deterministic=False` is refused, not ignored.
        """
        if not deterministic:
            raise ValueError(f"{str(self.path)!r} is an exported (deterministic) policy; deterministic=False "
                             "needs the SB3 .zip it was exported from")
        obs = np.asarray(observation, dtype=np.float64)
        single = obs.ndim == 1
        batch = obs.reshape(1, -1) if single else obs
        if batch.ndim != 2 or batch.shape[1] != self.observation_dim:
            raise ValueError(
                f"observation must have {self.observation_dim} values (or shape (n, {self.observation_dim})), "
                f"got shape {obs.shape}"
            )
        x = np.clip((batch - self.obs_mean) / self.obs_std, -self.obs_clip, self.obs_clip)
        last = len(self.weights) - 1
        for index, (weight, bias) in enumerate(zip(self.weights, self.biases)):
            x = x @ weight.T + bias
            if index < last:
                x = self._activation(x)
        if self.output_transform == "tanh":
            action = self.action_low + 0.5 * (np.tanh(x) + 1.0) * (self.action_high - self.action_low)
        else:
            action = np.clip(x, self.action_low, self.action_high)
        action = action.astype(np.float32)
        return (action[0] if single else action), None


def read_npz(path: Path) -> dict[str, np.ndarray]:
    """Every array of the policy file at `path`, read bounded (`read_policy_bytes`), with nothing
    unpickled and nothing allocated that the file does not hold (`_check_npz_members`);
    PolicyFileError for anything else."""
    data = read_policy_bytes(path)
    try:
        if not zipfile.is_zipfile(io.BytesIO(data)):  # np.load would try to unpickle it
            raise PolicyFileError(f"{str(path)!r} is not an .npz file (truncated, or something else); "
                                  "export the policy again")
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            _check_npz_members(archive, path)
        with np.load(io.BytesIO(data), allow_pickle=False) as arrays:
            return {name: arrays[name] for name in arrays.files}
    except PolicyFileError:
        raise
    # damaged members: BadZipFile, EOFError; an encrypted one: RuntimeError; an unknown method:
    # NotImplementedError; a bad compressed stream: zlib.error (members are checked stored)
    except (OSError, ValueError, EOFError, RuntimeError, NotImplementedError, zipfile.BadZipFile, zlib.error,
            MemoryError) as exc:
        raise PolicyFileError(f"cannot read policy file {str(path)!r}: {str(exc)[:200] or type(exc).__name__}") from None


def _check_npz_members(archive: zipfile.ZipFile, path: Path) -> None:
    """Refuse, before numpy reads it, an .npz that cannot be an export: more members than
    NPZ_MEMBER_LIMIT, a compressed member (numpy's savez stores them: nothing to inflate), more than
    NPZ_UNPACKED_LIMIT_BYTES unpacked, an array that is not float32/float64 or a short string (an
    int8 array grows eightfold as float64: an 880 KB file took gigabytes), or a member whose .npy
    header declares other than the data it holds (numpy allocates what the header declares before
    reading: a header declaring 10^11 floats was an allocation error)."""
    members = archive.infolist()
    if len(members) > NPZ_MEMBER_LIMIT:
        raise PolicyFileError(f"{str(path)!r} holds {len(members)} arrays, more than an export's {NPZ_MEMBER_LIMIT}: "
                              "not an exported policy")
    if any(member.compress_type != zipfile.ZIP_STORED for member in members):
        raise PolicyFileError(f"{str(path)!r} holds compressed arrays, which an export (numpy's savez) never "
                              "writes: not an exported policy")
    if sum(member.file_size for member in members) > NPZ_UNPACKED_LIMIT_BYTES:
        raise PolicyFileError(f"{str(path)!r} unpacks to more than {NPZ_UNPACKED_LIMIT_BYTES >> 20} MB: "
                              "not an exported policy")
    readers = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
    for member in members:
        with archive.open(member) as handle:
            version = np.lib.format.read_magic(handle)
            if version not in readers:
                raise PolicyFileError(f"{str(path)!r}: {member.filename!r} is an .npy of version {version}, "
                                      "which numpy's savez does not write: not an exported policy")
            shape, _, dtype = readers[version](handle)
            declared, held = math.prod(shape) * dtype.itemsize, member.file_size - handle.tell()
        if dtype not in NPZ_DTYPES and not (dtype.kind == "U" and declared <= NPZ_TEXT_LIMIT_BYTES):
            raise PolicyFileError(f"{str(path)!r}: {member.filename!r} holds {dtype} values; an export holds "
                                  "float64 or float32 arrays and short strings")
        if declared != held:
            raise PolicyFileError(f"{str(path)!r} is damaged: {member.filename!r} declares {declared} bytes of "
                                  f"data but holds {held}; export it again")


def _linear_chain(modules) -> tuple[list, list[str]]:
    """The Linear layers of a Sequential-like chain and the activation names between them."""
    import torch.nn as nn

    linears, activations = [], []
    for module in modules:
        if isinstance(module, nn.Linear):
            linears.append(module)
        elif isinstance(module, nn.Sequential):
            sub_linears, sub_acts = _linear_chain(module)
            linears += sub_linears
            activations += sub_acts
        elif type(module).__name__ in _TORCH_ACTIVATION_NAMES:
            activations.append(_TORCH_ACTIVATION_NAMES[type(module).__name__])
        elif isinstance(module, (nn.Identity, nn.Flatten)):
            continue
        else:
            raise PolicyFileError(f"cannot export layer {type(module).__name__}: only Linear and "
                                  f"{sorted(_TORCH_ACTIVATION_NAMES)} activations are supported")
    return linears, activations


def export_sb3_policy(model, path: str | os.PathLike, vec_normalize=None, metadata: dict | None = None) -> Path:
    """Write `model`'s deterministic actor (SB3 PPO or SAC, MlpPolicy, Box spaces) to `path` (.npz).

    `vec_normalize`: the training `VecNormalize` (its observation statistics are baked in).
    `metadata`: extra JSON-serialisable facts (env id, env kwargs, privileged, ...).
    """
    from stable_baselines3 import PPO, SAC

    policy = model.policy
    if not isinstance(model.observation_space, gym.spaces.Box) or len(model.observation_space.shape) != 1:
        raise PolicyFileError(
            f"only flat Box observations can be exported, got {model.observation_space}"
            " (privileged Dict observations are simulation-only)"
        )
    if not isinstance(model.action_space, gym.spaces.Box):
        raise PolicyFileError(f"only Box action spaces can be exported, got {model.action_space}")
    # gSDE only changes PPO's exploration noise: the deterministic action is still the mean (squashed
    # by tanh when the policy squashes its output), so such policies export like the others.
    # SAC's gSDE actor clips its mean with a Hardtanh before the tanh, which this format lacks.
    if isinstance(model, SAC) and getattr(model, "use_sde", False):
        raise PolicyFileError("SAC policies trained with gSDE (use_sde=True) cannot be exported; "
                              "train SAC without use_sde")
    from bh8_gym.agents.asymmetric import host_observation_count

    # An asymmetric actor zeroes the privileged entries: keep only the host columns of its first layer.
    host_observations = host_observation_count(model)
    if isinstance(model, PPO):
        chain = [*policy.mlp_extractor.policy_net, policy.action_net]
        output_transform = "tanh" if policy.squash_output else "clip"
    elif isinstance(model, SAC):
        chain = [*policy.actor.latent_pi, policy.actor.mu]
        output_transform = "tanh"
    else:
        raise PolicyFileError(f"cannot export {type(model).__name__}; supported: PPO, SAC")
    linears, activations = _linear_chain(chain)
    if len(set(activations)) > 1 or len(activations) != len(linears) - 1:
        raise PolicyFileError(f"expected one activation between consecutive linear layers, got {activations}")
    obs_dim = host_observations or model.observation_space.shape[0]
    if vec_normalize is not None and vec_normalize.norm_obs:
        obs_mean = np.asarray(vec_normalize.obs_rms.mean, dtype=np.float64)[:obs_dim]
        obs_var = np.asarray(vec_normalize.obs_rms.var, dtype=np.float64)[:obs_dim]
        obs_epsilon, obs_clip = float(vec_normalize.epsilon), float(vec_normalize.clip_obs)
    else:
        # identity: (obs - 0) / sqrt(1 - 0) and no clipping
        obs_mean, obs_var = np.zeros(obs_dim), np.ones(obs_dim)
        obs_epsilon, obs_clip = 0.0, np.inf
    meta = {
        "algorithm": type(model).__name__,
        "activation": activations[0] if activations else "tanh",
        "n_layers": len(linears),
        "output_transform": output_transform,
        "num_timesteps": int(model.num_timesteps),
        **(metadata or {}),
    }
    arrays: dict[str, np.ndarray] = {
        "format": np.array(FORMAT),
        "metadata": np.array(json.dumps(meta, sort_keys=True)),
        "obs_mean": obs_mean,
        "obs_var": obs_var,
        "obs_epsilon": np.array(obs_epsilon),
        "obs_clip": np.array(obs_clip),
        "action_low": np.asarray(model.action_space.low, dtype=np.float64),
        "action_high": np.asarray(model.action_space.high, dtype=np.float64),
    }
    for index, layer in enumerate(linears):
        weight = layer.weight.detach().cpu().numpy().astype(np.float64)
        arrays[f"layer{index}_weight"] = weight[:, :obs_dim] if index == 0 else weight
        arrays[f"layer{index}_bias"] = layer.bias.detach().cpu().numpy().astype(np.float64)
    path = Path(path)
    atomic_write_npz(path, arrays)
    return path
