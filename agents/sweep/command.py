"""`bh8 sweep`: seeds and hyperparameters of a `bh8 train` config as Ray Tune trials, on this
machine or on a Ray cluster; selection on the validation split, one evaluation on the test split.

Each trial is a `bh8 train` run (agents/sweep/trial.py) with its own run directory; the sweep
directory (`--out`) holds:

    sweep.json              the sweep's fixed settings (config, seeds, space, resources) and, for a
                            random/grid search, every trial drawn when it started: --resume reads them
                            (agents/sweep/settings.py)
    sweep.md                every trial (config, seed, best validation success with its 95 % CI, steps,
                            wall time, attempts, status), the spread over seeds, the test evaluation
    validation_curves.png   all trials' validation curves, their median and range
    test/<trial>/           `bh8 eval` report of the chosen model on the test split (made once)
    runs/<trial>_seed<s>/   the trials' run directories (bh8 train's layout), unless --storage puts
                            them elsewhere
    ray/                    Ray Tune's own files of each launch, which bh8 never reads

`--resume` restores no pickle: it rebuilds the sweep from our own JSON records (the plan in
sweep.json; each run directory's trial.json and result.json, checked) and launches a new Ray Tune
run of the trials that have not finished, each going on from its pickle-free checkpoint. Ray Tune's
saved state (tuner.pkl and the like, pickles that run code when loaded) is never restored. An
Optuna search goes on with a new study for the trials it had not started.

Ray is an optional dependency (`pip install "bh8-gym[cluster]"`). Usage errors exit 2; a sweep
whose trials all finished exits 0 (1 if any failed for good, or the test evaluation did); a sweep
stopped with unfinished trials (Ctrl-C) exits 130 and `bh8 sweep --resume DIR` continues it.
"""
from __future__ import annotations

import argparse
import sys
from datetime import datetime, timezone
from pathlib import Path

from bh8_gym.agents.evaluation.bounds import MAX_EPISODES, MAX_SEED
from bh8_gym.agents.training.config_check import MAX_ENVS, MAX_TIMESTEPS
from bh8_gym.agents.sweep.cluster import (
    CONNECT_TIMEOUT_S,
    MAX_CPUS,
    address_argument,
    check_reachable,
    resources_argument,
    start_ray,
)
from bh8_gym.agents.sweep.settings import (
    MAX_FAILURES,
    SETTINGS_FILE,
    new_settings,
    resumed_settings,
    write_settings,
)
from bh8_gym.agents.sweep.space import MAX_SAMPLES, MAX_TRIALS, SweepConfigError, count_trials, tune_domains
from bh8_gym.cli import integer_argument

RAY_DIR = "ray"  # Ray Tune's own files (never read: --resume restores nothing of Ray's)
INSTALL_HINT = ('bh8 sweep runs its trials on Ray Tune, which is not installed; install it with\n'
                '    pip install "bh8-gym[cluster]"        (from a clone: pip install -e ".[cluster]")')


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Train a bh8 train config for several seeds (and a search space over its keys, from the config's [sweep] "
        "table) as Ray Tune trials, on this machine or a Ray cluster. Each trial is a bh8 train run; the trials are "
        "ranked by their best validation success, the best one's model is evaluated once on the test split with "
        "bh8 eval, and sweep.md and validation_curves.png are written to --out. Needs the cluster extra: "
        'pip install "bh8-gym[cluster]". See docs/cluster.md.')
    what = parser.add_argument_group("what to train")
    what.add_argument("--config", type=Path, default=None,
                      help="bh8 train TOML config, with an optional [sweep] table: seeds, samples, search, "
                           "space (default agents/configs/<algo>_<grasp|reach>.toml)")
    what.add_argument("--algo", choices=("PPO", "SAC"), default=None, help="algorithm for the default config (default PPO)")
    what.add_argument("--env", default=None, help="environment for the default config (default BH8Grasp-v0)")
    what.add_argument("--seeds", default=None, metavar="LIST",
                      help="seeds, e.g. 0,1,2,3 or 0-3: every configuration trains once per seed "
                           "(default: the config's sweep.seeds, else 0)")
    what.add_argument("--samples", type=integer_argument(1, MAX_SAMPLES), default=None,
                      help="draws of the search space's random dimensions per grid point (Optuna: configurations "
                           "tried; default: the config's sweep.samples, else 1)")
    what.add_argument("--search", choices=("random", "optuna"), default=None,
                      help="search algorithm over the space: random/grid (Ray Tune's), or optuna (needs "
                           "`pip install optuna`; default: the config's sweep.search, else random)")
    what.add_argument("--timesteps", type=integer_argument(1, MAX_TIMESTEPS), default=None,
                      help="env steps per trial (default: the config's train.total_timesteps)")
    what.add_argument("--n-envs", type=integer_argument(1, MAX_ENVS), default=None,
                      help="envs per trial (default: the trial's CPUs from --resources-per-trial)")
    where = parser.add_argument_group("where it runs")
    where.add_argument("--out", type=Path, default=None, help="sweep directory (required unless --resume)")
    where.add_argument("--address", type=address_argument, default=None,
                       help="join a running Ray cluster (`ray start --head` prints it; 'auto' finds the one on this "
                            "machine); checked to answer within " f"{CONNECT_TIMEOUT_S:g} s; default: start Ray on "
                            "this machine for this sweep")
    where.add_argument("--num-cpus", type=integer_argument(1, MAX_CPUS), default=None,
                       help="CPUs of the local Ray (without --address; default: this machine's, os.cpu_count())")
    where.add_argument("--resources-per-trial", type=resources_argument, default=None, metavar="SPEC",
                       help="what one trial reserves, e.g. cpu=2 or cpu=1,gpu=0.5 (default cpu=1)")
    where.add_argument("--max-concurrent", type=integer_argument(1, MAX_TRIALS), default=None,
                       help="trials running at once (default: as many as the resources allow)")
    where.add_argument("--storage", type=Path, default=None,
                       help="folder for the trials' run directories and Ray Tune's state: on a cluster a path every "
                            "node sees (NFS); default: the sweep directory itself. With --resume: the --storage the "
                            "sweep started with, which it needs again")
    faults = parser.add_argument_group("faults")
    faults.add_argument("--max-failures", type=integer_argument(0, MAX_FAILURES), default=None,
                        help="retries of a trial that crashed or whose worker died, each from its last checkpoint "
                             "(default 0)")
    faults.add_argument("--resume", type=Path, default=None, metavar="DIR",
                        help="continue the sweep in DIR (stopped by Ctrl-C or a crash): unfinished and failed trials go "
                             "on from their checkpoints; its settings stay those it started with")
    test = parser.add_argument_group("test evaluation (bh8 eval of the chosen model)")
    test.add_argument("--test-episodes", type=integer_argument(1, MAX_EPISODES), default=50,
                      help="episodes per object set (default: %(default)s)")
    test.add_argument("--test-seed", type=integer_argument(0, MAX_SEED), default=100_000,
                      help="seed of the first test episode (default: %(default)s, bh8 eval's)")
    test.add_argument("--test-objects", default=None,
                      help="object sets (default: bh8 eval's, the test splits test,primitives-test)")
    test.add_argument("--test-top", type=integer_argument(1, 1000), default=1,
                      help="evaluate the best N trials on the test split (default: %(default)s)")


def _trainable(settings: dict):
    from ray import tune

    from bh8_gym.agents.sweep.trial import run_trial

    return tune.with_resources(tune.with_parameters(run_trial, settings=settings), settings["resources"])


def _tuner(settings: dict, launch: str, trials: list[dict] | None, optuna_trials: int = 0):
    """A Ray Tune run of `trials` (planned or relaunched ones, by their record), or of `optuna_trials`
    new Optuna draws (each trained once per seed). Ray Tune keeps its own files under ray/<launch>;
    nothing of them is ever read back."""
    from ray import tune

    from bh8_gym.agents.sweep.trial import METRIC

    search_alg = None
    if trials is not None:
        if all(trial["name"] in {t["name"] for t in settings["trials"]} for trial in trials):
            param_space, num_samples = {"trial": tune.grid_search([trial["name"] for trial in trials])}, 1
        else:
            param_space, num_samples = {"fixed": tune.grid_search(trials)}, 1
    else:
        from ray.tune.search import Repeater
        from ray.tune.search.optuna import OptunaSearch

        # Each configuration Optuna proposes is trained once per seed; Optuna sees their mean.
        seeds = settings["seeds"]
        search_alg = Repeater(OptunaSearch(metric=METRIC, mode="max"), repeat=len(seeds), set_index=True)
        param_space, num_samples = {"space": tune_domains(settings["space"])}, optuna_trials
    return tune.Tuner(
        _trainable(settings),
        param_space=param_space,
        tune_config=tune.TuneConfig(metric=METRIC, mode="max", num_samples=num_samples, search_alg=search_alg,
                                    max_concurrent_trials=settings["max_concurrent"]),
        run_config=tune.RunConfig(name=launch, storage_path=str(Path(settings["experiment_path"]) / RAY_DIR),
                                  verbose=1, failure_config=tune.FailureConfig(max_failures=settings["max_failures"])),
    )


def _launches(settings: dict) -> list[tuple[list[dict] | None, int]]:
    """What this run of bh8 sweep launches, from our records: (trials, 0) for a list of trials by
    their record, (None, n) for n new Optuna configurations. A trial with a result.json is done."""
    from bh8_gym.agents.sweep.report import started_trials

    started = started_trials(settings, strict=True)
    if settings["search"] == "random":
        done = {trial["name"] for trial in started if trial["finished"]}
        todo = [trial for trial in settings["trials"] if trial["name"] not in done]
        return [(todo, 0)] if todo else []
    relaunch = [{key: trial[key] for key in ("name", "seed", "space")} for trial in started if not trial["finished"]]
    configurations = len({repr(sorted(trial["space"].items())) for trial in started})
    remaining = settings["samples"] - configurations
    return ([(relaunch, 0)] if relaunch else []) + ([(None, remaining)] if remaining > 0 else [])


def _report(settings: dict, records, args: argparse.Namespace) -> tuple[list, Path, bool]:
    """Test evaluation of the chosen model(s) (only once every trial has finished), sweep.md, plot."""
    from bh8_gym.agents.evaluation.evaluate import DEFAULT_EVALUATION_SETS
    from bh8_gym.agents.sweep.report import (
        COMPLETE,
        PENDING,
        PLOT_FILE,
        REPORT_FILE,
        STOPPED,
        TEST_DIR,
        markdown,
        plot_curves,
        previous_test,
        ranked,
        test_evaluation,
    )
    from bh8_gym.agents.policy_io import atomic_write

    sweep_dir = Path(settings["sweep_dir"])
    test_arguments = {"episodes": args.test_episodes, "seed": args.test_seed,
                      "objects": args.test_objects or DEFAULT_EVALUATION_SETS}
    tests, failed = [], False
    if not any(r.status in (STOPPED, PENDING) for r in records):
        chosen = [r for r in ranked(records) if r.status == COMPLETE and r.best is not None][:args.test_top]
        for record in chosen:
            if previous_test(sweep_dir / TEST_DIR / record.run_dir.name, **test_arguments) is None:
                print(f"bh8 sweep: evaluating trial {record.trial_id} (seed {record.seed}) on the test split "
                      f"({test_arguments['episodes']} episodes per object set)", flush=True)
            try:
                tests.append((record, test_evaluation(record, sweep_dir, **test_arguments)))
            except RuntimeError as error:  # bh8 eval refused (e.g. an unknown --test-objects set): said, not hidden
                print(f"bh8 sweep: {error}", file=sys.stderr)
                failed = True
    plot = plot_curves(records, sweep_dir / PLOT_FILE)
    report = sweep_dir / REPORT_FILE
    text = markdown(settings, records, tests, test_arguments, plot)
    atomic_write(report, lambda handle: handle.write(text.encode()))
    return tests, report, failed


def run(args: argparse.Namespace) -> int:
    try:
        import ray  # noqa: F401
        from ray import tune  # noqa: F401
    except ImportError:
        print(INSTALL_HINT, file=sys.stderr)
        return 2
    from bh8_gym.agents.sweep.report import COMPLETE, ERROR, PENDING, STOPPED, check_folders, collect
    from bh8_gym.agents.training.trainer import TrainingError

    try:
        settings = resumed_settings(args) if args.resume is not None else new_settings(args)
        experiment = Path(settings["experiment_path"])
        if args.resume is not None:
            check_folders(settings)
            launches = _launches(settings)
        else:
            launches = [(settings["trials"], 0)] if settings["search"] == "random" else [(None, settings["samples"])]
        if args.address:
            check_reachable(args.address)
        owns_ray = start_ray(args, settings) if launches else False
        if args.resume is None:
            write_settings(settings)
    except (SweepConfigError, TrainingError, ValueError) as error:
        print(f"bh8 sweep: {error}", file=sys.stderr)
        return 2
    resume_hint = f"continue with bh8 sweep --resume {settings['sweep_dir']}"
    errors: dict[str, str] = {}
    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S%f")
    try:
        print(f"bh8 sweep: {'resuming ' if args.resume else ''}{count_trials(settings)} trials of "
              f"{settings['config']['algorithm']} on {settings['config']['env_id']} (seeds "
              f"{', '.join(map(str, settings['seeds']))}), {settings['resources']} per trial, "
              f"{'cluster ' + args.address if args.address else 'local Ray'}; runs in {experiment / 'runs'}", flush=True)
        for number, (trials, optuna_trials) in enumerate(launches):
            results = _tuner(settings, f"{stamp}-{number}", trials, optuna_trials).fit()
            errors.update(_errors(results, settings))
    except SweepConfigError as error:
        print(f"bh8 sweep: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # a second Ctrl-C while Ray Tune was stopping the trials
        print(f"\nbh8 sweep: stopped; {resume_hint}", file=sys.stderr)
        return 130
    finally:
        if owns_ray:
            import ray

            ray.shutdown()
    try:
        records = collect(settings, errors)
        tests, report, test_failed = _report(settings, records, args)
    except KeyboardInterrupt:
        print(f"\nbh8 sweep: stopped while writing the report; {resume_hint}", file=sys.stderr)
        return 130
    counts = {status: sum(r.status == status for r in records) for status in (COMPLETE, ERROR, STOPPED, PENDING)}
    print(f"bh8 sweep: {len(records)} trials: " + ", ".join(f"{n} {s}" for s, n in counts.items() if n)
          + f"; report {report}")
    for record, results_json in tests:
        summary = results_json["summary"]
        print(f"bh8 sweep: chosen trial {record.trial_id} (seed {record.seed}): validation "
              f"{record.best['success_rate']:.3f}, test {summary['success_rate']:.3f} "
              f"({summary['successes']}/{summary['episodes']}); model {record.model}")
    if counts[STOPPED] or counts[PENDING]:
        print(f"bh8 sweep: stopped with {counts[STOPPED] + counts[PENDING]} unfinished trials; {resume_hint}",
              file=sys.stderr)
        return 130
    return 1 if counts[ERROR] or test_failed else 0


def _errors(results, settings: dict) -> dict[str, str]:
    """The trials of one launch that failed for good, by name, with their error's informative line."""
    from bh8_gym.agents.sweep.report import error_line
    from bh8_gym.agents.sweep.trial import resolve_trial

    errors = {}
    for result in results:
        if result.error is not None and result.config:
            try:
                name = resolve_trial(result.config, settings, Path(result.path).name)["name"]
            except (RuntimeError, StopIteration):
                continue
            errors[name] = error_line(result.error)
    return errors
