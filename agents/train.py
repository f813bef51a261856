"""`bh8 train`: train a grasp policy with PPO (default) or SAC.

Output directory layout (`--out DIR`):

    run.json                     algorithm, env id and kwargs, seed, the resolved config
    checkpoints/latest.zip       the model, written atomically (temp file, then os.replace)
    checkpoints/latest_replay_buffer.pkl   SAC only
    checkpoints/latest.json      timestep counter, best evaluation so far, next evaluation step
    best_model.zip               the model with the best held-out success rate (then return)
    final_model.zip              the model at the end of training
    evaluations.csv              one row per periodic evaluation (the training curve)
    tb/                          TensorBoard logs

`--resume` continues an interrupted run from checkpoints/latest.*: model weights and optimiser,
SAC's replay buffer, the timestep counter and the evaluation bookkeeping.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import tempfile
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

from bh8_gym.agents.policy_file import RUN_METADATA_FILE

ALGORITHMS = ("PPO", "SAC")
ENV_CONFIG_NAMES = {"BH8Grasp-v0": "grasp", "BH8FingerReach-v0": "reach"}
EVALUATION_COLUMNS = ("timesteps", "success_rate", "success_ci_low", "success_ci_high", "mean_return",
                      "std_return", "mean_length", "episodes")
CHECKPOINT_DIR = "checkpoints"


class TrainingError(RuntimeError):
    """A training run that cannot start or resume (the message says why)."""


def default_config_path(algorithm: str, env_id: str) -> Path:
    """agents/configs/{ppo,sac}_{grasp,reach}.toml for the algorithm and environment."""
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
        with path.open("rb") as handle:
            config = tomllib.load(handle)
    except FileNotFoundError:
        raise TrainingError(f"config file {str(path)!r} does not exist") from None
    except tomllib.TOMLDecodeError as exc:
        raise TrainingError(f"config file {str(path)!r} is not valid TOML: {exc}") from None
    for key in ("algorithm", "env_id"):
        if key not in config:
            raise TrainingError(f"config file {str(path)!r} has no {key!r}")
    if config["algorithm"] not in ALGORITHMS:
        raise TrainingError(f"config {str(path)!r}: algorithm must be one of {ALGORITHMS}, got {config['algorithm']!r}")
    for table in ("env_kwargs", "eval_env_kwargs", "train", "eval", "hyperparameters", "policy_kwargs"):
        config.setdefault(table, {})
    return config


def write_json_atomic(path: Path, data: Any) -> None:
    """Write JSON so a crash leaves either the old file or the complete new one."""
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    with os.fdopen(fd, "w") as handle:
        json.dump(data, handle, indent=2, sort_keys=True)
    os.replace(tmp, path)


def save_model_atomic(model, path: Path) -> None:
    """`model.save` to a temp name then os.replace, so `path` is never half-written."""
    tmp = path.with_name(path.stem + ".tmp.zip")
    model.save(tmp)
    os.replace(tmp, path)


def _policy_kwargs(config: dict) -> dict:
    import torch.nn as nn

    kwargs = dict(config["policy_kwargs"])
    activation = kwargs.pop("activation", None)
    if activation is not None:
        activations = {"tanh": nn.Tanh, "relu": nn.ReLU, "elu": nn.ELU, "leaky_relu": nn.LeakyReLU, "silu": nn.SiLU}
        if activation not in activations:
            raise TrainingError(f"policy_kwargs.activation must be one of {sorted(activations)}, got {activation!r}")
        kwargs["activation_fn"] = activations[activation]
    return kwargs


SCHEDULED_HYPERPARAMETERS = ("learning_rate", "clip_range")


def _hyperparameters(config: dict) -> dict:
    """config["hyperparameters"] with rl-zoo's "lin_<start>" strings (learning_rate, clip_range) as
    schedules that fall linearly from <start> to 0 over the run."""
    from stable_baselines3.common.utils import LinearSchedule

    hyperparameters = dict(config["hyperparameters"])
    for name in SCHEDULED_HYPERPARAMETERS:
        value = hyperparameters.get(name)
        if not isinstance(value, str):
            continue
        try:
            if not value.startswith("lin_"):
                raise ValueError
            start = float(value[len("lin_"):])
        except ValueError:
            raise TrainingError(f"hyperparameters.{name} must be a number or 'lin_<start>' "
                                f"(linear decay to 0), got {value!r}") from None
        hyperparameters[name] = LinearSchedule(start, 0.0, 1.0)
    return hyperparameters


class Trainer:
    """One training run in `out_dir`: builds envs and model (or resumes them) and runs `learn`."""

    def __init__(self, config: dict, out_dir: Path, n_envs: int | None = None, seed: int = 0,
                 progress: bool = True, verbose: int = 0):
        self.config = config
        #: PPO with a critic that sees privileged simulator state (agents/asymmetric.py).
        self.asymmetric_critic = bool(config.get("asymmetric_critic", False))
        if self.asymmetric_critic and config["algorithm"] != "PPO":
            raise TrainingError(f"asymmetric_critic needs PPO, the config says {config['algorithm']!r}")
        if self.asymmetric_critic and config["env_kwargs"].get("privileged"):
            raise TrainingError("asymmetric_critic gives the critic privileged observations itself; "
                                "remove privileged from env_kwargs (the actor must not see them)")
        self.out_dir = Path(out_dir)
        self.n_envs = int(n_envs or config["train"].get("n_envs") or os.cpu_count() or 1)
        if self.n_envs < 1:
            raise ValueError(f"n_envs must be at least 1, got {self.n_envs}")
        self.seed = int(seed)
        self.progress = progress
        self.verbose = verbose
        self.checkpoint_dir = self.out_dir / CHECKPOINT_DIR

    @property
    def run_metadata(self) -> dict:
        config = self.config
        return {
            "algorithm": config["algorithm"],
            "env_id": config["env_id"],
            "env_kwargs": config["env_kwargs"],
            "eval_env_kwargs": config["eval_env_kwargs"],
            "privileged": bool(config["env_kwargs"].get("privileged", False)),
            "asymmetric_critic": self.asymmetric_critic,
            "seed": self.seed,
            "config": config,
        }

    def _check_env_kwargs(self) -> None:
        """Build the training and evaluation envs once here, so that a typo in the config is an
        error naming it rather than a SubprocVecEnv worker dying with a broken pipe."""
        from bh8_gym.agents.env_factory import make_env

        for table in ("env_kwargs", "eval_env_kwargs"):
            try:
                make_env(self.config["env_id"], self.config[table]).close()
            except ValueError as error:
                raise TrainingError(f"{table}: {error}") from None

    def _vec_env(self):
        from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

        from bh8_gym.agents.env_factory import EnvFactory

        env_kwargs = dict(self.config["env_kwargs"])
        if self.asymmetric_critic:
            env_kwargs["privileged"] = True  # for the critic; the policy masks it from the actor
        factories = [EnvFactory(self.config["env_id"], env_kwargs, seed=None) for _ in range(self.n_envs)]
        if self.n_envs == 1:
            return DummyVecEnv(factories)
        return SubprocVecEnv(factories)

    def _new_model(self, env):
        from stable_baselines3 import PPO, SAC

        algorithm = {"PPO": PPO, "SAC": SAC}[self.config["algorithm"]]
        policy, policy_kwargs = "MlpPolicy", _policy_kwargs(self.config)
        if self.asymmetric_critic:
            from bh8_gym.agents.asymmetric import AsymmetricActorCriticPolicy

            policy = AsymmetricActorCriticPolicy
            policy_kwargs["host_observations"] = int(env.get_attr("host_observation_size")[0])
        return algorithm(policy, env, seed=self.seed, device="cpu", verbose=self.verbose,
                         tensorboard_log=str(self.out_dir / "tb"), policy_kwargs=policy_kwargs,
                         **_hyperparameters(self.config))

    def _resume_model(self, env):
        from stable_baselines3 import PPO, SAC

        algorithm = {"PPO": PPO, "SAC": SAC}[self.config["algorithm"]]
        model = algorithm.load(self.checkpoint_dir / "latest.zip", env=env, device="cpu",
                               tensorboard_log=str(self.out_dir / "tb"), verbose=self.verbose)
        replay = self.checkpoint_dir / "latest_replay_buffer.pkl"
        if hasattr(model, "replay_buffer") and replay.exists():
            model.load_replay_buffer(replay)
        return model

    def save_checkpoint(self, model, state: dict) -> None:
        """Model, SAC replay buffer, then the state file (last: it names the step the others hold)."""
        self.checkpoint_dir.mkdir(parents=True, exist_ok=True)
        save_model_atomic(model, self.checkpoint_dir / "latest.zip")
        if getattr(model, "replay_buffer", None) is not None:
            tmp = self.checkpoint_dir / "latest_replay_buffer.tmp.pkl"
            model.save_replay_buffer(tmp)
            os.replace(tmp, self.checkpoint_dir / "latest_replay_buffer.pkl")
        write_json_atomic(self.checkpoint_dir / "latest.json", {**state, "num_timesteps": int(model.num_timesteps)})

    def run(self, total_timesteps: int, resume: bool = False) -> dict:
        """Train until `total_timesteps` env steps in all; returns the final state dict."""
        import torch

        from bh8_gym.agents.callbacks import CheckpointCallback, EvaluationCallback, ProgressBarCallback

        # One thread per process: with SubprocVecEnv on 2 cores this is the fastest (measured).
        torch.set_num_threads(1)
        if total_timesteps < 1:
            raise ValueError(f"total_timesteps must be positive, got {total_timesteps}")
        self._check_env_kwargs()
        has_checkpoint = (self.checkpoint_dir / "latest.zip").exists()
        if resume and not has_checkpoint:
            raise TrainingError(f"--resume: no checkpoint in {str(self.checkpoint_dir)!r}")
        if not resume and has_checkpoint:
            raise TrainingError(f"{str(self.out_dir)!r} already holds a run; pass --resume to continue it "
                                "or choose another --out")
        self.out_dir.mkdir(parents=True, exist_ok=True)
        state = {"best_success_rate": -1.0, "best_mean_return": float("-inf"), "next_evaluation": 0}
        if resume:
            state.update(json.loads((self.checkpoint_dir / "latest.json").read_text()))
        else:
            write_json_atomic(self.out_dir / RUN_METADATA_FILE, self.run_metadata)

        env = self._vec_env()
        try:
            model = self._resume_model(env) if resume else self._new_model(env)
            remaining = total_timesteps - model.num_timesteps
            if remaining <= 0:
                return {**state, "num_timesteps": int(model.num_timesteps)}
            eval_config = self.config["eval"]
            evaluation = EvaluationCallback(
                self, state, eval_freq=int(eval_config.get("freq", 10_000)),
                n_episodes=int(eval_config.get("episodes", 10)), eval_seed=int(eval_config.get("seed", 10_000)),
            )
            callbacks = [evaluation, CheckpointCallback(self, evaluation.state,
                                                        int(self.config["train"].get("checkpoint_freq", 10_000)))]
            if self.progress:
                callbacks.append(ProgressBarCallback(total_timesteps))
            try:
                model.learn(total_timesteps=remaining, callback=callbacks, reset_num_timesteps=not resume,
                            tb_log_name=self.config["algorithm"])
            except KeyboardInterrupt:
                self.save_checkpoint(model, evaluation.state)
                raise
            self.save_checkpoint(model, evaluation.state)
            save_model_atomic(model, self.out_dir / "final_model.zip")
            return {**evaluation.state, "num_timesteps": int(model.num_timesteps)}
        finally:
            env.close()


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--algo", choices=ALGORITHMS, default=None, help="algorithm (default: the config's, else PPO)")
    parser.add_argument("--env", default=None, help="environment id (default: the config's, else BH8Grasp-v0)")
    parser.add_argument("--config", type=Path, default=None,
                        help="TOML config (default agents/configs/<algo>_<grasp|reach>.toml)")
    parser.add_argument("--timesteps", type=int, default=None, help="total env steps (default: the config's)")
    parser.add_argument("--n-envs", type=int, default=None, help="parallel envs (default: os.cpu_count())")
    parser.add_argument("--seed", type=int, default=0, help="seeds the envs and the policy: the same seed repeats a run (default 0)")
    parser.add_argument("--out", type=Path, required=True, help="output directory")
    parser.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--verbose", type=int, default=0, help="SB3 verbosity (0, 1, 2)")


def run(args: argparse.Namespace) -> int:
    try:
        if args.resume and (args.out / RUN_METADATA_FILE).exists():
            # a resumed run keeps the hyperparameters it started with
            config = json.loads((args.out / RUN_METADATA_FILE).read_text())["config"]
        else:
            config_path = args.config or default_config_path(args.algo or "PPO", args.env or "BH8Grasp-v0")
            config = load_config(config_path)
            if args.algo and config["algorithm"] != args.algo:
                raise TrainingError(f"--algo {args.algo} contradicts {str(config_path)!r} (algorithm = "
                                    f"{config['algorithm']!r})")
            if args.env and args.env != config["env_id"]:
                raise TrainingError(f"--env {args.env} contradicts {str(config_path)!r} (env_id = {config['env_id']!r})")
        total = args.timesteps or int(config["train"].get("total_timesteps", 100_000))
        trainer = Trainer(config, args.out, n_envs=args.n_envs, seed=args.seed,
                          progress=not args.no_progress, verbose=args.verbose)
        state = trainer.run(total, resume=args.resume)
    except (TrainingError, ValueError) as exc:
        print(f"bh8 train: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"\nbh8 train: interrupted; checkpoint saved in {args.out / CHECKPOINT_DIR} (continue with --resume)",
              file=sys.stderr)
        return 130
    print(f"trained to {state['num_timesteps']} steps; best held-out success rate "
          f"{max(state['best_success_rate'], 0.0):.2f}; outputs in {args.out}")
    return 0


def read_evaluations(out_dir: Path) -> list[dict[str, float]]:
    """The rows of `evaluations.csv` (the training curve) as floats."""
    path = Path(out_dir) / "evaluations.csv"
    with path.open(newline="") as handle:
        return [{key: float(value) for key, value in row.items()} for row in csv.DictReader(handle)]
