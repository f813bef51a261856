"""A sweep's outcome: each trial's state read from its run directory (never a half-written one: a
trial is complete only when its result.json exists), the ranking on the validation split, the one
test evaluation of the chosen model(s) with `bh8 eval`'s code, sweep.md and the curves' plot."""
from __future__ import annotations

import argparse
import contextlib
import csv
import glob
import io
import json
import os
import shutil
import statistics
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bh8_gym.agents.sweep.space import describe
from bh8_gym.agents.sweep.trial import RESULT_FILE, RUNS_DIR, TRIAL_FILE, run_dir_name, trial_seed
from bh8_gym.agents.evaluation.run_files import BEST_MODEL_FILE
from bh8_gym.agents.training.trainer import CHECKPOINT_DIR

REPORT_FILE = "sweep.md"
PLOT_FILE = "validation_curves.png"
TEST_DIR = "test"
# Statuses, in the order sweep.md lists trials that are not complete.
COMPLETE, ERROR, STOPPED, PENDING = "complete", "error", "stopped", "pending"


@dataclass
class TrialRecord:
    trial_id: str
    seed: int | None  # None: a trial that never started (nothing says which seed it would train)
    space: dict
    run_dir: Path
    status: str
    error: str = ""
    attempts: int = 0
    wall_seconds: float = 0.0
    steps: int = 0
    evaluations: list[dict] = field(default_factory=list)

    @property
    def best(self) -> dict | None:
        """The evaluations.csv row of the best validation evaluation: success rate, then mean return
        (the rule that keeps best_model.zip)."""
        if not self.evaluations:
            return None
        return max(self.evaluations, key=lambda row: (row["success_rate"], row["mean_return"]))

    @property
    def model(self) -> Path:
        return self.run_dir / BEST_MODEL_FILE


def _read_json(path: Path) -> dict | None:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _read_evaluations(path: Path) -> list[dict[str, float]]:
    """A run's evaluations.csv rows as floats (none yet: empty). The rows are appended one at a time
    and a resumed run drops those past its checkpoint, so a row cut short by a kill is left out."""
    try:
        with path.open(newline="") as handle:
            rows = list(csv.DictReader(handle))
    except FileNotFoundError:
        return []
    complete = []
    for row in rows:
        try:
            complete.append({key: float(value) for key, value in row.items()})
        except (TypeError, ValueError):  # a partial last line: missing fields are None
            pass
    return complete


def _error_line(error: BaseException | None) -> str:
    """The informative line of a trial's error (the last line of a worker's traceback)."""
    if error is None:
        return ""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    text = lines[-1] if lines else type(error).__name__
    return text if len(text) <= 200 else text[:197] + "..."


def _trial_params(result, experiment_path: Path) -> tuple[dict, Path | None]:
    """A trial's draw (seed or Repeater index, "space") and its run directory if it has one. Ray's
    result carries the draw only once the trial has reported (a trial stopped by Ctrl-C before its
    first evaluation has not); then the trial.json of its run directory, which the trial writes
    when it starts."""
    trial_id = Path(result.path).name
    found = sorted((Path(experiment_path) / RUNS_DIR).glob(f"{glob.escape(trial_id)}_seed*"))
    run_dir = found[0] if found else None
    if result.config:
        return result.config, run_dir
    trial = _read_json(run_dir / TRIAL_FILE) if run_dir is not None else None
    if trial and isinstance(trial.get("seed"), int):
        return {"seed": trial["seed"], "space": trial.get("space") or {}}, run_dir
    return {}, run_dir


def collect(results, experiment_path: Path, seeds: list[int]) -> list[TrialRecord]:
    """One record per trial of Ray Tune's ResultGrid, its numbers from the run directory."""
    records = []
    for result in results:
        trial_id = Path(result.path).name
        params, found = _trial_params(result, experiment_path)
        seed = trial_seed(params, seeds)
        run_dir = (Path(experiment_path) / RUNS_DIR / run_dir_name(trial_id, seed) if seed is not None
                   else found or Path(experiment_path) / RUNS_DIR / trial_id)
        final = _read_json(run_dir / RESULT_FILE)
        trial = _read_json(run_dir / TRIAL_FILE) or {}
        if final is not None:
            status = COMPLETE
        elif result.error is not None:
            status = ERROR
        else:
            status = STOPPED if run_dir.exists() else PENDING
        evaluations = _read_evaluations(run_dir / "evaluations.csv")
        if final is not None:
            steps = int(final["num_timesteps"])
        else:  # the last checkpoint's step: what a resumed run starts from
            checkpoint = _read_json(run_dir / CHECKPOINT_DIR / "latest.json") or {}
            steps = int(checkpoint.get("num_timesteps", 0))
            # rows past the checkpoint are redone by the resumed run
            evaluations = [row for row in evaluations if row["timesteps"] <= steps]
        records.append(TrialRecord(
            trial_id=trial_id, seed=seed, space=params.get("space", {}), run_dir=run_dir, status=status,
            error=_error_line(result.error) if status == ERROR else "",
            attempts=int(trial.get("attempts", 0)), wall_seconds=float((final or trial).get("wall_seconds", 0.0)),
            steps=steps, evaluations=evaluations))
    return records


def ranked(records: list[TrialRecord]) -> list[TrialRecord]:
    """Complete trials by best validation success, then best mean return, then trial id; the rest
    after them by status."""
    complete = [r for r in records if r.status == COMPLETE and r.best is not None]
    complete.sort(key=lambda r: (-r.best["success_rate"], -r.best["mean_return"], r.trial_id))
    order = [ERROR, STOPPED, PENDING, COMPLETE]
    rest = sorted((r for r in records if r not in complete), key=lambda r: (order.index(r.status), r.trial_id))
    return complete + rest


def test_evaluation(record: TrialRecord, sweep_dir: Path, episodes: int, seed: int, objects: str) -> dict:
    """`bh8 eval` of the trial's best model on the test split, once: its report is kept in
    test/<trial>/ (written to a staging folder renamed into place when complete) and read back on
    later runs instead of evaluating again. Returns bh8 eval's results.json."""
    from bh8_gym.agents.evaluation import evaluate

    target = sweep_dir / TEST_DIR / record.run_dir.name
    done = previous_test(target, episodes, seed, objects)
    if done is not None:
        return done
    staging = target.with_name(target.name + ".partial")
    shutil.rmtree(staging, ignore_errors=True)
    parser = argparse.ArgumentParser()
    evaluate.configure_parser(parser)
    args = parser.parse_args(test_command_arguments(record.model, episodes, seed, objects) + ["--out", str(staging)])
    output = io.StringIO()
    with contextlib.redirect_stdout(output), contextlib.redirect_stderr(output):
        code = evaluate.run(args)
    if code != 0:
        raise RuntimeError(f"bh8 eval of {record.model} failed: {output.getvalue().strip()}")
    (staging / "eval.txt").write_text(output.getvalue())
    if target.exists():  # made with other --test-* settings: replaced by the one asked for now
        shutil.rmtree(target)
    os.replace(staging, target)
    return json.loads((target / "results.json").read_text())


def previous_test(target: Path, episodes: int, seed: int, objects: str) -> dict | None:
    """The test report in `target` if it was made with these settings (the test split is evaluated
    once; a resumed or repeated sweep reads it back), else None."""
    try:
        results = json.loads((target / "results.json").read_text())
    except (OSError, ValueError):
        return None
    sets = [name.strip() for name in objects.split(",") if name.strip()]
    if (results.get("seed") == seed and results.get("object_sets") in ([""], sets)
            and all(part["episodes"] == episodes for part in results["by_object_set"].values())):
        return results
    return None


def test_command_arguments(model: Path, episodes: int, seed: int, objects: str) -> list[str]:
    """The `bh8 eval` arguments of the sweep's test evaluation (sweep.md prints them)."""
    return [str(model), "--episodes", str(episodes), "--seed", str(seed), "--objects", objects,
            "--gif-episodes", "0", "--no-progress"]


def plot_curves(records: list[TrialRecord], path: Path) -> Path | None:
    """Every trial's validation success against env steps, with the median over trials and the
    min-max band at each evaluation step (over the trials evaluated at that step)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = [r for r in records if r.evaluations]
    if not curves:
        return None
    by_step: dict[float, list[float]] = {}
    figure, axes = plt.subplots(figsize=(7.5, 4.5))
    for record in curves:
        steps = [row["timesteps"] for row in record.evaluations]
        rates = [row["success_rate"] for row in record.evaluations]
        for step, rate in zip(steps, rates):
            by_step.setdefault(step, []).append(rate)
        axes.plot(steps, rates, linewidth=0.8, alpha=0.6, marker=".",
                  label=f"seed {record.seed}, {describe(record.space)}" if len(curves) <= 8 else None)
    steps = np.array(sorted(by_step))
    axes.fill_between(steps, [min(by_step[s]) for s in steps], [max(by_step[s]) for s in steps],
                      color="grey", alpha=0.25, label="range over trials")
    axes.plot(steps, [statistics.median(by_step[s]) for s in steps], color="black", linewidth=2.2, label="median")
    axes.set_ylim(-0.02, 1.02)
    axes.set_xlabel("env steps")
    axes.set_ylabel("validation success rate")
    axes.set_title(f"{len(curves)} trials")
    axes.legend(loc="best", fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)
    return path


def _duration(seconds: float) -> str:
    minutes, seconds = divmod(int(round(seconds)), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{seconds:02d}" if hours else f"{minutes}:{seconds:02d}"


def markdown(settings: dict, records: list[TrialRecord], tests: list[tuple[TrialRecord, dict]],
             test_arguments: dict, plot: Path | None) -> str:
    """sweep.md: the sweep, every trial, the seeds' spread per configuration, the test evaluation."""
    config = settings["config"]
    order = ranked(records)
    counts = {status: sum(r.status == status for r in records) for status in (COMPLETE, ERROR, STOPPED, PENDING)}
    validation = config["eval_env_kwargs"].get("object_set", "the config's eval_env_kwargs")
    lines = [
        f"# Sweep {Path(settings['sweep_dir']).name}",
        "",
        f"{config['algorithm']} on {config['env_id']}, config `{settings['config_path']}`; seeds "
        f"{', '.join(map(str, settings['seeds']))}; {settings['search']} search over "
        f"{', '.join(settings['space']) or 'no other keys'}; "
        f"{settings['timesteps'] or config['train'].get('total_timesteps', 100_000)} env steps per trial.",
        "",
        f"{len(records)} trials: " + ", ".join(f"{n} {status}" for status, n in counts.items() if n) + ".",
        "",
        f"Selection on the validation split ({validation}, {int(config['eval'].get('episodes', 10))} episodes per "
        "evaluation): each trial's best evaluation (success rate, then mean return), as `best_model.zip` keeps it. "
        "Only complete trials are ranked.",
        "",
        "| rank | trial | seed | config | best validation success | 95% CI (Wilson) | at step | steps | wall time "
        "| attempts | status |",
        "|---:|---|---:|---|---:|---|---:|---:|---:|---:|---|",
    ]
    rank = 0
    for record in order:
        best = record.best
        if record.status == COMPLETE and best is not None:
            rank += 1
        success = "-" if best is None else f"{best['success_rate']:.3f} ({int(round(best['success_rate'] * best['episodes']))}/{int(best['episodes'])})"
        ci = "-" if best is None else f"{best['success_ci_low']:.3f}-{best['success_ci_high']:.3f}"
        at = "-" if best is None else f"{int(best['timesteps'])}"
        status = record.status + (f": {record.error}" if record.error else "")
        lines.append(f"| {rank if record.status == COMPLETE and best is not None else '-'} | {record.trial_id} | "
                     f"{'-' if record.seed is None else record.seed} | {describe(record.space)} | {success} | {ci} | {at} | {record.steps} | "
                     f"{_duration(record.wall_seconds)} | {record.attempts} | {status.replace('|', '/')} |")
    lines += ["", "Run directories (`bh8 train` layout): "
              f"`{Path(settings['experiment_path']) / RUNS_DIR}/<trial>_seed<seed>/`."]

    groups: dict[str, list[float]] = {}
    for record in order:
        if record.status == COMPLETE and record.best is not None:
            groups.setdefault(describe(record.space), []).append(record.best["success_rate"])
    if any(len(rates) > 1 for rates in groups.values()):
        lines += ["", "## Over seeds", "",
                  "| config | complete seeds | median best validation success | range |", "|---|---:|---:|---|"]
        for name, rates in groups.items():
            lines.append(f"| {name} | {len(rates)} | {statistics.median(rates):.3f} | {min(rates):.3f}-{max(rates):.3f} |")

    lines += ["", "## Test evaluation of the chosen model" + ("s" if len(tests) > 1 else ""), ""]
    if not tests:
        lines.append("None yet: the sweep has unfinished trials (continue it with `bh8 sweep --resume`)."
                     if counts[STOPPED] + counts[PENDING] else "None: no trial completed.")
    for record, results in tests:
        arguments = test_command_arguments(record.model, **test_arguments)
        lines += [f"Trial {record.trial_id} (seed {record.seed}, {describe(record.space)}), `{record.model}`, "
                  f"evaluated once on the test split with `bh8 eval {' '.join(arguments)}`:", ""]
        for name, part in results["by_object_set"].items():
            lines.append(f"- {name or results['env_id']}: success rate {part['success_rate']:.3f} "
                         f"({part['successes']}/{part['episodes']}, 95% Wilson CI {part['success_ci_low']:.3f}-"
                         f"{part['success_ci_high']:.3f}); mean return {part['mean_return']:.2f}")
        summary = results["summary"]
        if len(results["by_object_set"]) > 1:
            lines.append(f"- all: success rate {summary['success_rate']:.3f} ({summary['successes']}/"
                         f"{summary['episodes']}, 95% Wilson CI {summary['success_ci_low']:.3f}-"
                         f"{summary['success_ci_high']:.3f}); mean return {summary['mean_return']:.2f}")
        lines += [f"- the report is in `{TEST_DIR}/{record.run_dir.name}/`", ""]
    if plot is not None:
        lines += ["", "## Validation curves", "", f"![validation curves]({plot.name})", "",
                  "Every trial's validation success; the black line is the median over trials, the band their range."]
    return "\n".join(lines) + "\n"
