"""`bh8 train`: train a grasp policy with PPO (default) or SAC.

The command: its options, the config files (the shipped ones, `default_config_path`; any one read
and checked, `load_config`), a resumed run's options checked against run.json, and the exit status.
The run itself is `trainer.Trainer`; its output directory and what --resume continues are in
trainer.py's docstring.

Ctrl-C, SIGTERM and SIGHUP stop training at the next env step (after an evaluation in progress):
a checkpoint, then exit status 128 + the signal number (130, 143, 129). Usage errors exit 2; a
worker process that died or failed (an env worker, the evaluation worker) exits 1 with one line,
every worker ended (bh8_gym.child_processes), and the run goes on from its last checkpoint.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

from bh8_gym.agents.policy_io import RUN_METADATA_FILE
from bh8_gym.agents.evaluation.run_files import BEST_MODEL_FILE
from bh8_gym.agents.training.config_check import (
    ALGORITHMS,
    MAX_CONFIG_BYTES,
    MAX_ENVS,
    MAX_TIMESTEPS,
    check_config,
    check_plain,
    check_run_metadata,
)
from bh8_gym.agents.training.trainer import CHECKPOINT_DIR, Trainer, TrainingError, TrainingInterrupted, read_run_json
from bh8_gym.cli import integer_argument
from bh8_gym.child_processes import WorkerDied
from bh8_gym.safe_files import read_text_bounded

ENV_CONFIG_NAMES = {"BH8Grasp-v0": "grasp", "BH8FingerReach-v0": "reach"}


def default_algorithm(env_id: str) -> str:
    """`bh8 train`'s algorithm when none is given: the grasp choice for the grasp env, PPO otherwise."""
    return "GraspChoice" if env_id == "BH8Grasp-v0" else "PPO"


def default_config_path(algorithm: str, env_id: str) -> Path:
    """agents/configs/{ppo,sac,graspchoice}_{grasp,reach}.toml for the algorithm and environment."""
    if algorithm == "GraspChoice" and env_id != "BH8Grasp-v0":
        raise ValueError(f"the grasp choice is for BH8Grasp-v0, not {env_id!r}")
    if algorithm not in ALGORITHMS:
        raise ValueError(f"algorithm must be one of {ALGORITHMS}, got {algorithm!r}")
    if env_id not in ENV_CONFIG_NAMES:
        raise ValueError(f"no default config for env {env_id!r}; pass --config (known: {sorted(ENV_CONFIG_NAMES)})")
    name = f"{algorithm.lower()}_{ENV_CONFIG_NAMES[env_id]}.toml"
    return Path(str(resources.files("bh8_gym.agents").joinpath("configs", name)))


def load_config(path: str | os.PathLike) -> dict[str, Any]:
    """A TOML training config: algorithm, env_id, env_kwargs, eval_env_kwargs, [train], [eval],
    [hyperparameters], [policy_kwargs]."""
    path = Path(path)
    try:
        if not os.path.lexists(path):
            raise TrainingError(f"config file {str(path)!r} does not exist")
        # bounded, and a FIFO is refused rather than waited on
        config = tomllib.loads(read_text_bounded(path, MAX_CONFIG_BYTES, "config file", TrainingError))
    except tomllib.TOMLDecodeError as exc:
        raise TrainingError(f"config file {str(path)!r} is not valid TOML: {exc}") from None
    except RecursionError:
        raise TrainingError(f"config file {str(path)!r} nests its tables or lists too deep") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise TrainingError(f"cannot read config file {str(path)!r}: {exc}") from None
    try:
        check_plain(config, f"config file {str(path)!r}")  # before anything walks it
    except ValueError as error:
        raise TrainingError(str(error)) from None
    for key in ("algorithm", "env_id"):
        if key not in config:
            raise TrainingError(f"config file {str(path)!r} has no {key!r}")
    if config["algorithm"] not in ALGORITHMS:
        raise TrainingError(f"config {str(path)!r}: algorithm must be one of {ALGORITHMS}, got {config['algorithm']!r}")
    for table in ("env_kwargs", "eval_env_kwargs", "train", "eval", "hyperparameters", "policy_kwargs"):
        config.setdefault(table, {})
    return config


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--algo", choices=ALGORITHMS, default=None, help="algorithm (default: the config's, else PPO)")
    parser.add_argument("--env", default=None, help="environment id (default: the config's, else BH8Grasp-v0)")
    parser.add_argument("--config", type=Path, default=None,
                        help="TOML config (default agents/configs/<algo>_<grasp|reach>.toml)")
    parser.add_argument("--timesteps", type=integer_argument(1, MAX_TIMESTEPS), default=None,
                        help="total env steps (default: the config's train.total_timesteps; with --resume the run's own total)")
    parser.add_argument("--n-envs", type=integer_argument(1, MAX_ENVS), default=None,
                        help="parallel envs (default: the config's train.n_envs, else os.cpu_count())")
    parser.add_argument("--seed", type=integer_argument(0, 2**32 - 1), default=None,
                        help="seeds the envs and the policy: the same seed repeats a run (default 0)")
    parser.add_argument("--out", type=Path, required=True, help="output directory")
    parser.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    parser.add_argument("--trust-file", action="store_true",
                        help="with --resume: unpickle a checkpoint's pickled replay buffer (latest_replay_buffer.pkl, "
                             "written by earlier versions), which runs whatever code is in it: only for a run you made "
                             "(default: refused; nothing else of a checkpoint is ever unpickled)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--verbose", type=int, choices=(0, 1, 2), default=0, help="SB3 verbosity (default: %(default)s)")


def _differing_keys(ours: dict, theirs: dict, prefix: str = "") -> list[str]:
    """The dotted keys whose values differ between two nested dicts."""
    keys = []
    for key in sorted(set(ours) | set(theirs)):
        mine, other = ours.get(key), theirs.get(key)
        if isinstance(mine, dict) and isinstance(other, dict):
            keys += _differing_keys(mine, other, f"{prefix}{key}.")
        elif mine != other:
            keys.append(f"{prefix}{key}")
    return keys


def _check_resume_arguments(args: argparse.Namespace, run: dict) -> None:
    """A resumed run keeps the configuration and seed it started with: an option that says otherwise
    is an error rather than silently ignored."""
    config, saved = run["config"], str(args.out / RUN_METADATA_FILE)
    if args.algo and args.algo != config["algorithm"]:
        raise TrainingError(f"--algo {args.algo} contradicts the run being resumed ({saved}: {config['algorithm']})")
    if args.env and args.env != config["env_id"]:
        raise TrainingError(f"--env {args.env} contradicts the run being resumed ({saved}: {config['env_id']})")
    if args.seed is not None and args.seed != run["seed"]:
        raise TrainingError(f"--seed {args.seed} contradicts the run being resumed ({saved}: seed {run['seed']})")
    if args.config:
        # compared as run.json holds it (JSON round trip)
        differing = _differing_keys(json.loads(json.dumps(load_config(args.config))), config)
        if differing:
            raise TrainingError(f"--config {str(args.config)!r} contradicts the run being resumed ({saved}) in "
                                f"{', '.join(differing)}; to train longer pass --timesteps")


def run(args: argparse.Namespace) -> int:
    from bh8_gym.agents.training.callbacks import console_line
    from bh8_gym.agents.evaluation.evaluate import percent

    try:
        if args.resume and (args.out / RUN_METADATA_FILE).exists():
            run_metadata = read_run_json(args.out / RUN_METADATA_FILE)
            check_run_metadata(run_metadata, str(args.out / RUN_METADATA_FILE))
            _check_resume_arguments(args, run_metadata)
            config, seed = run_metadata["config"], run_metadata["seed"]
        else:
            env_id = args.env or "BH8Grasp-v0"
            config_path = args.config or default_config_path(args.algo or default_algorithm(env_id), env_id)
            config = load_config(config_path)
            if args.algo and config["algorithm"] != args.algo:
                raise TrainingError(f"--algo {args.algo} contradicts {str(config_path)!r} (algorithm = "
                                    f"{config['algorithm']!r})")
            if args.env and args.env != config["env_id"]:
                raise TrainingError(f"--env {args.env} contradicts {str(config_path)!r} (env_id = {config['env_id']!r})")
            seed = 0 if args.seed is None else args.seed
        if config["algorithm"] == "GraspChoice":
            return _run_choice(args, config, seed, console_line)
        trainer = Trainer(config, args.out, n_envs=args.n_envs, seed=seed,
                          progress=not args.no_progress, verbose=args.verbose, log=console_line,
                          trust=args.trust_file)
        state = trainer.run(args.timesteps, resume=args.resume)
    except (TrainingError, ValueError) as exc:
        print(f"bh8 train: {exc}", file=sys.stderr)
        return 2
    except WorkerDied as exc:  # an env or evaluation worker died or failed (WorkerError, EvaluationWorkerError)
        print(f"bh8 train: {exc}; the run goes on from its last checkpoint with --resume", file=sys.stderr)
        return 1
    except TrainingInterrupted as stop:
        print(f"\nbh8 train: {stop}; checkpoint saved in {args.out / CHECKPOINT_DIR} (continue with --resume)",
              file=sys.stderr)
        return 128 + stop.signum
    if state["best_success_rate"] is None:
        final = args.out / "final_model.zip"
        model = final if final.exists() else args.out / CHECKPOINT_DIR / "latest.zip"
        print(f"trained to {state['num_timesteps']} steps; no validation evaluation ran (one every "
              f"{int(config['eval'].get('freq', 10_000))} steps, eval.freq), so there is no best_model.zip; "
              f"the trained model is {model}")
    else:
        print(f"trained to {state['num_timesteps']} steps; best validation success rate {percent(state['best_success_rate'])} "
              f"(step {state['best_timesteps']}, {args.out / BEST_MODEL_FILE}); outputs in {args.out}")
    return 0


def _run_choice(args: argparse.Namespace, config: dict, seed: int, log) -> int:
    """`bh8 train` of the grasp choice (agents/choice/trainer.py): labels, selector, validation."""
    from bh8_gym.agents.choice.trainer import POLICY_FILE, ChoiceTrainer
    from bh8_gym.agents.policy_io import atomic_write
    from bh8_gym.agents.evaluation.evaluate import percent

    if args.timesteps is not None:
        raise TrainingError("--timesteps is for SB3's algorithms; the grasp choice's size is [choice] contexts")
    check_config(config)
    args.out.mkdir(parents=True, exist_ok=True)
    run_json = json.dumps({"config": config, "seed": seed, "algorithm": "GraspChoice"}, indent=2)
    atomic_write(args.out / RUN_METADATA_FILE, lambda handle: handle.write(run_json.encode()))
    report = ChoiceTrainer(config, args.out, seed=seed, processes=args.n_envs, progress=not args.no_progress,
                           log=log).run()
    kept = report["validation"]["models"][report["validation"]["kept"]]
    print(f"trained the grasp choice in {report['seconds']:.0f} s; validation success rate {percent(kept)} against "
          f"{percent(report['validation']['probe'])} for its probe's grasp alone; policy {args.out / POLICY_FILE}")
    return 0
