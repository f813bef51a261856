"""A `bh8 sweep`'s fixed settings (sweep.json): made from the config and the command line, or read
back by --resume, and checked the same way either way: the config and every config the search
space can give as bh8 train checks one (agents/training/config_check.py), the seeds, the resources and
every number. A resumed sweep writes only where its command line says (`resumed_settings`)."""
from __future__ import annotations

import argparse
import re
import secrets
from datetime import datetime, timezone
from pathlib import Path

from bh8_gym.agents.training import config_check
from bh8_gym.agents.training.config_check import MAX_ENVS, MAX_TIMESTEPS
from bh8_gym.agents.sweep.cluster import check_resources
from bh8_gym.agents.sweep.space import (
    MAX_TRIALS,
    SweepConfigError,
    count_trials,
    check_seeds,
    check_space_values,
    check_spec,
    check_sweep,
    check_trial,
    parse_seeds,
    plan_trials,
    read_sweep_table,
    trial_name,
)

SETTINGS_FILE = "sweep.json"
SETTINGS_LIMIT_BYTES = 16 << 20  # sweep.json: 10,000 planned trials take about 2 MB
# Options fixed when a sweep starts: --resume takes them from sweep.json.
FIXED_OPTIONS = ("config", "algo", "env", "seeds", "samples", "search", "timesteps", "n_envs",
                 "resources_per_trial", "max_concurrent", "max_failures", "out")
MAX_FAILURES = 1000


def _absolute_object_files(config: dict) -> None:
    """Object files named relative to where bh8 sweep runs: a trial runs elsewhere (a Ray worker)."""
    for table in ("env_kwargs", "eval_env_kwargs"):
        files = config[table].get("object_files")
        if isinstance(files, list):
            config[table]["object_files"] = [
                str(Path(entry.split(":")[0]).resolve()) + entry[len(entry.split(":")[0]):]
                if isinstance(entry, str) and Path(entry.split(":")[0]).exists() else entry for entry in files]


def new_settings(args: argparse.Namespace) -> dict:
    """The settings of a new sweep from its config and the command line, checked (`check_settings`)."""
    from bh8_gym.agents.training.train import default_config_path, load_config
    from bh8_gym.agents.training.trainer import _check_config

    if args.out is None:
        raise SweepConfigError("--out DIR is required (or --resume DIR to continue a sweep)")
    config_path = args.config or default_config_path(args.algo or "PPO", args.env or "BH8Grasp-v0")
    config = load_config(config_path)
    if args.algo and config["algorithm"] != args.algo:
        raise SweepConfigError(f"--algo {args.algo} contradicts {str(config_path)!r} (algorithm = {config['algorithm']!r})")
    if args.env and args.env != config["env_id"]:
        raise SweepConfigError(f"--env {args.env} contradicts {str(config_path)!r} (env_id = {config['env_id']!r})")
    _check_config(config)
    sweep = read_sweep_table(config)
    if args.seeds is not None:
        sweep["seeds"] = parse_seeds(args.seeds)
    if args.samples is not None:
        sweep["samples"] = args.samples
    if args.search is not None:
        sweep["search"] = args.search
    if sweep["search"] == "optuna":
        try:
            import optuna  # noqa: F401
        except ImportError:
            raise SweepConfigError("--search optuna needs Optuna: pip install optuna") from None
    _absolute_object_files(config)
    resources = args.resources_per_trial or {"cpu": 1.0}
    sweep_dir = args.out.resolve()
    experiment = experiment_path(sweep_dir, args.storage)
    if (sweep_dir / SETTINGS_FILE).exists():
        raise SweepConfigError(f"{str(sweep_dir)!r} holds a sweep already; continue it with --resume {args.out} "
                               "or choose another --out")
    for folder in {sweep_dir, experiment}:
        if folder.exists() and any(folder.iterdir()):
            raise SweepConfigError(f"{str(folder)!r} is not empty; choose another --out")
    plan_seed = secrets.randbelow(2**31)
    return check_settings({
        "version": 1,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "sweep_dir": str(sweep_dir),
        "experiment_path": str(experiment),
        "config_path": str(Path(config_path).resolve()),
        "config": config,
        **sweep,
        "timesteps": args.timesteps,
        "n_envs": args.n_envs or config.get("train", {}).get("n_envs") or min(MAX_ENVS, max(1, int(resources["cpu"]))),
        "resources": resources,
        "max_concurrent": args.max_concurrent,
        "max_failures": args.max_failures or 0,
        # Every trial of a random/grid sweep, drawn now: --resume runs the unfinished ones from this
        # record, never from Ray Tune's pickled state (an Optuna sweep's trials are recorded as they
        # start, in their run directories).
        "plan_seed": plan_seed,
        # Ties the trials' records to this sweep: a run directory copied from another sweep is not one
        # of its trials (--resume refuses it).
        "sweep_id": secrets.token_hex(8),
        "trials": plan_trials(sweep, plan_seed) if sweep["search"] == "random" else [],
    })


def experiment_path(sweep_dir: Path, storage: Path | None) -> Path:
    """Where the trials' run directories and Ray Tune's state go: the sweep directory itself, or
    <--storage>/<its name>."""
    return (storage.resolve() if storage else sweep_dir.parent) / sweep_dir.name


def resumed_settings(args: argparse.Namespace) -> dict:
    """The settings of the sweep in --resume DIR (an option that would change them is an error),
    checked as a new sweep's are. It writes only in DIR and in the folder the command line names
    (--storage): the paths sweep.json records are not followed, so an edited one cannot send the
    sweep's writes elsewhere."""
    from bh8_gym.safe_files import FileError, read_json_bounded

    given = [f"--{name.replace('_', '-')}" for name in FIXED_OPTIONS if getattr(args, name) is not None]
    if given:
        raise SweepConfigError(f"--resume continues a sweep with the settings it started with; drop {', '.join(given)}")
    path = args.resume / SETTINGS_FILE
    if not args.resume.is_dir():
        raise SweepConfigError(f"--resume {str(args.resume)!r}: no such directory")
    try:
        settings = read_json_bounded(path, SETTINGS_LIMIT_BYTES, SETTINGS_FILE)
    except FileError as error:
        raise SweepConfigError(f"--resume {str(args.resume)!r}: not a sweep directory ({str(error)[:300]})") from None
    if not isinstance(settings, dict) or settings.get("version") != 1:
        raise SweepConfigError(f"--resume {str(args.resume)!r}: {SETTINGS_FILE} is not a bh8 sweep's")
    sweep_dir = args.resume.resolve()
    recorded_dir, recorded_experiment = settings.get("sweep_dir"), settings.get("experiment_path")
    if args.storage is None and recorded_experiment != recorded_dir:
        where = config_check.shown(recorded_experiment)
        raise SweepConfigError(f"--resume {str(args.resume)!r}: its trials are stored in {where} ({SETTINGS_FILE}), not "
                               "in the sweep directory; pass --storage with the folder holding them to go on there")
    settings.update(sweep_dir=str(sweep_dir), experiment_path=str(experiment_path(sweep_dir, args.storage)))
    try:
        return check_settings(settings)
    except (SweepConfigError, config_check.ConfigError) as error:
        raise SweepConfigError(f"--resume {str(args.resume)!r}: {SETTINGS_FILE}: {error}") from None


def check_settings(settings: dict) -> dict:
    """A sweep's settings (new, or sweep.json's on --resume): every field, the config and every
    config the search space can give (agents/training/config_check.py). Returns them."""
    config_check.check_plain(settings)
    config = settings.get("config")
    config_check.check_config(config)
    for table in config_check.TABLES:
        config.setdefault(table, {})
    for name in ("seeds", "samples", "search", "space"):
        if name not in settings:
            raise SweepConfigError(f"{name!r} is missing")
    check_seeds(settings["seeds"], "seeds")
    if not isinstance(settings["space"], dict):
        raise SweepConfigError(f"space must be a table, got {config_check.shown(settings['space'])}")
    for key, spec in settings["space"].items():
        if not isinstance(spec, dict):
            raise SweepConfigError(f"sweep.space.{key}: expected a table, got {config_check.shown(spec)}")
        check_spec(key, spec)
    check_sweep(config, settings)
    kinds = {"timesteps": config_check.Integer(1, MAX_TIMESTEPS), "n_envs": config_check.Integer(1, MAX_ENVS),
             "max_concurrent": config_check.Integer(1, MAX_TRIALS),
             "max_failures": config_check.Integer(0, MAX_FAILURES), "config_path": config_check.Text(),
             "created": config_check.Text()}
    for name, kind in kinds.items():
        value = settings.get(name)
        if not (kind.accepts(value) or (value is None and name in ("timesteps", "max_concurrent"))):
            raise SweepConfigError(f"{name} must be {kind}, got {config_check.shown(value)}")
    try:
        settings["resources"] = check_resources(settings.get("resources"))
    except SweepConfigError as error:
        raise SweepConfigError(f"resources: {error}") from None
    check_space_values(config, settings["space"], settings["n_envs"])
    _check_plan(settings)
    # The base config's envs, built once as bh8 train would (the env checks its nested settings); a
    # search dimension inside them is checked by the trial that builds its env.
    config_check.check_env_tables(config)
    total = settings["timesteps"] or config["train"].get("total_timesteps", 100_000)
    freq = config["eval"].get("freq", 10_000)
    if total < freq:
        raise SweepConfigError(f"a trial of {total} steps makes no validation evaluation (one every eval.freq = {freq} "
                               "steps), so there is nothing to select on; raise --timesteps or lower eval.freq")
    return settings


def _check_plan(settings: dict) -> None:
    """The planned trials: a random/grid sweep's every trial in order (`plan_trials`), each one its
    space can give; none for an Optuna sweep."""
    if not (isinstance(settings.get("sweep_id"), str) and re.fullmatch(r"[0-9a-f]{16}", settings["sweep_id"])):
        raise SweepConfigError(f"sweep_id must be 16 hexadecimal digits, got {config_check.shown(settings.get('sweep_id'))}")
    plan_seed, trials = settings.get("plan_seed"), settings.get("trials")
    if not config_check.Integer(0, 2**31 - 1).accepts(plan_seed):
        raise SweepConfigError(f"plan_seed must be an integer in 0..{2**31 - 1}, got {config_check.shown(plan_seed)}")
    expected = count_trials(settings) if settings["search"] == "random" else 0
    if not isinstance(trials, list) or len(trials) != expected:
        raise SweepConfigError(f"trials must list the sweep's {expected} planned trials, got "
                               f"{config_check.shown(trials)}")
    for index, trial in enumerate(trials):
        check_trial(trial, settings, "trials")
        if trial["name"] != trial_name(index):
            raise SweepConfigError(f"trials: trial {index} is named {trial['name']!r}, not {trial_name(index)!r}")


def write_settings(settings: dict) -> None:
    from bh8_gym.agents.evaluation.run_files import write_json_atomic

    sweep_dir = Path(settings["sweep_dir"])
    sweep_dir.mkdir(parents=True, exist_ok=True)
    write_json_atomic(sweep_dir / SETTINGS_FILE, settings)
