"""`bh8 calibrate` end to end without a real hand (issue 40 items 4-5): a "real hand" is the
simulator with parameters hidden from the fit, served by `bh8 serve --hand-parameters` on a pty;
`record` runs the excitation on it through the client, `fit` finds the hidden parameters from the
defaults and replays the log closer than the defaults did. A log in which the spread never moves is
fitted for what it shows and says what it could not identify; a 4.4 hand's log replays on the 4.4
firmware; bad logs end `fit` with one line and exit 2. The full-length version, on 10 drawn hands,
is benchmarks/bench_calibrate.py.
"""
from __future__ import annotations

import copy

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


class _Groups:
    """A stand-in for ResidualModel over stand-in replays: a replay *is* its residual groups."""

    @staticmethod
    def groups(signals):
        return signals


class _Replays:
    """A stand-in for fit._Evaluator: the residual groups of a point from `table` (by the point's
    coordinates), with the model above."""

    model = _Groups()

    def __init__(self, table):
        self.table = table

    def signals(self, points):
        return [self.table[tuple(sorted((k, v) for k, v in p.items() if v != 0.0))] for p in points]


def test_a_parameter_the_5_percent_test_misses_is_kept_when_the_log_tells_it_from_its_default():
    """Issue 40, seeds 1 and 7: a spread near its stall duty replays with so much scatter that a 5 %
    step does not stand out, though the fit found it 25 % from the default and it replays the log
    five times closer there; set back to the default, the replay moves by far more than the
    scatter and gets worse, so it stays fitted. One whose default replays as well stays untold."""
    from bh8_gym.calibration.fit import FIT_PARAMETERS, _told_from_default

    drive, friction = FIT_PARAMETERS[1], FIT_PARAMETERS[2]
    at = {"spread_drive_efficiency": 0.22, "spread_friction_torque": -0.01}
    rng = np.random.default_rng(0)
    fitted = rng.normal(0.0, 0.8, 400)  # the fitted replay: RMS 0.8 % of range
    table = {
        tuple(sorted(at.items())): {"spread positions": fitted},
        # the drive back at its default: the spread lags by 4 % of range
        (("spread_friction_torque", -0.01),): {"spread positions": fitted + 4.0},
        # the friction's ratio back at its default: a change within the scatter, no better, no worse
        (("spread_drive_efficiency", 0.22),): {"spread positions": fitted[::-1].copy()},
    }
    scatter = {"spread positions": 0.8}
    told = _told_from_default(_Replays(table), at, [drive, friction], scatter)
    assert told == [drive]
    # Closer to the log at the default than at the fit: not kept, however far the replay moved.
    table[(("spread_friction_torque", -0.01),)] = {"spread positions": 0.1 * fitted}
    assert _told_from_default(_Replays(table), at, [drive], scatter) == []
    assert _told_from_default(_Replays(table), at, [], scatter) == []


def test_a_practice_hand_draws_the_gauges_gain_too(tmp_path):
    """`bh8 calibrate draw`: every fitted parameter and the gauges' gain within ±30 % of its default,
    the gain drawn after the rest (a seed's other values are those it drew before the gain was)."""
    from bh8_gym.calibration.practice import draw_hand
    from bh8_gym.plant.parameters import PlantParameters

    defaults = PlantParameters()
    for seed in range(40):
        values = draw_hand(np.random.default_rng(seed))
        for name in ("finger_drive_efficiency", "spread_drive_efficiency", "spread_friction_torque", "strain_gain"):
            assert abs(values[name] / getattr(defaults, name) - 1.0) <= 0.30, (seed, name)
        rng = np.random.default_rng(seed)
        before = {name: float(getattr(defaults, name)) * float(rng.uniform(0.7, 1.3))
                  for name in ("finger_drive_efficiency", "spread_drive_efficiency", "spread_friction_torque")}
        assert values["strain_offsets"] == tuple(int(v) for v in rng.integers(100, 141, size=3))
        assert all(values[name] == before[name] for name in before)
    gains = [draw_hand(np.random.default_rng(seed))["strain_gain"] for seed in range(40)]
    assert np.ptp(gains) > 30.0  # drawn, not the default
    assert main(["calibrate", "draw", "--seed", "3", "-o", str(tmp_path / "hidden.toml")]) == 0
    assert load_hand_parameters(tmp_path / "hidden.toml").values["strain_gain"] == pytest.approx(gains[3])


def test_the_squeezes_tell_the_gauges_gain(tmp_path):
    """Palm-up with the calibration cube (docs/hardware.md): the squeezes come first, while the cube
    stands where it was put (the spread's sweeps swing F1's and F2's knuckles over the palm and push
    it about), so the fingertips grip it and the gauges read loads that differ from one squeeze to
    the next by far more than GAIN_LOAD_SPAN; read off the replay of the recorded hand, the gain is
    the hidden one (issue 40: drawn within ±30 %, identified)."""
    from urllib.parse import quote

    from bh8_gym.calibration.residuals import GAIN_LOAD_SPAN, REPLAY_GAIN, REPLAY_OFFSETS, ResidualModel
    from bh8_gym.calibration.scene import DEFAULT_CALIBRATION_OBJECT

    hidden = tmp_path / "hidden.toml"
    write_hand_parameters(hidden, HandParameters({"strain_gain": 76.0, "strain_offsets": (131, 104, 117)}))
    path = tmp_path / "cube.jsonl"
    with BarrettHand(f"bh8sim://?seed=0&hand={hidden}&object={quote(DEFAULT_CALIBRATION_OBJECT)}") as hand:
        complete, reason = Recorder(hand, path, "palm-up", DEFAULT_CALIBRATION_OBJECT, scale=0.05).run()
    assert complete, reason
    log = read_log(path)
    model = ResidualModel(observed(log), log.hand_clock)
    assert model.evidence.squeezes and len(model.holds) == 6  # three duties, twice
    replayed = replay(log, {"strain_offsets": REPLAY_OFFSETS})  # the hidden hand moves as the default one
    loads = [np.mean(replayed.strains[model._hold_mask(name)], axis=0) for name in model.holds]
    loads = (np.array(loads) - np.array(REPLAY_OFFSETS)) / REPLAY_GAIN
    assert np.ptp(loads) > 3 * GAIN_LOAD_SPAN and loads.min() > 0.05  # N·m: the fingertips press the cube
    gain, sigma = model.strain_gain(replayed)
    assert gain == pytest.approx(76.0, rel=0.05) and sigma < 0.05 * gain
    assert model.offsets(replayed) == (131, 104, 117)
    # A replay that lands differently in one squeeze (its loads 20 % higher there) moves the gain read
    # against it alone, and the reported uncertainty grows to cover that (the replays' estimate).
    other = copy.deepcopy(replayed)
    last = model._hold_mask(model.holds[-1])
    other.strains[last] = REPLAY_OFFSETS + 1.2 * (other.strains[last] - REPLAY_OFFSETS)
    alone = model.strain_gain(other)[0]
    both, spread = model.strain_gain(replayed, (other,))
    assert alone < 0.97 * gain and alone < both < gain
    assert spread >= abs(gain - alone) / 2 * np.sqrt(1.5) * 0.99 and spread > 2 * sigma


def test_a_squeeze_keeps_each_fingers_command_when_it_touches():
    """excitation.SqueezeLaw: a finger's velocity and gain are the squeeze's from the first block to
    the end of the hold, whether it touched or not: the replay sends the recorded blocks, so a
    switch at the recorded finger's touch would come early or late for a replayed finger."""
    from bh8_gym.calibration.excitation import SQUEEZE_VELOCITY, SWEEP_HIGH, Squeeze, SqueezeLaw

    law = SqueezeLaw(Squeeze("squeeze1", 100, 60), {1: 120, 2: 120, 3: 120})
    touches = {1: 5, 2: 9, 3: 14}  # the cycle each finger's gauge rises (it keeps closing, slowly)
    commands, phases = set(), []
    for cycle in range(40):
        positions = {1: SWEEP_HIGH + 100 + 30 * cycle, 2: SWEEP_HIGH + 100 + 30 * cycle,
                     3: SWEEP_HIGH + 100 + 30 * cycle, 4: 600}
        strains = {m: 120 + (10 if cycle >= touches[m] else 0) for m in (1, 2, 3)}
        velocities, gains = law.control(positions, strains)
        commands.add((tuple(velocities[:3]), tuple(gains[:3])))
        phases.append(law.phase)
    assert law.touched == {1, 2, 3} and phases[13] == "approach" and phases[14] == "hold" and phases[-1] == "hold"
    assert commands == {((SQUEEZE_VELOCITY,) * 3, (100,) * 3)}

