"""A training checkpoint read back without unpickling anything (`bh8 train --resume`, a sweep
trial's retry).

SB3's `load` unpickles the pickled entries of a model zip's `data` JSON (schedules, spaces, buffer
classes) and `load_replay_buffer` unpickles SAC's whole buffer: a checkpoint someone replaced
would run its code on resume. So a resumed run builds its model from the config in run.json as
the run started it (plain JSON, checked key by key by agents/training/config_check.py, schedules and all),
and takes from the checkpoint only what holds no code:

- the weights and optimiser states: the zip's .pth members under the names the algorithm saves,
  read by torch with weights_only=True (tensors and plain containers only) and loaded by SB3's
  `set_parameters`, which checks every name and shape;
- the counters: num_timesteps, _n_updates and _episode_num, plain integers of `data`;
- SAC's replay buffer: its arrays in an .npz (REPLAY_BUFFER_FILE, `save_replay_buffer`), read with
  allow_pickle=False and checked against the buffer the config builds.

The model zip stays an ordinary SB3 file (`bh8 eval`/`bh8 export` read it the same way). Only
checkpoints of earlier bh8-gym versions, whose SAC buffer is a pickle (LEGACY_REPLAY_BUFFER_FILE),
need the user's --trust-file; without it they are refused, saying why.
"""
from __future__ import annotations

import io
import json
import pickle
import zipfile
from pathlib import Path
from typing import BinaryIO

import numpy as np

from bh8_gym.agents.policy_io import POLICY_FILE_LIMIT_BYTES

from bh8_gym.agents.deployment.sb3_file import SB3_DATA_LIMIT_BYTES, ZIP_ERRORS
from bh8_gym.safe_files import open_regular, read_bounded

REPLAY_BUFFER_FILE = "latest_replay_buffer.npz"
LEGACY_REPLAY_BUFFER_FILE = "latest_replay_buffer.pkl"  # SB3's pickle, written before the .npz
COUNTERS = ("num_timesteps", "_n_updates", "_episode_num")


class CheckpointError(ValueError):
    """A checkpoint that cannot be resumed from as it is (the message says why)."""


def _limited_archive(path: Path) -> zipfile.ZipFile:
    """The checkpoint zip, refused unread past POLICY_FILE_LIMIT_BYTES packed or unpacked."""
    try:  # read bounded: a FIFO or a link to /dev/zero as latest.zip is refused, not waited on
        archive = zipfile.ZipFile(io.BytesIO(read_bounded(path, POLICY_FILE_LIMIT_BYTES, "checkpoint",
                                                          CheckpointError)))
    except (OSError, zipfile.BadZipFile) as error:
        raise CheckpointError(f"cannot read {str(path)!r}: {error}") from None
    if sum(member.file_size for member in archive.infolist()) > POLICY_FILE_LIMIT_BYTES:
        archive.close()
        raise CheckpointError(f"{str(path)!r} unpacks to more than {POLICY_FILE_LIMIT_BYTES >> 20} MB")
    return archive


def _torch_member(archive: zipfile.ZipFile, name: str, path: Path):
    import torch

    try:
        return torch.load(io.BytesIO(archive.read(name)), map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, KeyError, AttributeError, TypeError, *ZIP_ERRORS) as error:
        # weights_only refuses anything but tensors and containers; a damaged member: ZIP_ERRORS
        raise CheckpointError(f"{str(path)!r}: its {name} is not plain tensors ({str(error)[:200]})") from None


def load_checkpoint(model, path: Path) -> None:
    """Put the checkpoint's weights, optimiser states and counters into `model`, a model the run's
    config has just built (module docstring); CheckpointError if the checkpoint does not fit it."""
    path = Path(path)
    state_dicts, variables = model._get_torch_save_params()
    with _limited_archive(path) as archive:
        names = set(archive.namelist())
        expected = {f"{name}.pth" for name in state_dicts} | ({"pytorch_variables.pth"} if variables else set())
        missing = sorted(expected - names | ({"data"} - names))
        unknown = sorted(name for name in names - expected - {"pytorch_variables.pth"} if name.endswith(".pth"))
        if missing or unknown:
            raise CheckpointError(f"{str(path)!r} is not a {type(model).__name__} checkpoint of this run (missing "
                                  f"{', '.join(missing) or 'nothing'}; unexpected {', '.join(unknown) or 'nothing'})")
        counters = _counters(archive, path)
        params = {name: _torch_member(archive, f"{name}.pth", path) for name in state_dicts}
        bad = sorted(name for name, value in params.items() if not _finite(value))
        if bad:  # before: the run went on and stopped later with "action must be finite", no file named
            raise CheckpointError(f"{str(path)!r}: its {', '.join(bad)} hold NaN or infinite numbers; resume from "
                                  "an earlier checkpoint or start the run again")
        # SB3 writes the file even when the algorithm has no such variables (then it holds nothing)
        saved_variables = (_torch_member(archive, "pytorch_variables.pth", path)
                           if "pytorch_variables.pth" in names else {})
    try:
        model.set_parameters(params, exact_match=True, device="cpu")
        _set_variables(model, variables, saved_variables)
    except (RuntimeError, ValueError, KeyError, TypeError, IndexError, AttributeError) as error:
        raise CheckpointError(f"{str(path)!r} does not fit the model run.json's config builds "
                              f"({str(error).splitlines()[0][:200] if str(error) else type(error).__name__})") from None
    for name, value in counters.items():
        setattr(model, name, value)


def _finite(value) -> bool:
    """Whether every floating-point tensor in `value` (a state dict, nested) is finite."""
    import torch

    if isinstance(value, torch.Tensor):
        return not value.is_floating_point() or bool(torch.isfinite(value).all())
    if isinstance(value, dict):
        return all(_finite(item) for item in value.values())
    if isinstance(value, (list, tuple)):
        return all(_finite(item) for item in value)
    return True


def _counters(archive: zipfile.ZipFile, path: Path) -> dict[str, int]:
    try:
        with archive.open("data") as member:
            text = member.read(SB3_DATA_LIMIT_BYTES + 1)
    except ZIP_ERRORS as error:
        raise CheckpointError(f"{str(path)!r}: its data cannot be read ({str(error)[:200]})") from None
    try:
        if len(text) > SB3_DATA_LIMIT_BYTES:
            raise ValueError(f"larger than {SB3_DATA_LIMIT_BYTES >> 20} MB")
        data = json.loads(text)
        if not isinstance(data, dict):
            raise ValueError("not a JSON object")
    except (ValueError, RecursionError) as error:
        raise CheckpointError(f"{str(path)!r}: its data cannot be read ({str(error)[:200]})") from None
    counters = {}
    for name in COUNTERS:
        value = data.get(name, 0)
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < 2**62:
            raise CheckpointError(f"{str(path)!r}: its {name} must be a non-negative integer, got {str(value)[:60]}")
        counters[name] = value
    return counters


def _set_variables(model, names: list[str], saved) -> None:
    """SB3's extra tensors (SAC's log_ent_coef or ent_coef_tensor), each shaped as the model's."""
    import torch

    if saved is None or saved == []:  # what SB3 writes for none
        saved = {}
    if not isinstance(saved, dict) or set(saved) != set(names):
        raise ValueError(f"pytorch_variables hold {sorted(saved) if isinstance(saved, dict) else type(saved)}, "
                         f"not {names}")
    for name in names:
        target, value = getattr(model, name), saved[name]
        if not isinstance(value, torch.Tensor) or value.shape != target.shape:
            raise ValueError(f"{name} has the wrong shape")
        with torch.no_grad():
            target.data.copy_(value.data)


def _buffer_arrays(buffer) -> dict[str, np.ndarray]:
    """A replay buffer's arrays by name ("observations", or "observations/key" for a Dict space)."""
    arrays = {}
    for name, value in vars(buffer).items():
        if isinstance(value, np.ndarray):
            arrays[name] = value
        elif isinstance(value, dict) and value and all(isinstance(v, np.ndarray) for v in value.values()):
            arrays.update({f"{name}/{key}": array for key, array in value.items()})
    return arrays


def save_replay_buffer(model, handle: BinaryIO) -> None:
    """SAC's replay buffer as an .npz of its arrays and position (no pickle)."""
    buffer = model.replay_buffer
    counters = np.array([int(buffer.pos), int(buffer.full)], dtype=np.int64)
    np.savez(handle, **_buffer_arrays(buffer), **{"__counters__": counters})


def _member(archive: zipfile.ZipFile, name: str, like: np.ndarray, path: Path) -> np.ndarray:
    """The array `name` of an .npz, read only if its header declares `like`'s shape and dtype and
    its member holds exactly that data (numpy allocates what a header declares before reading: a
    header declaring 10^11 floats was a MemoryError)."""
    member = archive.getinfo(f"{name}.npy")
    with archive.open(member) as handle:
        version = np.lib.format.read_magic(handle)
        if version not in ((1, 0), (2, 0)):
            raise CheckpointError(f"{str(path)!r}: {name} is not an array numpy's savez writes")
        reader = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, fortran, dtype = reader(handle)
        held = member.file_size - handle.tell()
        if shape != like.shape or dtype != like.dtype or fortran or held != like.nbytes:
            raise CheckpointError(f"{str(path)!r}: {name} is {dtype}{list(shape)}, the run's buffer "
                                  f"{like.dtype}{list(like.shape)} (another buffer_size or --n-envs?)")
        data = handle.read(held)
    return np.frombuffer(data, dtype=dtype).reshape(shape)


def load_replay_buffer(model, path: Path) -> None:
    """Fill `model`'s replay buffer (the one its config built) from `save_replay_buffer`'s .npz:
    every array of the same name, shape and dtype, and a position inside the buffer."""
    buffer = model.replay_buffer
    arrays = _buffer_arrays(buffer)
    try:
        with open_regular(path, "replay buffer", CheckpointError) as handle, zipfile.ZipFile(handle) as archive:
            names = {name.removesuffix(".npy") for name in archive.namelist()}
            if names != set(arrays) | {"__counters__"}:
                raise CheckpointError(f"{str(path)!r} holds {sorted(names)}, not this run's replay buffer")
            counters = _member(archive, "__counters__", np.zeros(2, dtype=np.int64), path)
            pos, full = (int(v) for v in counters)
            for name, target in arrays.items():
                target[...] = _member(archive, name, target, path)
    except CheckpointError:
        raise
    except ZIP_ERRORS as error:
        raise CheckpointError(f"cannot read the replay buffer {str(path)!r}: {str(error)[:200]}") from None
    if not (0 <= pos < buffer.buffer_size and full in (0, 1)):
        raise CheckpointError(f"{str(path)!r}: position {pos} is outside the buffer of {buffer.buffer_size}")
    buffer.pos, buffer.full = pos, bool(full)
