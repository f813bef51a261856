"""Settings dataclasses from keyword arguments: the one checker every configurable part uses.

The environments, the plant and the agents take their settings (PlantParameters, ArmSchedule,
SafetyEnvelope, ...) as a dataclass, None for the defaults, or a dict of some fields, which is what
a TOML config or JSON `--env-kwargs` can carry; `dataclass_from` turns any of these into the
dataclass and names a bad field at once rather than at the first step.
"""
from __future__ import annotations

import math
from dataclasses import fields

import numpy as np


class SettingsError(ValueError):
    """A settings value of the wrong kind or an unknown field (names it)."""


def dataclass_from(cls, value, keyword: str, error: type[ValueError] = SettingsError):
    """`value` as a `cls` settings dataclass (fields of float, int, bool, fixed-length tuples): an
    instance as it is, None for the defaults, or a mapping of some field names to values (what a
    TOML config or JSON env kwargs can carry). An unknown name or a value of the wrong kind is a
    ValueError (`error`) naming it, at once rather than at the first step."""
    if value is None:
        return cls()
    if isinstance(value, cls):
        return value
    if not hasattr(value, "keys"):
        raise error(f"{keyword} must be {cls.__name__} or a dict of its fields, got {value!r}")
    kinds = {item.name: item.type for item in fields(cls)}
    unknown = sorted(str(name) for name in value if name not in kinds)
    if unknown:
        raise error(f"{cls.__name__} ({keyword}) has no field {', '.join(map(repr, unknown))}")
    values = {name: tuple(item) if isinstance(item, list) else item for name, item in value.items()}
    for name, item in values.items():
        if not matches_annotation(str(kinds[name]), item):
            raise error(f"{keyword}: {name} must be {kinds[name]}, got {item!r}")
    return cls(**values)


def matches_annotation(annotation: str, value) -> bool:
    """Whether `value` fits a settings field's annotation: float (finite; an int will do), int, bool,
    tuple[T, ...] of a fixed length, each optionally "| None"."""
    if annotation.endswith(" | None"):
        return value is None or matches_annotation(annotation[: -len(" | None")], value)
    if annotation.startswith("tuple["):
        kinds = [kind.strip() for kind in annotation[len("tuple["):-1].split(",")]
        return (isinstance(value, tuple) and len(value) == len(kinds)
                and all(matches_annotation(kind, item) for kind, item in zip(kinds, value)))
    if annotation == "bool":
        return isinstance(value, bool)
    if isinstance(value, bool):
        return False
    if annotation == "int":
        return isinstance(value, (int, np.integer))
    return isinstance(value, (int, float, np.integer, np.floating)) and math.isfinite(value)
