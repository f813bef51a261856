"""One `bh8 sweep` trial in a Ray worker: a `bh8 train` run (the same Trainer, config format, run
directory, checkpoints and resume) that reports each validation evaluation to Ray Tune.

The trial's run directory is `<experiment>/runs/<trial>_seed<seed>` on the sweep's storage (the
trial named by the sweep's plan, t0000 on, or by Ray for an Optuna draw), so a retried trial (a
crash, a killed worker, `bh8 sweep --resume`) finds its checkpoint there and goes on from it exactly
as `bh8 train --resume` would. Beside bh8 train's files it holds:

    trial.json    attempts so far and the step each started from, wall seconds of all attempts,
                  the worker's host and pid (rewritten atomically as the trial goes)
    result.json   written last and atomically when the run has finished: the trial is complete
                  only when this file exists
"""
from __future__ import annotations

import os
import socket
import threading
import time
from pathlib import Path

from bh8_gym.agents.sweep.space import apply_space
from bh8_gym.agents.evaluation.run_files import BEST_MODEL_FILE, write_json_atomic
from bh8_gym.agents.evaluation.bounds import MAX_SEED
from bh8_gym.agents.training.config_check import MAX_TIMESTEPS
from bh8_gym.agents.training.trainer import CHECKPOINT_STATE, Trainer, read_run_json
from bh8_gym.record_schema import Int, ListOf, Real, Schema, Table, Text

TRIAL_FILE = "trial.json"
RESULT_FILE = "result.json"
RUNS_DIR = "runs"
# Ray Tune's metric: the best validation success rate so far (the rule that keeps best_model.zip).
METRIC = "best_validation_success"
# Set by Ray Tune's Repeater (Optuna searches): which of the sweep's seeds this repetition trains.
TRIAL_INDEX = "__trial_index__"


def run_dir_name(trial_id: str, seed: int) -> str:
    return f"{trial_id}_seed{seed}"


# What a trial records: trial.json as it goes (its draw, so an Optuna trial can be relaunched from it),
# result.json when it has finished. Checked when read back (bh8 sweep --resume, the report).
TRIAL_RECORD = Schema("trial record", required={"trial_id": Text(64), "seed": Int(0, MAX_SEED), "space": Table()},
                      optional={"sweep_id": Text(64), "attempts": Int(0, 10**6), "wall_seconds": Real(0.0, 1e10),
                                "starts": ListOf(Int(0, MAX_TIMESTEPS), 10**6)})
TRIAL_RESULT = Schema("trial result", required={"metrics": Table(), "num_timesteps": Int(0, MAX_TIMESTEPS)},
                      optional={"sweep_id": Text(64), "wall_seconds": Real(0.0, 1e10), "attempts": Int(0, 10**6)})
METRICS = Schema("trial metrics", required={METRIC: Real(0.0, 1.0), "best_mean_return": Real(-1e15, 1e15)},
                 optional={"best_timesteps": Int(0, MAX_TIMESTEPS)})


def resolve_trial(params: dict, settings: dict, ray_trial_id: str) -> dict:
    """{"name", "seed", "space"} of the trial Ray Tune started with `params`: a planned trial by
    name (sweep.json's plan), one relaunched from its record ("fixed"), or an Optuna draw (named by
    Ray's trial id; its seed the Repeater's index into the seeds)."""
    if "trial" in params:
        return next(trial for trial in settings["trials"] if trial["name"] == params["trial"])
    if "fixed" in params:
        return params["fixed"]
    seed = trial_seed(params, settings["seeds"])
    if seed is None:
        raise RuntimeError(f"trial {ray_trial_id} was given no seed ({sorted(params)})")
    return {"name": ray_trial_id, "seed": seed, "space": params.get("space", {})}


def trial_seed(params: dict, seeds: list[int]) -> int | None:
    """The seed of an Optuna trial: the Repeater's index into the seeds (None: none given)."""
    if "seed" in params:
        return int(params["seed"])
    if TRIAL_INDEX in params:
        return int(seeds[int(params[TRIAL_INDEX]) % len(seeds)])
    return None


def _metrics(state: dict, row: dict | None = None) -> dict:
    metrics = {METRIC: float(state["best_success_rate"]), "best_mean_return": float(state["best_mean_return"]),
               "best_timesteps": int(state.get("best_timesteps", 0))}
    if row is not None:
        metrics.update(timesteps=int(row["timesteps"]), validation_success=float(row["success_rate"]),
                       validation_ci_low=float(row["success_ci_low"]),
                       validation_ci_high=float(row["success_ci_high"]), validation_episodes=int(row["episodes"]))
    return metrics


class _WallClock:
    """Keeps trial.json's wall_seconds (all attempts) up to date: at each evaluation and every
    HEARTBEAT_SECONDS, so a killed attempt's time is counted too."""

    HEARTBEAT_SECONDS = 10.0

    def __init__(self, path: Path, record: dict):
        self.path, self.record = path, record
        self.started, self.before = time.monotonic(), float(record["wall_seconds"])
        self.lock = threading.Lock()
        self.stopped = threading.Event()
        threading.Thread(target=self._beat, daemon=True, name="bh8-sweep-wall-clock").start()

    def save(self) -> None:
        with self.lock:
            self.record["wall_seconds"] = self.before + time.monotonic() - self.started
            write_json_atomic(self.path, self.record)

    def _beat(self) -> None:
        while not self.stopped.wait(self.HEARTBEAT_SECONDS):
            self.save()

    def stop(self) -> None:
        self.stopped.set()
        self.save()


def run_trial(params: dict, settings: dict) -> None:
    """The Ray Tune function trainable. `params`: which trial (`resolve_trial`); `settings`: the
    sweep's fixed settings (sweep.json)."""
    from ray import tune

    trial = resolve_trial(params, settings, tune.get_context().get_trial_id())
    trial_id, seed = trial["name"], trial["seed"]
    config = apply_space(settings["config"], trial["space"])
    run_dir = Path(settings["experiment_path"]) / RUNS_DIR / run_dir_name(trial_id, seed)
    run_dir.mkdir(parents=True, exist_ok=True)
    result_path = run_dir / RESULT_FILE
    result = read_run_json(result_path, TRIAL_RESULT) if result_path.exists() else None
    if result is not None and result.get("sweep_id") == settings["sweep_id"]:
        # finished before Tune heard of it (a kill in between): nothing to redo
        tune.report(METRICS.check(result["metrics"], str(result_path), RuntimeError))
        return

    record = (read_run_json(run_dir / TRIAL_FILE, TRIAL_RECORD) if (run_dir / TRIAL_FILE).exists()
              else {"attempts": 0, "wall_seconds": 0.0})
    record.update(attempts=record.get("attempts", 0) + 1, trial_id=trial_id, seed=seed, space=trial["space"],
                  sweep_id=settings["sweep_id"], host=socket.gethostname(), pid=os.getpid())
    write_json_atomic(run_dir / TRIAL_FILE, record)
    clock = _WallClock(run_dir / TRIAL_FILE, record)

    def on_evaluation(row: dict, state: dict) -> None:
        clock.save()
        tune.report(_metrics(state, row))

    try:
        trainer = Trainer(config, run_dir, n_envs=settings["n_envs"], seed=seed, progress=False,
                          on_evaluation=on_evaluation, processes=max(1, int(settings["resources"]["cpu"])))
        resume = trainer.has_checkpoint()
        if not resume:  # an attempt killed before its first checkpoint: its evaluations are redone
            for leftover in ("evaluations.csv", BEST_MODEL_FILE):
                (run_dir / leftover).unlink(missing_ok=True)
        start = read_run_json(trainer.checkpoint_dir / "latest.json", CHECKPOINT_STATE)["num_timesteps"] if resume else 0
        with clock.lock:
            record.setdefault("starts", []).append(int(start))  # the step each attempt started from
        clock.save()
        state = trainer.run(settings["timesteps"], resume=resume)
    finally:
        clock.stop()
    if state["best_success_rate"] is None:
        raise RuntimeError(f"the run made no validation evaluation in {state['num_timesteps']} steps "
                           f"(eval.freq {config['eval'].get('freq', 10_000)})")
    metrics = _metrics(state)
    write_json_atomic(result_path, {"metrics": metrics, "num_timesteps": int(state["num_timesteps"]),
                                    "wall_seconds": record["wall_seconds"], "attempts": record["attempts"],
                                    "sweep_id": settings["sweep_id"]})
    tune.report(metrics)
