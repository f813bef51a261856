"""Numpy-only policy files: export a trained SB3 policy to .npz and run it without torch.

An exported file holds the deterministic actor of a PPO or SAC `MlpPolicy` (Box observations and
actions): the weights of every linear layer, the hidden activation's name, the observation
normalisation of a `VecNormalize` used in training (identity when none was used), the action
space bounds and how the network's output becomes an action ("clip" for PPO's Gaussian mean,
"tanh" for SAC's squashed mean). Metadata (algorithm, env id and kwargs, whether the policy was
trained on privileged observations) is one JSON string, so `np.load(allow_pickle=False)` reads
every entry: the file carries no code.

An SB3 `.zip` is another matter: its `data` JSON stores every setting that is not plain JSON
(policy class, spaces, schedules, buffer classes) as a cloudpickle, and SB3's loader unpickles
them, which runs whatever code the file carries. `SB3Policy` therefore never lets SB3 unpickle
anything unless the caller trusts the file (`trust=True`, the commands' `--trust-file`): each
pickled entry is replaced by a stand-in rebuilt from the plain JSON SB3 writes beside it
(`SB3_STAND_INS`: the policy class and torch classes from an allowlist, Box spaces from their
bounds, schedules by constants, which prediction does not use), and a file carrying any other
pickled entry is refused. The weights are read by torch with `weights_only=True` either way.

This module imports numpy and gymnasium at import time; torch and SB3 only when a function needs them.
"""
from __future__ import annotations

import io
import json
import math
import os
import pickle
import re
import tempfile
import zipfile
from pathlib import Path
from typing import Any, BinaryIO, Callable

import gymnasium as gym
import numpy as np

FORMAT = "bh8-numpy-policy/1"
# Our bounds on a policy file (an exported MLP is KBs to a few MB): past them it is refused unread,
# so a zip bomb cannot exhaust memory.
POLICY_FILE_LIMIT_BYTES = 1 << 30
SB3_DATA_LIMIT_BYTES = 16 << 20  # the `data` JSON of an SB3 .zip
# What an SB3 .zip may make SB3 build when it is loaded (bh8-gym's networks have about 20 k
# parameters, two layers of 128; its buffers about 10 M numbers); _check_sb3_sizes.
SB3_LAYER_WIDTH_LIMIT = 4096
SB3_PARAMETER_LIMIT = 1 << 25  # 128 MB of float32 weights
SB3_BUFFER_VALUE_LIMIT = 1 << 28  # numbers in the rollout or replay buffer (1 GB of float32)
SB3_SPACE_LIMIT = 1 << 16  # entries of an observation or action
MAX_LAYERS = 64
NPZ_MEMBER_LIMIT = 2 * MAX_LAYERS + 16  # an export's arrays: two per layer and eight others

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


class PolicyFileError(ValueError):
    """A policy file that cannot be read, or a model that cannot be exported."""


def atomic_write(path: Path, write: Callable[[BinaryIO], None]) -> None:
    """`write(handle)` into a temp file beside `path`, fsync, then rename it over `path`: a crash leaves
    either the old file or the complete new one. The file gets the umask's mode, as an open() would
    (mkstemp's 0600 would keep the other accounts of a lab, e.g. the one that deploys, out)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())  # on disk before the rename: a power loss leaves old or new, not empty
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Write `arrays` to `path` as .npz, atomically (`atomic_write`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda handle: np.savez(handle, **arrays))


class NumpyPolicy:
    """A deterministic MLP actor read from an exported .npz; `predict(obs)` needs only numpy."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        try:
            if self.path.is_file() and not zipfile.is_zipfile(self.path):  # np.load would try to unpickle it
                raise PolicyFileError(f"{str(self.path)!r} is not an .npz file (truncated, or something else); "
                                      "export the policy again")
            with zipfile.ZipFile(self.path) as archive:
                _check_npz_members(archive, self.path)
            with np.load(self.path, allow_pickle=False) as data:
                arrays = {name: data[name] for name in data.files}
        except PolicyFileError:
            raise
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:  # damaged members: BadZipFile, EOFError
            raise PolicyFileError(f"cannot read policy file {str(self.path)!r}: {exc}") from exc
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
        self.metadata: dict[str, Any] = json.loads(str(arrays["metadata"]))
        if not isinstance(self.metadata, dict):
            raise PolicyFileError(f"{str(self.path)!r}: its metadata is not a JSON object")
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


def _check_npz_members(archive: zipfile.ZipFile, path: Path) -> None:
    """Refuse, before numpy reads it, an .npz that cannot be an export: more members than
    NPZ_MEMBER_LIMIT, more than POLICY_FILE_LIMIT_BYTES unpacked, or a member whose .npy header
    declares other than the data it holds (numpy allocates what the header declares before reading:
    a header declaring 10^12 floats was an allocation error)."""
    members = archive.infolist()
    if len(members) > NPZ_MEMBER_LIMIT:
        raise PolicyFileError(f"{str(path)!r} holds {len(members)} arrays, more than an export's {NPZ_MEMBER_LIMIT}: "
                              "not an exported policy")
    if sum(member.file_size for member in members) > POLICY_FILE_LIMIT_BYTES:
        raise PolicyFileError(f"{str(path)!r} unpacks to more than {POLICY_FILE_LIMIT_BYTES >> 20} MB: "
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
        if declared != held:
            raise PolicyFileError(f"{str(path)!r} is damaged: {member.filename!r} declares {declared} bytes of "
                                  f"data but holds {held}; export it again")


def check_policy_runs(policy, observations, action_shape: tuple[int, ...]) -> None:
    """PolicyFileError unless `policy` gives a finite action of `action_shape` for each of the
    `observations`: a forward pass before anything depends on the policy (one whose weights
    overflow to NaN, or whose last layer has an output too few, passes the load checks). Each is
    passed as a batch of one, computed as a single observation is (a larger batch goes through
    other BLAS kernels, which can turn the NaN of inf - inf into an infinity)."""
    for observation in observations:
        try:
            with np.errstate(all="ignore"):  # an overflow is reported below, not warned about
                batch = np.asarray(observation, dtype=np.float32)[None]
                action = np.asarray(policy.predict(batch, deterministic=True)[0])
        except Exception as error:  # whatever a broken policy raises, named on one line
            raise PolicyFileError(f"{str(policy.path)!r} fails on a test observation ({type(error).__name__}: "
                                  f"{error})") from None
        if action.shape != (1, *action_shape):
            raise PolicyFileError(f"{str(policy.path)!r} gives actions of shape {action.shape[1:]}, the env's are "
                                  f"{tuple(action_shape)}")
        if not np.all(np.isfinite(action)):
            raise PolicyFileError(f"{str(policy.path)!r} gives a non-finite action ({action[0].tolist()}) for a test "
                                  "observation: its weights overflow, or are not a trained policy's")


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


RUN_METADATA_FILE = "run.json"


def find_run_metadata(model_path: Path) -> dict:
    """The `run.json` that `bh8 train` writes into its output directory (searched upwards 2 levels)."""
    for folder in (model_path.parent, model_path.parent.parent):
        candidate = folder / RUN_METADATA_FILE
        if candidate.exists():
            return json.loads(candidate.read_text())
    return {}


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


def _sb3_data(raw: bytes, path: Path) -> tuple[dict | None, int]:
    """An SB3 .zip's `data` JSON (None if it has none: not an SB3 model, SB3's own error says so)
    and the unpacked size of its weights (`policy.pth`, 0 without), read without unpickling."""
    try:
        with zipfile.ZipFile(io.BytesIO(raw)) as archive:
            names = archive.namelist()
            if "data" not in names:
                return None, 0
            weights = archive.getinfo("policy.pth").file_size if "policy.pth" in names else 0
            with archive.open("data") as member:
                text = member.read(SB3_DATA_LIMIT_BYTES + 1)
        if len(text) > SB3_DATA_LIMIT_BYTES:
            raise PolicyFileError(f"{str(path)!r}: its data is larger than {SB3_DATA_LIMIT_BYTES >> 20} MB")
        data = json.loads(text)
    except (zipfile.BadZipFile, EOFError, ValueError, RecursionError) as error:
        raise PolicyFileError(f"cannot read SB3 model {str(path)!r}: {error}") from None
    if not isinstance(data, dict):
        raise PolicyFileError(f"cannot read SB3 model {str(path)!r}: its data is not a JSON object")
    return data, weights


def _check_sb3_sizes(data: dict, weights_bytes: int, path: Path) -> None:
    """PolicyFileError unless what SB3 builds when it loads the model `data` describes is bounded,
    checked before it builds anything (a 20 KB .zip asking for net_arch [12000, 12000] took minutes
    and 3 GB; n_steps 1e12 was an allocation error): the spaces, the buffer SB3 allocates (rollout:
    n_steps x n_envs transitions; replay: buffer_size), every layer's width and the network's depth,
    and the parameters, which must fit in the weights the file stores (4 bytes each at least)."""
    def bad(what: str) -> PolicyFileError:
        return PolicyFileError(f"{str(path)!r}: {what}; not a model bh8-gym loads")

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
            continue  # SB3's default: two layers of 64 (PPO) or 256 (SAC)
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
        try:
            if Path(path).stat().st_size > POLICY_FILE_LIMIT_BYTES:
                raise PolicyFileError(f"{str(path)!r} is larger than {POLICY_FILE_LIMIT_BYTES >> 20} MB: not a policy")
            raw = Path(path).read_bytes()
        except OSError as error:
            raise PolicyFileError(f"cannot read SB3 model {str(path)!r}: {error}") from None
        data, weights_bytes = _sb3_data(raw, Path(path))
        if data is not None:
            _check_sb3_sizes(data, weights_bytes, Path(path))
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
            except (AssertionError, AttributeError, KeyError, ValueError, TypeError, RuntimeError) as exc:
                errors.append(f"{algorithm.__name__}: {exc}")
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


def add_trust_argument(parser) -> None:
    """`--trust-file` of the commands that load policies (bh8 eval, export, deploy)."""
    parser.add_argument(
        "--trust-file", action="store_true",
        help="let SB3 unpickle the Python objects an SB3 .zip carries, which runs whatever code is in them: "
             "only for a file you made or trust (default: never; the known settings are rebuilt without "
             "unpickling and a .zip carrying anything else is refused; an .npz never holds code)",
    )


def load_policy(path: str | os.PathLike, trust: bool = False):
    """A policy with `predict(obs, deterministic=True)` and `metadata` from an .npz or an SB3 .zip.

    Only SB3 files need torch (imported here, lazily); they are unpickled only with `trust`.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"policy file {str(path)!r} does not exist")
    if path.suffix == ".npz":
        return NumpyPolicy(path)
    if path.suffix == ".zip":
        return SB3Policy(path, trust=trust)
    raise PolicyFileError(f"policy file {str(path)!r}: expected an exported .npz or an SB3 .zip")
