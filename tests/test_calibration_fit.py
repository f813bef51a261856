"""`bh8 calibrate` end to end without a real hand (issue 40 items 4-5): a "real hand" is the
simulator with parameters hidden from the fit, served by `bh8 serve --hand-parameters` on a pty;
`record` runs the excitation on it through the client, `fit` finds the hidden parameters from the
defaults and replays the log closer than the defaults did. A log in which the spread never moves is
fitted for what it shows and says what it could not identify; a 4.4 hand's log replays on the 4.4
firmware; bad logs end `fit` with one line and exit 2. The full-length version, on 10 drawn hands,
is benchmarks/bench_calibrate.py.
"""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from bh8_gym.calibration.fit import fit
from bh8_gym.hand_file import HandParameters, load_hand_parameters, write_hand_parameters
from bh8_gym.calibration.log_format import LogWriter, read_log
from bh8_gym.calibration.recorder import Recorder
from bh8_gym.calibration.replay import observed, replay
from bh8_gym.calibration.rollouts import LocalRollouts
from bh8_gym.cli import main
from bh8_gym.client import BarrettHand

HIDDEN = {"finger_drive_efficiency": 0.31, "spread_drive_efficiency": 0.88, "spread_friction_torque": 0.039,
          "strain_offsets": (117, 104, 131)}


@pytest.fixture()
def served_hand(tmp_path):
    """`bh8 serve --hand-parameters hidden.toml` (the hand palm-down, nothing in reach): its device."""
    hidden = tmp_path / "hidden.toml"
    write_hand_parameters(hidden, HandParameters(HIDDEN))
    server = subprocess.Popen([sys.executable, "-m", "bh8_gym.cli", "serve", "--state", str(tmp_path / "state"),
                               "--hand-parameters", str(hidden)], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                              text=True)
    try:
        yield server.stdout.readline().strip()
    finally:
        server.terminate()
        server.wait(timeout=30)


def test_record_and_fit_find_the_hidden_hand(served_hand, tmp_path, capsys):
    log, hand = tmp_path / "hand-log.jsonl", tmp_path / "hand.toml"
    assert main(["calibrate", "record", "--port", served_hand, "--mounting", "palm-down", "--scale", "0.1",
                 "-o", str(log)]) == 0
    assert read_log(log).hand_clock == "line"  # bh8 serve's clock stands still while the host waits
    assert main(["calibrate", "fit", str(log), "-o", str(hand), "--iterations", "4", "--jobs", "2"]) == 0
    report = capsys.readouterr().out
    fitted = load_hand_parameters(hand)
    for name in ("finger_drive_efficiency", "spread_drive_efficiency", "spread_friction_torque"):
        assert fitted.values[name] == pytest.approx(HIDDEN[name], rel=0.10), name
        assert 0 < fitted.uncertainty[name] < 0.1 * fitted.values[name]
    assert all(abs(a - b) <= 1 for a, b in zip(fitted.values["strain_offsets"], HIDDEN["strain_offsets"]))
    # The replay: under 1 % of the motors' range after the fit, and a third of what it was at the defaults.
    assert fitted.fit["position_rms_percent"] < 1.0
    assert fitted.fit["position_rms_percent"] < fitted.fit["position_rms_percent_before"] / 3
    # No calibration object: the gauges' gain is not identified, and the report says why.
    assert "strain_gain" in fitted.fit["not_identified"] and "strain_gain" not in fitted.values
    assert "no squeeze of a calibration object" in report
    assert (tmp_path / "hand.png").stat().st_size > 10_000


def test_a_motor_that_never_moved_is_named_and_the_rest_fitted(tmp_path):
    """The spread held by friction its drive cannot overcome: the fit says the spread's parameters
    cannot be identified and fits the fingers (issue 40 item 5)."""
    stuck = {"spread_friction_torque": 1.0, "finger_drive_efficiency": 0.5}
    path = tmp_path / "stuck.jsonl"
    hidden = tmp_path / "stuck.toml"
    write_hand_parameters(hidden, HandParameters(stuck))
    with BarrettHand(f"bh8sim://?seed=2&hand={hidden}") as hand:
        assert Recorder(hand, path, "palm-down", scale=0.1).run()[0]
    log = read_log(path)
    rollouts = LocalRollouts(path.read_bytes(), str(path), jobs=1)
    try:
        result = fit(log, rollouts, iterations=2)
    finally:
        rollouts.close()
    status = {p.name: p.status for p in result.parameters}
    assert status["spread_drive_efficiency"].startswith("not identified: the spread did not move")
    assert status["spread_friction_torque"].startswith("not identified: the spread did not move")
    assert any(note.startswith("motor(s) 4 did not move") for note in result.notes)
    assert status["finger_drive_efficiency"] == "fitted"
    assert result.hand_values()["finger_drive_efficiency"] == pytest.approx(0.5, rel=0.1)


def test_a_firmware_44_log_replays_on_the_44_firmware_and_a_real_hands_clock_runs_on(tmp_path):
    path = tmp_path / "hand44.jsonl"
    with BarrettHand("bh8sim://?seed=4&firmware=4.4") as hand:
        assert Recorder(hand, path, "palm-down", scale=0.05).run()[0]
    log = read_log(path)
    assert log.header.profile == "4.4" and log.header.version_text == "4.40"
    replayed, recorded = replay(log, {"strain_offsets": (120, 120, 120)}, anchored=False), observed(log)
    np.testing.assert_array_equal(replayed.positions, recorded.positions)  # the same hand: the same counts
    # A real hand's clock runs while the host waits (the clock probe says "wall"): the replay lets the
    # simulated hand run for as long as the logged blocks were apart (here 20 ms each).
    records = [dict(r) for r in (json.loads(line) for line in path.read_bytes().splitlines())]
    blocks = 0
    for record in records:
        if record["kind"] == "clock":
            record["hand_clock"] = "wall"
        if record["kind"] == "block":
            record["t"], blocks = 1e6 + 0.02 * blocks, blocks + 1
        elif "t" in record and blocks:
            record["t"] = 1e6 + 0.02 * blocks - 0.01
    with LogWriter(tmp_path / "wall.jsonl") as writer:
        for record in records:
            writer.write({key: value for key, value in record.items() if key not in ("i", "h")})
    wall = read_log(tmp_path / "wall.jsonl")
    assert wall.hand_clock == "wall"
    times = replay(wall, {}, anchored=False).times
    # Within a physics step (2 ms) of the logged 20 ms apart, from the second block on.
    np.testing.assert_allclose(np.diff(times[1:]), 0.02, atol=0.0021)


def test_fit_refuses_bad_logs_in_one_line(tmp_path, capsys):
    cases = {"empty.jsonl": b"", "deploy.jsonl": b'{"cycle": 0, "t": 0.1, "control": "41", "feedback": "2a"}\n'}
    for name, content in cases.items():
        (tmp_path / name).write_bytes(content)
        assert main(["calibrate", "fit", str(tmp_path / name), "-o", str(tmp_path / "hand.toml")]) == 2
        error = capsys.readouterr().err.strip()
        assert error.startswith("bh8 calibrate fit: ") and "\n" not in error and "Traceback" not in error
    assert main(["calibrate", "fit", str(tmp_path / "missing.jsonl"), "-o", str(tmp_path / "hand.toml")]) == 2
    assert "cannot be read" in capsys.readouterr().err
    assert not (tmp_path / "hand.toml").exists()
