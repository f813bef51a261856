"""The seal `bh8 sweep` puts on Ray Tune's pickled state (agents/sweep/state_seal.py, issue 32 item 2):
state it sealed passes unchanged; a file changed, added, replaced by a link or a device, a seal
made with another account's key, a damaged seal or none at all fail, each saying why, without
reading what a link points to.
"""
from __future__ import annotations

import json
import os
import stat
import time
from pathlib import Path

import pytest

from bh8_gym.agents.sweep.state_seal import SealError, check_sealed, key_path, seal


@pytest.fixture(autouse=True)
def _own_key(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "config-home"))


@pytest.fixture
def state(tmp_path) -> Path:
    folder = tmp_path / "experiment"
    (folder / "trial_1").mkdir(parents=True)
    (folder / "runs" / "trial_1_seed0").mkdir(parents=True)
    (folder / "tuner.pkl").write_bytes(b"\x80\x04state")
    (folder / "trial_1" / "params.pkl").write_bytes(b"\x80\x04params")
    (folder / "runs" / "trial_1_seed0" / "evaluations.csv").write_text("ours\n")
    return folder


def test_sealed_state_passes_and_the_key_is_private(state, tmp_path):
    seal(state, tmp_path / "seal.json", skip=("runs",))
    check_sealed(state, tmp_path / "seal.json", skip=("runs",))
    assert stat.S_IMODE(os.stat(key_path()).st_mode) == 0o600
    assert key_path().stat().st_size == 32
    # what `skip` names is not sealed: bh8 sweep's own files change freely
    (state / "runs" / "trial_1_seed0" / "evaluations.csv").write_text("more rows\n")
    (state / "tuner.pkl").unlink()  # a sealed file gone: nothing loads it
    check_sealed(state, tmp_path / "seal.json", skip=("runs",))


@pytest.mark.parametrize("change", ["changed", "added", "link", "fifo"])
def test_a_file_changed_or_put_there_fails(state, tmp_path, change):
    seal(state, tmp_path / "seal.json", skip=("runs",))
    if change == "changed":
        (state / "tuner.pkl").write_bytes(b"\x80\x04evil")
        name = "tuner.pkl"
    elif change == "added":
        (state / "trial_1" / "error.pkl").write_bytes(b"\x80\x04evil")
        name = "trial_1/error.pkl"
    elif change == "link":
        (state / "tuner.pkl").unlink()
        (state / "tuner.pkl").symlink_to("/dev/zero")
        name = "tuner.pkl"
    else:
        os.mkfifo(state / "trial_1" / "searcher-state.pkl")  # reading it would never end
        name = "trial_1/searcher-state.pkl"
    started = time.monotonic()
    with pytest.raises(SealError, match=f"{name} changed or appeared"):
        check_sealed(state, tmp_path / "seal.json", skip=("runs",))
    assert time.monotonic() - started < 10


def test_a_seal_made_with_another_key_or_edited_fails(state, tmp_path, monkeypatch):
    seal(state, tmp_path / "seal.json")
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "another-account"))
    with pytest.raises(SealError, match="not made by this account"):
        check_sealed(state, tmp_path / "seal.json")
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "config-home"))
    record = json.loads((tmp_path / "seal.json").read_text())
    (state / "tuner.pkl").write_bytes(b"\x80\x04evil")
    record["files"]["tuner.pkl"] = "0" * 64  # the attacker cannot make the MAC match
    (tmp_path / "seal.json").write_text(json.dumps(record))
    with pytest.raises(SealError, match="not made by this account"):
        check_sealed(state, tmp_path / "seal.json")


@pytest.mark.parametrize("content", [None, b"", b"{}", b"[" * 100_000, b'{"format": "bh8-state-seal/1", "files": [], '
                                                                     b'"mac": 1}'])
def test_no_seal_or_a_damaged_one_fails(state, tmp_path, content):
    if content is not None:
        (tmp_path / "seal.json").write_bytes(content)
    with pytest.raises(SealError, match="never sealed" if content is None else "damaged"):
        check_sealed(state, tmp_path / "seal.json")


def test_a_damaged_key_is_said(state, tmp_path):
    seal(state, tmp_path / "seal.json")
    key_path().write_bytes(b"short")
    with pytest.raises(SealError, match="seal key .* is damaged"):
        check_sealed(state, tmp_path / "seal.json")
