"""bh8_gym.realtime_codec.LoopLayout: block layout, sizes, encode/decode (manual §6.2-§6.4, Tables
4-5; SPEC.md §5 and §7). Expected sizes are computed here from the manual's datum sizes, not from
the codec's own tables."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bh8_gym.realtime_codec import (
    HEADER_ACK,
    HEADER_CONTROL_ACK,
    HEADER_CONTROL_FEEDBACK,
    HEADER_EXIT,
    HEADER_FEEDBACK,
    LoopLayout,
    MotorFlags,
)

# Datum sizes and ranges as the manual states them (§6.2.1, §6.2.2, Tables 4-5; SPEC.md §7 for 4.4).
SIZE = {"LCV": 1, "LCPG": 1, "LCT": 2, "LFV": 1, "LFS": 1, "LFAP": 2, "LFDP": 1, "LFBP": 2, "LFAIN": 1}
RANGE = {
    "LCV": (-128, 127), "LCPG": (0, 255), "LCT": (-32768, 32767), "LFV": (-128, 127), "LFS": (0, 255),
    "LFAP": (0, 65535), "LFDP": (-128, 127), "LFBP": (0, 65535), "LFAIN": (0, 255),
}
LFT_SIZE = {"4.3": 2, "4.4": 1}
LFT_RANGE = {"4.3": (-32768, 32767), "4.4": (-128, 127)}
FLAG_NAMES = ("LCV", "LCPG", "LFV", "LFS", "LFAP", "LFDP", "LCT", "LFBP", "LFAIN")

flags_strategy = st.builds(MotorFlags, **{name: st.booleans() for name in FLAG_NAMES})


@st.composite
def layouts(draw):
    motors = draw(st.lists(st.sampled_from((1, 2, 3, 4)), min_size=1, max_size=4, unique=True))
    flags = {m: draw(flags_strategy) for m in motors}
    return LoopLayout(motors, flags, lft=draw(st.booleans()), firmware=draw(st.sampled_from(("4.3", "4.4"))))


def expected_fields(layout: LoopLayout):
    """The manual's order: per motor in motor order, control LCV then LCPG (4.4: LCT alone when set);
    feedback LFV LFS LFAP LFDP (4.4: then LFBP LFAIN); then LFT."""
    control, feedback = [], []
    is_44 = layout.firmware == "4.4"
    for m in sorted(layout.motors):
        f = layout.flags[m]
        if is_44 and f.LCT:
            control.append((m, "LCT"))
        else:
            control += [(m, n) for n in ("LCV", "LCPG") if getattr(f, n)]
        names = ("LFV", "LFS", "LFAP", "LFDP") + (("LFBP", "LFAIN") if is_44 else ())
        feedback += [(m, n) for n in names if getattr(f, n)]
    if layout.lft:
        feedback.append((None, "LFT"))
    return control, feedback


def value_strategy(layout, fields):
    return st.tuples(*[
        st.integers(*(LFT_RANGE[layout.firmware] if name == "LFT" else RANGE[name])) for _, name in fields
    ])


@given(data=st.data(), layout=layouts())
def test_round_trip_and_sizes_for_random_layouts(data, layout):
    """§6.2: encode→decode is the identity for every layout and every in-range value (data bytes may
    be 0x00, 0x03, 0x0D: counted, never parsed); block sizes are the sum of the datum sizes."""
    control, feedback = expected_fields(layout)
    assert list(layout.control_fields) == control and list(layout.feedback_fields) == feedback
    control_bytes = sum(SIZE[n] for _, n in control)
    feedback_bytes = sum(LFT_SIZE[layout.firmware] if n == "LFT" else SIZE[n] for _, n in feedback)
    assert layout.control_block_size(b"C") == layout.control_block_size(b"c") == 1 + control_bytes
    assert layout.control_block_size(b"A") == layout.control_block_size(b"a") == 1
    assert layout.feedback_size == 1 + feedback_bytes

    values = data.draw(value_strategy(layout, control))
    for header in (HEADER_CONTROL_FEEDBACK, HEADER_CONTROL_ACK):
        block = layout.encode_control(values, header)
        assert block[:1] == header and len(block) == 1 + control_bytes
        assert layout.decode_control(block[1:]) == values
    fb_values = data.draw(value_strategy(layout, feedback))
    block = layout.encode_feedback(fb_values)
    assert block[:1] == b"*" and len(block) == layout.feedback_size
    assert layout.decode_feedback(block) == fb_values


@given(layout=layouts(), data=st.data())
def test_every_feedback_byte_string_decodes_and_reencodes(layout, data):
    """Decoding is a bijection on blocks of the right size: any payload bytes decode to in-range
    values that encode back to the same bytes."""
    payload = data.draw(st.binary(min_size=layout.feedback_size - 1, max_size=layout.feedback_size - 1))
    values = layout.decode_feedback(b"*" + payload)
    assert layout.encode_feedback(values) == b"*" + payload


def test_manual_section_6_4_example_sizes():
    """§6.4: fingers 1, 2 send velocity and report strain + delta position, the spread reports delta
    position, LFT on: control blocks are 3 bytes, feedback blocks 8 bytes."""
    finger = MotorFlags(LCV=True, LCPG=False, LFV=False, LFS=True, LFAP=False, LFDP=True)
    spread = MotorFlags(LCV=False, LCPG=False, LFV=False, LFS=False, LFAP=False, LFDP=True)
    layout = LoopLayout((1, 2, 4), {1: finger, 2: finger, 4: spread}, lft=True)
    assert layout.control_block_size(b"C") == 3
    assert layout.feedback_size == 8
    assert layout.control_fields == ((1, "LCV"), (2, "LCV"))
    assert layout.feedback_fields == ((1, "LFS"), (1, "LFDP"), (2, "LFS"), (2, "LFDP"), (4, "LFDP"), (None, "LFT"))
    assert layout.encode_control((-1, 3), b"C") == b"C\xff\x03"
    assert layout.decode_feedback(b"*\x78\x05\x80\xfb\x00\x01\x9c") == (120, 5, 128, -5, 0, 412)


def test_default_flags_block_sizes_from_spec_section_6():
    """SPEC.md §6: all four motors with the §5.3.3 defaults: 9-byte control, 21-byte feedback (+2 LFT)."""
    assert LoopLayout().control_block_size(b"C") == 9
    assert LoopLayout().feedback_size == 21
    assert LoopLayout(lft=True).feedback_size == 23


@pytest.mark.parametrize(
    "values, fragment",
    [((128, 0), "LCV for motor 1 must be in -128..127, got 128"), ((0, 256), "LCPG for motor 1 must be in 0..255, got 256"),
     ((-129, 0), "got -129"), ((0, -1), "LCPG for motor 1 must be in 0..255, got -1")],
)
def test_control_range_errors_name_the_value(values, fragment):
    """Table 4: LCV is a signed byte, LCPG an unsigned byte; out-of-range values are named."""
    layout = LoopLayout((1,), MotorFlags())
    with pytest.raises(ValueError) as info:
        layout.encode_control(values)
    assert fragment in str(info.value)


def test_feedback_range_errors_name_the_value():
    """§6.2.2: LFAP is an unsigned 2-byte word; 65536 is named in the error."""
    layout = LoopLayout((2,), MotorFlags(LFV=False, LFS=False, LFDP=False))
    with pytest.raises(ValueError) as info:
        layout.encode_feedback((65536,))
    assert "LFAP for motor 2" in str(info.value) and "65536" in str(info.value)


def test_headers_without_data_and_bad_headers():
    """§6.2.1: A and a carry no data, ^C leaves LOOP; any other header is refused."""
    layout = LoopLayout()
    assert layout.encode_control((), HEADER_FEEDBACK) == b"A"
    assert layout.encode_control((), HEADER_ACK) == b"a"
    assert layout.encode_control((), HEADER_EXIT) == b"\x03"
    with pytest.raises(ValueError, match="carries no control data"):
        layout.encode_control((1,) * 8, HEADER_FEEDBACK)
    with pytest.raises(ValueError, match="invalid RealTime header b'X'"):
        layout.encode_control((), b"X")
    with pytest.raises(ValueError, match="expected 8 control values"):
        layout.encode_control((1, 2), HEADER_CONTROL_FEEDBACK)


@pytest.mark.parametrize("value", [1.5, 3.0, np.float64(3.0), "3", None])
def test_non_integer_values_are_refused_with_value_error(value):
    """Table 4: the data are bytes and words; an in-range non-integer is a ValueError naming the
    values, as out-of-range ones are (it was struct.error)."""
    layout = LoopLayout((1,), MotorFlags())
    with pytest.raises(ValueError, match="must be integers"):
        layout.encode_control((value, 0))
    with pytest.raises(ValueError, match="must be integers"):
        layout.encode_feedback((value, 0, 0, 0))


def test_control_block_size_by_header():
    """§6.2.1: C and c carry the control data, A, a and ^C none; anything else is refused."""
    layout = LoopLayout()
    assert layout.control_payload_size == 8
    for header, size in ((b"C", 9), (b"c", 9), (b"A", 1), (b"a", 1), (b"\x03", 1), (ord("C"), 9), (ord("a"), 1)):
        assert layout.control_block_size(header) == size
    for bad in (b"X", b"", b"CC", "C", 0x58, None):
        with pytest.raises(ValueError, match="invalid RealTime header"):
            layout.control_block_size(bad)


def test_malformed_feedback_blocks_are_refused():
    """A feedback block is "*" plus exactly the layout's bytes (§6.2.2)."""
    layout = LoopLayout((1,), MotorFlags())
    with pytest.raises(ValueError, match="got 5 bytes"):
        layout.decode_feedback(b"*\x00\x00\x00\x00")
    with pytest.raises(ValueError, match="starting b'\\\\n'"):
        layout.decode_feedback(b"\n\x00\x00\x00\x00\x00")


def test_firmware_44_additions():
    """SPEC.md §7: LCT (2-byte signed) replaces LCV/LCPG for its motor; LFBP (2 bytes) and LFAIN
    (1 byte) follow LFDP; LFT is one byte. On 4.3 those flags add nothing."""
    flags = MotorFlags(LCT=True, LFBP=True, LFAIN=True)
    layout = LoopLayout((1, 4), {1: flags, 4: MotorFlags()}, lft=True, firmware="4.4")
    assert layout.control_fields == ((1, "LCT"), (4, "LCV"), (4, "LCPG"))
    assert layout.control_block_size(b"C") == 1 + 2 + 1 + 1
    assert layout.feedback_fields[:6] == ((1, "LFV"), (1, "LFS"), (1, "LFAP"), (1, "LFDP"), (1, "LFBP"), (1, "LFAIN"))
    assert layout.feedback_size == 1 + 8 + 5 + 1
    assert layout.encode_control((-2, 5, 200)) == b"C\xff\xfe\x05\xc8"
    assert layout.decode_feedback(layout.encode_feedback((0,) * 10 + (45,)))[-1] == 45
    with pytest.raises(ValueError, match=r"LFT .*must be in -128..127, got 412"):
        layout.encode_feedback((0,) * 10 + (412,))
    legacy = LoopLayout((1, 4), {1: flags, 4: MotorFlags()}, lft=True, firmware="4.3")
    assert legacy.control_fields == ((1, "LCV"), (1, "LCPG"), (4, "LCV"), (4, "LCPG"))
    assert legacy.feedback_size == 1 + 5 + 5 + 2


def test_bad_layouts_are_refused():
    """LOOP motors are a non-empty subset of 1..4; profiles are 4.3 and 4.4."""
    with pytest.raises(ValueError, match="non-empty subset"):
        LoopLayout(())
    with pytest.raises(ValueError, match="non-empty subset"):
        LoopLayout((5,))
    with pytest.raises(ValueError, match="'4.5'"):
        LoopLayout(firmware="4.5")
    with pytest.raises(ValueError, match=r"no flags given for LOOP motor\(s\) \[2\]"):
        LoopLayout((1, 2), {1: MotorFlags()})
