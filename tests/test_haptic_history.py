"""The haptic history a host keeps of an episode's feedback blocks (bh8_gym/haptic_history.py).

Its inputs are decoded feedback blocks (SPEC.md §6: LFS strain 0-255 per finger, LFAP position per
motor); its contract is that it is built from the blocks alone, so `bh8 deploy` builds on a real
hand exactly what the env builds (tests/test_hil.py checks that end to end).
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bh8_gym.haptic_history import CONTACT_RISE, LONG_LAG, SHORT_LAG, HapticHistory

# The grasp env's default feedback: LFS and LFAP of F1-F3, LFAP of the spread.
FIELDS = [(1, "LFS"), (1, "LFAP"), (2, "LFS"), (2, "LFAP"), (3, "LFS"), (3, "LFAP"), (4, "LFAP")]
CYCLE = 0.00647


def block(strains, positions, spread=0):
    return [strains[0], positions[0], strains[1], positions[1], strains[2], positions[2], spread]


def entries(history: HapticHistory) -> dict[str, float]:
    return dict(zip(history.names, history.values()))


def test_contact_is_the_second_block_running_with_the_strain_risen():
    """A finger is in contact once its strain has risen CONTACT_RISE over its first reading in two
    blocks running (one block's swing is not a contact); its position then is kept, and so is
    the time since."""
    history = HapticHistory(FIELDS, 2.0)
    zero = [120, 130, 110]
    history.observe(block(zero, [0, 0, 0]), CYCLE)
    history.observe(block([120 + CONTACT_RISE, 130, 110], [500, 500, 500]), 2 * CYCLE)  # one block only
    history.observe(block([120, 130, 110], [900, 900, 900]), 3 * CYCLE)
    assert entries(history)["contact1"] == 0.0
    history.observe(block([120 + CONTACT_RISE, 130, 110], [1200, 1200, 1200]), 4 * CYCLE)
    history.observe(block([120 + CONTACT_RISE + 5, 130, 110], [1300, 1500, 1500]), 5 * CYCLE)
    e = entries(history)
    assert e["contact1"] == 1.0 and e["contact2"] == 0.0 and e["contact3"] == 0.0
    assert e["contact_position1"] == pytest.approx(1300 / 17_500)
    assert e["since_contact1"] == 0.0
    assert e["rise1"] == pytest.approx((CONTACT_RISE + 5) / 128) and e["peak_rise1"] == e["rise1"]
    history.observe(block([121, 130, 110], [1300, 1700, 1700]), 6 * CYCLE)
    e = entries(history)
    assert e["since_contact1"] == pytest.approx(CYCLE / 2.0)
    assert e["rise1"] == pytest.approx(1 / 128) and e["peak_rise1"] == pytest.approx((CONTACT_RISE + 5) / 128)


def test_movement_is_measured_over_the_short_and_long_lags():
    """moved*_short / _long: the position's change over SHORT_LAG and LONG_LAG blocks (fewer at the
    episode's start: since the first block)."""
    history = HapticHistory(FIELDS, 2.0)
    for k in range(LONG_LAG + 10):
        history.observe(block([128, 128, 128], [100 * k, 50 * k, 0], spread=10 * k), k * CYCLE)
    e = entries(history)
    assert e["moved1_short"] == pytest.approx(100 * SHORT_LAG / 2000)
    assert e["moved1_long"] == pytest.approx(100 * LONG_LAG / 2000)
    assert e["moved2_long"] == pytest.approx(50 * LONG_LAG / 2000)
    assert e["moved3_short"] == 0.0
    assert e["moved4_short"] == pytest.approx(10 * SHORT_LAG / 400)
    history.reset()
    history.observe(block([128, 128, 128], [0, 0, 0]), CYCLE)
    history.observe(block([128, 128, 128], [300, 0, 0]), 2 * CYCLE)
    assert entries(history)["moved1_long"] == pytest.approx(300 / 2000)


def test_values_before_any_block_is_an_error():
    with pytest.raises(ValueError, match="before the first"):
        HapticHistory(FIELDS, 2.0).values()


def test_a_layout_without_finger_strain_has_no_history():
    with pytest.raises(ValueError, match="LFS and LFAP"):
        HapticHistory([(1, "LFAP"), (4, "LFAP")], 2.0)


blocks = st.lists(st.tuples(st.lists(st.integers(0, 255), min_size=3, max_size=3),
                            st.lists(st.integers(0, 20_000), min_size=4, max_size=4)), min_size=1, max_size=80)


@settings(max_examples=60, deadline=None)
@given(blocks)
def test_any_block_stream_gives_bounded_entries_and_replays_after_reset(stream):
    """Whatever the hand sends (any strain byte, any position), every entry is finite and of the
    observation's scale, and a reset history fed the same blocks gives the same entries."""
    history = HapticHistory(FIELDS, 2.0)

    def run():
        out = []
        for k, (strains, positions) in enumerate(stream):
            history.observe(block(strains, positions[:3], positions[3]), (k + 1) * CYCLE)
            out.append(history.values())
        return np.array(out)

    first = run()
    history.reset()
    assert np.array_equal(run(), first)
    assert np.all(np.isfinite(first)) and np.all(np.abs(first) <= 51.0)


def test_the_env_observation_carries_the_history_only_when_asked():
    """history=True appends the history's entries to the host observation (deploy builds them too);
    without it the observation is as before."""
    import gymnasium as gym

    plain = gym.make("BH8Grasp-v0", randomize=False)
    with_history = gym.make("BH8Grasp-v0", randomize=False, history=True)
    try:
        obs, _ = plain.reset(seed=3)
        hobs, _ = with_history.reset(seed=3)
        extra = with_history.unwrapped.host_observation_size - plain.unwrapped.host_observation_size
        assert extra == len(HapticHistory(FIELDS, 2.0).names) == 25
        assert np.array_equal(hobs[:len(obs)], obs)
        assert with_history.unwrapped.observation_fields[len(obs):][:2] == ("rise1", "peak_rise1")
        with pytest.raises(ValueError, match="haptic history"):
            with_history.unwrapped.observation_from_feedback([0] * 7, np.zeros(8), 0.01)
    finally:
        plain.close()
        with_history.close()
