"""The non-volatile store: persistence, atomic writes, fallback to factory defaults.

Sources: manual §5.2.2-§5.2.3 (FSAVE/FLOAD/PSAVE/PLOAD), §5.3.2 OD and §5.4.2 PTEMP/UPSECS/SN
("never reset; maintained through power failures"); SPEC.md §3 (write-then-rename).
"""
import json
import os

import pytest

from bh8_gym.nvstore import STORE_FILENAME, NVStore


def test_new_store_has_factory_defaults_and_a_fixed_serial_number(tmp_path):
    """§5.3/§5.4 defaults; SN is fixed per store from the first power-up on (§5.4.2)."""
    store = NVStore(tmp_path, seed=3)
    contents = store.load()
    assert contents.motors[1]["DP"] == 8500 and contents.motors[4]["DP"] == 1575
    assert contents.globals["BAUD"] == 96
    again = NVStore(tmp_path, seed=99).load()
    assert again.serial_number == contents.serial_number
    assert NVStore(tmp_path / "other", seed=4).load().serial_number != contents.serial_number


def test_saved_sets_and_counters_survive_a_new_instance(tmp_path):
    """§5.2.2 FSAVE, §5.2.3 PSAVE and the never-reset counters persist across restarts."""
    store = NVStore(tmp_path)
    motor = store.load().motors[2]
    motor["DP"] = 1234
    store.save_motor_parameters(2, motor)
    store.save_global_parameters({**store.load().globals, "LFT": 1})
    store.save_counters({1: 5000.0, 2: 0.0, 3: 1.5, 4: 2.0}, 512, 77.5)
    loaded = NVStore(tmp_path).load()
    assert loaded.motors[2]["DP"] == 1234 and loaded.motors[1]["DP"] == 8500
    assert loaded.globals["LFT"] == 1
    assert loaded.odometer_counts[1] == 5000.0 and loaded.peak_temperature == 512 and loaded.uptime_seconds == 77.5


@pytest.mark.parametrize("garbage", [b"", b"{not json", b"[1, 2]", b"\xff\xfe\x00"])
def test_corrupt_store_falls_back_to_defaults(tmp_path, garbage):
    """SPEC.md §3: a torn or corrupt store must not crash the firmware; defaults are used."""
    (tmp_path / STORE_FILENAME).write_bytes(garbage)
    contents = NVStore(tmp_path).load()
    assert contents.motors[3]["CT"] == 17000 and contents.globals["OTEMP"] == 0


def test_out_of_range_values_in_the_file_are_ignored(tmp_path):
    """§5.3 ranges: a stored value outside its range is replaced by the default."""
    store = NVStore(tmp_path)
    store.load()
    raw = json.loads((tmp_path / STORE_FILENAME).read_text())
    raw["motors"]["1"]["MCV"] = 99999
    raw["motors"]["1"]["DP"] = "text"
    raw["motors"]["1"]["DS"] = 42
    raw["globals"]["BAUD"] = 97
    (tmp_path / STORE_FILENAME).write_text(json.dumps(raw))
    loaded = NVStore(tmp_path).load()
    assert loaded.motors[1]["MCV"] == 100 and loaded.motors[1]["DP"] == 8500 and loaded.motors[1]["DS"] == 42
    assert loaded.globals["BAUD"] == 96


def test_write_is_atomic_when_replace_fails(tmp_path, monkeypatch):
    """SPEC.md §3: a crash mid-write leaves the previous file intact and no temporary behind."""
    store = NVStore(tmp_path)
    store.save_counters({m: 1000.0 for m in (1, 2, 3, 4)}, 400, 10.0)
    before = (tmp_path / STORE_FILENAME).read_bytes()

    def crash(*args):
        raise OSError("power failure")

    monkeypatch.setattr(os, "replace", crash)
    with pytest.raises(OSError):
        store.save_counters({m: 9000.0 for m in (1, 2, 3, 4)}, 500, 20.0)
    assert (tmp_path / STORE_FILENAME).read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == [STORE_FILENAME]


def test_memory_store_writes_nothing(tmp_path):
    """directory=None: a memory-only store (no files), still answering loads and saves."""
    store = NVStore(None)
    store.save_counters({m: 1.0 for m in (1, 2, 3, 4)}, 300, 1.0)
    assert store.load().peak_temperature == 300
    assert list(tmp_path.iterdir()) == []
