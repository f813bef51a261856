"""Numpy-only policy files: export a trained SB3 policy to .npz and run it without torch.

An exported file holds the deterministic actor of a PPO or SAC `MlpPolicy` (Box observations and
actions): the weights of every linear layer, the hidden activation's name, the observation
normalisation of a `VecNormalize` used in training (identity when none was used), the action
space bounds and how the network's output becomes an action ("clip" for PPO's Gaussian mean,
"tanh" for SAC's squashed mean). Metadata (algorithm, env id and kwargs, whether the policy was
trained on privileged observations) is one JSON string, so `np.load(allow_pickle=False)` reads
every entry: the file carries no code.

This module imports only numpy at import time; `export_sb3_policy` imports torch lazily.
"""
from __future__ import annotations

import json
import os
import tempfile
import zipfile
from pathlib import Path
from typing import Any, BinaryIO, Callable

import numpy as np

FORMAT = "bh8-numpy-policy/1"

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
            with np.load(self.path, allow_pickle=False) as data:
                arrays = {name: data[name] for name in data.files}
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

    def _read(self, arrays: dict[str, np.ndarray]) -> None:
        self.metadata: dict[str, Any] = json.loads(str(arrays["metadata"]))
        n_layers = int(self.metadata["n_layers"])
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
        self.obs_std = np.sqrt(arrays["obs_var"].astype(np.float64) + float(arrays["obs_epsilon"]))
        self.obs_clip = float(arrays["obs_clip"])
        self.action_low = arrays["action_low"].astype(np.float64)
        self.action_high = arrays["action_high"].astype(np.float64)
        self.observation_dim = self.weights[0].shape[1]
        self.action_dim = self.weights[-1].shape[0]

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
    import gymnasium as gym
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


class SB3Policy:
    """An SB3 model with the same `predict` and `metadata` as `NumpyPolicy` (needs torch)."""

    def __init__(self, path: Path, device: str = "cpu"):
        from stable_baselines3 import PPO, SAC

        algorithms = {"PPO": PPO, "SAC": SAC}
        self.path = path
        self.metadata = find_run_metadata(path)
        name = self.metadata.get("algorithm")
        if name is not None and name not in algorithms:
            raise PolicyFileError(f"{str(path)!r}: unsupported algorithm {name!r}")
        candidates = [algorithms[name]] if name else [PPO, SAC]
        errors = []
        for algorithm in candidates:
            try:
                self.model = algorithm.load(path, device=device)
                break
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


def load_policy(path: str | os.PathLike):
    """A policy with `predict(obs, deterministic=True)` and `metadata` from an .npz or an SB3 .zip.

    Only SB3 files need torch (imported here, lazily).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"policy file {str(path)!r} does not exist")
    if path.suffix == ".npz":
        return NumpyPolicy(path)
    if path.suffix == ".zip":
        return SB3Policy(path)
    raise PolicyFileError(f"policy file {str(path)!r}: expected an exported .npz or an SB3 .zip")
