"""The hand's non-volatile store (the 68HC811 EEPROM of §9.1) kept in a directory.

What it holds (manual §5.2.2-§5.2.3, §5.3.2, §5.4.2; SPEC.md §3): the saved motor parameter set of
each motor (FSAVE/FLOAD), the saved global parameter set (PSAVE/PLOAD), and the never-reset
counters: odometer OD per motor (kept as total counts travelled, a float), peak temperature PTEMP,
uptime UPSECS and the serial number SN.

One JSON file, `nvstore.json`, written atomically: a temporary file in the same directory, fsync,
`os.replace`, then fsync of the directory, so a crash mid-write leaves the old or the new file,
never a torn one (SPEC.md §3). One command's save (FSAVE of several motors with the counters) is
one write. A bad value in the file (out of range, or of the wrong JSON type: `true` is not a
number) falls back to its factory default. A file that cannot be read at all (corrupt, unreadable,
another format, nested too deep for the parser, larger than `STORE_SIZE_LIMIT`) is set aside as
`nvstore.json.unreadable-<time>`, never overwritten, with a `StoreWarning`, and the hand starts
from factory values.

One simulated hand at a time owns a directory: the first load takes an exclusive lock
(`StoreError` if another process or store holds it) until `close()`. A save that fails later (disk
full, directory made read-only) keeps the values in memory and warns (`StoreWarning`): a real
hand's EEPROM does not fail, so the command still succeeds. `directory=None` keeps the store in
memory only (nothing survives the process): handy for environments that reset by snapshot.
"""
from __future__ import annotations

import json
import math
import os
import random
import tempfile
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

try:
    import fcntl
except ImportError:  # Windows: no advisory lock
    fcntl = None

from bh8_gym.safe_files import read_bounded
from bh8_gym.parameters import (
    MOTORS,
    UINT32_MAX,
    default_global_values,
    default_motor_values,
    global_parameters,
    motor_parameters,
)

STORE_FILENAME = "nvstore.json"
LOCK_FILENAME = ".nvstore.lock"
TEMPORARY_PREFIX = ".nvstore-"


class StoreError(OSError):
    """The store's directory cannot be used: another simulated hand holds it, or it cannot be
    created, locked or written when the store starts."""


class StoreWarning(UserWarning):
    """A save failed (the values stay in memory), or an unreadable store file was set aside."""
FORMAT_VERSION = 1
# Our bound on the file read: a store is about 3 KB; anything much larger is not one of ours, and
# reading it whole could exhaust memory.
STORE_SIZE_LIMIT = 1 << 20
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
        self._lock_fd: int | None = None

    @property
    def path(self) -> Path | None:
        return None if self.directory is None else self.directory / STORE_FILENAME

    def load(self) -> StoreContents:
        """Read the store (a copy); a new store gets factory defaults and a seeded serial number."""
        if self._contents is None:
            self._contents = self._read()
        return _copy(self._contents)

    def save(self, counters: tuple[dict[int, float], int, float], motors: dict[int, dict[str, int]] | None = None,
             global_values: dict[str, int] | None = None) -> None:
        """One write: the never-reset `counters` (odometer counts per motor, PTEMP, UPSECS), plus the
        saved parameter sets of `motors` (FSAVE) and/or the global set (PSAVE). A failed write
        keeps the values in memory and warns (StoreWarning)."""
        contents = self._current()
        odometer_counts, peak_temperature, uptime_seconds = counters
        # A counter that is not a finite number (a simulation whose physics failed) keeps its saved
        # value: these counters are never reset, and the file must stay readable.
        for m in MOTORS:
            if _is_finite(odometer_counts[m]):
                contents.odometer_counts[m] = float(odometer_counts[m])
        if _is_finite(peak_temperature):
            contents.peak_temperature = int(peak_temperature)
        if _is_finite(uptime_seconds):
            contents.uptime_seconds = float(uptime_seconds)
        for motor, values in (motors or {}).items():
            contents.motors[motor] = dict(values)
        if global_values is not None:
            contents.globals = dict(global_values)
        try:
            self._write(contents)
        except OSError as error:
            warnings.warn(StoreWarning(f"cannot write the store {str(self.path)!r} ({error}); the saved values are "
                                       "kept only until this simulated hand stops"), stacklevel=2)

    def close(self) -> None:
        """Release the directory for another simulated hand (the contents stay readable)."""
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    # -- internals ---------------------------------------------------------------------------

    def _current(self) -> StoreContents:
        if self._contents is None:
            self._contents = self._read()
        return self._contents

    def _lock(self) -> None:
        """Own the directory (before reading it); remove temporary files a killed writer left."""
        directory = self.directory
        if directory.exists() and not directory.is_dir():  # mkdir would only say "File exists"
            raise StoreError(f"the store must be a directory; {str(directory)!r} is a file")
        try:
            directory.mkdir(parents=True, exist_ok=True)
            fd = os.open(directory / LOCK_FILENAME, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as error:
            raise StoreError(f"cannot use the store directory {str(directory)!r}: {error}") from None
        if fcntl is not None:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                os.close(fd)
                raise StoreError(f"the store directory {str(directory)!r} is in use by another simulated hand "
                                 "(bh8 serve, bh8sim:// or a Firmware): give each its own --state / state=") from None
        self._lock_fd = fd
        for leftover in directory.glob(TEMPORARY_PREFIX + "*.tmp"):
            leftover.unlink(missing_ok=True)

    def _set_aside(self, path: Path, reason: str) -> None:
        """Keep an unreadable store file under another name (never overwrite a hand's counters)."""
        aside = path.with_name(f"{STORE_FILENAME}.unreadable-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}")
        try:
            os.replace(path, aside)
        except OSError as error:
            raise StoreError(f"the store {str(path)!r} cannot be read ({reason}) nor set aside ({error}); "
                             "fix or remove it") from None
        warnings.warn(StoreWarning(f"the store {str(path)!r} cannot be read ({reason}); it is kept as "
                                   f"{str(aside)!r} and this hand starts from factory values"), stacklevel=4)

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
        if path is None:
            return contents
        if self._lock_fd is None:
            self._lock()
        raw = None
        if path.exists():
            try:
                raw = _read_json(path)
            except (OSError, ValueError, RecursionError) as error:  # RecursionError: nested too deep
                self._set_aside(path, "nested too deep" if isinstance(error, RecursionError) else str(error))
            else:
                if not isinstance(raw, dict) or not _is_integer(raw.get("format")) or raw["format"] != FORMAT_VERSION:
                    found = raw.get("format") if isinstance(raw, dict) else type(raw).__name__
                    self._set_aside(path, f"format {found!r}, this version reads format {FORMAT_VERSION}")
                    raw = None
        if raw is None:
            try:
                self._write(contents)  # the serial number is fixed from the first power-up on
            except OSError as error:
                raise StoreError(f"cannot write the store {str(path)!r}: {error}") from None
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
            if _is_integer(ptemp) and 0 <= ptemp <= 1250:
                contents.peak_temperature = ptemp
            upsecs = counters.get("uptime_seconds")
            if _is_number(upsecs) and 0 <= upsecs <= UINT32_MAX:
                contents.uptime_seconds = float(upsecs)
            serial = counters.get("serial_number")
            if _is_integer(serial) and 0 <= serial <= UINT32_MAX:
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
        handle, temporary = tempfile.mkstemp(prefix=TEMPORARY_PREFIX, suffix=".tmp", dir=path.parent)
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


def _read_json(path: Path):
    """The file's JSON; ValueError if it is not a regular file (a FIFO would block the read, a
    device never end it), is larger than STORE_SIZE_LIMIT, or is not JSON (`bh8_gym.safe_files`)."""
    return json.loads(read_bounded(path, STORE_SIZE_LIMIT, "store").decode("utf-8"))


def _is_integer(value) -> bool:
    """A JSON integer (bool is an int to Python, but `true` is no count)."""
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and value == value


def _is_finite(value) -> bool:
    return _is_number(value) and math.isfinite(value)


def _merge(target: dict[str, int], raw, table) -> None:
    """Copy valid stored values over the defaults in `target`; ignore unknown or bad entries."""
    if not isinstance(raw, dict):
        return
    for name in target:
        value = raw.get(name)
        if _is_integer(value) and table[name].accepts(value):
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
