"""Hand files (bh8_gym/hand_file.py, issue 40 items 2-3): written atomically and read
back through a strict schema (known keys only, each in its range, the scene's settings refused);
used by both environments (`hand_parameters=`), with domain randomisation about the fitted values;
by `bh8 serve --hand-parameters` and bh8sim://?hand=.
"""
from __future__ import annotations

import os

import gymnasium as gym
import numpy as np
import pytest

import bh8_gym  # noqa: F401  (registers the envs)
from bh8_gym.hand_file import (
    HandFileError,
    HandParameters,
    load_hand_parameters,
    parse_hand_parameters,
    write_hand_parameters,
)
from bh8_gym.client import BarrettHand
from bh8_gym.envs.randomization import RandomizationRanges, calibrated_ranges, sample_plant_parameters
from bh8_gym.plant import PlantParameters

FITTED = HandParameters({"finger_drive_efficiency": 0.45, "spread_friction_torque": 0.035,
                         "strain_offsets": (111, 122, 133)},
                        {"finger_drive_efficiency": 0.004, "spread_friction_torque": 0.0005,
                         "strain_offsets": (0.6, 0.7, 0.6)},
                        {"log": "hand-log.jsonl", "fitted": ["finger_drive_efficiency"], "position_rms_percent": 0.3})


def test_written_atomically_and_read_back(tmp_path):
    path = tmp_path / "hand.toml"
    path.write_text("old contents")
    loaded = write_hand_parameters(path, FITTED, comment="a test")
    assert loaded.values == FITTED.values and loaded.uncertainty == FITTED.uncertainty
    assert loaded.fit == FITTED.fit and path.read_text().startswith("# a test\n")
    assert [p.name for p in tmp_path.iterdir()] == ["hand.toml"]  # no temporary file left
    assert loaded.plant_parameters().finger_drive_efficiency == 0.45


@pytest.mark.parametrize("text, message", [
    ("[hand]\nfinger_drive_efficiency = 1.5", r"finger_drive_efficiency must be a number in 0.02..1"),
    ("[hand]\nfinger_drive_efficiency = nan", "must be a number"),
    ("[hand]\nfinger_drive_efficiency = true", "must be a number"),
    ("[hand]\ntime_step = 0.001", "setting of the scene or the solver, not a property of the hand"),
    ("[hand]\nwrist_position = [0, 0, 1]", "not a property of the hand"),
    ("[hand]\nfinger_efficiency = 0.4", "is not a hand parameter"),
    ("[hand]\nstrain_offsets = [100, 300, 120]", "three integers in 0..255"),
    ("[hand]\nstrain_offsets = [100, 120]", "three integers"),
    ("[hands]\nstrain_gain = 100", "unknown key or table 'hands'"),
    ("format = 'bh8-hand-parameters/2'\n[hand]", "this bh8-gym reads"),
    ("[uncertainty]\nstrain_gain = 1", r"no \[hand\] table"),
    ("[hand]\nstrain_gain = 100\n[uncertainty]\nstrain_gain = -1", "must be a number >= 0"),
    ("[hand]\nstrain_gain = 100\n[uncertainty]\nworm_slack = 1", "has no value in"),
    ("[hand]\nstrain_gain = 100\n[fit]\nnote = 'x'", "not a key bh8 calibrate writes"),
    ("[hand\nstrain_gain = 100", "not valid TOML"),
    ("[hand]\n" + "a." * 5000 + "b = 1", "not valid TOML|not a hand parameter"),
])
def test_the_schema_refuses_with_one_line(text, message):
    with pytest.raises(HandFileError, match=message) as caught:
        parse_hand_parameters(text, "hand.toml")
    assert str(caught.value).startswith("hand.toml: ") and "\n" not in str(caught.value)


def test_reads_are_bounded(tmp_path):
    with pytest.raises(HandFileError, match="is a folder"):
        load_hand_parameters(tmp_path)
    fifo = tmp_path / "fifo.toml"
    os.mkfifo(fifo)
    with pytest.raises(HandFileError, match="not a regular file"):  # refused without waiting for a writer
        load_hand_parameters(fifo)
    big = tmp_path / "big.toml"
    big.write_text("# " + "x" * 70_000 + "\n[hand]\n")
    with pytest.raises(HandFileError, match="larger than"):
        load_hand_parameters(big)


def test_randomisation_is_centred_on_the_fit_with_ranges_from_its_uncertainty():
    ranges = calibrated_ranges(RandomizationRanges(), FITTED.values, FITTED.uncertainty)
    # 3 sd of 0.004 in 0.45 is 2.7 %: under the 3 % floor (the model's own error).
    assert ranges.finger_drive_efficiency == (0.97, 1.03)
    assert ranges.motor_peak_torque == RandomizationRanges().motor_peak_torque  # not fitted: as before
    assert ranges.strain_offset_jitter == 3  # ceil(3 x 0.7)
    base = FITTED.plant_parameters()
    rng = np.random.default_rng(0)
    draws = [sample_plant_parameters(base, rng, ranges) for _ in range(200)]
    efficiency = np.array([d.finger_drive_efficiency for d in draws])
    assert 0.45 * 0.97 <= efficiency.min() and efficiency.max() <= 0.45 * 1.03
    offsets = np.array([d.strain_offsets for d in draws])
    assert np.all(np.abs(offsets - np.array([111, 122, 133])) <= 3)
    # Uncalibrated ranges draw the offsets as before (the trajectory digest's draws stay).
    plain = sample_plant_parameters(PlantParameters(), np.random.default_rng(0))
    assert 100 <= min(plain.strain_offsets) and max(plain.strain_offsets) <= 140


@pytest.mark.parametrize("env_id", ["BH8Grasp-v0", "BH8FingerReach-v0"])
def test_the_envs_take_a_hand_file(env_id, tmp_path):
    path = tmp_path / "hand.toml"
    write_hand_parameters(path, FITTED)
    env = gym.make(env_id, hand_parameters=str(path), randomize=False)
    try:
        env.reset(seed=0)
        plant = env.unwrapped.plant
        assert plant.params.finger_drive_efficiency == 0.45 and plant.strain_offsets == (111, 122, 133)
        assert plant.params.spread_friction_torque == 0.035
    finally:
        env.close()
    randomized = gym.make(env_id, hand_parameters=str(path))
    try:
        randomized.reset(seed=3)
        drawn = randomized.unwrapped.plant.params.finger_drive_efficiency
        assert 0.45 * 0.97 <= drawn <= 0.45 * 1.03
    finally:
        randomized.close()
    with pytest.raises(ValueError, match="which hand_parameters .* sets too"):
        gym.make(env_id, hand_parameters=str(path), plant_parameters={"finger_drive_efficiency": 0.3})
    with pytest.raises(ValueError, match="hand-parameters file .* cannot be read"):
        gym.make(env_id, hand_parameters=str(tmp_path / "missing.toml"))


def test_the_served_hand_takes_a_hand_file(tmp_path):
    path = tmp_path / "hand.toml"
    write_hand_parameters(path, FITTED)
    with BarrettHand(f"bh8sim://?hand={path}") as hand:
        plant = hand.port.firmware.plant
        assert plant.params.finger_drive_efficiency == 0.45 and plant.strain_offsets == (111, 122, 133)
    (tmp_path / "bad.toml").write_text("[hand]\ntable = false\n")
    with pytest.raises(Exception, match="not a property of the hand"):
        BarrettHand(f"bh8sim://?hand={tmp_path / 'bad.toml'}")
