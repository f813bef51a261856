"""`bh8 sweep`: seeds and hyperparameters of a `bh8 train` config as Ray Tune trials, on this
machine or on a Ray cluster; selection on the validation split, one evaluation on the test split.

Each trial is a `bh8 train` run (agents/sweep/trial.py) with its own run directory; the sweep
directory (`--out`) holds:

    sweep.json              the sweep's fixed settings (config, seeds, space, resources): --resume reads them
                            (agents/sweep/settings.py)
    ray_state.seal.json     the seal on Ray Tune's pickled state, made when the sweep stops: --resume
                            restores that state only under it, or with --trust-file (agents/sweep/state_seal.py)
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
import sys
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

INSTALL_HINT = ('bh8 sweep runs its trials on Ray Tune, which is not installed; install it with\n'
                '    pip install "bh8-gym[cluster]"        (from a clone: pip install -e ".[cluster]")')
# Ray Tune's state in the experiment folder is pickles: --resume loads it only under this account's
# seal (agents/sweep/state_seal.py) or with --trust-file.
SEAL_FILE = "ray_state.seal.json"


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
    faults.add_argument("--trust-file", action="store_true",
                        help="with --resume: load Ray Tune's saved state even if this account's bh8 sweep did not seal "
                             "it (a sweep killed with kill -9, or a folder from elsewhere). It is pickles, and "
                             "unpickling runs whatever code is in them: only for a folder you trust (default: refuse)")
    test = parser.add_argument_group("test evaluation (bh8 eval of the chosen model)")
    test.add_argument("--test-episodes", type=integer_argument(1, MAX_EPISODES), default=50,
                      help="episodes per object set (default: %(default)s)")
    test.add_argument("--test-seed", type=integer_argument(0, MAX_SEED), default=100_000,
                      help="seed of the first test episode (default: %(default)s, bh8 eval's)")
    test.add_argument("--test-objects", default=None,
                      help="object sets (default: bh8 eval's, the test splits test,primitives-test)")
    test.add_argument("--test-top", type=integer_argument(1, 1000), default=1,
                      help="evaluate the best N trials on the test split (default: %(default)s)")


def _trial_dirname(trial) -> str:
    """Ray Tune's folder of a trial: its id (sweep_report finds the run directory from it)."""
    return trial.trial_id


def _trainable(settings: dict):
    from ray import tune

    from bh8_gym.agents.sweep.trial import run_trial

    return tune.with_resources(tune.with_parameters(run_trial, settings=settings), settings["resources"])


def _tuner(settings: dict, resume: bool):
    from ray import tune

    from bh8_gym.agents.sweep.trial import METRIC

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


def _ours() -> tuple[str, ...]:
    """What bh8 sweep itself keeps in the experiment folder (the sweep directory unless --storage):
    Ray Tune reads none of it, so the seal leaves it out."""
    from bh8_gym.agents.sweep.report import PLOT_FILE, REPORT_FILE, TEST_DIR
    from bh8_gym.agents.sweep.trial import RUNS_DIR

    return RUNS_DIR, SETTINGS_FILE, SEAL_FILE, REPORT_FILE, PLOT_FILE, TEST_DIR


def _check_ray_state(settings: dict, trust: bool) -> None:
    """Before Ray Tune unpickles a stopped sweep's state: this account's bh8 sweep sealed it and
    it is unchanged (agents/sweep/state_seal.py), unless the user trusts the folder."""
    from ray import tune

    from bh8_gym.agents.sweep.state_seal import SealError, check_sealed

    experiment = Path(settings["experiment_path"])
    if trust or not tune.Tuner.can_restore(str(experiment)):
        return
    try:
        check_sealed(experiment, Path(settings["sweep_dir"]) / SEAL_FILE, skip=_ours())
    except (SealError, OSError) as error:
        raise SweepConfigError(
            f"--resume: Ray Tune's saved state in {str(experiment)!r} is pickles, which run code when loaded, and "
            f"{error}. If the folder is yours alone (bh8 sweep was killed before it could seal it), resume with "
            "--trust-file") from None


def _seal_ray_state(settings: dict) -> None:
    """Seal what Ray Tune saved in the experiment folder, so that --resume can load it (a failure is
    said: the next --resume then needs --trust-file)."""
    from bh8_gym.agents.sweep.state_seal import SealError, seal

    try:
        seal(Path(settings["experiment_path"]), Path(settings["sweep_dir"]) / SEAL_FILE, skip=_ours())
    except (SealError, OSError) as error:
        print(f"bh8 sweep: cannot seal Ray Tune's state ({error}); --resume will need --trust-file", file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    try:
        import ray  # noqa: F401
        from ray import tune  # noqa: F401
    except ImportError:
        print(INSTALL_HINT, file=sys.stderr)
        return 2
    from bh8_gym.agents.sweep.report import COMPLETE, ERROR, PENDING, STOPPED, collect
    from bh8_gym.agents.training.trainer import TrainingError

    try:
        settings = resumed_settings(args) if args.resume is not None else new_settings(args)
        experiment = Path(settings["experiment_path"])
        if args.resume is not None:
            _check_ray_state(settings, args.trust_file)
        if args.address:
            check_reachable(args.address)
        owns_ray = start_ray(args, settings)
        if args.resume is None:
            write_settings(settings)
    except (SweepConfigError, TrainingError, ValueError) as error:
        print(f"bh8 sweep: {error}", file=sys.stderr)
        return 2
    resume_hint = f"continue with bh8 sweep --resume {settings['sweep_dir']}"
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
    except KeyboardInterrupt:  # a second Ctrl-C while Ray Tune was stopping the trials
        print(f"\nbh8 sweep: stopped; {resume_hint}", file=sys.stderr)
        return 130
    finally:
        _seal_ray_state(settings)
        if owns_ray:
            import ray

            ray.shutdown()
    try:
        records = collect(results, experiment, settings["seeds"])
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
