"""The non-volatile store: persistence, atomic writes, damaged files set aside, one owner per directory.

Sources: manual §5.2.2-§5.2.3 (FSAVE/FLOAD/PSAVE/PLOAD), §5.3.2 OD and §5.4.2 PTEMP/UPSECS/SN
("never reset; maintained through power failures"); SPEC.md §3 (write-then-rename).
"""
import json
import os
import sys

import pytest

from bh8_gym.nvstore import LOCK_FILENAME, STORE_FILENAME, NVStore, StoreError, StoreWarning

COUNTERS = ({1: 5000.0, 2: 0.0, 3: 1.5, 4: 2.0}, 512, 77.5)


def loaded_and_closed(directory, **kwargs):
    store = NVStore(directory, **kwargs)
    try:
        return store.load()
    finally:
        store.close()


def store_files(directory) -> list[str]:
    return sorted(p.name for p in directory.iterdir() if p.name != LOCK_FILENAME)


def test_new_store_has_factory_defaults_and_a_fixed_serial_number(tmp_path):
    """§5.3/§5.4 defaults; SN is fixed per store from the first power-up on (§5.4.2)."""
    contents = loaded_and_closed(tmp_path, seed=3)
    assert contents.motors[1]["DP"] == 8500 and contents.motors[4]["DP"] == 1575
    assert contents.globals["BAUD"] == 96
    assert loaded_and_closed(tmp_path, seed=99).serial_number == contents.serial_number
    assert loaded_and_closed(tmp_path / "other", seed=4).serial_number != contents.serial_number


def test_saved_sets_and_counters_survive_a_new_instance(tmp_path):
    """§5.2.2 FSAVE, §5.2.3 PSAVE and the never-reset counters persist across restarts."""
    store = NVStore(tmp_path)
    contents = store.load()
    contents.motors[2]["DP"] = 1234
    store.save(COUNTERS, motors={2: contents.motors[2]}, global_values={**contents.globals, "LFT": 1})
    store.close()
    loaded = loaded_and_closed(tmp_path)
    assert loaded.motors[2]["DP"] == 1234 and loaded.motors[1]["DP"] == 8500
    assert loaded.globals["LFT"] == 1
    assert loaded.odometer_counts[1] == 5000.0 and loaded.peak_temperature == 512 and loaded.uptime_seconds == 77.5


@pytest.mark.parametrize("garbage", [b"", b"{not json", b"[1, 2]", b"\xff\xfe\x00", b'{"format": 2, "counters": {}}'])
def test_an_unreadable_store_is_set_aside_not_overwritten(tmp_path, garbage):
    """SPEC.md §3: a torn or corrupt store must not crash the firmware: factory values are used,
    with a warning, and the file is kept under another name (OD, PTEMP, UPSECS and SN are "never
    reset": a file from another format or a damaged one may still hold them)."""
    (tmp_path / STORE_FILENAME).write_bytes(garbage)
    with pytest.warns(StoreWarning, match="cannot be read"):
        contents = loaded_and_closed(tmp_path)
    assert contents.motors[3]["CT"] == 17000 and contents.globals["OTEMP"] == 0
    aside = [name for name in store_files(tmp_path) if name.startswith(STORE_FILENAME + ".unreadable-")]
    assert len(aside) == 1 and (tmp_path / aside[0]).read_bytes() == garbage
    assert json.loads((tmp_path / STORE_FILENAME).read_text())["format"] == 1


def test_out_of_range_values_in_the_file_are_ignored(tmp_path):
    """§5.3 ranges: a stored value outside its range is replaced by the default."""
    loaded_and_closed(tmp_path)
    raw = json.loads((tmp_path / STORE_FILENAME).read_text())
    raw["motors"]["1"]["MCV"] = 99999
    raw["motors"]["1"]["DP"] = "text"
    raw["motors"]["1"]["DS"] = 42
    raw["globals"]["BAUD"] = 97
    (tmp_path / STORE_FILENAME).write_text(json.dumps(raw))
    loaded = loaded_and_closed(tmp_path)
    assert loaded.motors[1]["MCV"] == 100 and loaded.motors[1]["DP"] == 8500 and loaded.motors[1]["DS"] == 42
    assert loaded.globals["BAUD"] == 96


def test_a_failed_write_keeps_the_file_and_the_values_and_warns(tmp_path, monkeypatch):
    """SPEC.md §3: a crash mid-write leaves the previous file intact and no temporary behind. A
    save that fails (disk full, read-only directory) is a warning, not an exception: a real hand's
    EEPROM does not fail, so the firmware's FSAVE/PSAVE still succeed; memory holds the values."""
    store = NVStore(tmp_path)
    store.save(({m: 1000.0 for m in (1, 2, 3, 4)}, 400, 10.0))
    before = (tmp_path / STORE_FILENAME).read_bytes()

    def crash(*args):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", crash)
    with pytest.warns(StoreWarning, match="No space left"):
        store.save(({m: 9000.0 for m in (1, 2, 3, 4)}, 500, 20.0))
    assert (tmp_path / STORE_FILENAME).read_bytes() == before
    assert store_files(tmp_path) == [STORE_FILENAME]
    assert store.load().peak_temperature == 500


def test_one_command_is_one_write(tmp_path, monkeypatch):
    """FSAVE of several motors and the counters land together or not at all (each per-motor write
    used to be its own file replacement: a kill between them left a half-saved FSAVE)."""
    store = NVStore(tmp_path)
    motors = store.load().motors
    replaced = []
    real_replace = os.replace
    monkeypatch.setattr(os, "replace", lambda *args: (replaced.append(args), real_replace(*args)))
    store.save(COUNTERS, motors={m: {**motors[m], "ACCEL": 40} for m in (1, 2, 3, 4)})
    assert len(replaced) == 1
    store.close()


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX advisory lock")
def test_a_directory_has_one_owner_at_a_time(tmp_path):
    """Two simulated hands on one directory would undo each other's saves (each writes its whole
    copy): the second is refused, clearly, until the first closes."""
    first = NVStore(tmp_path)
    first.load()
    with pytest.raises(StoreError, match="in use by another simulated hand"):
        NVStore(tmp_path).load()
    first.close()
    assert loaded_and_closed(tmp_path).globals["BAUD"] == 96


def test_a_file_where_the_store_directory_should_be_is_named(tmp_path):
    """`--state hand.json` (a file, not a directory) is refused saying so, not with mkdir's "File exists"."""
    path = tmp_path / "hand.json"
    path.write_text("{}")
    with pytest.raises(StoreError, match="must be a directory; .*hand.json' is a file"):
        NVStore(path).load()
    assert path.read_text() == "{}"


def test_temporary_files_of_a_killed_writer_are_removed(tmp_path):
    loaded_and_closed(tmp_path)
    (tmp_path / ".nvstore-abc123.tmp").write_text("{half")
    loaded_and_closed(tmp_path)
    assert store_files(tmp_path) == [STORE_FILENAME]


def test_memory_store_writes_nothing(tmp_path):
    """directory=None: a memory-only store (no files), still answering loads and saves."""
    store = NVStore(None)
    store.save(({m: 1.0 for m in (1, 2, 3, 4)}, 300, 1.0))
    assert store.load().peak_temperature == 300
    assert list(tmp_path.iterdir()) == []


# -- hostile store files (issue 19) -----------------------------------------------------------


def _aside(directory) -> list[str]:
    return [name for name in store_files(directory) if name.startswith(STORE_FILENAME + ".unreadable-")]


def test_a_store_nested_too_deep_for_the_parser_is_set_aside(tmp_path):
    """JSON nested 200,000 deep makes json.loads raise RecursionError, not ValueError: it is one
    more unreadable store (SPEC.md §3: set aside with a warning, factory values), not a crash."""
    (tmp_path / STORE_FILENAME).write_text("[" * 200_000 + "]" * 200_000)
    with pytest.warns(StoreWarning, match="nested too deep"):
        contents = loaded_and_closed(tmp_path)
    assert contents.globals["BAUD"] == 96
    assert len(_aside(tmp_path)) == 1


def test_a_store_larger_than_any_store_is_set_aside_unread(tmp_path):
    """A store is a few KB; a file past STORE_SIZE_LIMIT is not read whole into memory."""
    from bh8_gym.nvstore import STORE_SIZE_LIMIT

    (tmp_path / STORE_FILENAME).write_text(json.dumps({"format": 1, "pad": "x" * STORE_SIZE_LIMIT}))
    with pytest.warns(StoreWarning, match="larger than"):
        loaded_and_closed(tmp_path)
    assert len(_aside(tmp_path)) == 1


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX FIFO")
@pytest.mark.timeout(30)
def test_a_store_that_is_a_fifo_is_set_aside_without_blocking(tmp_path):
    """A FIFO in place of nvstore.json would block the read for ever: refused as not a regular file."""
    os.mkfifo(tmp_path / STORE_FILENAME)
    with pytest.warns(StoreWarning, match="not a regular file"):
        loaded_and_closed(tmp_path)
    assert len(_aside(tmp_path)) == 1


def test_values_of_the_wrong_json_type_fall_back_to_their_defaults(tmp_path):
    """`true` is an int to Python but no count: §5.4.2 SN, PTEMP and the §5.3 parameters are
    integers, so a boolean in the file is a bad value (its default is used), and PGET SN answers
    the hand's number, never "True"."""
    from bh8_gym.firmware import Firmware

    serial_number = loaded_and_closed(tmp_path, seed=5).serial_number
    raw = json.loads((tmp_path / STORE_FILENAME).read_text())
    raw["counters"].update(serial_number=True, peak_temperature=True)
    raw["motors"]["1"]["HOLD"] = True
    raw["globals"]["LFT"] = True
    (tmp_path / STORE_FILENAME).write_text(json.dumps(raw))
    contents = loaded_and_closed(tmp_path, seed=5)
    assert type(contents.serial_number) is int and contents.serial_number == serial_number  # the seeded draw
    assert type(contents.peak_temperature) is int and contents.peak_temperature == 0
    assert type(contents.motors[1]["HOLD"]) is int and type(contents.globals["LFT"]) is int
    firmware = Firmware(store_dir=tmp_path, seed=5)
    try:
        assert firmware.transact(b"PGET SN\r") == b"PGET SN\n\r%d\n\r=> " % serial_number
    finally:
        firmware.shutdown()
    saved = json.loads((tmp_path / STORE_FILENAME).read_text())["counters"]
    assert saved["serial_number"] == serial_number and type(saved["peak_temperature"]) is int


def test_a_format_of_true_is_not_format_1(tmp_path):
    (tmp_path / STORE_FILENAME).write_text('{"format": true, "counters": {}}')
    with pytest.warns(StoreWarning, match="format True"):
        loaded_and_closed(tmp_path)
    assert len(_aside(tmp_path)) == 1


def test_counters_that_are_not_finite_keep_their_saved_values(tmp_path):
    """§5.3.2 OD, §5.4.2 PTEMP/UPSECS are never reset: a save from a simulation whose physics
    failed (NaN positions, temperature) keeps the last good values and a readable file."""
    store = NVStore(tmp_path)
    store.save(COUNTERS)
    nan = float("nan")
    store.save(({1: nan, 2: float("inf"), 3: 7.0, 4: 2.0}, nan, nan))
    store.close()
    loaded = loaded_and_closed(tmp_path)
    assert loaded.odometer_counts == {1: 5000.0, 2: 0.0, 3: 7.0, 4: 2.0}
    assert loaded.peak_temperature == 512 and loaded.uptime_seconds == 77.5
    assert "NaN" not in (tmp_path / STORE_FILENAME).read_text()
