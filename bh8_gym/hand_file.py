"""A hand's parameters in a file (`hand.toml`): what `bh8 calibrate fit` writes and what the
environments (`hand_parameters=`), `bh8 train`'s config and `bh8 serve --hand-parameters` read.

```toml
format = "bh8-hand-parameters/1"       # optional; refused if it names another format

[hand]                                  # PlantParameters fields, in their own units
finger_drive_efficiency = 0.431
strain_offsets = [121, 117, 133]

[uncertainty]                           # optional: one standard deviation of each fitted value
finger_drive_efficiency = 0.004

[fit]                                   # optional: where the values came from (bh8 calibrate fit)
log = "hand-log.jsonl"
```

Only the properties of a hand (`HAND_FIELDS`: motors, drive train, TorqueSwitch, gauges, masses,
pads, heat) may be set, each within a range that still describes a BH8-262; the scene's settings
(time step, table, wrist pose, solver) are the environment's and are refused, and so is any
unknown key or table. `load_hand_parameters` bounds the read (a regular file of at most
MAX_HAND_FILE_BYTES) and raises HandFileError with one line naming the key. `write_hand_parameters`
writes atomically (bh8_gym.atomic_files) and reads the result back through the same checks.
"""
from __future__ import annotations

import math
import os
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path

from bh8_gym.atomic_files import atomic_write
from bh8_gym.plant.parameters import PlantError, PlantParameters
from bh8_gym.safe_files import read_bounded

HAND_FORMAT = "bh8-hand-parameters/1"
MAX_HAND_FILE_BYTES = 64 << 10
_DEG = math.pi / 180.0

# The hand's properties a file may set: name -> (lowest, highest, unit). The ranges are wide (a
# worn or odd hand) but physical: a drive with no efficiency or a gauge with no gain is no BH8.
HAND_FIELDS: dict[str, tuple[float, float, str]] = {
    "motor_peak_torque": (0.005, 0.5, "N·m"),
    "motor_constant": (0.001, 0.1, "N·m/sqrt(W)"),
    "motor_no_load_speed": (5_000.0, 500_000.0, "counts/s"),
    "finger_drive_efficiency": (0.02, 1.0, ""),
    "spread_drive_efficiency": (0.02, 1.0, ""),
    "spread_friction_torque": (0.0, 1.0, "N·m"),
    "worm_slack": (0.0, 2.0 * _DEG, "rad"),
    "breakaway_base_torque": (0.0, 5.0, "N·m"),
    "breakaway_preload_slope": (0.0, 5.0, ""),
    "rotor_impact_gain": (0.0, 10.0, "N·m·s/rad"),
    "preload_limit": (0.1, 20.0, "N·m"),
    "strain_gain": (5.0, 2_000.0, "counts/N·m"),
    "strain_offsets": (0, 255, "counts"),
    "link_mass_scale": (0.3, 3.0, ""),
    "finger_friction": (0.0, 3.0, ""),
    "palm_friction": (0.0, 3.0, ""),
    "electronics_power": (0.0, 100.0, "W"),
    "thermal_resistance": (0.01, 100.0, "K/W"),
    "heat_capacity": (10.0, 100_000.0, "J/K"),
}
FIT_KEYS = {
    "log": str, "log_sha256": str, "excitation": str, "hand_clock": str, "fitted": list, "not_identified": list,
    "position_rms_percent": float, "position_rms_percent_before": float, "strain_rms_counts": float,
    "timing_rms_s": float, "iterations": int, "rollouts": int, "seconds": float,
}
TOP_LEVEL = {"format", "hand", "uncertainty", "fit"}


class HandFileError(ValueError):
    """A hand-parameters file that cannot be used (the message names the file and the key)."""


@dataclass(frozen=True)
class HandParameters:
    """A hand's measured PlantParameters fields, their uncertainties and the fit's provenance."""

    values: dict
    uncertainty: dict = field(default_factory=dict)
    fit: dict = field(default_factory=dict)
    source: str = ""

    def plant_parameters(self, base: PlantParameters | None = None) -> PlantParameters:
        """`base` (default: the defaults) with this hand's values."""
        params = replace(base if base is not None else PlantParameters(), **self.values)
        params.validate()
        return params


def check_hand_values(values, where: str = "[hand]") -> dict:
    """The [hand] table checked: known fields only, each in its range. Returns PlantParameters
    overrides (strain_offsets as a tuple of three ints)."""
    if not isinstance(values, dict):
        raise HandFileError(f"{where} must be a table of hand parameters, got {_shown(values)}")
    checked = {}
    for name, value in values.items():
        if name not in HAND_FIELDS:
            scene = name in PlantParameters.__dataclass_fields__
            why = ("is a setting of the scene or the solver, not a property of the hand" if scene
                   else f"is not a hand parameter (known: {', '.join(sorted(HAND_FIELDS))})")
            raise HandFileError(f"{where} {_key(name)} {why}")
        low, high, unit = HAND_FIELDS[name]
        unit = f" {unit}" if unit else ""
        if name == "strain_offsets":
            if (not isinstance(value, (list, tuple)) or len(value) != 3
                    or not all(isinstance(v, int) and not isinstance(v, bool) and low <= v <= high for v in value)):
                raise HandFileError(f"{where} strain_offsets must be three integers in {low}..{high}, got {_shown(value)}")
            checked[name] = tuple(int(v) for v in value)
            continue
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                or not low <= value <= high:
            raise HandFileError(f"{where} {name} must be a number in {low:g}..{high:g}{unit}, got {_shown(value)}")
        checked[name] = float(value)
    try:
        replace(PlantParameters(), **checked).validate()
    except PlantError as error:
        raise HandFileError(f"{where}: {error}") from None
    return checked


def _check_uncertainty(table, values: dict) -> dict:
    if not isinstance(table, dict):
        raise HandFileError(f"[uncertainty] must be a table, got {_shown(table)}")
    checked = {}
    for name, value in table.items():
        if name not in values:
            raise HandFileError(f"[uncertainty] {_key(name)} has no value in [hand]")
        items = value if name == "strain_offsets" else [value]
        if (not isinstance(items, (list, tuple)) or len(items) != (3 if name == "strain_offsets" else 1)
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0
                           for v in items)):
            raise HandFileError(f"[uncertainty] {name} must be {'three numbers' if name == 'strain_offsets' else 'a number'}"
                                f" >= 0, got {_shown(value)}")
        checked[name] = tuple(float(v) for v in items) if name == "strain_offsets" else float(value)
    return checked


def _check_fit(table) -> dict:
    if not isinstance(table, dict):
        raise HandFileError(f"[fit] must be a table, got {_shown(table)}")
    for name, value in table.items():
        kind = FIT_KEYS.get(name)
        if kind is None:
            raise HandFileError(f"[fit] {_key(name)} is not a key bh8 calibrate writes ({', '.join(sorted(FIT_KEYS))})")
        ok = (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) if kind is float
              else isinstance(value, kind) and not isinstance(value, bool))
        if kind is list:
            ok = ok and len(value) <= 64 and all(isinstance(v, str) and len(v) <= 64 for v in value)
        if kind is str:
            ok = ok and len(value) <= 4096
        if not ok:
            raise HandFileError(f"[fit] {name} must be {kind.__name__}, got {_shown(value)}")
    return dict(table)


def parse_hand_parameters(text: str, source: str = "<hand parameters>") -> HandParameters:
    """HandParameters from a file's TOML text (HandFileError prefixed with `source`)."""
    try:
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as error:
            raise HandFileError(f"not valid TOML ({error})") from None
        except RecursionError:
            raise HandFileError("not valid TOML (nested too deeply)") from None
        unknown = sorted(set(data) - TOP_LEVEL)
        if unknown:
            raise HandFileError(f"unknown key or table {_key(unknown[0])} (a hand file has {', '.join(sorted(TOP_LEVEL))})")
        if "format" in data and data["format"] != HAND_FORMAT:
            raise HandFileError(f"format is {_shown(data['format'])}; this bh8-gym reads {HAND_FORMAT!r}")
        if "hand" not in data:
            raise HandFileError("no [hand] table (the hand's parameters)")
        values = check_hand_values(data["hand"])
        uncertainty = _check_uncertainty(data.get("uncertainty", {}), values)
        fit = _check_fit(data.get("fit", {}))
    except HandFileError as error:
        raise HandFileError(f"{source}: {error}") from None
    return HandParameters(values, uncertainty, fit, source)


def load_hand_parameters(path: str | os.PathLike) -> HandParameters:
    """Read and check a hand-parameters file (module docstring)."""
    data = read_bounded(path, MAX_HAND_FILE_BYTES, "hand-parameters file", HandFileError)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise HandFileError(f"{path}: not UTF-8 text; not a hand-parameters file") from None
    return parse_hand_parameters(text, str(path))


def hand_parameters_from(value) -> HandParameters | None:
    """A HandParameters from what an env keyword or a config holds: None, a HandParameters, a path
    (str or PathLike) to a file, or a dict of [hand] values."""
    if value is None or isinstance(value, HandParameters):
        return value
    if isinstance(value, (str, os.PathLike)):
        if not str(value).strip():
            raise HandFileError("hand_parameters needs a file path, got an empty value")
        return load_hand_parameters(value)
    if isinstance(value, dict):
        return HandParameters(check_hand_values(value, "hand_parameters"), source="hand_parameters")
    raise HandFileError(f"hand_parameters must be a path to a hand file (bh8 calibrate fit -o) or a dict of hand "
                        f"parameters, got {_shown(value)}")


def format_hand_parameters(hand: HandParameters, comment: str = "") -> str:
    """The TOML text of `hand` (what `write_hand_parameters` writes)."""
    lines = [f"# {line}".rstrip() for line in comment.splitlines()]
    lines += [f"format = {_toml(HAND_FORMAT)}", "", "[hand]"]
    lines += [f"{name} = {_toml(value)}" for name, value in sorted(hand.values.items())]
    if hand.uncertainty:
        lines += ["", "[uncertainty]  # one standard deviation"]
        lines += [f"{name} = {_toml(value)}" for name, value in sorted(hand.uncertainty.items())]
    if hand.fit:
        lines += ["", "[fit]"]
        lines += [f"{name} = {_toml(value)}" for name, value in hand.fit.items()]
    return "\n".join(lines) + "\n"


def write_hand_parameters(path: str | os.PathLike, hand: HandParameters, comment: str = "") -> HandParameters:
    """Write `hand` to `path` atomically (temporary file, fsync, rename) and return it as read back
    through `load_hand_parameters` (HandFileError if it does not read back the same)."""
    text = format_hand_parameters(hand, comment)
    parse_hand_parameters(text, str(path))  # refuse before touching the disk
    target = Path(path)
    atomic_write(target, lambda handle: handle.write(text.encode("utf-8")))
    loaded = load_hand_parameters(target)
    if loaded.values != hand.values:
        raise HandFileError(f"{target}: read back {loaded.values} instead of {hand.values}")
    return loaded


def _toml(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, str):
        import json

        return json.dumps(value, ensure_ascii=True)  # a JSON string is a TOML basic string
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml(item) for item in value) + "]"
    raise TypeError(f"cannot write {value!r} to TOML")


def _key(name) -> str:
    return repr(str(name)[:60])


def _shown(value) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."
