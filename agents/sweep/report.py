"""A sweep's outcome: each trial's state read from its run directory (never a half-written one: a
trial is complete only when its result.json exists), the ranking on the validation split, the one
test evaluation of the chosen model(s) with `bh8 eval`'s code, sweep.md and the curves' plot."""
from __future__ import annotations

import argparse
import contextlib
import csv
import io
import math
import os
import shutil
import stat
import statistics
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bh8_gym.agents.policy_io import atomic_write
from bh8_gym.agents.evaluation.run_files import BEST_MODEL_FILE
from bh8_gym.agents.sweep.space import SweepConfigError, check_trial, describe
from bh8_gym.agents.sweep.trial import (
    RESULT_FILE,
    RUNS_DIR,
    TRIAL_FILE,
    TRIAL_RECORD,
    TRIAL_RESULT,
    run_dir_name,
)
from bh8_gym.agents.training.trainer import CHECKPOINT_DIR, CHECKPOINT_STATE, TrainingError, read_run_json
from bh8_gym.record_schema import Int, Schema, Table
from bh8_gym.safe_files import FileError, read_text_bounded

REPORT_FILE = "sweep.md"
PLOT_FILE = "validation_curves.png"
TEST_DIR = "test"
RESULTS_LIMIT_BYTES = 64 << 20  # bh8 eval's results.json: a row per episode
EVALUATIONS_LIMIT_BYTES = 16 << 20  # evaluations.csv: a row per evaluation, ~100 bytes each
TEST_RESULTS = Schema("bh8 eval report", required={"by_object_set": Table(), "summary": Table()},
                      optional={"seed": Int(0, 2**32)})
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


def _read_json(path: Path, schema) -> dict | None:
    """A trial's JSON record, read bounded and checked (None: missing or damaged)."""
    try:
        return read_run_json(path, schema)
    except TrainingError:
        return None


def _read_evaluations(path: Path) -> list[dict[str, float]]:
    """A run's evaluations.csv rows as finite floats (none yet: empty), read bounded. The rows are
    appended one at a time and a resumed run drops those past its checkpoint, so a row cut short by
    a kill, or one that is not numbers, is left out."""
    try:
        text = read_text_bounded(path, EVALUATIONS_LIMIT_BYTES, "evaluations.csv")
    except FileError:
        return []
    complete = []
    for row in csv.DictReader(io.StringIO(text, newline="")):
        try:
            values = {key: float(value) for key, value in row.items()}
        except (TypeError, ValueError):  # a partial last line: missing fields are None
            continue
        if all(math.isfinite(value) for value in values.values()) and {"timesteps", "success_rate"} <= set(values):
            complete.append(values)
    return complete


def error_line(error: BaseException | None) -> str:
    """The informative line of a trial's error (the last line of a worker's traceback)."""
    if error is None:
        return ""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    text = lines[-1] if lines else type(error).__name__
    return text if len(text) <= 200 else text[:197] + "..."


def started_trials(settings: dict, strict: bool = False) -> list[dict]:
    """The trials that have a run directory: {"name", "seed", "space", "finished", "run_dir"}, from
    their trial.json (checked against the sweep's space and its sweep_id) and whether their
    result.json is whole and this sweep's. `strict`: a run directory of another sweep (its records
    copied in) is a SweepConfigError, not left out."""
    runs = Path(settings["experiment_path"]) / RUNS_DIR
    found = []
    for run_dir in sorted(runs.iterdir()) if runs.is_dir() else []:
        record = _read_json(run_dir / TRIAL_FILE, TRIAL_RECORD)
        if record is None:
            continue
        if record.get("sweep_id") != settings["sweep_id"]:
            if strict:
                raise SweepConfigError(f"--resume: {str(run_dir)!r} holds another sweep's trial (its trial.json names "
                                       "another sweep_id); remove it")
            continue
        trial = {"name": record["trial_id"], "seed": record["seed"], "space": record["space"]}
        try:
            check_trial(trial, settings, str(run_dir / TRIAL_FILE))
        except SweepConfigError:
            continue  # not a trial this sweep gives: never relaunched
        if run_dir.name != run_dir_name(trial["name"], trial["seed"]):
            continue
        result = _read_json(run_dir / RESULT_FILE, TRIAL_RESULT)
        found.append({**trial, "finished": result is not None and result.get("sweep_id") == settings["sweep_id"],
                      "run_dir": run_dir})
    return found


def check_folders(settings: dict) -> None:
    """Before --resume writes anything: the folders it writes in and every entry of runs/ and test/
    are what bh8 sweep makes (folders and files), not symbolic links or other special files a
    planted one could redirect its writes through (test/<trial>.partial once sent bh8 eval's report
    over another folder's)."""
    for folder in {Path(settings["sweep_dir"]), Path(settings["experiment_path"])}:
        entries = [folder, *(folder / name for name in (RUNS_DIR, TEST_DIR, REPORT_FILE, PLOT_FILE))]
        for top in (RUNS_DIR, TEST_DIR):
            if (folder / top).is_dir() and not (folder / top).is_symlink():
                entries += [path for run_dir in (folder / top).iterdir()
                            for path in [run_dir, *(run_dir.iterdir() if _plain_folder(run_dir) else [])]]
        for path in entries:
            try:
                mode = os.lstat(path).st_mode
            except FileNotFoundError:
                continue
            if not (stat.S_ISDIR(mode) or stat.S_ISREG(mode)):
                raise SweepConfigError(f"--resume: {str(path)!r} is a symbolic link or special file, which bh8 sweep "
                                       "never makes; remove it")


def _plain_folder(path: Path) -> bool:
    return stat.S_ISDIR(os.lstat(path).st_mode)


def collect(settings: dict, errors: dict[str, str]) -> list[TrialRecord]:
    """One record per trial of the sweep from our own records: a random/grid sweep's plan, or an
    Optuna sweep's started trials and the rest pending; `errors`: this run's trials that failed for
    good (by name). A trial's numbers come from its run directory."""
    experiment = Path(settings["experiment_path"])
    started = {trial["name"]: trial for trial in started_trials(settings)}
    if settings["search"] == "random":
        planned = settings["trials"]
    else:
        planned = list(started.values())
        configurations = len({repr(sorted(trial["space"].items())) for trial in planned})
        missing = max(0, settings["samples"] - configurations) * len(settings["seeds"])
        planned += [{"name": f"(not started {index + 1})", "seed": None, "space": {}} for index in range(missing)]
    records = []
    for trial in planned:
        name, seed = trial["name"], trial["seed"]
        run_dir = experiment / RUNS_DIR / (run_dir_name(name, seed) if seed is not None else name)
        final = _read_json(run_dir / RESULT_FILE, TRIAL_RESULT) if seed is not None else None
        record = _read_json(run_dir / TRIAL_FILE, TRIAL_RECORD) if seed is not None else None
        if final is not None and final.get("sweep_id") != settings["sweep_id"]:
            final = None  # another sweep's result: not this trial's
        if record is not None and record.get("sweep_id") != settings["sweep_id"]:
            record = None
        if final is not None:
            status = COMPLETE
        elif name in errors:
            status = ERROR
        else:
            status = STOPPED if name in started else PENDING
        evaluations = _read_evaluations(run_dir / "evaluations.csv") if seed is not None else []
        if final is not None:
            steps = final["num_timesteps"]
        else:  # the last checkpoint's step: what a resumed run starts from
            checkpoint = _read_json(run_dir / CHECKPOINT_DIR / "latest.json", CHECKPOINT_STATE) or {}
            steps = int(checkpoint.get("num_timesteps", 0))
            # rows past the checkpoint are redone by the resumed run
            evaluations = [row for row in evaluations if row["timesteps"] <= steps]
        records.append(TrialRecord(
            trial_id=name, seed=seed, space=trial["space"], run_dir=run_dir, status=status,
            error=errors.get(name, "") if status == ERROR else "",
            attempts=int((record or {}).get("attempts", 0)),
            wall_seconds=float((final or record or {}).get("wall_seconds", 0.0)), steps=steps,
            evaluations=evaluations))
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
    (sweep_dir / TEST_DIR).mkdir(exist_ok=True)
    # A folder of our own, made new (never one already there, which could be a planted link).
    staging = Path(tempfile.mkdtemp(prefix=f"{target.name}.partial-", dir=sweep_dir / TEST_DIR))
    parser = argparse.ArgumentParser()
    evaluate.configure_parser(parser)
    args = parser.parse_args(test_command_arguments(record.model, episodes, seed, objects) + ["--out", str(staging)])
    output = io.StringIO()
    with contextlib.redirect_stdout(output), contextlib.redirect_stderr(output):
        code = evaluate.run(args)
    if code != 0:
        shutil.rmtree(staging, ignore_errors=True)
        raise RuntimeError(f"bh8 eval of {record.model} failed: {output.getvalue().strip()}")
    atomic_write(staging / "eval.txt", lambda handle: handle.write(output.getvalue().encode()))
    if os.path.lexists(target):  # made with other --test-* settings: replaced by the one asked for now
        aside = Path(tempfile.mkdtemp(prefix=f"{target.name}.old-", dir=sweep_dir / TEST_DIR))
        os.replace(target, aside / "old")  # a link is moved, never followed
        shutil.rmtree(aside, ignore_errors=True)
    os.replace(staging, target)
    return read_run_json(target / "results.json", TEST_RESULTS, RESULTS_LIMIT_BYTES)


def previous_test(target: Path, episodes: int, seed: int, objects: str) -> dict | None:
    """The test report in `target` if it was made with these settings (the test split is evaluated
    once; a resumed or repeated sweep reads it back), else None."""
    try:
        results = read_run_json(target / "results.json", TEST_RESULTS, RESULTS_LIMIT_BYTES)
    except TrainingError:
        return None
    if not all(isinstance(part, dict) for part in results["by_object_set"].values()):
        return None
    sets = [name.strip() for name in objects.split(",") if name.strip()]
    if (results.get("seed") == seed and results.get("object_sets") in ([""], sets)
            and all(part.get("episodes") == episodes for part in results["by_object_set"].values())):
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
    atomic_write(path, lambda handle: figure.savefig(handle, dpi=100, format="png"))  # a planted link is replaced
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
