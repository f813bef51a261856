"""The hand's non-volatile store (the 68HC811 EEPROM of §9.1) kept in a directory.

What it holds (manual §5.2.2-§5.2.3, §5.3.2, §5.4.2; SPEC.md §3): the saved motor parameter set of
each motor (FSAVE/FLOAD), the saved global parameter set (PSAVE/PLOAD), and the never-reset
counters: odometer OD per motor (kept as total counts travelled, a float), peak temperature PTEMP,
uptime UPSECS and the serial number SN.

One JSON file, `nvstore.json`, written atomically: a temporary file in the same directory, fsync,
`os.replace`, then fsync of the directory, so a crash mid-write leaves the old or the new file,
never a torn one (SPEC.md §3). A missing, unreadable or corrupt file, or a bad value in it, falls
back to factory defaults for what is bad; loading never raises. `directory=None` keeps the store in
memory only (nothing survives the process): handy for environments that reset by snapshot.
"""
from __future__ import annotations

import json
import os
import random
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from bh8_gym.parameters import (
    MOTORS,
    UINT32_MAX,
    default_global_values,
    default_motor_values,
    global_parameters,
    motor_parameters,
)

STORE_FILENAME = "nvstore.json"
FORMAT_VERSION = 1
# Our choice: serial numbers of simulated hands are drawn (seeded) from this range, so two stores
# made with different seeds look like two different hands. §5.4.2: field upgrades read 0.
SERIAL_NUMBER_RANGE = (1000, 9999)


@dataclass
class StoreContents:
    """Everything the store holds. Parameter sets hold only stored (writable) parameters."""

    motors: dict[int, dict[str, int]]
    globals: dict[str, int]
    odometer_counts: dict[int, float] = field(default_factory=lambda: {m: 0.0 for m in MOTORS})
    peak_temperature: int = 0  # PTEMP, tenths of a degree C
    uptime_seconds: float = 0.0  # UPSECS before this power-up (fractions kept, so short runs add up)
    serial_number: int = 0


class NVStore:
    """A directory-backed non-volatile store; `load()` and the `save_*` methods are all it does."""

    def __init__(self, directory: str | os.PathLike | None, profile: str = "4.3", seed: int = 0):
        self.directory = None if directory is None else Path(directory)
        self.profile = profile
        self.seed = seed
        self._contents: StoreContents | None = None

    @property
    def path(self) -> Path | None:
        return None if self.directory is None else self.directory / STORE_FILENAME

    def load(self) -> StoreContents:
        """Read the store (a copy); a new store gets factory defaults and a seeded serial number."""
        if self._contents is None:
            self._contents = self._read()
        return _copy(self._contents)

    def save_motor_parameters(self, motor: int, values: dict[str, int]) -> None:
        """FSAVE for one motor."""
        contents = self._current()
        contents.motors[motor] = dict(values)
        self._write(contents)

    def save_global_parameters(self, values: dict[str, int]) -> None:
        """PSAVE."""
        contents = self._current()
        contents.globals = dict(values)
        self._write(contents)

    def save_counters(self, odometer_counts: dict[int, float], peak_temperature: int, uptime_seconds: float) -> None:
        """Persist the never-reset counters (OD, PTEMP, UPSECS)."""
        contents = self._current()
        contents.odometer_counts = {m: float(odometer_counts[m]) for m in MOTORS}
        contents.peak_temperature = int(peak_temperature)
        contents.uptime_seconds = float(uptime_seconds)
        self._write(contents)

    # -- internals ---------------------------------------------------------------------------

    def _current(self) -> StoreContents:
        if self._contents is None:
            self._contents = self._read()
        return self._contents

    def _factory(self) -> StoreContents:
        rng = random.Random(self.seed)
        return StoreContents(
            motors={m: default_motor_values(m, self.profile) for m in MOTORS},
            globals=default_global_values(self.profile),
            serial_number=rng.randint(*SERIAL_NUMBER_RANGE),
        )

    def _read(self) -> StoreContents:
        contents = self._factory()
        path = self.path
        if path is None or not path.exists():
            if path is not None:
                self._write(contents)  # the serial number is fixed from the first power-up on
            return contents
        try:
            raw = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return contents
        if not isinstance(raw, dict):
            return contents
        motor_table = motor_parameters(self.profile)
        global_table = global_parameters(self.profile)
        raw_motors = raw.get("motors")
        if isinstance(raw_motors, dict):
            for m in MOTORS:
                _merge(contents.motors[m], raw_motors.get(str(m)), motor_table)
        _merge(contents.globals, raw.get("globals"), global_table)
        counters = raw.get("counters")
        if isinstance(counters, dict):
            odometer = counters.get("odometer_counts")
            if isinstance(odometer, dict):
                for m in MOTORS:
                    value = odometer.get(str(m))
                    if _is_number(value) and 0 <= value <= UINT32_MAX * 1000.0:
                        contents.odometer_counts[m] = float(value)
            ptemp = counters.get("peak_temperature")
            if isinstance(ptemp, int) and 0 <= ptemp <= 1250:
                contents.peak_temperature = ptemp
            upsecs = counters.get("uptime_seconds")
            if _is_number(upsecs) and 0 <= upsecs <= UINT32_MAX:
                contents.uptime_seconds = float(upsecs)
            serial = counters.get("serial_number")
            if isinstance(serial, int) and 0 <= serial <= UINT32_MAX:
                contents.serial_number = serial
        return contents

    def _write(self, contents: StoreContents) -> None:
        self._contents = contents
        path = self.path
        if path is None:
            return
        payload = {
            "format": FORMAT_VERSION,
            "motors": {str(m): contents.motors[m] for m in MOTORS},
            "globals": contents.globals,
            "counters": {
                "odometer_counts": {str(m): contents.odometer_counts[m] for m in MOTORS},
                "peak_temperature": contents.peak_temperature,
                "uptime_seconds": contents.uptime_seconds,
                "serial_number": contents.serial_number,
            },
        }
        path.parent.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(prefix=".nvstore-", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(handle, "w", encoding="utf-8") as stream:
                json.dump(payload, stream, indent=1, sort_keys=True)
                stream.flush()
                os.fsync(stream.fileno())
            os.replace(temporary, path)
        except BaseException:
            try:
                os.unlink(temporary)
            except OSError:
                pass
            raise
        try:
            directory_fd = os.open(path.parent, os.O_RDONLY)
        except OSError:
            return
        try:
            os.fsync(directory_fd)
        except OSError:
            pass
        finally:
            os.close(directory_fd)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and value == value


def _merge(target: dict[str, int], raw, table) -> None:
    """Copy valid stored values over the defaults in `target`; ignore unknown or bad entries."""
    if not isinstance(raw, dict):
        return
    for name in target:
        value = raw.get(name)
        if isinstance(value, int) and not isinstance(value, bool) and table[name].accepts(value):
            target[name] = value


def _copy(contents: StoreContents) -> StoreContents:
    return StoreContents(
        motors={m: dict(v) for m, v in contents.motors.items()},
        globals=dict(contents.globals),
        odometer_counts=dict(contents.odometer_counts),
        peak_temperature=contents.peak_temperature,
        uptime_seconds=contents.uptime_seconds,
        serial_number=contents.serial_number,
    )
