"""SB3 callbacks for `bh8 train`: validation evaluation with best-model keeping, atomic checkpoints,
a tqdm progress bar (SB3's own bar needs `rich`, which is not a dependency), and stopping on a
signal. Named apart from SB3's own CheckpointCallback and ProgressBarCallback, which work otherwise."""
from __future__ import annotations

import numpy as np
import torch
from stable_baselines3.common.callbacks import BaseCallback
from tqdm.auto import tqdm

from bh8_gym.agents.env_factory import make_env
from bh8_gym.child_processes import check_alive
from bh8_gym.agents.evaluation.eval_worker import BATCH_ENVS, EvaluationWorker, PolicyJob, predictor
from bh8_gym.agents.evaluation.episodes import run_episodes
from bh8_gym.agents.evaluation.evaluate import percent, summarize
from bh8_gym.agents.training.pretrain import actor_cloning_loss, keep_weight_after
from bh8_gym.agents.evaluation.run_files import BEST_MODEL_FILE, EVALUATION_COLUMNS, append_evaluation, save_model_atomic


class EvaluationCallback(BaseCallback):
    """Every `eval_freq` env steps: evaluate the deterministic policy on the validation env (eval_env_kwargs), log it
    (TensorBoard and evaluations.csv), and keep the best model (success rate, then mean return).

    `state` (best scores, None before the first evaluation; next evaluation step) is shared with
    the checkpoint writer so a resumed run neither repeats nor skips evaluations and keeps comparing
    against the same best.
    """

    def __init__(self, trainer, state: dict, eval_freq: int, n_episodes: int, eval_seed: int,
                 ignore_signals: tuple = ()):
        super().__init__()
        if eval_freq < 1 or n_episodes < 1:
            raise ValueError(f"eval freq and episodes must be positive, got {eval_freq}, {n_episodes}")
        self.trainer = trainer
        self.state = state
        self.eval_freq = eval_freq
        self.n_episodes = n_episodes
        self.eval_seed = eval_seed
        #: BATCH_ENVS validation envs, running episodes at once with one forward pass per step.
        self._envs = []
        #: Half of each evaluation's episodes run in a worker process when training uses several
        #: processes (agents/evaluation/eval_worker.py: the same episodes); it ignores `ignore_signals`.
        self._worker = None
        self._ignore_signals = ignore_signals
        if state.get("next_evaluation", 0) <= 0:
            state["next_evaluation"] = eval_freq

    def _on_training_start(self) -> None:
        # A warm-started model ([pretrain]) is a candidate before RL changes it.
        if self.trainer.pretrain is not None and self.num_timesteps == 0 and self.state["best_success_rate"] is None:
            self.evaluate()

    def _on_step(self) -> bool:
        if self.num_timesteps >= self.state["next_evaluation"]:
            self.evaluate()
            self.state["next_evaluation"] += self.eval_freq * (
                1 + (self.num_timesteps - self.state["next_evaluation"]) // self.eval_freq)
        return True

    def evaluate(self) -> dict:
        config = self.trainer.config
        if self._worker is None and self.trainer.processes > 1 and self.n_episodes > 1:
            # Started by the first evaluation: it builds its env while this process runs its first episodes.
            self._worker = EvaluationWorker(config["env_id"], self.trainer.evaluation_env_kwargs,
                                            ignore_signals=self._ignore_signals)
        if not self._envs:
            self._envs = [make_env(config["env_id"], self.trainer.evaluation_env_kwargs) for _ in range(BATCH_ENVS)]
        # Same seeds at every evaluation: the curve compares policies, not episode draws.
        if self._worker is not None:
            results = self._worker.run(PolicyJob(self.model.policy), self._envs, self.n_episodes, self.eval_seed)
        else:
            results = run_episodes(predictor(self.model), self._envs, self.n_episodes, seed=self.eval_seed,
                                   progress=self.trainer.progress)
        summary = summarize(results)
        row = {"timesteps": self.num_timesteps, **{key: summary[key] for key in EVALUATION_COLUMNS[1:]}}
        append_evaluation(self.trainer.out_dir, row)
        for key in ("success_rate", "mean_return", "mean_length"):
            self.logger.record(f"eval/{key}", summary[key])
        score = (summary["success_rate"], summary["mean_return"])
        best = (self.state["best_success_rate"], self.state["best_mean_return"])
        if best[0] is None or score > best:
            self.state["best_success_rate"], self.state["best_mean_return"] = score
            self.state["best_timesteps"] = self.num_timesteps
            save_model_atomic(self.model, self.trainer.out_dir / BEST_MODEL_FILE)
        if getattr(self.trainer, "log", None) is not None:
            self.trainer.log(evaluation_line(row, self.state))
        if getattr(self.trainer, "on_evaluation", None) is not None:
            self.trainer.on_evaluation(row, self.state)
        return summary

    def _on_training_end(self) -> None:
        self.close()

    def close(self, graceful: bool = True) -> None:
        """Close the validation envs and end the evaluation worker (`EvaluationWorker.close`)."""
        for env in self._envs:
            env.close()
        self._envs = []
        if self._worker is not None:
            self._worker.close(graceful)
            self._worker = None


def evaluation_line(row: dict, state: dict) -> str:
    """One validation evaluation (its evaluations.csv row) as `bh8 train` prints it, with whether it
    is the run's new best (`state` as EvaluationCallback keeps it, this evaluation counted)."""
    line = (f"step {row['timesteps']}: validation success {percent(row['success_rate'])} (95% Wilson CI "
            f"{percent(row['success_ci_low'], row['success_ci_high'])}, {row['episodes']} episodes), "
            f"mean return {row['mean_return']:.2f}; ")
    if state.get("best_timesteps") == row["timesteps"]:
        return line + "new best"
    return line + f"best so far {percent(state['best_success_rate'])} at step {state['best_timesteps']}"


def console_line(text: str) -> None:
    """Print a line on stdout without breaking a progress bar drawn on the terminal."""
    tqdm.write(text)


class KeepDemonstrationsCallback(BaseCallback):
    """[pretrain] keep_weight: after every rollout, `keep_batches` minibatches of the cloning loss
    on the script's demonstrations through the policy's own optimizer, weighted
    keep_weight × keep_decay ** rollouts, never under keep_floor (from the run's start, so a resumed
    run goes on decaying)."""

    def __init__(self, demonstrations, settings, rollout_steps: int, seed: int):
        super().__init__()
        self.demonstrations = demonstrations
        self.settings = settings
        self.rollout_steps = rollout_steps
        self._rng = np.random.default_rng(seed)

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        rollouts_before = max(self.num_timesteps // self.rollout_steps - 1, 0)  # num_timesteps counts this one
        weight = keep_weight_after(self.settings, rollouts_before)
        if weight < 1e-4:
            return
        policy, demonstrations = self.model.policy, self.demonstrations
        losses = []
        for _ in range(self.settings.keep_batches):
            batch = self._rng.integers(0, len(demonstrations.actions), self.settings.batch_size)
            actor_loss = actor_cloning_loss(policy, torch.as_tensor(demonstrations.observations[batch]),
                                            torch.as_tensor(demonstrations.actions[batch]))
            policy.optimizer.zero_grad()
            (weight * actor_loss).backward()
            policy.optimizer.step()
            losses.append(float(actor_loss.detach()))
        self.logger.record("pretrain/keep_weight", weight)
        self.logger.record("pretrain/actor_mse", float(np.mean(losses)))


class RunCheckpointCallback(BaseCallback):
    """Every `checkpoint_freq` env steps: the trainer's atomic checkpoint (model, buffer, state)."""

    def __init__(self, trainer, state: dict, checkpoint_freq: int):
        super().__init__()
        if checkpoint_freq < 1:
            raise ValueError(f"checkpoint_freq must be positive, got {checkpoint_freq}")
        self.trainer = trainer
        self.state = state
        self.checkpoint_freq = checkpoint_freq
        self._next = None

    def _on_training_start(self) -> None:
        self._next = (self.num_timesteps // self.checkpoint_freq + 1) * self.checkpoint_freq

    def _on_step(self) -> bool:
        if self.num_timesteps >= self._next:
            self.trainer.save_checkpoint(self.model, self.state)
            self._next = (self.num_timesteps // self.checkpoint_freq + 1) * self.checkpoint_freq
        return True


class TrainingProgressCallback(BaseCallback):
    """A tqdm bar over the run's total env steps, starting where a resumed run left off; drawn on a
    terminal only (disable=None), so a log file gets the evaluation lines and no bar updates."""

    def __init__(self, total_timesteps: int):
        super().__init__()
        self.total_timesteps = total_timesteps
        self._bar = None

    def _on_training_start(self) -> None:
        self._bar = tqdm(total=self.total_timesteps, initial=self.num_timesteps, unit="step", dynamic_ncols=True,
                         desc="training", disable=None)

    def _on_step(self) -> bool:
        # PPO collects whole rollouts, so the run may end a little past the requested total
        if self.num_timesteps > self._bar.total:
            self._bar.total = self.num_timesteps
        self._bar.update(self.num_timesteps - self._bar.n)
        return True

    def _on_training_end(self) -> None:
        self._bar.close()


class StopCallback(BaseCallback):
    """Ends `learn` at the next env step once a signal asked the trainer to stop (`stop_signal`)."""

    def __init__(self, trainer):
        super().__init__()
        self.trainer = trainer

    def _on_step(self) -> bool:
        check_alive()  # the evaluation worker killed between evaluations: stop now (WorkerDied)
        return self.trainer.stop_signal is None
