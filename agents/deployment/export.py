"""`bh8 export`: a trained SB3 policy (.zip) to a numpy-only .npz (see numpy_policy.py).

The exported file carries the run's env id and kwargs (from the run directory's run.json) so
`bh8 eval` and `bh8 deploy` rebuild the same observation layout and action mapping. After
writing, the export is checked: on random observations the numpy actions must match SB3's
deterministic actions within `--tolerance`.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from bh8_gym.agents.env_factory import make_env
from bh8_gym.agents.deployment.numpy_policy import NumpyPolicy, export_sb3_policy
from bh8_gym.agents.deployment.policy_file import PolicyFileError, add_trust_argument
from bh8_gym.agents.deployment.sb3_file import SB3Policy
from bh8_gym.cli import float_argument, integer_argument

# float32 torch against float64 numpy on a few-layer MLP: differences are ~1e-6; 1e-4 leaves margin
DEFAULT_TOLERANCE = 1e-4


def max_action_difference(sb3_policy, numpy_policy: NumpyPolicy, n_observations: int, seed: int = 0) -> float:
    """Largest |SB3 action - numpy action| over random observations drawn around the obs space.

    Observations are uniform in the space's bounds where finite, else standard normal (×3),
    which exercises saturating tanh/clip outputs as well as the linear region.
    """
    space = sb3_policy.model.observation_space
    size = sb3_policy.observation_dim  # the actor's inputs (fewer than the space for an asymmetric model)
    rng = np.random.default_rng(seed)
    low = np.where(np.isfinite(space.low), space.low, -3.0)[:size]
    high = np.where(np.isfinite(space.high), space.high, 3.0)[:size]
    observations = rng.uniform(low, high, size=(n_observations, size)).astype(np.float32)
    expected, _ = sb3_policy.predict(observations, deterministic=True)
    actual, _ = numpy_policy.predict(observations)
    return float(np.max(np.abs(np.asarray(expected, dtype=np.float64) - actual)))


def check_run_metadata(sb3_policy, model_path: Path) -> None:
    """The run.json found beside the model must exist and describe it: eval and deploy rebuild the
    observation layout from it, so a missing or foreign one makes an unusable export."""
    env_id = sb3_policy.metadata.get("env_id")
    if env_id is None:
        raise PolicyFileError(f"no run.json beside {str(model_path)!r} (or one folder up): the export would not know "
                              "its environment; export the model from the run directory `bh8 train` wrote")
    env = make_env(env_id, sb3_policy.metadata.get("env_kwargs", {}))
    try:
        expected = env.observation_space.shape
    finally:
        env.close()
    trained = (sb3_policy.observation_dim,)  # the actor's inputs (an asymmetric critic reads more)
    if trained != expected:
        raise PolicyFileError(f"{str(model_path)!r} takes observations of shape {trained}, but the run.json beside it "
                              f"describes {env_id} with shape {expected}: it belongs to another run")


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", type=Path, help="trained SB3 model (.zip), e.g. RUN/best_model.zip")
    parser.add_argument("-o", "--out", type=Path, default=None, help="output .npz (default: MODEL with .npz)")
    parser.add_argument("--check", type=integer_argument(0, 10**6), default=256,
                        help="random observations on which numpy and SB3 actions are compared (0: skip; default %(default)s)")
    parser.add_argument("--tolerance", type=float_argument(0.0, 1e6), default=DEFAULT_TOLERANCE,
                        help="largest accepted |SB3 - numpy| action difference (default %(default)s)")
    add_trust_argument(parser)


def run(args: argparse.Namespace) -> int:
    out = args.out or args.model.with_suffix(".npz")
    if out.suffix != ".npz":
        print(f"bh8 export: output must end in .npz, got {str(out)!r}", file=sys.stderr)
        return 2
    try:
        if not args.model.exists():
            raise FileNotFoundError(f"model {str(args.model)!r} does not exist")
        sb3_policy = SB3Policy(args.model, trust=args.trust_file)
        check_run_metadata(sb3_policy, args.model)
        metadata = {key: sb3_policy.metadata[key] for key in ("env_id", "env_kwargs", "eval_env_kwargs", "privileged")
                    if key in sb3_policy.metadata}
        export_sb3_policy(sb3_policy.model, out, metadata=metadata)
        numpy_policy = NumpyPolicy(out)
    except (PolicyFileError, FileNotFoundError, ValueError) as exc:
        print(f"bh8 export: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"bh8 export: cannot write {str(out)!r}: {exc}", file=sys.stderr)
        return 1
    print(f"exported {args.model} -> {out} ({numpy_policy.observation_dim} observations, "
          f"{numpy_policy.action_dim} actions, {len(numpy_policy.weights)} layers)")
    if args.check > 0:
        difference = max_action_difference(sb3_policy, numpy_policy, args.check)
        print(f"max |SB3 - numpy| action difference over {args.check} random observations: {difference:.2e}")
        if not difference <= args.tolerance:
            print(f"bh8 export: difference exceeds tolerance {args.tolerance}", file=sys.stderr)
            return 1
    return 0
