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
import dataclasses
import inspect
import math
from typing import Any

from bh8_gym.agents.pretrain import PretrainSettings

SWEEP_TABLE = "sweep"
SWEEP_KEYS = ("seeds", "samples", "search", "space")
SEARCHES = ("random", "optuna")
KINDS = ("grid", "choice", "uniform", "loguniform")
# Keys of the config's [train] and [eval] tables that bh8 train reads.
TRAIN_KEYS = ("total_timesteps", "checkpoint_freq", "n_envs")
EVAL_KEYS = ("freq", "episodes", "seed")
ENV_TABLES = ("env_kwargs", "eval_env_kwargs")


class SweepConfigError(ValueError):
    """A [sweep] table, search space or seed list that cannot be run (the message says why)."""


def parse_seeds(text: str) -> list[int]:
    """`--seeds 0,1,2,3` (or a range `0-3`) as a list of distinct non-negative integers."""
    seeds: list[int] = []
    for part in text.split(","):
        part = part.strip()
        try:
            if "-" in part[1:]:
                low, high = (int(x) for x in part.split("-", 1))
                if high < low:
                    raise ValueError
                seeds += range(low, high + 1)
            else:
                seeds.append(int(part))
        except ValueError:
            raise SweepConfigError(f"--seeds: expected comma-separated integers or ranges such as 0,1,2 or "
                                   f"0-3, got {text!r}") from None
    return check_seeds(seeds, "--seeds")


def check_seeds(seeds: Any, where: str) -> list[int]:
    if (not isinstance(seeds, list) or not seeds
            or any(isinstance(s, bool) or not isinstance(s, int) or not 0 <= s < 2**32 for s in seeds)):
        raise SweepConfigError(f"{where}: expected a non-empty list of integers in 0..2**32-1, got {seeds!r}")
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
    if not isinstance(values, list) or not values:
        raise SweepConfigError(f"sweep.space.{key}: {kind} takes a non-empty list, got {values!r}")
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


def _env_parameters(env_id: str) -> set[str] | None:
    """The keyword arguments the env's class takes (None: it takes any)."""
    import gymnasium as gym

    import bh8_gym  # noqa: F401  (registers the environments)

    creator = gym.envs.registration.load_env_creator(gym.registry[env_id].entry_point)
    parameters = inspect.signature(creator).parameters
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values()):
        return None
    return set(parameters) | {"max_episode_steps"}


def _policy_parameters(algorithm: str) -> set[str]:
    """The policy_kwargs bh8 train passes on: the policy class's keywords, and `activation`."""
    from stable_baselines3.common.policies import ActorCriticPolicy
    from stable_baselines3.sac.policies import SACPolicy

    policy = ActorCriticPolicy if algorithm == "PPO" else SACPolicy
    return (set(inspect.signature(policy).parameters) - {"observation_space", "action_space", "lr_schedule"}) | {"activation"}


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
    if head == "train":
        known = TRAIN_KEYS
    elif head == "eval":
        known = EVAL_KEYS
    elif head == "hyperparameters":
        from bh8_gym.agents.train import TRAINER_ARGUMENTS, _algorithm_class

        known = tuple(set(inspect.signature(_algorithm_class(config["algorithm"])).parameters) - set(TRAINER_ARGUMENTS))
    elif head == "policy_kwargs":
        known = tuple(_policy_parameters(config["algorithm"]))
    elif head == "pretrain":
        known = tuple(f.name for f in dataclasses.fields(PretrainSettings))
    else:
        parameters = _env_parameters(config["env_id"])
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
    if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
        raise SweepConfigError(f"sweep.samples must be a positive integer, got {samples!r}")
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


def count_trials(sweep: dict) -> int:
    """How many trials the sweep runs: seeds x grid points x samples."""
    grid = math.prod(len(spec["grid"]) for spec in sweep["space"].values() if "grid" in spec)
    return len(sweep["seeds"]) * grid * sweep["samples"]


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
