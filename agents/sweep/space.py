"""What a `bh8 sweep` varies: the seeds and a search space over dotted config keys, read from a
training config's `[sweep]` table (and the command line), checked before any trial starts.

    [sweep]
    seeds = [0, 1, 2, 3]      # every configuration is trained once per seed
    samples = 1               # draws of the random dimensions (choice, uniform, loguniform)
    search = "random"         # or "optuna" (needs `pip install optuna`)

    [sweep.space]
    "hyperparameters.learning_rate" = {loguniform = [1e-4, 1e-3]}
    "hyperparameters.n_steps" = {grid = [512, 1024]}
    "hyperparameters.ent_coef" = {choice = [0.0, 0.01]}
    "hyperparameters.gamma" = {uniform = [0.95, 0.995]}

Grid dimensions are crossed with each other and with the seeds; `samples` draws of the random
dimensions are made for each grid point. No Ray here: `tune_domains` converts the checked space.
"""
from __future__ import annotations

import copy
import itertools
import math
import re
from typing import Any

from bh8_gym.agents.evaluation.bounds import MAX_SEED
from bh8_gym.agents.training import config_check

SWEEP_TABLE = "sweep"
SWEEP_KEYS = ("seeds", "samples", "search", "space")
SEARCHES = ("random", "optuna")
KINDS = ("grid", "choice", "uniform", "loguniform")
ENV_TABLES = ("env_kwargs", "eval_env_kwargs")
MAX_SEEDS = 1000  # seeds of one sweep (--seeds 0-999)
MAX_TRIALS = 10_000  # seeds x grid points x samples
MAX_SAMPLES = MAX_TRIALS
MAX_VALUES = 1000  # of one grid or choice dimension
# Past this many combinations of the space's values, each dimension's values are checked on the
# base config alone (`check_space_values`).
MAX_CHECKED_COMBINATIONS = 4096
# A trial's name: t0000.. for a planned (random/grid) trial, Ray Tune's id for one Optuna proposed.
TRIAL_NAME = re.compile(r"t[0-9]{4}|[0-9a-f]{5,16}_[0-9]{5}")


class SweepConfigError(ValueError):
    """A [sweep] table, search space or seed list that cannot be run (the message says why)."""


def parse_seeds(text: str) -> list[int]:
    """`--seeds 0,1,2,3` (or a range `0-3`) as a list of distinct integers in 0..MAX_SEED, at most
    MAX_SEEDS of them: checked before a range is expanded, so `0-4294967295` is refused at once."""
    seeds: list[int] = []
    usage = (f"--seeds: expected at most {MAX_SEEDS} seeds in 0..{MAX_SEED}, as comma-separated "
             f"integers or ranges such as 0,1,2 or 0-3")
    if len(text) > 100_000:
        raise SweepConfigError(f"{usage}; got {len(text)} characters")
    for part in text.split(","):
        part = part.strip()
        try:
            low, _, high = part.partition("-") if "-" in part[1:] else (part, "", part)
            low, high = int(low), int(high)  # more than 4300 digits: ValueError
        except ValueError:
            raise SweepConfigError(f"{usage}, got {text!r}") from None
        if not 0 <= low <= high <= MAX_SEED or len(seeds) + high - low + 1 > MAX_SEEDS:
            raise SweepConfigError(f"{usage}, got {part!r}")
        seeds += range(low, high + 1)
    return check_seeds(seeds, "--seeds")


def check_seeds(seeds: Any, where: str) -> list[int]:
    if (not isinstance(seeds, list) or not 0 < len(seeds) <= MAX_SEEDS
            or any(isinstance(s, bool) or not isinstance(s, int) or not 0 <= s <= MAX_SEED
                   for s in seeds)):
        raise SweepConfigError(f"{where}: expected a list of 1..{MAX_SEEDS} integers in 0..{MAX_SEED}, "
                               f"got {config_check.shown(seeds)}")
    if len(set(seeds)) != len(seeds):
        raise SweepConfigError(f"{where}: seeds repeat in {seeds!r}")
    return list(seeds)


def flatten_space(table: dict, prefix: str = "") -> dict[str, dict]:
    """[sweep.space] as {dotted key: spec}; a spec is a table with one of KINDS, and any other table
    is a level of the key (so `[sweep.space.hyperparameters]` works as well as quoted dotted keys)."""
    space: dict[str, dict] = {}
    for key, value in table.items():
        dotted = f"{prefix}{key}"
        if not isinstance(value, dict):
            raise SweepConfigError(f"sweep.space.{dotted}: expected a table such as {{grid = [...]}}, "
                                   f"{{choice = [...]}}, {{uniform = [low, high]}} or {{loguniform = [low, high]}}, "
                                   f"got {value!r}")
        if set(value) & set(KINDS):
            space[dotted] = value
        else:
            space.update(flatten_space(value, f"{dotted}."))
    return space


def check_spec(key: str, spec: dict) -> dict:
    """One dimension: exactly one kind; grid/choice a non-empty list, uniform/loguniform [low, high]."""
    if len(spec) != 1 or next(iter(spec)) not in KINDS:
        raise SweepConfigError(f"sweep.space.{key}: give exactly one of {', '.join(KINDS)}, got {spec!r}")
    kind, values = next(iter(spec.items()))
    if not isinstance(values, list) or not 0 < len(values) <= MAX_VALUES:
        raise SweepConfigError(f"sweep.space.{key}: {kind} takes a list of 1..{MAX_VALUES} values, "
                               f"got {config_check.shown(values)}")
    if kind in ("uniform", "loguniform"):
        if (len(values) != 2 or any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in values)
                or not values[0] < values[1] or (kind == "loguniform" and values[0] <= 0)
                or not all(math.isfinite(v) for v in values)):
            raise SweepConfigError(f"sweep.space.{key}: {kind} takes [low, high] with low < high"
                                   f"{' and low > 0' if kind == 'loguniform' else ''}, got {values!r}")
    return {kind: values}


def set_dotted(config: dict, key: str, value: Any) -> None:
    """config["a"]["b"]["c"] = value for key "a.b.c" (missing tables are created)."""
    *tables, last = key.split(".")
    node = config
    for name in tables:
        node = node.setdefault(name, {})
        if not isinstance(node, dict):
            raise SweepConfigError(f"sweep.space.{key}: {name!r} is not a table in the config")
    node[last] = value


def apply_space(config: dict, values: dict[str, Any]) -> dict:
    """A copy of the base config with a trial's values of the search space set."""
    config = copy.deepcopy(config)
    for key, value in values.items():
        set_dotted(config, key, value)
    return config


def check_key(config: dict, key: str) -> None:
    """A search-space key must name a setting bh8 train reads, so a typo is an error now rather than
    a key every trial silently ignores."""
    head, _, rest = key.partition(".")
    if key == "seed" or head == "seed":
        raise SweepConfigError(f"sweep.space.{key}: the seeds are [sweep] seeds (or --seeds), not a search dimension")
    if head in ("algorithm", "env_id"):
        raise SweepConfigError(f"sweep.space.{key}: one sweep trains one algorithm on one environment; "
                               "run a sweep per algorithm or environment")
    if head == "asymmetric_critic" and not rest:
        return
    tables = ("train", "eval", "hyperparameters", "policy_kwargs", "pretrain", *ENV_TABLES)
    if head not in tables or not rest:
        raise SweepConfigError(f"sweep.space.{key}: unknown config key; a search dimension is asymmetric_critic or "
                               f"a key in one of the tables {', '.join(tables)} (e.g. hyperparameters.learning_rate)")
    name = rest.split(".")[0]
    tables = {"train": config_check.TRAIN_KEYS, "eval": config_check.EVAL_KEYS,
              "hyperparameters": config_check.HYPERPARAMETERS[config["algorithm"]],
              "policy_kwargs": config_check.POLICY_KWARGS[config["algorithm"]], "pretrain": config_check.PRETRAIN_KEYS}
    if head in tables:
        known = tuple(key for key, kind in tables[head].items() if not isinstance(kind, config_check.Unsupported))
    else:
        parameters = config_check.env_parameters(config["env_id"])
        known = None if parameters is None else tuple(parameters)
    if known is not None and name not in known:
        raise SweepConfigError(f"sweep.space.{key}: unknown config key ({head} has no {name!r}; "
                               f"known: {', '.join(sorted(known))})")


def read_sweep_table(config: dict) -> dict:
    """The [sweep] table of a loaded config (removed from it), checked: seeds, samples, search and
    the flattened space. Keys are checked against the config (`check_key`)."""
    table = config.pop(SWEEP_TABLE, {})
    if not isinstance(table, dict):
        raise SweepConfigError(f"[sweep] must be a table, got {table!r}")
    unknown = sorted(set(table) - set(SWEEP_KEYS))
    if unknown:
        raise SweepConfigError(f"[sweep]: unknown key(s) {', '.join(unknown)} (known: {', '.join(SWEEP_KEYS)})")
    sweep = {"seeds": check_seeds(table["seeds"], "sweep.seeds") if "seeds" in table else [0],
             "samples": table.get("samples", 1), "search": table.get("search", "random"),
             "space": {}}
    space_table = table.get("space", {})
    if not isinstance(space_table, dict):
        raise SweepConfigError(f"[sweep] space must be a table, got {space_table!r}")
    for key, spec in flatten_space(space_table).items():
        sweep["space"][key] = check_spec(key, spec)
    check_sweep(config, sweep)
    return sweep


def check_sweep(config: dict, sweep: dict) -> None:
    """samples, search and every search-space key (also after the command line changed them)."""
    samples = sweep["samples"]
    if isinstance(samples, bool) or not isinstance(samples, int) or not 1 <= samples <= MAX_SAMPLES:
        raise SweepConfigError(f"sweep.samples must be an integer in 1..{MAX_SAMPLES}, got {samples!r}")
    if sweep["search"] not in SEARCHES:
        raise SweepConfigError(f"sweep.search must be one of {', '.join(SEARCHES)}, got {sweep['search']!r}")
    for key in sweep["space"]:
        check_key(config, key)
    if sweep["search"] == "optuna":
        grids = [key for key, spec in sweep["space"].items() if "grid" in spec]
        if grids:
            raise SweepConfigError(f"sweep.search = 'optuna' takes no grid dimensions ({', '.join(grids)}); "
                                   "use choice")
        if not sweep["space"]:
            raise SweepConfigError("sweep.search = 'optuna' needs a [sweep.space] to search")
    trials = count_trials(sweep)
    if trials > MAX_TRIALS:
        raise SweepConfigError(f"the sweep has {trials} trials (seeds x grid points x samples); at most {MAX_TRIALS}")


def check_space_values(config: dict, space: dict[str, dict], n_envs: int) -> None:
    """Every config the space can give passes bh8 train's checks (agents/training/config_check.py): each
    combination of the grid and choice values and of the ends of each range, and for a range one
    value between its ends too (an integer setting drawn from a range would get fractions). The
    checks are intervals, so a draw between two good ends is good. Past MAX_CHECKED_COMBINATIONS
    each dimension is checked on the base config alone."""
    options = {}
    for key, spec in space.items():
        (kind, values), = spec.items()
        options[key] = list(values) if kind in ("grid", "choice") else [values[0], values[1],
                                                                         values[0] + 0.382 * (values[1] - values[0])]
    combinations = math.prod(len(values) for values in options.values())
    if combinations <= MAX_CHECKED_COMBINATIONS:
        drawn = (dict(zip(options, values)) for values in itertools.product(*options.values()))
    else:
        drawn = ({key: value} for key, values in options.items() for value in values)
    for values in drawn:
        trial = apply_space(config, values)
        try:
            config_check.check_config(trial)
            config_check.check_rollout(trial, n_envs)
        except config_check.ConfigError as error:
            shown = ", ".join(f"{key} = {config_check.shown(value)}" for key, value in values.items())
            raise SweepConfigError(f"[sweep.space] gives a config bh8 train refuses ({shown}): {error}") from None


def count_trials(sweep: dict) -> int:
    """How many trials the sweep runs: seeds x grid points x samples."""
    grid = math.prod(len(spec["grid"]) for spec in sweep["space"].values() if "grid" in spec)
    return len(sweep["seeds"]) * grid * sweep["samples"]


def plan_trials(sweep: dict, plan_seed: int) -> list[dict]:
    """Every trial of a random/grid sweep, drawn here once when it starts (bh8 sweep records them in
    sweep.json, and --resume runs the unfinished ones from that record, never from Ray Tune's
    pickled state): the seeds crossed with the grid points, `samples` draws of the random
    dimensions at each, in a fixed order. Each is {"name": "t0000", "seed": s, "space": {key: value}}."""
    import numpy as np

    rng = np.random.default_rng(plan_seed)
    grids = {key: spec["grid"] for key, spec in sweep["space"].items() if "grid" in spec}
    trials = []
    for point in itertools.product(*grids.values()):
        for _ in range(sweep["samples"]):
            draw = {}
            for key, spec in sweep["space"].items():
                (kind, values), = spec.items()
                if kind == "choice":
                    draw[key] = copy.deepcopy(values[int(rng.integers(len(values)))])
                elif kind == "uniform":
                    draw[key] = float(rng.uniform(values[0], values[1]))
                elif kind == "loguniform":
                    draw[key] = float(math.exp(rng.uniform(math.log(values[0]), math.log(values[1]))))
            values = {key: copy.deepcopy(value) for key, value in zip(grids, point)}
            values.update(draw)
            ordered = {key: values[key] for key in sweep["space"]}
            trials += [{"seed": seed, "space": ordered} for seed in sweep["seeds"]]
    return [{"name": trial_name(index), **trial} for index, trial in enumerate(trials)]


def trial_name(index: int) -> str:
    return f"t{index:04d}"


def check_trial(trial: Any, sweep: dict, where: str) -> dict:
    """A recorded trial ({"name", "seed", "space"}: sweep.json's plan, or a trial.json) whose seed is
    one of the sweep's and whose every value is one its space can give (a grid or choice value, or
    within a range): what --resume will train is what the sweep was started with."""
    if not isinstance(trial, dict) or set(trial) != {"name", "seed", "space"}:
        raise SweepConfigError(f"{where}: a trial must be {{name, seed, space}}, got {config_check.shown(trial)}")
    name, seed, values = trial["name"], trial["seed"], trial["space"]
    if not isinstance(name, str) or not TRIAL_NAME.fullmatch(name):
        raise SweepConfigError(f"{where}: trial name {config_check.shown(name)} is not one bh8 sweep gives")
    if seed not in sweep["seeds"] or isinstance(seed, bool):
        raise SweepConfigError(f"{where}: trial {name}'s seed {config_check.shown(seed)} is not one of the sweep's")
    if not isinstance(values, dict) or set(values) != set(sweep["space"]):
        raise SweepConfigError(f"{where}: trial {name}'s values must set exactly the space's keys")
    for key, value in values.items():
        (kind, allowed), = sweep["space"][key].items()
        if kind in ("grid", "choice"):
            good = any(type(value) is type(option) and value == option for option in allowed)
        else:
            good = (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
                    and allowed[0] <= value <= allowed[1])
        if not good:
            raise SweepConfigError(f"{where}: trial {name}'s {key} = {config_check.shown(value)} is not in the space")
    return trial


def tune_domains(space: dict[str, dict]) -> dict[str, Any]:
    """The checked space as Ray Tune search domains (keys stay dotted)."""
    from ray import tune

    makers = {"grid": tune.grid_search, "choice": tune.choice,
              "uniform": lambda bounds: tune.uniform(*bounds), "loguniform": lambda bounds: tune.loguniform(*bounds)}
    return {key: makers[kind](values) for key, spec in space.items() for kind, values in spec.items()}


def describe(values: dict[str, Any]) -> str:
    """A trial's search-space values, short: "learning_rate=0.000316, n_steps=512"."""
    if not values:
        return "(base config)"
    names = [key.split(".")[-1] for key in values]
    parts = []
    for key, value in values.items():
        name = key.split(".")[-1] if names.count(key.split(".")[-1]) == 1 else key
        parts.append(f"{name}={value:.3g}" if isinstance(value, float) else f"{name}={value}")
    return ", ".join(parts)
