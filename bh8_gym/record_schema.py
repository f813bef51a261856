"""What a JSON record of ours may hold, checked before anything uses it: one `Schema` per kind of
file (a checkpoint's latest.json, a run's run.json, a sweep trial's trial.json and result.json, a
policy file's metadata). A number from a file drives loops and allocations (`total_timesteps` 1e308
trained past every bound; a hold of 1e300 s never ended), so every number is range-checked and every
type checked here, and a bad record is one `error` naming the file, the key and what it must be.

A schema names the keys it knows; keys it does not know are kept (newer files) but never used.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Int:
    low: int
    high: int

    def accepts(self, value: Any) -> bool:
        return isinstance(value, int) and not isinstance(value, bool) and self.low <= value <= self.high

    def __str__(self) -> str:
        return f"an integer in {self.low}..{self.high}"


@dataclass(frozen=True)
class Real:
    low: float
    high: float

    def accepts(self, value: Any) -> bool:
        return (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
                and self.low <= value <= self.high)

    def __str__(self) -> str:
        return f"a number in [{self.low:g}, {self.high:g}]"


@dataclass(frozen=True)
class Text:
    limit: int = 4096

    def accepts(self, value: Any) -> bool:
        return isinstance(value, str) and len(value) <= self.limit

    def __str__(self) -> str:
        return "a string"


@dataclass(frozen=True)
class Flag:
    def accepts(self, value: Any) -> bool:
        return isinstance(value, bool)

    def __str__(self) -> str:
        return "true or false"


@dataclass(frozen=True)
class Table:
    def accepts(self, value: Any) -> bool:
        return isinstance(value, dict)

    def __str__(self) -> str:
        return "a table"


@dataclass(frozen=True)
class ListOf:
    kind: Any
    limit: int = 10_000

    def accepts(self, value: Any) -> bool:
        return isinstance(value, list) and len(value) <= self.limit and all(self.kind.accepts(v) for v in value)

    def __str__(self) -> str:
        return f"a list of at most {self.limit} ({self.kind})"


@dataclass(frozen=True)
class Maybe:
    """`kind`, or null."""

    kind: Any

    def accepts(self, value: Any) -> bool:
        return value is None or self.kind.accepts(value)

    def __str__(self) -> str:
        return f"{self.kind} or null"


class Schema:
    """`required` and `optional` keys with their kinds."""

    def __init__(self, what: str, required: dict[str, Any], optional: dict[str, Any] | None = None):
        self.what, self.required, self.optional = what, required, optional or {}

    def check(self, record: Any, where: str, error: type[Exception] = ValueError) -> dict:
        """`record` if it is a table whose every known key holds its kind, else an `error` naming
        `where` (the file), the key and what it must be."""
        if not isinstance(record, dict):
            raise error(f"{where} is not a {self.what} (a JSON object expected, got {type(record).__name__})")
        for key, kind in self.required.items():
            if key not in record:
                raise error(f"{where}: {self.what} has no {key!r}")
        for key, kind in {**self.required, **self.optional}.items():
            if key in record and not kind.accepts(record[key]):
                raise error(f"{where}: {key} must be {kind}, got {_shown(record[key])}")
        return record


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."
