"""The calibration log (bh8_gym/calibration/log_format.py, issue 40 item 5): what `bh8 calibrate
record` writes reads back; a truncated, edited, foreign, oversized or special file, a deploy log, a
header whose firmware profile VERS contradicts, a record out of place: each one clear
CalibrationLogError naming the line, never another exception (Hypothesis, over bytes and over
records); the recorder leaves a hand it was stopped on as it found it and marks the log incomplete.
"""
from __future__ import annotations

import json
import os
import signal

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bh8_gym.calibration.log_format import (
    LOG_FORMAT,
    MAX_LINE_BYTES,
    CalibrationLogError,
    LogWriter,
    chain_digest,
    parse_log,
    read_log,
)
from bh8_gym.calibration.recorder import Recorder
from bh8_gym.client import BarrettHand

SCALE = 0.05  # the shortest excitation: a few hundred blocks, about a second of simulation


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A complete log of the shortest excitation on the in-process simulated hand (palm-down)."""
    path = tmp_path_factory.mktemp("calibration") / "hand-log.jsonl"
    with BarrettHand("bh8sim://?seed=5") as hand:
        complete, reason = Recorder(hand, path, "palm-down", scale=SCALE).run()
    assert complete, reason
    return path


def _records(path) -> list[dict]:
    return [json.loads(line) for line in path.read_bytes().splitlines()]


def _rewrite(records: list[dict], path) -> None:
    """Write `records` as a consistent log (numbers and digests made anew): what an editor with the
    format's description could make."""
    with LogWriter(path) as writer:
        for record in records:
            writer.write({key: value for key, value in record.items() if key not in ("i", "h")})


def test_a_recorded_log_reads_back_complete(recorded):
    log = read_log(recorded)
    assert log.complete and log.reason == "done"
    assert log.hand_clock == "line"  # the simulated hand's clock stands still while the host waits
    assert log.header.profile == "4.3" and log.header.version_text == "4.34"
    assert log.header.mounting == "palm-down" and log.header.scale == SCALE
    kinds = {record["kind"] for record in log.records}
    assert {"command", "baud", "loop", "block", "loop_exit", "clock", "segment", "end"} <= kinds
    assert log.blocks > 100
    # The hand was found at 9600 baud with its factory parameters: the header keeps them.
    assert log.header.baud_found == 9600 and log.header.found["motors"]["MCV"] == [100, 100, 100, 60]


def test_a_cut_log_is_incomplete_and_an_edited_one_refused(recorded, tmp_path):
    data = recorded.read_bytes()
    cut = tmp_path / "cut.jsonl"
    cut.write_bytes(data[: len(data) // 2])  # killed mid-record: the half line is dropped
    log = read_log(cut)
    assert not log.complete and "cut before its end record" in log.reason
    edited = data.replace(b'"line":"1234HI"', b'"line":"1234HO"', 1)
    assert edited != data
    (tmp_path / "edited.jsonl").write_bytes(edited)
    with pytest.raises(CalibrationLogError, match="changed after it was recorded"):
        read_log(tmp_path / "edited.jsonl")
    lines = data.splitlines(keepends=True)
    (tmp_path / "dropped.jsonl").write_bytes(b"".join(lines[:10] + lines[11:]))
    with pytest.raises(CalibrationLogError, match="record number"):
        read_log(tmp_path / "dropped.jsonl")


def test_foreign_files_are_named_for_what_they_are(tmp_path):
    deploy = tmp_path / "deploy_log.jsonl"
    deploy.write_text(json.dumps({"cycle": 0, "t": 1.0, "control": "41", "feedback": "2a00"}) + "\n")
    with pytest.raises(CalibrationLogError, match="bh8 deploy --log"):
        read_log(deploy)
    for name, content in (("empty", b""), ("binary", b"\x89PNG\r\n\x1a\n\x00\x00"), ("json", b"[1, 2]\n"),
                          ("text", b"hello world\n"), ("nan", b'{"kind": NaN}\n'),
                          ("huge number", b'{"kind": ' + b"9" * 5000 + b"}\n")):
        path = tmp_path / name
        path.write_bytes(content)
        with pytest.raises(CalibrationLogError, match=str(path)):
            read_log(path)
    newer = {"kind": "header", "format": LOG_FORMAT, "version": 2, "i": 0}
    newer["h"] = chain_digest("", newer)
    (tmp_path / "newer.jsonl").write_text(json.dumps(newer) + "\n")
    with pytest.raises(CalibrationLogError, match="newer than this bh8-gym reads"):
        read_log(tmp_path / "newer.jsonl")


def test_reads_are_bounded_and_regular_files_only(tmp_path, monkeypatch):
    with pytest.raises(CalibrationLogError, match="is a folder"):
        read_log(tmp_path)
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    with pytest.raises(CalibrationLogError, match="regular file"):  # refused without waiting for a writer
        read_log(fifo)
    big = tmp_path / "big.jsonl"
    big.write_bytes(b"x" * 2048)
    monkeypatch.setattr("bh8_gym.calibration.log_format.MAX_LOG_BYTES", 1024)
    with pytest.raises(CalibrationLogError, match="larger than 1 KB"):
        read_log(big)
    with pytest.raises(CalibrationLogError, match="longer than any record"):
        parse_log(b"x" * (MAX_LINE_BYTES + 1) + b"\n")


def test_the_firmware_profile_must_agree_with_vers(recorded, tmp_path):
    """A log of firmware 4.4 names it (and its blocks are 4.4's); a header claiming 4.4 over a 4.3
    hand's VERS, or a LOOP layout of the other profile, is refused (SPEC.md §7)."""
    records = _records(recorded)
    records[0]["hand"]["profile"] = "4.4"
    _rewrite(records, tmp_path / "claims44.jsonl")
    with pytest.raises(CalibrationLogError, match="VERS '4.34'"):
        read_log(tmp_path / "claims44.jsonl")
    records = _records(recorded)
    loop = next(r for r in records if r["kind"] == "loop")
    loop["layout"]["firmware"] = "4.4"
    _rewrite(records, tmp_path / "layout44.jsonl")
    with pytest.raises(CalibrationLogError, match="header's profile 4.3"):
        read_log(tmp_path / "layout44.jsonl")


def test_records_out_of_place_are_refused(recorded, tmp_path):
    records = _records(recorded)
    block = next(i for i, r in enumerate(records) if r["kind"] == "block")
    cases = {
        "block outside LOOP": records[:block - 2] + [records[block]],  # before the loop record
        "time runs backwards": records[:block] + [{**records[block], "t": records[block]["t"] - 100.0}],
        "does not fit the LOOP's layout": records[:block] + [{**records[block], "control": "4300"}],
        "unknown field": records[:block] + [{**records[block], "extra": 1}],
        "unknown record kind": records[:block] + [{"kind": "firmware-update", "t": 1e9}],
        "after the end record": records + [records[-2]],
    }
    for message, edited in cases.items():
        path = tmp_path / "case.jsonl"
        _rewrite(edited, path)
        with pytest.raises(CalibrationLogError, match=message.split()[-1]):
            read_log(path)


@settings(max_examples=150)
@given(st.binary(max_size=3000))
def test_any_bytes_give_a_log_or_one_clear_error(data):
    try:
        parse_log(data, "fuzz")
    except CalibrationLogError as error:
        assert str(error).startswith("fuzz")


_SCALARS = st.one_of(st.none(), st.booleans(), st.integers(-2**70, 2**70), st.floats(allow_nan=False),
                     st.text(max_size=20))
_VALUES = st.recursive(_SCALARS, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8),
                                                                                              inner, max_size=4),
                       max_leaves=12)


@settings(max_examples=150)
@given(data=st.data())
def test_any_change_to_a_record_gives_a_log_or_one_clear_error(recorded_records, data):
    """Records changed by an editor who also made the digests anew: each change is read or refused
    with a CalibrationLogError naming its line."""
    records = [dict(r) for r in recorded_records]
    index = data.draw(st.integers(0, len(records) - 1))
    key = data.draw(st.sampled_from(sorted(set(records[index]) | {"kind", "t", "extra"})))
    records[index][key] = data.draw(_VALUES)
    lines = []
    previous = ""
    for number, record in enumerate(records):
        record = {k: v for k, v in record.items() if k not in ("i", "h")}
        record["i"] = number
        try:
            record["h"] = chain_digest(previous, record)
        except (TypeError, ValueError):
            return  # not JSON-serialisable (an infinity, a huge int as a key): no file can hold it
        previous = record["h"]
        lines.append(json.dumps(record))
    try:
        parse_log(("\n".join(lines) + "\n").encode("ascii"), "edited")
    except CalibrationLogError as error:
        assert str(error).startswith("edited")


@pytest.fixture(scope="module")
def recorded_records(recorded):
    return _records(recorded)[:40] + _records(recorded)[-3:]


def test_a_stopped_recording_leaves_the_hand_as_found_and_marks_the_log(tmp_path):
    """Ctrl-C in the middle of LOOP: a zero block, ^C, the parameters and baud rate back as found,
    and an end record saying why (issue 40 item 1)."""
    path = tmp_path / "stopped.jsonl"
    with BarrettHand("bh8sim://?seed=6") as hand:
        hand.set("1", {"MCV": 80})  # found with a changed parameter

        def interrupt(part, index, parts):
            if part == "sweep2":
                os.kill(os.getpid(), signal.SIGINT)  # what Ctrl-C does; the recorder stops at the next block

        recorder = Recorder(hand, path, "palm-down", scale=SCALE, progress=interrupt)
        complete, reason = recorder.run()
        assert not complete and reason == "interrupted (Ctrl-C)"
        assert not hand.in_loop and hand.baudrate == 9600
        assert hand.get("MCV HOLD LCPG", "1234") == {"MCV": [80, 100, 100, 60], "HOLD": [0, 0, 0, 1],
                                                   "LCPG": [1, 1, 1, 1]}
    log = read_log(path)
    assert not log.complete and log.reason == "interrupted (Ctrl-C)"
    assert log.records[-1]["kind"] == "end"
    kinds = [r["kind"] for r in log.records]
    assert "loop_exit" in kinds and kinds.index("loop_exit") > kinds.index("loop")
