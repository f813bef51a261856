"""A policy file, read and checked before anything depends on it: `load_policy` (an exported .npz,
`numpy_policy`; a grasp-choice .npz, `agents/choice/policy.py`; or an SB3 .zip, `sb3_file`), `check_policy_runs` (a forward pass on test
observations) and the commands' `--trust-file`.

This module imports numpy at import time; torch and SB3 only when an SB3 file is loaded.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from bh8_gym.agents.choice.policy import FORMAT as CHOICE_FORMAT
from bh8_gym.agents.deployment.numpy_policy import NumpyPolicy, read_npz
from bh8_gym.agents.policy_io import PolicyFileError, check_metadata
from bh8_gym.agents.deployment.sb3_file import SB3Policy


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
        arrays = read_npz(path)
        if str(arrays.get("format", "")) == CHOICE_FORMAT:
            return load_choice_policy(path, arrays)
        return NumpyPolicy(path)
    if path.suffix == ".zip":
        return SB3Policy(path, trust=trust)
    raise PolicyFileError(f"policy file {str(path)!r}: expected an exported .npz or an SB3 .zip")


def load_choice_policy(path: Path, arrays: dict):
    """A grasp-choice policy file (`agents/choice/policy.py`): its settings, selector and predictor,
    each checked (names of known grasps, ranges, layers that chain, finite numbers)."""
    from bh8_gym.agents.choice.policy import GraspChoicePolicy

    try:
        policy = GraspChoicePolicy.from_arrays(arrays, where=repr(str(path)))
    except PolicyFileError:
        raise
    except (KeyError, ValueError, TypeError) as exc:  # json's errors are ValueErrors
        raise PolicyFileError(f"{str(path)!r} is not a usable grasp-choice file ({type(exc).__name__}: {exc}); "
                              "train it again") from None
    except RecursionError:
        raise PolicyFileError(f"{str(path)!r} is damaged: its metadata is nested too deep") from None
    check_metadata(policy.metadata, f"{str(path)!r}'s metadata")  # env id, env kwargs, seed: as an export's
    policy.path = path
    return policy
