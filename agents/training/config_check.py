"""Checks of a `bh8 train` config before anything is built or written: every key of every table it
reads, its type and its range, with the table and key named in a one-line message
("[hyperparameters] gamma must be in (0, 1], got 2.0"). A key bh8 train does not know is an error,
not silently ignored. `bh8 train` checks the config it starts with and the copy in run.json that
`--resume` reads; `bh8 sweep` checks the base config and every value its search space can give.

The tables (`KEYS`, one row per key): the top level, [train], [eval], [hyperparameters] per
algorithm, [policy_kwargs], [pretrain], and the env keywords bh8-gym's environments take as plain
values (`ENV_KEYWORDS`; the env checks its nested settings tables itself when it is built,
`check_env_tables`). Everywhere a number must be finite and nesting is at most MAX_DEPTH deep.
[sweep] is bh8 sweep's (agents/sweep/space.py checks it).

The bounds are what one machine or cluster can train (a rollout or replay buffer past them does
not fit in memory; a run past MAX_TIMESTEPS does not end) and what the algorithms define (gamma in
(0, 1], a clip range in (0, 1]); they are stated in each message.
"""
from __future__ import annotations

import dataclasses
import inspect
import math
import re
import reprlib
from typing import Any

from bh8_gym.agents.evaluation.bounds import MAX_EPISODES, MAX_SEED

ALGORITHMS = ("PPO", "SAC", "GraspChoice")  # GraspChoice: agents/choice/, no SB3 model
# torch.nn class of each `activation` name in [policy_kwargs]
ACTIVATION_CLASSES = {"tanh": "Tanh", "relu": "ReLU", "elu": "ELU", "leaky_relu": "LeakyReLU", "silu": "SiLU"}
MAX_DEPTH = 16  # tables and lists inside each other (TOML's dotted headers can nest thousands deep)
# A config file is a few KB; past this it is refused unread (tomllib takes cubic time over nested
# dotted headers: 1000 of them, 1 MB, parse in seconds).
MAX_CONFIG_BYTES = 1 << 20
MAX_TIMESTEPS = 10**10  # about four months of env steps at 1000 a second
MAX_ENVS = 256
MAX_ROLLOUT = 10**6  # PPO's n_steps x n_envs transitions held in memory
MAX_REPLAY = 10**7  # SAC's buffer_size transitions held in memory
MAX_LAYERS = 16
MAX_WIDTH = 4096
TABLES = ("env_kwargs", "eval_env_kwargs", "train", "eval", "hyperparameters", "policy_kwargs")


class ConfigError(ValueError):
    """A config value bh8 train cannot use (the message names its table and key)."""


_REPR = reprlib.Repr()
_REPR.maxlevel, _REPR.maxlist, _REPR.maxdict, _REPR.maxstring, _REPR.maxother, _REPR.maxlong = 3, 6, 6, 40, 40, 40


def shown(value: Any) -> str:
    """`value` for a message, cut short (a config can hold a million-item list or a 10**400)."""
    return _REPR.repr(value)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


# -- kinds of value: `accepts(value)` and a description for the message ------------------------


@dataclasses.dataclass(frozen=True)
class Integer:
    low: int
    high: int

    def accepts(self, value) -> bool:
        return isinstance(value, int) and not isinstance(value, bool) and self.low <= value <= self.high

    def __str__(self) -> str:
        return f"an integer in {self.low}..{self.high}"


@dataclasses.dataclass(frozen=True)
class Real:
    low: float
    high: float
    low_open: bool = False
    high_open: bool = False

    def accepts(self, value) -> bool:
        if not _is_number(value) or not math.isfinite(value):
            return False
        above = value > self.low if self.low_open else value >= self.low
        below = value < self.high if self.high_open else value <= self.high
        return above and below

    def __str__(self) -> str:
        return f"in {'(' if self.low_open else '['}{self.low:g}, {self.high:g}{')' if self.high_open else ']'}"


@dataclasses.dataclass(frozen=True)
class Flag:
    def accepts(self, value) -> bool:
        return isinstance(value, bool)

    def __str__(self) -> str:
        return "true or false"


@dataclasses.dataclass(frozen=True)
class Text:
    choices: tuple[str, ...] = ()

    def accepts(self, value) -> bool:
        return isinstance(value, str) and (not self.choices or value in self.choices) and len(value) <= 4096

    def __str__(self) -> str:
        return f"one of {', '.join(map(repr, self.choices))}" if self.choices else "a string"


@dataclasses.dataclass(frozen=True)
class Prefixed:
    """A string "<prefix><number>" (rl-zoo's "lin_3e-4", SB3's "auto_0.1"), the number in `number`."""

    prefix: str
    number: Real

    def accepts(self, value) -> bool:
        if not isinstance(value, str) or not value.startswith(self.prefix) or len(value) > 64:
            return False
        try:
            return self.number.accepts(float(value[len(self.prefix):]))
        except ValueError:
            return False

    def __str__(self) -> str:
        return f"'{self.prefix}<x>' with x {self.number}"


@dataclasses.dataclass(frozen=True)
class Either:
    kinds: tuple

    def accepts(self, value) -> bool:
        return any(kind.accepts(value) for kind in self.kinds)

    def __str__(self) -> str:
        return " or ".join(str(kind) for kind in self.kinds)


@dataclasses.dataclass(frozen=True)
class ListOf:
    item: Any
    shortest: int
    longest: int

    def accepts(self, value) -> bool:
        return (isinstance(value, list) and self.shortest <= len(value) <= self.longest
                and all(self.item.accepts(item) for item in value))

    def __str__(self) -> str:
        return f"a list of {self.shortest}..{self.longest} items, each {self.item}"


@dataclasses.dataclass(frozen=True)
class Layers:
    """net_arch: hidden layer widths, or a table of them per network (PPO: pi, vf; SAC: pi, qf)."""

    networks: tuple[str, ...]

    def accepts(self, value) -> bool:
        widths = ListOf(Integer(1, MAX_WIDTH), 0, MAX_LAYERS)
        if isinstance(value, dict):
            return bool(value) and set(value) <= set(self.networks) and all(widths.accepts(v) for v in value.values())
        return widths.accepts(value)

    def __str__(self) -> str:
        return (f"a list of at most {MAX_LAYERS} layer widths in 1..{MAX_WIDTH}, or a table of such lists "
                f"with keys {', '.join(self.networks)}")


@dataclasses.dataclass(frozen=True)
class Table:
    """A table of plain values, the names given (their kinds in `keys`)."""

    keys: dict

    def accepts(self, value) -> bool:
        return (isinstance(value, dict) and set(value) <= set(self.keys)
                and all(self.keys[name].accepts(item) for name, item in value.items()))

    def __str__(self) -> str:
        return f"a table with keys among {', '.join(self.keys) or '(none)'}"


@dataclasses.dataclass(frozen=True)
class HandFile:
    """hand_parameters: a hand file (`bh8 calibrate fit -o FILE`) or a table of a hand's parameters,
    read and checked through the file's own schema (bh8_gym/hand_file.py)."""

    def problem(self, value) -> str | None:
        """Why `value` cannot be used, or None."""
        from bh8_gym.hand_file import HandFileError, hand_parameters_from

        if not (isinstance(value, dict) or (isinstance(value, str) and 0 < len(value) <= 4096 and value.isprintable())):
            return f"must be {self}, got {shown(value)}"
        try:
            hand_parameters_from(value)
        except HandFileError as error:
            return str(error)
        return None

    def accepts(self, value) -> bool:
        return self.problem(value) is None

    def __str__(self) -> str:
        return "the path of a hand file (bh8 calibrate fit -o) or a table of hand parameters"


@dataclasses.dataclass(frozen=True)
class Unsupported:
    """A keyword SB3 takes that only a Python object can fill: a TOML config cannot give it."""

    reason: str

    def accepts(self, value) -> bool:
        return False

    def __str__(self) -> str:
        return f"left out ({self.reason})"


# -- the tables -------------------------------------------------------------------------------

TIMESTEPS = Integer(1, MAX_TIMESTEPS)
UNIT_OPEN_LOW = Real(0, 1, low_open=True)  # (0, 1]
FRACTION = Real(0, 1)
SCHEDULED = Either((UNIT_OPEN_LOW, Prefixed("lin_", UNIT_OPEN_LOW)))  # learning_rate, clip_range
OBJECT_ONLY = "it takes a Python object; bh8 train does not support it"

TRAIN_KEYS = {"total_timesteps": TIMESTEPS, "checkpoint_freq": TIMESTEPS, "n_envs": Integer(1, MAX_ENVS)}
EVAL_KEYS = {"freq": TIMESTEPS, "episodes": Integer(1, MAX_EPISODES), "seed": Integer(0, MAX_SEED)}
_SET_BY_TRAIN = {
    "seed": Unsupported("give --seed"),
    "policy_kwargs": Unsupported("give [policy_kwargs]"),
    **{name: Unsupported("bh8 train sets it") for name in ("policy", "env", "device", "verbose", "tensorboard_log",
                                                            "_init_setup_model")},
}
_COMMON_ALGORITHM_KEYS = {
    **_SET_BY_TRAIN,
    "learning_rate": SCHEDULED,
    "gamma": UNIT_OPEN_LOW,
    "use_sde": Flag(),
    "sde_sample_freq": Integer(-1, MAX_TIMESTEPS),
    "stats_window_size": Integer(1, 10**6),
}
HYPERPARAMETERS = {
    "PPO": {
        **_COMMON_ALGORITHM_KEYS,
        "n_steps": Integer(1, MAX_ROLLOUT),
        "batch_size": Integer(1, MAX_ROLLOUT),
        "n_epochs": Integer(1, 1000),
        "gae_lambda": FRACTION,
        "clip_range": SCHEDULED,
        "clip_range_vf": Real(0, 1000, low_open=True),
        "normalize_advantage": Flag(),
        "ent_coef": Real(0, 1),
        "vf_coef": Real(0, 100),
        "max_grad_norm": Real(0, 10**6, low_open=True),
        "target_kl": Real(0, 100, low_open=True),
        "rollout_buffer_class": Unsupported(OBJECT_ONLY),
        "rollout_buffer_kwargs": Unsupported(OBJECT_ONLY),
    },
    "SAC": {
        **_COMMON_ALGORITHM_KEYS,
        "buffer_size": Integer(1, MAX_REPLAY),
        "learning_starts": Integer(0, MAX_TIMESTEPS),
        "batch_size": Integer(1, 2**16),
        "tau": UNIT_OPEN_LOW,
        "train_freq": Either((Integer(1, 10**6), ListOf(Either((Integer(1, 10**6), Text(("step", "episode")))), 2, 2))),
        "gradient_steps": Either((Integer(-1, -1), Integer(1, 1000))),
        "n_steps": Integer(1, 1000),
        "ent_coef": Either((Text(("auto",)), Prefixed("auto_", Real(0, 100, low_open=True)), Real(0, 100))),
        "target_update_interval": Integer(1, 10**6),
        "target_entropy": Either((Text(("auto",)), Real(-1000, 1000))),
        "use_sde_at_warmup": Flag(),
        "action_noise": Unsupported(OBJECT_ONLY),
        "replay_buffer_class": Unsupported(OBJECT_ONLY),
        "replay_buffer_kwargs": Unsupported(OBJECT_ONLY),
        # SB3's replay buffer refuses it together with its default handle_timeout_termination
        "optimize_memory_usage": Unsupported("SB3's replay buffer refuses it with timeout handling, which bh8 "
                                             "train's time-limited episodes need"),
    },
}
_COMMON_POLICY_KEYS = {
    "activation": Text(tuple(ACTIVATION_CLASSES)),
    "log_std_init": Real(-20, 2),
    "use_sde": Flag(),
    "use_expln": Flag(),
    "share_features_extractor": Flag(),
    "normalize_images": Flag(),
    "optimizer_kwargs": Table({"eps": UNIT_OPEN_LOW, "weight_decay": FRACTION, "amsgrad": Flag(),
                               "betas": ListOf(Real(0, 1, high_open=True), 2, 2)}),
    "activation_fn": Unsupported("give activation = 'tanh', 'relu', ... instead"),
    "optimizer_class": Unsupported(OBJECT_ONLY),
    "features_extractor_class": Unsupported(OBJECT_ONLY),
    "features_extractor_kwargs": Unsupported(OBJECT_ONLY),
}
HYPERPARAMETERS["GraspChoice"] = {}  # its settings are the [choice] table's

POLICY_KWARGS = {
    "GraspChoice": {},
    "PPO": {**_COMMON_POLICY_KEYS, "net_arch": Layers(("pi", "vf")), "ortho_init": Flag(), "full_std": Flag(),
            "squash_output": Flag(), "host_observations": Unsupported("bh8 train sets it for asymmetric_critic")},
    "SAC": {**_COMMON_POLICY_KEYS, "net_arch": Layers(("pi", "qf")), "clip_mean": Real(0, 100, low_open=True),
            "n_critics": Integer(1, 10)},
}
PRETRAIN_KEYS = {
    "baseline": Text(("loop", "squeeze")),  # agents.evaluation.baselines.LOOP_BASELINES (checked equal in the tests)
    "baseline_kwargs": Table({}),  # the baseline class's keywords, checked in `_check_pretrain`
    "episodes": Integer(1, 100_000),
    "epochs": Integer(1, 10_000),
    "learning_rate": UNIT_OPEN_LOW,
    "batch_size": Integer(1, 2**16),
    "seed": Integer(0, MAX_SEED),
    "value_weight": Real(0, 100),
    "action_noise": FRACTION,
    "keep_weight": Real(0, 100),
    "keep_decay": UNIT_OPEN_LOW,
    "keep_batches": Integer(1, 10_000),
    "keep_floor": Real(0, 100),
    "teacher": ListOf(Text(), 1, 64),  # script names of the ceiling family: `_check_pretrain` checks them and the count
    "dagger_iterations": Integer(1, 20),
    "dagger_beta": FRACTION,
}
# The LOOP scripts' keywords (agents/grasps.py): control-block bytes (LCV a signed byte, gains 0..255),
# encoder counts, strain bytes, seconds; a velocity of 1e9 or a gain of 0.5 is no byte.
_BYTE, _VELOCITY, _COUNTS = Integer(0, 255), Integer(0, 127), Integer(0, 100_000)
BASELINE_KWARGS = {
    **dict.fromkeys(("close_velocity", "squeeze_velocity", "wrap_velocity"), _VELOCITY),
    **dict.fromkeys(("gain", "close_gain", "hold_gain", "spread_hold_gain", "wrap_gain", "capped_gain",
                     "strain_limit", "strain_target", "contact_rise"), _BYTE),
    **dict.fromkeys(("spread", "spread_tolerance", "stall_counts", "stall_cycles"), _COUNTS),
    **dict.fromkeys(("spread_gain", "squeeze_gain", "limit_gain"), Real(0, 100)),
    "squeeze_after": Real(0, 60), "lock_stalled": Flag(),
}
# The grasp choice's training (agents/choice/trainer.py); its settings are ChoiceSettings' fields,
# checked by building them (`_check_choice`).
CHOICE_KEYS = {
    "contexts": Integer(2, 10**6),
    "rl_episodes": Integer(0, 10**7),
    "settings": Table({name: Either((Real(-1e9, 1e9), Text(), ListOf(Text(), 1, 64)))
                       for name in ("probe", "grasps", "decision_seconds", "retries", "check_seconds",
                                    "retry_threshold", "reopen_fraction", "reopen_velocity")}),
    "models": ListOf(Table({"hidden": ListOf(Integer(1, 4096), 1, 8), "weight_decay": Real(0, 10)}), 1, 16),
}
# Env keywords taken as plain values. Others (the nested settings tables, the LOOP options) are the
# env's to check when it is built; the names are the env constructor's (`env_parameters`).
ENV_KEYWORDS = {
    "randomize": Flag(),
    "privileged": Flag(),
    "object_set": Text(),
    "object_files": ListOf(Text(), 1, 10_000),
    "success_bonus": Real(0, 1000),
    "success_height": Real(0, 1, low_open=True),
    "episode_seconds": Real(0, 3600, low_open=True),
    "max_episode_steps": Integer(1, 10**7),
    "render_mode": Unsupported("training renders nothing"),
    "render_size": ListOf(Integer(1, 4096), 2, 2),
    "hand_parameters": HandFile(),  # a calibrated hand (docs/hardware.md, bh8 calibrate)
}
TOP_LEVEL = {"algorithm": Text(ALGORITHMS), "env_id": Text(), "asymmetric_critic": Flag()}
KNOWN_TABLES = (*TABLES, "pretrain", "sweep", "choice")


# -- checking ------------------------------------------------------------------------------


def _bad(where: str, key: str, kind, value) -> ConfigError:
    if isinstance(kind, Unsupported):
        return ConfigError(f"{where} {key} is not supported: {kind.reason}")
    return ConfigError(f"{where} {key} must be {kind}, got {shown(value)}")


# A key TOML writes bare; any other is shown quoted, its control characters escaped.
_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


def check_plain(value: Any, where: str = "", path: tuple[str, ...] = ()) -> None:
    """Plain data only (tables, lists, strings, booleans, finite numbers), at most MAX_DEPTH deep:
    what TOML and JSON give, without the NaN, infinity, 10**400 or thousand-deep nesting that
    would reach torch, numpy or a recursive function as they are. `where` prefixes the message."""
    def bad(what: str) -> ConfigError:
        location = (f"[{path[0]}] {''.join(path[1:]).lstrip('.')}" if len(path) > 1
                    else f"config: {path[0]}" if path else "config")
        return ConfigError(f"{where + ': ' if where else ''}{location} {what}")

    if len(path) > MAX_DEPTH:
        raise bad(f"is nested more than {MAX_DEPTH} deep")
    if isinstance(value, dict):
        for key, item in value.items():
            if not isinstance(key, str):
                raise bad(f"has a key that is not a string: {shown(key)}")
            name = key if _BARE_KEY.fullmatch(key) else shown(key)  # quoted as TOML would: one line
            check_plain(item, where, (*path, name if not path else f".{name}"))
    elif isinstance(value, list):
        for index, item in enumerate(value):
            check_plain(item, where, (*path, f"[{index}]"))
    elif isinstance(value, float):
        if not math.isfinite(value):
            raise bad(f"must be a finite number, got {value}")
    elif isinstance(value, int) and not isinstance(value, bool):
        if abs(value) >= 2**63:
            raise bad(f"must be a 64-bit integer, got {shown(value)}")
    elif not (value is None or isinstance(value, (str, bool))):
        raise bad(f"holds an unsupported value {shown(value)}")


def _check_value(where: str, key: str, kind, value) -> None:
    """One value; a Table's entries each against their own kind, named "key.entry"."""
    if isinstance(kind, Table) and isinstance(value, dict):
        for name, item in value.items():
            if name not in kind.keys:
                raise ConfigError(f"{where} {key} has no key {shown(name)} (known: {', '.join(kind.keys) or 'none'})")
            _check_value(where, f"{key}.{name}", kind.keys[name], item)
    elif not kind.accepts(value):
        raise _bad(where, key, kind, value)


def _check_table(config: dict, table: str, keys: dict, what: str) -> None:
    values = config.get(table, {})
    if not isinstance(values, dict):
        raise ConfigError(f"[{table}] must be a table, got {shown(values)}")
    for key, value in values.items():
        if key not in keys:
            raise ConfigError(f"[{table}] has no key {key!r}{' ' + what if what else ''} "
                              f"(known: {', '.join(sorted(keys))})")
        _check_value(f"[{table}]", key, keys[key], value)


def check_config(config: Any) -> None:
    """The whole config (as load_config returns it, or run.json's copy): ConfigError names the
    first bad key. Needs no env, torch or SB3 (`check_env_tables` builds the envs)."""
    if not isinstance(config, dict):
        raise ConfigError(f"a config must be a table, got {shown(config)}")
    check_plain(config)
    for key, value in config.items():
        if key in TOP_LEVEL:
            if not TOP_LEVEL[key].accepts(value):
                raise _bad("config:", key, TOP_LEVEL[key], value)
        elif key not in KNOWN_TABLES:
            raise ConfigError(f"config: unknown key or table {key!r} (known: "
                              f"{', '.join((*TOP_LEVEL, *KNOWN_TABLES))})")
    for key in ("algorithm", "env_id"):
        if key not in config:
            raise ConfigError(f"config: {key!r} is missing")
    _check_env_id(config["env_id"])
    algorithm = config["algorithm"]
    _check_table(config, "train", TRAIN_KEYS, "")
    _check_table(config, "eval", EVAL_KEYS, "")
    _check_table(config, "hyperparameters", HYPERPARAMETERS[algorithm], f"for {algorithm}")
    _check_table(config, "policy_kwargs", POLICY_KWARGS[algorithm], f"for {algorithm}'s MlpPolicy")
    for table in ("env_kwargs", "eval_env_kwargs"):
        _check_env_table(config, table)
    _check_rules(config)
    if "pretrain" in config:
        _check_pretrain(config)
    if "choice" in config or algorithm == "GraspChoice":
        _check_choice(config)


def _check_choice(config: dict) -> None:
    if config["algorithm"] != "GraspChoice" or "choice" not in config:
        raise ConfigError("config: the [choice] table and algorithm = \"GraspChoice\" go together")
    if not config["env_id"].startswith("BH8Grasp"):
        raise ConfigError(f"config: the grasp choice grasps: it needs BH8Grasp-v0, not {config['env_id']}")
    for table in ("hyperparameters", "policy_kwargs", "pretrain"):
        if config.get(table):
            raise ConfigError(f"config: [{table}] is for SB3's algorithms; the grasp choice takes [choice]")
    _check_table(config, "choice", CHOICE_KEYS, "")
    from bh8_gym.agents.choice.policy import ChoiceSettings

    try:
        ChoiceSettings(**config["choice"].get("settings", {}))
    except (TypeError, ValueError) as error:
        raise ConfigError(f"[choice.settings] {error}") from None


def _check_env_id(env_id: str) -> None:
    import gymnasium as gym

    from bh8_gym.envs import ENV_IDS

    if env_id not in gym.registry or env_id not in ENV_IDS:  # another package's env has no LOOP to train
        raise ConfigError(f"config: env_id {env_id!r} is not a bh8-gym environment ({', '.join(ENV_IDS)})")


def _check_env_table(config: dict, table: str) -> None:
    """The env keywords ENV_KEYWORDS knows; the names against the env's constructor when it takes
    no **keywords (bh8-gym's pass those to the LOOP interface, which names a typo when built)."""
    values = config.get(table, {})
    if not isinstance(values, dict):
        raise ConfigError(f"[{table}] must be a table, got {shown(values)}")
    known = env_parameters(config["env_id"])
    for key, value in values.items():
        if known is not None and key not in known:
            raise ConfigError(f"[{table}] has no key {key!r} for {config['env_id']} (known: {', '.join(sorted(known))})")
        if isinstance(ENV_KEYWORDS.get(key), HandFile):
            problem = ENV_KEYWORDS[key].problem(value)
            if problem is not None:
                raise ConfigError(f"[{table}] {key}: {problem}")
        elif key in ENV_KEYWORDS and not ENV_KEYWORDS[key].accepts(value):
            raise _bad(f"[{table}]", key, ENV_KEYWORDS[key], value)


def _check_rules(config: dict) -> None:
    """What no single key says: rules between keys."""
    hyperparameters = config.get("hyperparameters", {})
    if config["algorithm"] == "PPO" and hyperparameters.get("normalize_advantage", True):
        if hyperparameters.get("batch_size", 64) < 2:
            raise ConfigError("[hyperparameters] batch_size must be at least 2 with normalize_advantage "
                              f"(the advantages of one sample have no spread), got {hyperparameters['batch_size']}")
    if config.get("asymmetric_critic") and config["algorithm"] != "PPO":
        raise ConfigError(f"config: asymmetric_critic needs PPO, the config says {config['algorithm']!r}")
    if config.get("asymmetric_critic") and config.get("env_kwargs", {}).get("privileged"):
        raise ConfigError("config: asymmetric_critic gives the critic privileged observations itself; remove "
                          "privileged from env_kwargs (the actor must not see them)")


def check_rollout(config: dict, n_envs: int) -> None:
    """PPO's rollout, n_steps x n_envs transitions: more than one (SB3 normalises advantages over it)
    and at most MAX_ROLLOUT (it is held in memory)."""
    if config["algorithm"] != "PPO":
        return
    n_steps = config.get("hyperparameters", {}).get("n_steps", 2048)
    if not 2 <= n_steps * n_envs <= MAX_ROLLOUT:
        raise ConfigError(f"[hyperparameters] n_steps x n_envs (the rollout) must be in 2..{MAX_ROLLOUT}, got "
                          f"{n_steps} x {n_envs}")
    batch_size = config.get("hyperparameters", {}).get("batch_size", 64)
    if batch_size > n_steps * n_envs:
        raise ConfigError(f"[hyperparameters] batch_size {batch_size} is larger than the rollout it is drawn from "
                          f"(n_steps x n_envs = {n_steps} x {n_envs})")


def _check_pretrain(config: dict) -> None:
    from bh8_gym.agents import grasps
    from bh8_gym.agents.evaluation import baselines

    if config["algorithm"] != "PPO":
        raise ConfigError("[pretrain] warm-starts an actor-critic: it needs PPO")
    if config["env_id"] != "BH8Grasp-v0":
        raise ConfigError(f"[pretrain] clones a scripted grasp: it needs BH8Grasp-v0, not {config['env_id']}")
    table = config["pretrain"]
    keys = dict(PRETRAIN_KEYS)
    baseline = table.get("baseline", "squeeze") if isinstance(table, dict) else None
    if baseline in baselines.LOOP_BASELINES:
        classes = grasps.LOOP_SCRIPTS
        names = [name for name in inspect.signature(classes[baseline]).parameters if name != "env"]
        keys["baseline_kwargs"] = Table({name: BASELINE_KWARGS.get(name, Real(-1e6, 1e6)) for name in names})
    keys["teacher"] = ListOf(Text(tuple(grasps.FAMILY)), 1, len(grasps.FAMILY))
    _check_table(config, "pretrain", keys, "")
    if table.get("keep_floor", 0.0) > table.get("keep_weight", 0.0):
        raise ConfigError(f"[pretrain] keep_floor must be in [0, keep_weight], got {table['keep_floor']}")
    teachers = table.get("teacher")
    if teachers is None and ({"dagger_iterations", "dagger_beta"} & set(table)):
        raise ConfigError("[pretrain] dagger_iterations and dagger_beta steer a teacher's DAgger: give a teacher")
    if teachers is not None and ("baseline" in table or "baseline_kwargs" in table):
        raise ConfigError("[pretrain] clones either a baseline or a teacher's choice: give baseline or teacher, "
                          "not both")
    if teachers is not None and len(set(teachers)) != len(teachers):
        raise ConfigError(f"[pretrain] teacher names a script twice: {shown(teachers)}")


def env_parameters(env_id: str) -> set[str] | None:
    """The keyword arguments the env's class takes (None: it takes any); `env_id` is registered."""
    import gymnasium as gym

    import bh8_gym  # noqa: F401  (registers the environments)

    creator = gym.envs.registration.load_env_creator(gym.registry[env_id].entry_point)
    parameters = inspect.signature(creator).parameters
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values()):
        return None
    return set(parameters) | {"max_episode_steps"}


def check_env_tables(config: dict) -> None:
    """Build the config's training and evaluation envs once (then close them): the env checks its
    nested settings and LOOP options itself, and names a bad one; the policy the one trains must
    act in the other (a `history` on one side only failed at the first evaluation, a rollout in)."""
    from bh8_gym.agents.env_factory import make_env

    spaces = {}
    for table in ("env_kwargs", "eval_env_kwargs"):
        try:
            env = make_env(config["env_id"], config.get(table, {}))
        except (TypeError, ValueError, OverflowError) as error:
            raise ConfigError(f"{table}: {error}") from None
        spaces[table] = (env.observation_space, env.action_space)
        env.close()
    if spaces["env_kwargs"] != spaces["eval_env_kwargs"]:
        raise ConfigError("env_kwargs and eval_env_kwargs give envs of different observations or actions "
                          f"({spaces['env_kwargs'][0]} against {spaces['eval_env_kwargs'][0]}): a setting such as "
                          "history must be the same in both")


def check_run_metadata(run: Any, where: str) -> None:
    """run.json as `bh8 train --resume` reads it: a config (`check_config`) and a seed."""
    if not isinstance(run, dict) or not isinstance(run.get("config"), dict):
        raise ConfigError(f"{where} holds no training config; the run cannot be resumed")
    if not Integer(0, MAX_SEED).accepts(run.get("seed")):
        raise ConfigError(f"{where}: seed must be an integer in 0..{MAX_SEED}, got {shown(run.get('seed'))}")
    try:
        check_config(run["config"])
    except ConfigError as error:
        raise ConfigError(f"{where}: {error}") from None
