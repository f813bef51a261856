"""The parameter table against the manual's values, written out here independently of parameters.py.

Sources: manual §5.3.1-§5.3.4 (motor), §5.4.1-§5.4.3 (global), §6.3 Table 4; SPEC.md §3, §3.1
(breakaway parameters, from a later manual edition and Barrett's API documentation), §7.
"""
import pytest

from bh8_gym import parameters as P

# name: (min, max, finger default, spread default, read-only, advanced) — copied from the manual.
MANUAL_MOTOR = {
    "BS": (0, 1, 0, 0, False, False),  # SPEC.md §3.1: a flag (API docs); default 0 (§9.3.1: the outer link closes on)
    "DP": (0, 65535, 8500, 1575, False, False),  # §5.3.1
    "DS": (0, 65535, 1700, 315, False, False),
    "HSG": (0, 256, 256, 256, False, False),
    "LSG": (0, 256, 256, 256, False, False),
    "MOV": (16, 4080, 100, 60, False, False),
    "MCV": (16, 4080, 100, 60, False, False),
    "MSG": (0, 256, 256, 256, False, False),
    "BD": (0, 1, None, None, True, False),  # SPEC.md §3.1 (manual D3000 AF.00 §5.3.2)
    "BP": (0, 20000, None, None, True, False),  # SPEC.md §3.1: "0 or 20000"
    "OD": (0, 4_294_967_295, None, None, True, False),  # §5.3.2 "0 to 4 billion"
    "P": (None, None, None, None, True, False),
    "S": (None, None, None, None, True, False),
    "SG": (0, 255, None, None, True, False),
    "LCV": (0, 1, 1, 1, False, False),  # §5.3.3
    "LCVC": (0, 255, 1, 1, False, False),
    "LCPG": (0, 1, 1, 1, False, False),
    "LFV": (0, 1, 1, 1, False, False),
    "LFVC": (0, 255, 1, 1, False, False),
    "LFS": (0, 1, 1, 1, False, False),
    "LFAP": (0, 1, 1, 1, False, False),
    "LFDP": (0, 1, 1, 1, False, False),
    "LFDPC": (0, 255, 1, 1, False, False),
    "ACCEL": (0, 65535, 4, 2, False, True),  # §5.3.4
    "BDAT": (0, 65535, 100, 100, False, True),  # SPEC.md §3.1: range and default our choice
    "CT": (0, 65535, 17000, 3150, False, True),
    "EN": (0, 1, 1, 1, False, True),
    "FDZ": (0, 255, 0, 0, False, True),
    "FIP": (0, 255, 0, 0, False, True),
    "FPG": (0, 255, 10, 10, False, True),
    "HOLD": (0, 1, 0, 1, False, True),
    "IHIT": (0, 65535, 2, 0, False, True),
    "IOFF": (0, 65535, 50, 0, False, True),
    "IVEL": (16, 4080, 300, 150, False, True),
    "MPE": (0, 65535, 50, 50, False, True),
    "OT": (0, 65535, 0, 0, False, True),
    "SAMPLE": (15, 255, 31, 31, False, True),
    "SGFLIP": (0, 1, 0, 0, False, True),  # no documented default: the brief fixes 0
    "TSTOP": (0, 65535, 30, 30, False, True),
}
MANUAL_MOTOR_44 = {"LCT": (0, 1, 0, 0, False, False), "LFBP": (0, 1, 0, 0, False, False), "LFAIN": (0, 1, 0, 0, False, False)}
MANUAL_GLOBAL = {
    "BAUD": (None, None, 96, None, False, False),  # §5.4.1, only 7 values
    "LFT": (0, 1, 0, None, False, False),
    "OTEMP": (0, 1250, 0, None, False, False),
    "TEMP": (-550, 1250, None, None, True, False),  # §5.4.2
    "PTEMP": (0, 1250, None, None, True, False),
    "UPSECS": (0, 4_294_967_295, None, None, True, False),
    "SN": (None, None, None, None, True, False),
    "LFDPD": (0, 1, 0, None, False, True),  # §5.4.3
}


@pytest.mark.parametrize("name", sorted(MANUAL_MOTOR))
def test_motor_parameter_matches_manual(name):
    """§5.3: range, finger/spread default, read-only and advanced status of every motor parameter."""
    lo, hi, finger, spread, read_only, advanced = MANUAL_MOTOR[name]
    p = P.motor_parameters("4.3")[name]
    assert p.read_only == read_only
    assert p.advanced == advanced
    if lo is not None:
        assert (p.minimum, p.maximum) == (lo, hi)
        assert p.accepts(lo) and p.accepts(hi)
        assert not p.accepts(lo - 1) and not p.accepts(hi + 1)
    if not read_only:
        assert p.default_for(1) == finger and p.default_for(2) == finger and p.default_for(3) == finger
        assert p.default_for(4) == spread


@pytest.mark.parametrize("name", sorted(MANUAL_GLOBAL))
def test_global_parameter_matches_manual(name):
    """§5.4: range, default, read-only and advanced status of every global parameter."""
    lo, hi, default, _, read_only, advanced = MANUAL_GLOBAL[name]
    p = P.global_parameters("4.3")[name]
    assert p.read_only == read_only and p.advanced == advanced
    if lo is not None:
        assert (p.minimum, p.maximum) == (lo, hi)
        assert p.accepts(lo) and p.accepts(hi) and not p.accepts(lo - 1) and not p.accepts(hi + 1)
    if not read_only:
        assert P.default_global_values("4.3")[name] == default


def test_tables_hold_exactly_the_manual_parameters():
    """§5.3, §5.4, SPEC.md §7: no parameter missing or invented; 4.4 adds LCT LFBP LFAIN only."""
    assert set(P.motor_parameters("4.3")) == set(MANUAL_MOTOR)
    assert set(P.motor_parameters("4.4")) == set(MANUAL_MOTOR) | set(MANUAL_MOTOR_44)
    assert set(P.global_parameters("4.3")) == set(MANUAL_GLOBAL)
    for name, (lo, hi, finger, spread, ro, adv) in MANUAL_MOTOR_44.items():
        p = P.motor_parameters("4.4")[name]
        assert (p.minimum, p.maximum, p.default_for(1), p.default_for(4), p.read_only) == (lo, hi, finger, spread, ro)


def test_baud_accepts_only_its_seven_values():
    """§5.4.1: BAUD values 6, 12, 24, 48, 96, 192, 384 (baud/100), nothing in between."""
    baud = P.global_parameters()["BAUD"]
    assert [v for v in range(0, 400) if baud.accepts(v)] == [6, 12, 24, 48, 96, 192, 384]


def test_msg_is_an_alias_of_hsg():
    """§5.3.1: MSG is an alias for HSG — one stored value."""
    table = P.motor_parameters()
    assert table["MSG"].stored_name == "HSG"
    assert "MSG" not in P.default_motor_values(1)


def test_list_membership():
    """§5.3.4/§5.2.5: FLIST shows standard parameters only, FLISTA all; PLIST vs PLISTA likewise."""
    motor = P.motor_parameters("4.3")
    standard = {p.name for p in P.listed(motor, advanced=False)}
    everything = {p.name for p in P.listed(motor, advanced=True)}
    assert standard == {n for n, row in MANUAL_MOTOR.items() if not row[5]}
    assert everything == set(MANUAL_MOTOR)
    globals_ = P.global_parameters("4.3")
    assert {p.name for p in P.listed(globals_, advanced=False)} == {"BAUD", "LFT", "OTEMP", "TEMP", "PTEMP", "UPSECS", "SN"}
    assert {p.name for p in P.listed(globals_, advanced=True)} == set(MANUAL_GLOBAL)


def test_listing_order_follows_the_manual():
    """§5.3.1: FLIST prints in the manual's order, movement parameters first; SPEC.md §3.1: BS
    heads the movement parameters, BD and BP the status ones, BDAT follows ACCEL."""
    names = [p.name for p in P.listed(P.motor_parameters(), advanced=False)]
    assert names[:8] == ["BS", "DP", "DS", "HSG", "LSG", "MOV", "MCV", "MSG"]
    assert names[8:12] == ["BD", "BP", "OD", "P"]
    advanced = [p.name for p in P.listed(P.motor_parameters(), advanced=True) if p.advanced]
    assert advanced[:3] == ["ACCEL", "BDAT", "CT"]


def test_coefficient_zero_scales_as_one():
    """SPEC.md §3: coefficients accept 0..255 and 0 is treated as 1 when scaling."""
    assert P.coefficient(0) == 1 and P.coefficient(1) == 1 and P.coefficient(255) == 255
    assert P.motor_parameters()["LCVC"].accepts(0)


def test_descriptions_are_the_manual_names():
    """§5.3: FLIST prints each parameter with its description (the manual's Name field)."""
    table = P.motor_parameters()
    assert table["DP"].description == "Default Position"
    assert table["TSTOP"].description == "Time to Stop"
    assert P.global_parameters()["UPSECS"].description == "Uptime Seconds"


def test_bad_profile_and_motor_raise_naming_the_value():
    """API hygiene: a bad profile or motor raises ValueError naming it."""
    with pytest.raises(ValueError, match="4.9"):
        P.motor_parameters("4.9")
    with pytest.raises(ValueError, match="7"):
        P.default_motor_values(7)
