"""One training run (`Trainer`): envs and model built or resumed, the warm start, `learn`,
checkpoints and the best model, for `bh8 train` and `bh8 sweep`.

Output directory layout (`--out DIR`):

    run.json                     algorithm, env id and kwargs, seed, the resolved config
    checkpoints/latest.zip       the model; a checkpoint's files are replaced as one unit (each staged
                                 as NAME.next first), so a kill leaves the old checkpoint or the new one
    checkpoints/latest_replay_buffer.npz   SAC only (its arrays: no pickle)
    checkpoints/latest.json      timestep counter, the run's total, best evaluation so far, next
                                 evaluation step
    checkpoints/best_model.zip   the best model as of that checkpoint (restored by --resume)
    best_model.zip               the model with the best validation success rate (then return)
    final_model.zip              the model at the end of training
    evaluations.csv              one row per periodic evaluation (the training curve)
    tb/                          TensorBoard logs

`--resume` continues an interrupted run from checkpoints/latest.*: model weights and optimiser,
SAC's replay buffer, the timestep counter and the evaluation bookkeeping, with the configuration
and seed in run.json (an --algo, --env, --config or --seed that contradicts them is an error;
--timesteps may extend the run; without it the run trains to the total it was started with).
Nothing in the run directory is unpickled (agents/training/checkpoint_file.py; an earlier version's pickled
SAC replay buffer only with --trust-file).
Evaluations made after the checkpoint are undone (their evaluations.csv rows, and a best_model.zip
they wrote: the checkpoint's best model is put back).

Ctrl-C, SIGTERM and SIGHUP stop training at the next env step (after an evaluation in progress):
a checkpoint, then `TrainingInterrupted` (`bh8 train` exits 128 + the signal number).
"""
from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from pathlib import Path

from bh8_gym.agents.training.config_check import (
    ACTIVATION_CLASSES,
    MAX_ENVS,
    MAX_TIMESTEPS,
    check_config,
    check_env_tables,
    check_rollout,
)
from bh8_gym.agents.training.checkpoint_file import (
    LEGACY_REPLAY_BUFFER_FILE,
    REPLAY_BUFFER_FILE,
    CheckpointError,
    load_checkpoint,
    load_replay_buffer,
    save_replay_buffer,
)
from bh8_gym.agents.env_factory import EnvFactory
from bh8_gym.agents.policy_io import RUN_METADATA_FILE, atomic_write
from bh8_gym.agents.training.pretrain import (
    DEMONSTRATIONS_FILE,
    PretrainSettings,
    clone,
    load_demonstrations,
    record,
    save_demonstrations,
)
from bh8_gym.agents.evaluation.run_files import (
    BEST_MODEL_FILE,
    copy_atomic,
    drop_evaluations_after,
    save_model_atomic,
    write_json_atomic,
)
from bh8_gym.cli import handling_signals
from bh8_gym.record_schema import Int, Maybe, Real, Schema
from bh8_gym.safe_files import SMALL_FILE_LIMIT_BYTES, FileError, read_json_bounded
from bh8_gym.envs.interfaces import host_options

CHECKPOINT_DIR = "checkpoints"
# A checkpoint's files besides latest.json, which names their step and is replaced after them.
CHECKPOINT_FILES = ("latest.zip", REPLAY_BUFFER_FILE, BEST_MODEL_FILE)
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class TrainingError(RuntimeError):
    """A training run that cannot start or resume (the message says why)."""


class TrainingInterrupted(Exception):
    """Training stopped early by one of STOP_SIGNALS, after saving a checkpoint."""

    def __init__(self, signum: int, num_timesteps: int):
        self.signum = signum
        self.num_timesteps = num_timesteps
        super().__init__(f"stopped by {signal.Signals(signum).name} at step {num_timesteps}")


def _pretrain_settings(config: dict):
    """The config's [pretrain] table (agents/training/pretrain.py), checked; None without one."""
    if "pretrain" not in config:
        return None
    try:
        return PretrainSettings.from_table(dict(config["pretrain"]))
    except (TypeError, ValueError) as error:
        raise TrainingError(str(error)) from None


# checkpoints/latest.json: every number is bounded before the run uses it (a total of 1e308 trained
# past MAX_TIMESTEPS; a string raised a TypeError mid-run).
CHECKPOINT_STATE = Schema("checkpoint state", required={"num_timesteps": Int(0, MAX_TIMESTEPS)}, optional={
    "total_timesteps": Int(1, MAX_TIMESTEPS), "next_evaluation": Int(0, 2 * MAX_TIMESTEPS),
    "best_timesteps": Int(0, MAX_TIMESTEPS), "best_success_rate": Maybe(Real(0.0, 1.0)),
    "best_mean_return": Maybe(Real(-1e15, 1e15))})


def read_run_json(path: Path, schema: Schema | None = None, limit: int = SMALL_FILE_LIMIT_BYTES) -> dict:
    """A run's JSON file (run.json, checkpoints/latest.json, a sweep trial's), read bounded (a FIFO or
    a link to /dev/zero is refused, not waited on) and checked by `schema`; TrainingError names a
    damaged one."""
    try:
        data = read_json_bounded(path, limit, "run file", constants=True)
        return (schema or _TABLE).check(data, str(path), FileError)
    except FileError as error:
        raise TrainingError(f"--resume: {error}; the run cannot be resumed") from None


_TABLE = Schema("JSON object", required={})


def _staged(path: Path) -> Path:
    """Where a checkpoint file waits until its whole checkpoint is written (`Trainer.save_checkpoint`)."""
    return path.with_name(path.name + ".next")




def _policy_kwargs(config: dict) -> dict:
    import torch.nn as nn

    kwargs = dict(config["policy_kwargs"])
    activation = kwargs.pop("activation", None)
    if activation is not None:  # a name config_check accepted
        kwargs["activation_fn"] = getattr(nn, ACTIVATION_CLASSES[activation])
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


def _algorithm_class(name: str):
    from stable_baselines3 import PPO, SAC

    return {"PPO": PPO, "SAC": SAC}[name]


def _check_config(config: dict) -> None:
    """Every key of the config, checked before anything is built or written (agents/training/config_check.py)."""
    try:
        check_config(config)
    except ValueError as error:
        raise TrainingError(str(error)) from None


class Trainer:
    """One training run in `out_dir`: builds envs and model (or resumes them) and runs `learn`."""

    def __init__(self, config: dict, out_dir: Path, n_envs: int | None = None, seed: int = 0,
                 progress: bool = True, verbose: int = 0, on_evaluation=None, log=None, trust: bool = False,
                 processes: int | None = None):
        self.config = config
        #: Called with a line of text for each step of the warm start and each validation evaluation
        #: (`bh8 train` prints them); None: silent.
        self.log = log
        #: --trust-file: a checkpoint's pickled replay buffer (earlier versions') may be unpickled.
        self.trust = trust
        #: Called after each validation evaluation with its evaluations.csv row and the run's state
        #: (best so far); `bh8 sweep` reports them to Ray Tune.
        self.on_evaluation = on_evaluation
        #: PPO with a critic that sees privileged simulator state (agents/asymmetric.py).
        _check_config(config)
        self.asymmetric_critic = bool(config.get("asymmetric_critic", False))
        self.pretrain = _pretrain_settings(config)
        self.out_dir = Path(out_dir)
        self.n_envs = int(n_envs if n_envs is not None
                          else config["train"].get("n_envs", min(os.cpu_count() or 1, MAX_ENVS)))
        if not 1 <= self.n_envs <= MAX_ENVS:
            raise ValueError(f"n_envs must be in 1..{MAX_ENVS}, got {self.n_envs}")
        check_rollout(config, self.n_envs)
        #: Processes the envs are stepped in (this one and workers), and the validation evaluations
        #: (a second one only if > 1): one per core by default, never more than the envs; a `bh8
        #: sweep` trial passes the CPUs Ray gave it.
        self.processes = min(self.n_envs, int(processes if processes is not None else os.cpu_count() or 1))
        if self.processes < 1:
            raise ValueError(f"processes must be positive, got {processes!r}")
        self.seed = int(seed)
        self.progress = progress
        self.verbose = verbose
        self.checkpoint_dir = self.out_dir / CHECKPOINT_DIR
        #: The signal that asked training to stop (StopCallback ends `learn` at the next step).
        self.stop_signal: int | None = None

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

    @property
    def evaluation_env_kwargs(self) -> dict:
        """The validation env's keywords: eval_env_kwargs over the training env's host options
        (LOOP layout, history, safety: what shapes the policy's observation and action), so the
        policy is validated on the observation it was trained on."""
        return {**host_options(self.config["env_id"], self.config["env_kwargs"]), **self.config["eval_env_kwargs"]}

    def _check_env_kwargs(self) -> None:
        """Build the training and evaluation envs once here, so that a typo in the config is an
        error naming it rather than a SubprocVecEnv worker dying with a broken pipe."""
        check_env_tables(self.config)

    def _vec_env(self):
        from stable_baselines3.common.vec_env import DummyVecEnv

        from bh8_gym.agents.training.vec_env import ShardedVecEnv

        factories = [EnvFactory(self.config["env_id"], self._training_env_kwargs, seed=None)
                     for _ in range(self.n_envs)]
        if self.n_envs == 1:
            return DummyVecEnv(factories)
        # Workers ignore STOP_SIGNALS: a Ctrl-C or a kill sent to the whole process group then stops
        # training through this process (checkpoint, then it closes the workers), not mid-step.
        return ShardedVecEnv(factories, n_processes=self.processes, ignore_signals=STOP_SIGNALS)

    def _new_model(self, env):
        algorithm = _algorithm_class(self.config["algorithm"])
        policy, policy_kwargs = "MlpPolicy", _policy_kwargs(self.config)
        if self.asymmetric_critic:
            from bh8_gym.agents.asymmetric import AsymmetricActorCriticPolicy

            policy = AsymmetricActorCriticPolicy
            policy_kwargs["host_observations"] = int(env.get_attr("host_observation_size")[0])
        return algorithm(policy, env, seed=self.seed, device="cpu", verbose=self.verbose,
                         tensorboard_log=str(self.out_dir / "tb"), policy_kwargs=policy_kwargs,
                         **_hyperparameters(self.config))

    @property
    def _training_env_kwargs(self) -> dict:
        """The training envs' keywords (the warm start records on the same env)."""
        env_kwargs = dict(self.config["env_kwargs"])
        if self.asymmetric_critic:
            env_kwargs["privileged"] = True  # for the critic; the policy masks it from the actor
        return env_kwargs

    def _warm_start(self, model):
        """[pretrain]: clone the scripted grasp into the new model; pretrain.json says how well.
        Returns the demonstrations (also saved in the run for a resume to keep cloning them)."""
        settings, log = self.pretrain, self.log or (lambda _line: None)
        if settings.teacher:
            from bh8_gym.agents.training.teacher import distill

            log(f"warm start: a teacher choosing among {', '.join(settings.teacher)} on {settings.episodes} "
                f"training episodes, distilled in {settings.dagger_iterations} DAgger iterations ([pretrain])")
            demonstrations, summary = distill(model, self.config["env_id"], self._training_env_kwargs, settings,
                                              seed=self.seed, progress=self.progress, report=log)
            save_demonstrations(self.out_dir / DEMONSTRATIONS_FILE, demonstrations)
            write_json_atomic(self.out_dir / "pretrain.json", {**summary, "steps": int(len(demonstrations.actions))})
            return demonstrations
        log(f"warm start: recording {settings.episodes} episodes of the {settings.baseline} grasp, then "
            f"{settings.epochs} epochs of cloning ([pretrain])")
        demonstrations = record(self.config["env_id"], self._training_env_kwargs, settings,
                                gamma=float(model.gamma), progress=self.progress)
        log(f"warm start: the script held {demonstrations.successes} of {demonstrations.episodes} episodes "
            f"({len(demonstrations.actions)} steps recorded)")
        save_demonstrations(self.out_dir / DEMONSTRATIONS_FILE, demonstrations)
        losses = clone(model, demonstrations, settings, seed=self.seed, progress=self.progress)
        log(f"warm start: cloned; actor MSE {losses['actor_mse']:.4g}, value MSE {losses['value_mse']:.4g}")
        write_json_atomic(self.out_dir / "pretrain.json", {
            "baseline": self.pretrain.baseline, "baseline_kwargs": self.pretrain.baseline_kwargs,
            "episodes": demonstrations.episodes, "successes": demonstrations.successes,
            "steps": int(len(demonstrations.actions)), **losses})
        return demonstrations

    def _resume_model(self, env):
        """The model as the run's config builds it, with the checkpoint's weights, optimiser states,
        counters and SAC's replay buffer: nothing of the checkpoint is unpickled (checkpoint_file)."""
        model = self._new_model(env)
        try:
            load_checkpoint(model, self.checkpoint_dir / "latest.zip")
            replay, legacy = self.checkpoint_dir / REPLAY_BUFFER_FILE, self.checkpoint_dir / LEGACY_REPLAY_BUFFER_FILE
            if hasattr(model, "replay_buffer") and replay.exists():
                load_replay_buffer(model, replay)
            elif hasattr(model, "replay_buffer") and legacy.exists():
                if not self.trust:
                    raise CheckpointError(
                        f"{str(legacy)!r} (an earlier version's replay buffer) is a pickle, and unpickling runs "
                        "whatever code it holds: resume with --trust-file if the run is yours, or remove the file "
                        "to go on with an empty buffer")
                model.load_replay_buffer(legacy)
        except CheckpointError as error:
            raise TrainingError(f"--resume: {error}") from None
        # SB3's load re-seeds the envs with the run's seed: the resumed half would replay the first
        # half's scenes. A seed of its own, fixed by the checkpoint's step, keeps the run deterministic.
        model.set_random_seed(self.seed + int(model.num_timesteps))
        return model

    def save_checkpoint(self, model, state: dict) -> None:
        """The checkpoint's files replace the last checkpoint's as one unit, so a kill at any point
        leaves a model and a state file of the same step. Each file is first staged beside its
        predecessor (NAME.next, each written atomically): the model, SAC's replay buffer, the best
        model, then the state file, whose staged copy marks the set complete. Then every staged file
        replaces its predecessor, the state file last (`_finish_checkpoint`, which the next run
        repeats if a kill came in between; a set killed before its state file is discarded)."""
        directory = self.checkpoint_dir
        directory.mkdir(parents=True, exist_ok=True)
        self._finish_checkpoint()
        save_model_atomic(model, _staged(directory / "latest.zip"))
        if getattr(model, "replay_buffer", None) is not None:
            atomic_write(_staged(directory / REPLAY_BUFFER_FILE), lambda handle: save_replay_buffer(model, handle))
        best = self.out_dir / BEST_MODEL_FILE
        if best.exists():
            copy_atomic(best, _staged(directory / BEST_MODEL_FILE))
        write_json_atomic(_staged(directory / "latest.json"), {**state, "num_timesteps": int(model.num_timesteps)})
        self._finish_checkpoint()

    def _finish_checkpoint(self) -> None:
        """Put a complete staged checkpoint (its state file staged) in place, or discard an incomplete
        one and the temporary files of a staged file a kill cut short (`atomic_write`'s NAME.*.tmp)."""
        directory = self.checkpoint_dir
        for leftover in directory.glob("*.next.*.tmp"):
            leftover.unlink()
        state = _staged(directory / "latest.json")
        complete = state.exists()
        for name in CHECKPOINT_FILES:
            staged = _staged(directory / name)
            if staged.exists():
                if complete:
                    os.replace(staged, directory / name)
                else:
                    staged.unlink()
        if complete:
            os.replace(state, directory / "latest.json")

    @contextlib.contextmanager
    def _stopping_on_signals(self):
        """While training: STOP_SIGNALS (Ctrl-C, `kill`, a closed terminal) ask for a stop at the next
        env step, so the checkpoint is taken with the workers between steps. Signal handlers can
        only be set from the main thread; elsewhere nothing changes."""
        if threading.current_thread() is not threading.main_thread():
            yield
            return

        def request_stop(signum, _frame):
            if self.stop_signal is None:
                self.stop_signal = signum

        with handling_signals(STOP_SIGNALS, request_stop):
            yield

    def has_checkpoint(self) -> bool:
        """Whether the run directory holds a checkpoint to resume from (one a kill left staged but
        complete is put in place first)."""
        if self.checkpoint_dir.is_dir():
            self._finish_checkpoint()
        return (self.checkpoint_dir / "latest.zip").exists()

    def _read_checkpoint_state(self) -> dict:
        path = self.checkpoint_dir / "latest.json"
        if not path.exists():
            raise TrainingError(f"--resume: the checkpoint in {str(self.checkpoint_dir)!r} is incomplete "
                                "(latest.zip without latest.json: not written by this version's checkpoints, "
                                "which replace both together); remove that folder to start the run again")
        state = read_run_json(path)
        if state.get("best_mean_return") == float("-inf"):  # older checkpoints: -1.0 and -Infinity, not null
            state.update(best_success_rate=None, best_mean_return=None)
        try:
            return CHECKPOINT_STATE.check(state, str(path), TrainingError)
        except TrainingError as error:
            raise TrainingError(f"--resume: {error}; the run cannot be resumed") from None

    def _restore_best_model(self, state: dict) -> None:
        """best_model.zip as of the checkpoint: an evaluation after it (the run was killed before the
        next checkpoint) may have replaced or created it, and the resumed run compares against the
        checkpoint's best. Checkpoints of older versions hold no copy: their best_model.zip stays."""
        saved, best = self.checkpoint_dir / BEST_MODEL_FILE, self.out_dir / BEST_MODEL_FILE
        if saved.exists():
            copy_atomic(saved, best)
        elif state["best_success_rate"] is None:
            best.unlink(missing_ok=True)

    def run(self, total_timesteps: int | None = None, resume: bool = False) -> dict:
        """Train until `total_timesteps` env steps in all (None: a resumed run's own total, which its
        checkpoint records, else the config's train.total_timesteps); returns the final state dict
        (best_success_rate None: no evaluation ran). Raises TrainingInterrupted after the checkpoint
        if a signal stopped it."""
        import torch

        from bh8_gym.agents.training.callbacks import (
            EvaluationCallback,
            KeepDemonstrationsCallback,
            RunCheckpointCallback,
            StopCallback,
            TrainingProgressCallback,
        )

        # One thread per process: with env worker processes on 2 cores this is the fastest (measured).
        torch.set_num_threads(1)
        # torch.distributions' argument checks only check: the same numbers, ~20 % less CPU per
        # policy forward (docs/benchmarks.md, "Training").
        torch.distributions.Distribution.set_default_validate_args(False)
        if total_timesteps is not None and total_timesteps < 1:
            raise ValueError(f"total_timesteps must be positive, got {total_timesteps}")
        self._finish_checkpoint()  # one a kill interrupted
        has_checkpoint = (self.checkpoint_dir / "latest.zip").exists()
        if resume and not has_checkpoint:
            raise TrainingError(f"--resume: no checkpoint in {str(self.checkpoint_dir)!r}")
        if not resume and has_checkpoint:
            raise TrainingError(f"{str(self.out_dir)!r} already holds a run; pass --resume to continue it "
                                "or choose another --out")
        state = {"best_success_rate": None, "best_mean_return": None, "next_evaluation": 0}
        if resume:
            state.update(self._read_checkpoint_state())
        if total_timesteps is None:
            total_timesteps = state.get("total_timesteps") or int(self.config["train"].get("total_timesteps", 100_000))
        state["total_timesteps"] = total_timesteps
        self._check_env_kwargs()
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise TrainingError(f"cannot create the output directory {str(self.out_dir)!r}: {error.strerror}") from None
        if resume:
            cut = drop_evaluations_after(self.out_dir, state["num_timesteps"])
            if cut:  # rows a kill or a full disk cut short: dropped, not merged with the next
                print(f"bh8 train: dropped the cut-short line(s) {', '.join(map(str, cut))} of evaluations.csv",
                      file=sys.stderr)
            self._restore_best_model(state)
        else:
            write_json_atomic(self.out_dir / RUN_METADATA_FILE, self.run_metadata)

        with self._stopping_on_signals():
            env = self._vec_env()
            try:
                model = self._resume_model(env) if resume else self._new_model(env)
                demonstrations = None
                if self.pretrain is not None and not resume:
                    demonstrations = self._warm_start(model)
                remaining = total_timesteps - model.num_timesteps
                if remaining <= 0:
                    return {**state, "num_timesteps": int(model.num_timesteps)}
                eval_config = self.config["eval"]
                evaluation = EvaluationCallback(
                    self, state, eval_freq=int(eval_config.get("freq", 10_000)),
                    n_episodes=int(eval_config.get("episodes", 10)), eval_seed=int(eval_config.get("seed", 10_000)),
                    ignore_signals=STOP_SIGNALS,
                )
                callbacks = [evaluation, RunCheckpointCallback(self, evaluation.state,
                                                               int(self.config["train"].get("checkpoint_freq", 10_000)))]
                if self.progress:
                    callbacks.append(TrainingProgressCallback(total_timesteps))
                if self.pretrain is not None and self.pretrain.keep_weight > 0:
                    if demonstrations is None:  # a resumed run: the ones its warm start saved
                        demonstrations = load_demonstrations(self.out_dir / DEMONSTRATIONS_FILE)
                    callbacks.append(KeepDemonstrationsCallback(
                        demonstrations, self.pretrain, rollout_steps=int(model.n_steps) * self.n_envs,
                        seed=self.seed))
                callbacks.append(StopCallback(self))
                try:
                    model.learn(total_timesteps=remaining, callback=callbacks, reset_num_timesteps=not resume,
                                tb_log_name=self.config["algorithm"])
                except BaseException:
                    # SB3 ends its callbacks only when learn returns: the evaluation worker (which
                    # ignores the stop signals) would outlive the process's exit; killed here at once.
                    evaluation.close(graceful=False)
                    raise
                self.save_checkpoint(model, evaluation.state)
                if self.stop_signal is not None:
                    raise TrainingInterrupted(self.stop_signal, int(model.num_timesteps))
                save_model_atomic(model, self.out_dir / "final_model.zip")
                return {**evaluation.state, "num_timesteps": int(model.num_timesteps)}
            finally:
                env.close()
