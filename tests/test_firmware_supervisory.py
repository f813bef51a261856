"""Supervisory mode conformance: framing, every command, parameters, status codes, RESET, store.

Run through the `link` fixture (in-process and through the pty of `bh8 serve`) where the wire
matters. Sources: manual §5.1-§5.4 (commands, prefixes, parameters, Table 3), SPEC.md §2-§3.
"""
import pytest

from bh8_gym.firmware import Firmware
from test_parameters import MANUAL_GLOBAL, MANUAL_MOTOR

PROMPT = b"=> "


def error_of(reply: bytes) -> int | None:
    """The n of an "ERR n" reply (SPEC.md §2: nothing precedes the error line), else None."""
    if reply.startswith(b"\n\rERR "):
        assert reply.endswith(b"\n\r=> "), reply
        return int(reply[6:-5])
    return None


def test_bare_cr_gets_lf_cr_prompt(link):
    """SPEC.md §2: a bare CR gets "\\n\\r=> "."""
    link.write(b"\r")
    assert link.read_until(PROMPT, 10) == b"\n\r=> "


def test_echo_then_lines_then_prompt(link):
    """SPEC.md §2: echo without the CR, "\\n\\r", output lines each "\\n\\r", then "=> "."""
    link.write(b"1FGET P\r")
    reply = link.read_until(PROMPT, 10)
    assert reply == b"1FGET P\n\r0\n\r=> "


def test_lower_case_is_accepted(link):
    """SPEC.md §2: lower case lines work like upper case ones."""
    assert link.lines("sfget dp") == ["1575"]


def test_fget_prints_one_line_per_name_values_in_f1_f2_f3_s_order(link):
    """§5.2.2 FGET / SPEC.md §2: one line per name, one value per selected motor, F1 F2 F3 S order."""
    link.command("3FSET DP 3333")
    assert link.lines("S31FGET DP DS") == ["8500 3333 1575", "1700 1700 315"]
    assert link.lines("FGET MOV") == ["100 100 100 60"]
    assert link.lines("GFGET CT") == ["17000 17000 17000"]


def test_fset_takes_several_pairs(link):
    """§5.2.2 FSET: several name/value pairs in one command (example "SFSET DS 100 DP 1500")."""
    assert link.lines("SFSET DS 100 DP 1500") == []
    assert link.lines("SFGET DS DP") == ["100", "1500"]


def test_pset_takes_several_pairs(link):
    """§5.2.3 PSET: several pairs; PGET prints one line per name."""
    assert link.lines("PSET OTEMP 600 LFT 1") == []
    assert link.lines("PGET OTEMP LFT") == ["600", "1"]


@pytest.mark.parametrize("name", sorted(MANUAL_MOTOR))
def test_motor_parameter_default_range_and_read_only(link, name):
    """§5.3: every motor parameter's finger/spread default, range edges and read-only status."""
    lo, hi, finger, spread, read_only, _ = MANUAL_MOTOR[name]
    if read_only:
        assert error_of(link.command(f"FSET {name} 0")) == 256
        assert len(link.lines(f"FGET {name}")[0].split()) == 4
        return
    assert link.lines(f"FGET {name}") == [f"{finger} {finger} {finger} {spread}"]
    assert link.lines(f"1FSET {name} {lo}") == [] and link.lines(f"1FGET {name}") == [str(lo)]
    assert link.lines(f"1FSET {name} {hi}") == [] and link.lines(f"1FGET {name}") == [str(hi)]
    assert error_of(link.command(f"1FSET {name} {lo - 1}")) == 128
    assert error_of(link.command(f"1FSET {name} {hi + 1}")) == 128
    assert link.lines(f"1FGET {name}") == [str(hi)]


@pytest.mark.parametrize("name", sorted(MANUAL_GLOBAL))
def test_global_parameter_default_range_and_read_only(link, name):
    """§5.4: every global parameter's default, range edges and read-only status."""
    lo, hi, default, _, read_only, _ = MANUAL_GLOBAL[name]
    if read_only:
        assert error_of(link.command(f"PSET {name} 1")) == 256
        value = int(link.lines(f"PGET {name}")[0])
        if lo is not None:
            assert lo <= value <= hi
        return
    assert link.lines(f"PGET {name}") == [str(default)]
    if name == "BAUD":
        assert error_of(link.command("PSET BAUD 97")) == 128
        return
    assert link.lines(f"PSET {name} {hi}") == [] and link.lines(f"PGET {name}") == [str(hi)]
    assert link.lines(f"PSET {name} {lo}") == [] and link.lines(f"PGET {name}") == [str(lo)]
    assert error_of(link.command(f"PSET {name} {hi + 1}")) == 128
    assert error_of(link.command(f"PSET {name} {lo - 1}")) == 128


def test_msg_and_hsg_are_one_value(link):
    """§5.3.1: MSG is an alias of HSG."""
    link.command("FSET MSG 200")
    assert link.lines("FGET HSG MSG") == ["200 200 200 200", "200 200 200 200"]


@pytest.mark.parametrize(
    "line, code",
    [
        ("XYZZY", 32),  # unknown command
        ("S", 32),  # a prefix alone
        ("FGET NOPE", 64),  # unknown parameter
        ("FSET DP", 128),  # missing value
        ("FSET DP abc", 128),  # not a number
        ("M 20001", 128),  # §5.2.1 M position 0 to 20000
        ("IC -5", 128),
        ("FSET SG 5", 256),  # read-only
        ("PSET TEMP 5", 256),
        ("FSET DP 1 NOPE 2", 64),
        ("FSET NOPE 1 DP 99999", 64 + 128),  # SPEC.md §2: the sum of the codes encountered
        ("HI 5", 1024),  # too many arguments
        ("M 5 6", 1024),
        ("VERS 1", 1024),
        ("1PGET TEMP", 4096),  # prefix on a command that takes none
        ("GFLIST", 4096),
        ("SRESET", 4096),
        ("M 100", 4),  # motion before HI
        ("GC", 4),
        ("LOOP", 4),
        ("T", 1),  # §5.2.1 T note: "ERR 1" when a selected motor isn't initialized
    ],
)
def test_status_codes(link, line, code):
    """Table 3 / SPEC.md §2: each error gets "ERR n" then the prompt, nothing before it."""
    assert error_of(link.command(line)) == code


@pytest.mark.parametrize("line", ["1FSET DP \xb2", "ERR \xb9", "PSET OTEMP 1\xb2", "FSET DP +\xb9"])
def test_only_ascii_digits_are_numbers(link, line):
    """SPEC.md §2: 128 = "not a number". Latin-1 superscripts ("²" is 0xB2) are not digits; they
    used to raise inside the parser and end `bh8 serve`."""
    assert error_of(link.command(line)) == 128
    assert link.lines("1FGET DP") == ["8500"]


@pytest.mark.parametrize("line", ["\xdf\xdfC", "\xdfFGET P", "1\xdfFGET P"])
def test_non_ascii_letters_are_not_prefixes(link, line):
    """Manual Table 2: the prefixes are 1, 2, 3, 4, G and S only. Upper-casing is ASCII's ("ß",
    0xDF, is not "SS", which made line noise a spread prefix)."""
    link.command("HI")
    assert error_of(link.command(line)) == 32
    assert link.lines("SFGET P") == ["0"]


def test_failed_fset_sets_nothing(link):
    """Our all-or-nothing FSET (documented in firmware.py): a bad pair leaves every value alone."""
    assert error_of(link.command("FSET DP 100 MCV 5")) == 128
    assert link.lines("1FGET DP") == ["8500"]


def test_every_command_once_after_hi(link):
    """§5.2: every supervisory command answers with the framing of SPEC.md §2."""
    assert link.lines("HI") == []
    commands = [
        "C", "O", "HOME", "IC", "IO", "IC 100", "IO 100", "M", "M 1000", "TC", "TO", "T",
        "FSET DP 8000", "FGET DP", "FLOAD", "FSAVE", "FDEF", "FLIST", "FLISTV", "FLISTA", "FLISTAV",
        "PSET LFT 0", "PGET LFT", "PLOAD", "PSAVE", "PDEF", "PLIST", "PLISTV", "PLISTA", "PLISTAV",
        "?", "?HI", "A?", "ERR", "ERR 3", "VERS", "HOME",
    ]
    for line in commands:
        reply = link.command(line)
        assert error_of(reply) is None, (line, reply)
        assert reply.startswith(b"\n\r") and reply.endswith(PROMPT)


def test_listings(link):
    """§5.2.2-§5.2.5: FLIST standard only with descriptions, FLISTA all, FLISTV values per motor;
    SPEC.md §3.1: BS first, BD and BP before OD, BDAT only in FLISTA."""
    flist = link.lines("FLIST")
    names = [line.split()[0] for line in flist]
    assert names[:4] == ["BS", "DP", "DS", "HSG"] and "ACCEL" not in names and "BDAT" not in names
    assert names[names.index("MSG") + 1:names.index("MSG") + 4] == ["BD", "BP", "OD"]
    assert "BDAT" in [line.split()[0] for line in link.lines("FLISTA")]
    assert any(line.startswith("DP") and "Default Position" in line for line in flist)
    assert "TSTOP" in [line.split()[0] for line in link.lines("FLISTA")]
    flistv = link.lines("3FLISTV")
    assert "DP 8500" in flistv and "MCV 100" in flistv
    assert "IVEL 150" in link.lines("SFLISTAV")
    assert [line.split()[0] for line in link.lines("PLIST")] == ["BAUD", "LFT", "OTEMP", "TEMP", "PTEMP", "UPSECS", "SN"]
    assert "LFDPD 0" in link.lines("PLISTAV") and "LFDPD" not in " ".join(link.lines("PLISTV"))


def test_help_and_error_commands(link):
    """§5.2.4-§5.2.5: ? lists standard commands, ?NAME one, A? also advanced; ERR n decodes n."""
    standard = [line.split()[0] for line in link.lines("?")]
    assert "HI" in standard and "FLISTA" not in standard
    assert "FLISTA" in [line.split()[0] for line in link.lines("A?")]
    assert link.lines("?HI") == ["HI       Hand Initialize"]
    assert error_of(link.command("?NOPE")) == 32
    assert link.lines("ERR 3") == ["1 No motor board found", "2 No motor found"]
    assert link.lines("ERR 16384") == ["16384 Cntl-C abort command received"]
    assert len(link.lines("ERR")) == 15


def test_vers_reports_a_4_3x_version(link):
    """SPEC.md §7: VERS reports a 4.3x version on the default profile."""
    assert link.lines("VERS")[0].startswith("4.3")


def test_reset_prints_banner_and_reloads_parameters(link):
    """§5.2.4 RESET = power cycle; SPEC.md §2: banner containing "BarrettHand Firmware" + LF;
    parameters come back from the store and motors are uninitialised."""
    link.command("HI")
    link.command("FSET DP 1000")
    link.command("2FSET DP 2000")
    link.command("2FSAVE")
    reply = link.command("RESET")
    assert b"BarrettHand Firmware\n" in reply and reply.endswith(PROMPT)
    assert link.lines("FGET DP") == ["8500 2000 8500 1575"]
    assert error_of(link.command("M")) == 4
    assert link.lines("FGET S") == ["4 4 4 4"]


def test_pset_baud_then_bare_cr(link):
    """Barrett API 4.4.3 baud sequence (SPEC.md §2 sources): "PSET BAUD n" answers normally, then a
    bare CR gets "\\n\\r=> "."""
    assert link.lines("PSET BAUD 384") == []
    link.write(b"\r")
    assert link.read_until(PROMPT, 10) == b"\n\r=> "
    assert link.lines("PGET BAUD") == ["384"]


def test_ctrl_c_when_idle_gives_a_prompt_and_cr_after_is_harmless(link):
    """SPEC.md §2: ^C alone when idle just gets a prompt; a CR right after it is harmless."""
    link.write(b"FGE\x03")
    assert link.read_until(PROMPT, 10) == b"FGE\n\r=> "
    link.write(b"\r")
    assert link.read_until(PROMPT, 10) == b"\n\r=> "


def test_ctrl_c_aborts_a_motion(inproc_link):
    """§5.5 case 4: ^C during a motion terminates every motor; reply ERR 16384, then S shows it.

    In-process: ^C written with the command arrives while the motion runs (over an unpaced pty
    the server may finish the motion before reading the ^C; `bh8 serve --realtime` tests that)."""
    link = inproc_link
    link.command("HI")
    link.write(b"GC\r\x03")
    reply = link.read_until(PROMPT, 30)
    assert reply == b"GC\n\rERR 16384\n\r=> "
    assert link.lines("GFGET S") == ["16384 16384 16384"]
    positions = [int(v) for v in link.lines("GFGET P")[0].split()]
    assert all(p < 5000 for p in positions)


def test_enabled_motors_are_the_default_selection_of_movement_commands_only(link):
    """§5.3.4 EN: "a motion command with no motor prefix will act on this motor"; §5.2: other motor
    commands without a prefix act on all four (so FSET EN 1 undoes FSET EN 0)."""
    link.command("3FSET EN 0")
    assert link.lines("FGET DP EN") == ["8500 8500 8500 1575", "1 1 0 1"]
    link.command("HI")
    assert link.lines("FGET S") == ["0 0 4 0"]  # F3 was left out: still not initialised
    link.command("FSET EN 0")
    assert link.lines("FGET EN") == ["0 0 0 0"]
    link.command("FSET EN 1")
    assert link.lines("FGET EN") == ["1 1 1 1"]


def test_over_temperature_fails_motor_commands(link):
    """§5.4.1 OTEMP: TEMP > OTEMP (OTEMP ≠ 0) makes motor commands fail with 8192."""
    link.command("PSET OTEMP 1")
    assert error_of(link.command("HI")) == 8192
    assert link.lines("T") is not None
    link.command("PSET OTEMP 0")
    assert link.lines("HI") == []


def test_backspace_edits_the_line(link):
    """Backspace (documented in firmware.py) removes the last character and echoes "\\b \\b"."""
    link.write(b"VERX\bS\r")
    reply = link.read_until(PROMPT, 10)
    assert reply.startswith(b"VERX\b \bS\n\r4.3")


def test_over_long_line_is_an_error_not_a_crash(link):
    """Our limit (MAX_LINE_LENGTH 255): a longer line answers ERR 128 and the next line works."""
    assert error_of(link.command("FGET " + "P " * 200)) == 128
    assert link.lines("1FGET DP") == ["8500"]


def test_fsave_and_psave_on_a_full_disk_answer_as_the_hand_and_warn(tmp_path, monkeypatch):
    """SPEC.md §3 (our choice): a save the host's disk refuses (ENOSPC) is not the hand's error.
    Table 3 has no status for a failed save (a worn EEPROM, §5.2.2 FSAVE / §5.2.3 PSAVE notes, is
    not reported either), so FSAVE and PSAVE answer the prompt as on the hand, and the failure is
    a StoreWarning for the host (`bh8 serve` prints it on stderr). Nothing saved before is lost
    (the file is replaced atomically, no temporary left); the values live in memory (FLOAD, PLOAD
    and RESET give them back) and reach the disk with the next save that succeeds."""
    import errno
    import warnings

    import bh8_gym.nvstore as nvstore

    store = tmp_path / "store"
    firmware = Firmware(store_dir=store, seed=0)
    try:
        assert firmware.transact(b"PSAVE\r") == b"PSAVE\n\r=> "
        before = (store / nvstore.STORE_FILENAME).read_bytes()

        def disk_full(fd):
            raise OSError(errno.ENOSPC, "No space left on device")

        monkeypatch.setattr(nvstore.os, "fsync", disk_full)
        with pytest.warns(nvstore.StoreWarning, match="No space left on device"):
            assert firmware.transact(b"1FSET DP 4321\r1FSAVE\r") == b"1FSET DP 4321\n\r=> 1FSAVE\n\r=> "
        with pytest.warns(nvstore.StoreWarning, match="No space left on device"):
            assert firmware.transact(b"PSET OTEMP 111\rPSAVE\r") == b"PSET OTEMP 111\n\r=> PSAVE\n\r=> "
        assert (store / nvstore.STORE_FILENAME).read_bytes() == before
        assert sorted(path.name for path in store.iterdir() if not path.name.startswith(".")) == [nvstore.STORE_FILENAME]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", nvstore.StoreWarning)
            assert firmware.transact(b"1FSET DP 1\r1FLOAD\r1FGET DP\r").endswith(b"1FGET DP\n\r4321\n\r=> ")
            assert firmware.transact(b"RESET\r").endswith(PROMPT)
        assert firmware.transact(b"PGET OTEMP\r") == b"PGET OTEMP\n\r111\n\r=> "
        monkeypatch.undo()
        assert firmware.transact(b"PSAVE\r") == b"PSAVE\n\r=> "
    finally:
        firmware.shutdown()
    again = Firmware(store_dir=store, seed=0)
    try:
        assert again.transact(b"1FGET DP\rPGET OTEMP\r") == b"1FGET DP\n\r4321\n\r=> PGET OTEMP\n\r111\n\r=> "
    finally:
        again.shutdown()


def test_store_persists_across_firmware_instances(tmp_path):
    """§5.2.2-§5.2.3, §5.3.2, §5.4.2: saved sets, OD, PTEMP, UPSECS and SN survive a restart."""
    first = Firmware(store_dir=tmp_path, seed=5)
    assert first.transact(b"HI\r").endswith(PROMPT)
    first.transact(b"GC\r")
    first.transact(b"1FSET MCV 80\r1FSAVE\r")
    first.run_until_idle()
    first.transact(b"PSET LFT 1\r")
    first.transact(b"PSAVE\r")
    od = first.transact(b"FGET OD\r").split(b"\n\r")[1]
    sn = first.transact(b"PGET SN\r").split(b"\n\r")[1]
    upsecs = float(first.transact(b"PGET UPSECS\r").split(b"\n\r")[1])
    first.shutdown()
    assert [int(v) for v in od.split()][:3] >= [16, 16, 16]

    second = Firmware(store_dir=tmp_path, seed=6)
    assert second.transact(b"1FGET MCV\r") == b"1FGET MCV\n\r80\n\r=> "
    assert second.transact(b"PGET LFT\r") == b"PGET LFT\n\r1\n\r=> "
    assert second.transact(b"FGET OD\r").split(b"\n\r")[1] == od
    assert second.transact(b"PGET SN\r").split(b"\n\r")[1] == sn
    assert int(second.transact(b"PGET PTEMP\r").split(b"\n\r")[1]) > 0
    second.transact(b"HI\r")
    assert int(second.transact(b"PGET UPSECS\r").split(b"\n\r")[1]) >= upsecs
    second.shutdown()


def test_fresh_firmware_sends_nothing_until_asked(tmp_path):
    """Our power-up choice (firmware.py): no banner at construction; a CR gets the prompt."""
    fw = Firmware(store_dir=tmp_path, seed=0)
    fw.run_until_idle()
    assert fw.read() == b""
    assert fw.transact(b"\r") == b"\n\r=> "
    assert fw.idle and not fw.in_loop
    fw.shutdown()
