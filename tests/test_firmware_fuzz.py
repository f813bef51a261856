"""No byte sequence makes the firmware raise, hang or leave its parameter ranges.

Sources: the firmware brief's robustness rule ("no byte sequence makes it raise or hang");
SPEC.md §2 (a CR yields a prompt), §5 (RealTime byte counting); manual §5.3-§5.4 (ranges).
"""
import re

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bh8_gym.firmware import Firmware
from bh8_gym.parameters import global_parameters, motor_parameters

# Fragments that reach deep states (motions, LOOP, baud changes, edits) mixed with raw bytes.
FRAGMENTS = [
    b"HI\r", b"GC\r", b"SO\r", b"1M 3000\r", b"2IC\r", b"TC\r", b"T\r", b"LOOP\r", b"12LOOP\r",
    b"C", b"c", b"A", b"a", b"\x03", b"\r", b"\n", b"\x08", b"FSET DP 5 MCV 4080\r",
    b"PSET BAUD 384 LFT 1\r", b"FSET LFDPC 0 LFVC 0 LCVC 0\r", b"FSET TSTOP 0\r", b"RESET\r",
    b"FGET P SG OD\r", b"PGET TEMP\r", b"?\r", b"ERR 99999999999\r", b"FSET ACCEL 0\r",
    b"1FSET LCV 0 LCPG 0\r", b"FSET SAMPLE 15\r", b"PSET LFDPD 1\r", b"FLISTAV\r",
]
streams = st.lists(
    st.one_of(st.sampled_from(FRAGMENTS), st.binary(max_size=12)), max_size=25
).map(b"".join)


@pytest.fixture(scope="module")
def machine(tmp_path_factory):
    fw = Firmware(store_dir=tmp_path_factory.mktemp("store"), seed=0)
    yield fw, fw.snapshot()
    fw.shutdown()


def back_to_prompt(fw: Firmware) -> bytes:
    """Leave LOOP (filling any partial control block first), then send a CR."""
    fw.run_until_idle()
    if fw.in_loop:
        fw.write(b"\x03" * (fw.loop_layout.control_payload_size + 1))
        fw.run_until_idle()
    assert not fw.in_loop
    fw.read()
    return fw.transact(b"\r")


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=streams)
def test_random_streams_keep_the_firmware_answering(machine, data):
    """Any bytes: no exception, run_until_idle returns, a CR afterwards yields a prompt, and
    every parameter stays within its §5.3/§5.4 range."""
    fw, snap = machine
    fw.restore(snap)
    fw.write(data)
    reply = back_to_prompt(fw)
    assert reply.endswith(b"=> ")
    assert fw.idle
    motor_table = motor_parameters()
    for motor, values in fw._motor_values.items():
        for name, value in values.items():
            assert motor_table[name].accepts(value), (motor, name, value)
    global_table = global_parameters()
    for name, value in fw._globals.items():
        assert global_table[name].accepts(value), (name, value)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.binary(max_size=64))
def test_random_bytes_in_loop_mode(machine, data):
    """SPEC.md §5: in LOOP every byte is counted (headers, data, 0x03/0x0D inside data); a bad
    header returns to supervisory mode with ERR 2048; nothing raises."""
    fw, snap = machine
    fw.restore(snap)
    assert fw.transact(b"HI\r").endswith(b"=> ")
    assert fw.transact(b"GLOOP\r") == b"GLOOP*"
    fw.write(data)
    fw.run_until_idle()
    out = fw.read()
    if data and data[0] not in b"CcAa\x03":
        assert out.startswith(b"\n\rERR 2048\n\r=> ")
    assert back_to_prompt(fw).endswith(b"=> ")


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(value=st.text(st.one_of(st.sampled_from("0123456789+- \xa0\xb2\xb3\xb9"),  # digits, signs, look-alikes
                               st.characters(min_codepoint=0x20, max_codepoint=0xFF, exclude_characters="\x7f")),
                     min_size=1, max_size=4))
def test_any_latin1_value_is_a_number_or_err_128(machine, value):
    """SPEC.md §2: a value that is not a number gets ERR 128 and sets nothing; only ASCII digits
    with an optional sign are numbers (str.isdigit() also accepts "²", which used to raise)."""
    fw, snap = machine
    fw.restore(snap)
    reply = fw.transact(b"1FSET DP " + value.encode("latin-1") + b"\r")
    assert reply.endswith(b"\n\r=> ")
    text = value.strip(" ")
    valid = re.fullmatch(r"[+-]?[0-9]+", text) is not None and 0 <= int(text) <= 65535  # "-0" is 0
    set_value = fw.transact(b"1FGET DP\r").split(b"\n\r")[1]
    if valid:
        assert b"ERR" not in reply and set_value == str(int(text)).encode()
    else:
        assert reply.endswith(b"\n\rERR 128\n\r=> ") and set_value == b"8500"
