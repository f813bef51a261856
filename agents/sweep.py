"""`bh8 sweep`: seeds and hyperparameters of a `bh8 train` config as Ray Tune trials, on this
machine or on a Ray cluster; selection on the validation split, one evaluation on the test split.

Each trial is a `bh8 train` run (agents/sweep_trial.py) with its own run directory; the sweep
directory (`--out`) holds:

    sweep.json              the sweep's fixed settings (config, seeds, space, resources): --resume reads them
    sweep.md                every trial (config, seed, best validation success with its 95 % CI, steps,
                            wall time, attempts, status), the spread over seeds, the test evaluation
    validation_curves.png   all trials' validation curves, their median and range
    test/<trial>/           `bh8 eval` report of the chosen model on the test split (made once)
    runs/<trial>_seed<s>/   the trials' run directories (bh8 train's layout), and Ray Tune's
                            experiment state, unless --storage puts them elsewhere

Ray is an optional dependency (`pip install "bh8-gym[cluster]"`). Usage errors exit 2; a sweep
whose trials all finished exits 0 (1 if any failed for good, or the test evaluation did); a sweep
stopped with unfinished trials (Ctrl-C) exits 130 and `bh8 sweep --resume DIR` continues it.
"""
from __future__ import annotations

import argparse
import os
import sys
from datetime import datetime, timezone
from pathlib import Path

from bh8_gym.agents.sweep_space import (
    SweepConfigError,
    check_sweep,
    count_trials,
    parse_seeds,
    read_sweep_table,
    tune_domains,
)
from bh8_gym.cli import integer_argument

SETTINGS_FILE = "sweep.json"
INSTALL_HINT = ('bh8 sweep runs its trials on Ray Tune, which is not installed; install it with\n'
                '    pip install "bh8-gym[cluster]"        (from a clone: pip install -e ".[cluster]")')
# Options fixed when a sweep starts: --resume takes them from sweep.json.
FIXED_OPTIONS = ("config", "algo", "env", "seeds", "samples", "search", "timesteps", "n_envs",
                 "resources_per_trial", "max_concurrent", "max_failures", "storage", "out")


def resources_argument(text: str) -> dict[str, float]:
    """argparse `type=` for --resources-per-trial: "cpu=2", "cpu=1,gpu=0.5", custom resources too."""
    resources: dict[str, float] = {}
    for item in text.split(","):
        name, equals, value = item.strip().partition("=")
        try:
            amount = float(value)
        except ValueError:
            amount = float("nan")
        if not equals or not name or not amount >= 0 or name in resources:
            raise argparse.ArgumentTypeError(f"expected NAME=AMOUNT pairs such as cpu=2 or cpu=1,gpu=0.5, got {text!r}")
        resources[name.lower() if name.lower() in ("cpu", "gpu", "memory") else name] = amount
    if resources.get("cpu", 1) <= 0:
        raise argparse.ArgumentTypeError(f"a trial needs at least some CPU (cpu > 0), got {text!r}")
    resources.setdefault("cpu", 1.0)
    return resources


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
    what.add_argument("--samples", type=integer_argument(1), default=None,
                      help="draws of the search space's random dimensions per grid point (Optuna: configurations "
                           "tried; default: the config's sweep.samples, else 1)")
    what.add_argument("--search", choices=("random", "optuna"), default=None,
                      help="search algorithm over the space: random/grid (Ray Tune's), or optuna (needs "
                           "`pip install optuna`; default: the config's sweep.search, else random)")
    what.add_argument("--timesteps", type=integer_argument(1), default=None,
                      help="env steps per trial (default: the config's train.total_timesteps)")
    what.add_argument("--n-envs", type=integer_argument(1), default=None,
                      help="envs per trial (default: the trial's CPUs from --resources-per-trial)")
    where = parser.add_argument_group("where it runs")
    where.add_argument("--out", type=Path, default=None, help="sweep directory (required unless --resume)")
    where.add_argument("--address", default=None,
                       help="join a running Ray cluster (`ray start --head` prints it; 'auto' finds the one on this "
                            "machine); default: start Ray on this machine for this sweep")
    where.add_argument("--num-cpus", type=integer_argument(1), default=None,
                       help="CPUs of the local Ray (without --address; default: this machine's, os.cpu_count())")
    where.add_argument("--resources-per-trial", type=resources_argument, default=None, metavar="SPEC",
                       help="what one trial reserves, e.g. cpu=2 or cpu=1,gpu=0.5 (default cpu=1)")
    where.add_argument("--max-concurrent", type=integer_argument(1), default=None,
                       help="trials running at once (default: as many as the resources allow)")
    where.add_argument("--storage", type=Path, default=None,
                       help="folder for the trials' run directories and Ray Tune's state: on a cluster a path every "
                            "node sees (NFS); default: the sweep directory itself")
    faults = parser.add_argument_group("faults")
    faults.add_argument("--max-failures", type=integer_argument(0), default=None,
                        help="retries of a trial that crashed or whose worker died, each from its last checkpoint "
                             "(default 0)")
    faults.add_argument("--resume", type=Path, default=None, metavar="DIR",
                        help="continue the sweep in DIR (stopped by Ctrl-C or a crash): unfinished and failed trials go "
                             "on from their checkpoints; its settings stay those it started with")
    test = parser.add_argument_group("test evaluation (bh8 eval of the chosen model)")
    test.add_argument("--test-episodes", type=integer_argument(1), default=50,
                      help="episodes per object set (default: %(default)s)")
    test.add_argument("--test-seed", type=integer_argument(0), default=100_000,
                      help="seed of the first test episode (default: %(default)s, bh8 eval's)")
    test.add_argument("--test-objects", default=None,
                      help="object sets (default: bh8 eval's, the test splits test,primitives-test)")
    test.add_argument("--test-top", type=integer_argument(1), default=1,
                      help="evaluate the best N trials on the test split (default: %(default)s)")


def _absolute_object_files(config: dict) -> None:
    """Object files named relative to where bh8 sweep runs: a trial runs elsewhere (a Ray worker)."""
    for table in ("env_kwargs", "eval_env_kwargs"):
        files = config[table].get("object_files")
        if isinstance(files, list):
            config[table]["object_files"] = [
                str(Path(entry.split(":")[0]).resolve()) + entry[len(entry.split(":")[0]):]
                if isinstance(entry, str) and Path(entry.split(":")[0]).exists() else entry for entry in files]


def new_settings(args: argparse.Namespace) -> dict:
    """The settings of a new sweep from its config and the command line, checked; sweep dir created."""
    from bh8_gym.agents.train import _check_config, default_config_path, load_config

    if args.out is None:
        raise SweepConfigError("--out DIR is required (or --resume DIR to continue a sweep)")
    config_path = args.config or default_config_path(args.algo or "PPO", args.env or "BH8Grasp-v0")
    config = load_config(config_path)
    if args.algo and config["algorithm"] != args.algo:
        raise SweepConfigError(f"--algo {args.algo} contradicts {str(config_path)!r} (algorithm = {config['algorithm']!r})")
    if args.env and args.env != config["env_id"]:
        raise SweepConfigError(f"--env {args.env} contradicts {str(config_path)!r} (env_id = {config['env_id']!r})")
    sweep = read_sweep_table(config)
    _check_config(config)
    if args.seeds is not None:
        sweep["seeds"] = parse_seeds(args.seeds)
    if args.samples is not None:
        sweep["samples"] = args.samples
    if args.search is not None:
        sweep["search"] = args.search
    check_sweep(config, sweep)
    if sweep["search"] == "optuna":
        try:
            import optuna  # noqa: F401
        except ImportError:
            raise SweepConfigError("--search optuna needs Optuna: pip install optuna") from None
    timesteps = args.timesteps
    total = timesteps or int(config["train"].get("total_timesteps", 100_000))
    freq = int(config["eval"].get("freq", 10_000))
    if total < freq:
        raise SweepConfigError(f"a trial of {total} steps makes no validation evaluation (one every eval.freq = {freq} "
                               "steps), so there is nothing to select on; raise --timesteps or lower eval.freq")
    _absolute_object_files(config)
    resources = args.resources_per_trial or {"cpu": 1.0}
    sweep_dir = args.out.resolve()
    experiment = (args.storage.resolve() if args.storage else sweep_dir.parent) / sweep_dir.name
    if (sweep_dir / SETTINGS_FILE).exists():
        raise SweepConfigError(f"{str(sweep_dir)!r} holds a sweep already; continue it with --resume {args.out} "
                               "or choose another --out")
    for folder in {sweep_dir, experiment}:
        if folder.exists() and any(folder.iterdir()):
            raise SweepConfigError(f"{str(folder)!r} is not empty; choose another --out")
    return {
        "version": 1,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "sweep_dir": str(sweep_dir),
        "experiment_path": str(experiment),
        "config_path": str(Path(config_path).resolve()),
        "config": config,
        **sweep,
        "timesteps": timesteps,
        "n_envs": args.n_envs or max(1, int(resources["cpu"])),
        "resources": resources,
        "max_concurrent": args.max_concurrent,
        "max_failures": args.max_failures or 0,
    }


def resumed_settings(args: argparse.Namespace) -> dict:
    """The settings of the sweep in --resume DIR (an option that would change them is an error)."""
    import json

    given = [f"--{name.replace('_', '-')}" for name in FIXED_OPTIONS if getattr(args, name) is not None]
    if given:
        raise SweepConfigError(f"--resume continues a sweep with the settings it started with; drop {', '.join(given)}")
    path = args.resume / SETTINGS_FILE
    if not args.resume.is_dir():
        raise SweepConfigError(f"--resume {str(args.resume)!r}: no such directory")
    try:
        settings = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise SweepConfigError(f"--resume {str(args.resume)!r}: not a sweep directory (cannot read {SETTINGS_FILE}: "
                               f"{error})") from None
    if not isinstance(settings, dict) or settings.get("version") != 1:
        raise SweepConfigError(f"--resume {str(args.resume)!r}: {SETTINGS_FILE} is not a bh8 sweep's")
    return settings


def _write_settings(settings: dict) -> None:
    from bh8_gym.agents.train import write_json_atomic

    sweep_dir = Path(settings["sweep_dir"])
    sweep_dir.mkdir(parents=True, exist_ok=True)
    write_json_atomic(sweep_dir / SETTINGS_FILE, settings)


def _trial_dirname(trial) -> str:
    """Ray Tune's folder of a trial: its id (sweep_report finds the run directory from it)."""
    return trial.trial_id


def _trainable(settings: dict):
    from ray import tune

    from bh8_gym.agents.sweep_trial import run_trial

    return tune.with_resources(tune.with_parameters(run_trial, settings=settings), settings["resources"])


def _tuner(settings: dict, resume: bool):
    from ray import tune

    from bh8_gym.agents.sweep_trial import METRIC

    experiment = Path(settings["experiment_path"])
    # A sweep stopped before Ray Tune saved any state (Ray failed to start, Ctrl-C at once) starts anew.
    if resume and tune.Tuner.can_restore(str(experiment)):
        # Errored trials go on from their checkpoints too: a resume usually follows a fixed fault.
        return tune.Tuner.restore(str(experiment), trainable=_trainable(settings), resume_unfinished=True,
                                  resume_errored=True)
    space = tune_domains(settings["space"])
    seeds = settings["seeds"]
    if settings["search"] == "optuna":
        from ray.tune.search import Repeater
        from ray.tune.search.optuna import OptunaSearch

        # Each configuration Optuna proposes is trained once per seed; Optuna sees their mean.
        search_alg = Repeater(OptunaSearch(metric=METRIC, mode="max"), repeat=len(seeds), set_index=True)
        param_space, num_samples = {"space": space}, settings["samples"] * len(seeds)
    else:
        search_alg = None
        param_space, num_samples = {"seed": tune.grid_search(seeds), "space": space}, settings["samples"]
    return tune.Tuner(
        _trainable(settings),
        param_space=param_space,
        tune_config=tune.TuneConfig(metric=METRIC, mode="max", num_samples=num_samples, search_alg=search_alg,
                                    max_concurrent_trials=settings["max_concurrent"],
                                    trial_dirname_creator=_trial_dirname),
        run_config=tune.RunConfig(name=experiment.name, storage_path=str(experiment.parent), verbose=1,
                                  failure_config=tune.FailureConfig(max_failures=settings["max_failures"])),
    )


def _start_ray(args: argparse.Namespace, settings: dict) -> bool:
    """Join --address or start Ray here; True if this process started it (and shuts it down)."""
    import ray

    if ray.is_initialized():
        return False
    try:
        if args.address:
            ray.init(address=args.address, log_to_driver=True)
        else:
            # "local": a Ray of its own even when `ray start` left one running here (that one: --address auto)
            ray.init(address="local", num_cpus=args.num_cpus or os.cpu_count() or 1, include_dashboard=False)
    except (ConnectionError, RuntimeError, ValueError) as error:
        where = f"the Ray cluster at {args.address!r}" if args.address else "a local Ray"
        hint = ("; a cluster with token authentication (Ray's default once ~/.ray/auth_token exists) also needs "
                "RAY_AUTH_MODE=token and its token here (docs/cluster.md)") if args.address else ""
        raise SweepConfigError(f"cannot start or join {where}: {error}{hint}") from None
    total = ray.cluster_resources()
    names = {"cpu": "CPU", "gpu": "GPU"}  # Ray's names in cluster_resources()
    short = {name: amount for name, amount in settings["resources"].items()
             if amount > total.get(names.get(name, name), 0.0)}
    if short:
        ray.shutdown()
        raise SweepConfigError("--resources-per-trial asks for more than the whole cluster has: " + ", ".join(
            f"{name}={amount:g} > {total.get(names.get(name, name), 0.0):g}" for name, amount in short.items()))
    return True


def _report(settings: dict, records, args: argparse.Namespace) -> tuple[list, Path, bool]:
    """Test evaluation of the chosen model(s) (only once every trial has finished), sweep.md, plot."""
    from bh8_gym.agents.evaluate import DEFAULT_EVALUATION_SETS
    from bh8_gym.agents.sweep_report import (
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
    from bh8_gym.agents.policy_file import atomic_write

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
    from bh8_gym.agents.sweep_report import COMPLETE, ERROR, PENDING, STOPPED, collect
    from bh8_gym.agents.train import TrainingError

    try:
        settings = resumed_settings(args) if args.resume is not None else new_settings(args)
        experiment = Path(settings["experiment_path"])
        owns_ray = _start_ray(args, settings)
        if args.resume is None:
            _write_settings(settings)
    except (SweepConfigError, TrainingError, ValueError) as error:
        print(f"bh8 sweep: {error}", file=sys.stderr)
        return 2
    try:
        tuner = _tuner(settings, resume=args.resume is not None)
        print(f"bh8 sweep: {'resuming ' if args.resume else ''}{count_trials(settings)} trials of "
              f"{settings['config']['algorithm']} on {settings['config']['env_id']} (seeds "
              f"{', '.join(map(str, settings['seeds']))}), {settings['resources']} per trial, "
              f"{'cluster ' + args.address if args.address else 'local Ray'}; runs in {experiment / 'runs'}", flush=True)
        results = tuner.fit()
    except SweepConfigError as error:
        print(f"bh8 sweep: {error}", file=sys.stderr)
        return 2
    finally:
        if owns_ray:
            import ray

            ray.shutdown()
    records = collect(results, experiment, settings["seeds"])
    tests, report, test_failed = _report(settings, records, args)
    counts = {status: sum(r.status == status for r in records) for status in (COMPLETE, ERROR, STOPPED, PENDING)}
    print(f"bh8 sweep: {len(records)} trials: " + ", ".join(f"{n} {s}" for s, n in counts.items() if n)
          + f"; report {report}")
    for record, results_json in tests:
        summary = results_json["summary"]
        print(f"bh8 sweep: chosen trial {record.trial_id} (seed {record.seed}): validation "
              f"{record.best['success_rate']:.3f}, test {summary['success_rate']:.3f} "
              f"({summary['successes']}/{summary['episodes']}); model {record.model}")
    if counts[STOPPED] or counts[PENDING]:
        print(f"bh8 sweep: stopped with {counts[STOPPED] + counts[PENDING]} unfinished trials; continue with "
              f"bh8 sweep --resume {settings['sweep_dir']}", file=sys.stderr)
        return 130
    return 1 if counts[ERROR] or test_failed else 0
