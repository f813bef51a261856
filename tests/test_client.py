"""bh8_gym.client.BarrettHand: framing, typed results, time-outs and recovery.

Three ends of the line:
- `ScriptedHand` behind `FakePort`: a small test-local GCL responder (SPEC.md §2 framing, §5
  RealTime) with fault injection: silence mid-reply, garbage, ERR inside RealTime, an unplugged port;
- bh8sim:// (the firmware in this process) for every call of the client;
- `bh8 serve` on a pty (conftest.PtyLink starts it) for a representative set.
"""
from __future__ import annotations

import contextlib
import time

import pytest
import serial
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bh8_gym.client import line as line_module
from bh8_gym.client import supervisory as supervisory_module  # BAUD_SWITCH_SETTLE_S
from bh8_gym.client import (
    BarrettHand,
    HandConnectionError,
    LoopFeedback,
    firmware_profile_of,
    parse_motors,
)
from bh8_gym.realtime_codec import LoopLayout, MotorFlags
from bh8_gym.status import BH8Error, HandError, HandTimeout, ProtocolError

# ---------------------------------------------------------------------------------------------
# A scripted hand on a fake pyserial port
# ---------------------------------------------------------------------------------------------

FLAG_DEFAULTS = {"LCV": 1, "LCVC": 1, "LCPG": 1, "LFV": 1, "LFVC": 1, "LFS": 1, "LFAP": 1, "LFDP": 1, "LFDPC": 1}


class ScriptedHand:
    """The hand's end of `FakePort`: echo, "\\n\\r", output lines, "=> " (SPEC.md §2); LOOP blocks
    counted with LoopLayout (SPEC.md §5). Faults are armed by setting attributes:

    - `cut_next_reply` = n: the next reply stops after n bytes (the hand goes silent);
    - `garbage_next_reply` = bytes: sent before the next reply;
    - `error_next_block` = code: the next RealTime block gets "\\n\\rERR code\\n\\r=> " instead of "*";
    - `delay_next_reply` = seconds: the next reply arrives that much later;
    - `mute` = True: nothing is ever answered (a hand that is off).
    """

    def __init__(self, firmware: str = "4.3"):
        self.firmware = firmware
        self.motor = {m: dict(FLAG_DEFAULTS, P=1000 * m, MCV=100, MOV=100, LCT=0, LFBP=0, LFAIN=0) for m in (1, 2, 3, 4)}
        self.globals = {"LFT": 0, "TEMP": 412, "BAUD": 96, "LFDPD": 0}
        self.saved_motor = {m: dict(v) for m, v in self.motor.items()}
        self.line = bytearray()
        self.layout: LoopLayout | None = None
        self.block = bytearray()
        self.feedback_deltas: list[int] = []
        self.lines_received: list[str] = []
        self.cut_next_reply = None
        self.garbage_next_reply = b""
        self.error_next_block = None
        self.delay_next_reply = 0.0
        self.mute = False
        self.baud_switches: list[int] = []

    # -- bytes in, bytes out --------------------------------------------------------------------

    def receive(self, data: bytes) -> bytes:
        out = bytearray()
        for byte in data:
            out += self._receive_byte(byte)
        if self.mute:
            return b""
        if out and (self.garbage_next_reply or self.cut_next_reply is not None):
            out[:0] = self.garbage_next_reply
            self.garbage_next_reply = b""
            if self.cut_next_reply is not None:
                del out[self.cut_next_reply:]
                self.cut_next_reply = None
        return bytes(out)

    def _receive_byte(self, byte: int) -> bytes:
        if self.layout is not None:
            return self._loop_byte(byte)
        if byte == 0x03:
            self.line.clear()
            return b"\n\r=> "
        if byte == 0x0D:
            line = self.line.decode("ascii")
            self.line.clear()
            self.lines_received.append(line)
            return self._execute(line)
        self.line.append(byte)
        return bytes([byte])

    def _loop_byte(self, byte: int) -> bytes:
        self.block.append(byte)
        header = self.block[0]
        if header == 0x03:
            self.block.clear()
            self.layout = None
            return b"\n\r=> "
        if header not in b"CcAa":
            return self._loop_error(2048)
        if len(self.block) < self.layout.control_block_size(header):
            return b""
        self.block.clear()
        if self.error_next_block is not None:  # §6.1: the ERR replaces the next "*"
            code, self.error_next_block = self.error_next_block, None
            return self._loop_error(code)
        if header in b"ca":
            return b"*"
        return self._feedback()

    def _loop_error(self, code: int) -> bytes:
        self.block.clear()
        self.layout = None
        return f"\n\rERR {code}\n\r=> ".encode()

    def _feedback(self) -> bytes:
        delta = self.feedback_deltas.pop(0) if self.feedback_deltas else 0
        values = []
        for motor, name in self.layout.feedback_fields:
            values.append({"LFV": -3, "LFS": 120, "LFAP": 1000 * (motor or 0), "LFDP": delta, "LFBP": 77,
                           "LFAIN": 9, "LFT": 41 if self.firmware == "4.4" else 412}[name])
        return self.layout.encode_feedback(values)

    def _execute(self, line: str) -> bytes:
        reply = b"\n\r"  # the line itself was echoed character by character
        prefix = ""
        while line[:1] in tuple("1234GS") and line[:1]:
            prefix += line[0]
            line = line[1:]
        motors = sorted({m for c in prefix for m in {"G": (1, 2, 3), "S": (4,)}.get(c, (int(c),) if c.isdigit() else ())}) or [1, 2, 3, 4]
        words = line.split()
        verb = words[0].upper() if words else ""
        args = words[1:]
        out: list[str] = []
        if verb == "":
            pass
        elif verb == "VERS":
            out = ["4.44" if self.firmware == "4.4" else "4.34"]
        elif verb == "FGET":
            for name in args:
                if name not in self.motor[1]:
                    out = ["ERR 64"]
                    break
                out.append(" ".join(str(self.motor[m][name]) for m in motors))
        elif verb == "PGET":
            for name in args:
                if name not in self.globals:
                    out = ["ERR 64"]
                    break
                out.append(str(self.globals[name]))
        elif verb in ("FSET", "PSET"):
            for name, value in zip(args[::2], args[1::2]):
                if verb == "PSET" and name == "BAUD":
                    self.baud_switches.append(int(value))
                    return b""  # the rest comes at the new rate: lost to the host
                for m in motors if verb == "FSET" else ():
                    self.motor[m][name] = int(value)
                if verb == "PSET":
                    self.globals[name] = int(value)
        elif verb in ("HI", "C", "O", "M", "HOME", "IO", "IC", "TC", "TO", "T", "FLOAD", "FDEF", "PSAVE", "PLOAD", "PDEF"):
            pass
        elif verb == "FSAVE":
            for m in motors:
                self.saved_motor[m] = dict(self.motor[m])
        elif verb == "RESET":
            out = ["", "BarrettHand Firmware Version 4.34 (scripted)"]
        elif verb == "LOOP":
            flags = {m: MotorFlags.from_parameters(self.motor[m]) for m in motors}
            self.layout = LoopLayout(motors, flags, lft=bool(self.globals["LFT"]), firmware=self.firmware)
            return b"*"
        else:
            out = ["ERR 32"]
        return reply + b"".join(text.encode() + b"\n\r" for text in out) + b"=> "


class FakePort:
    """Enough of pyserial's Serial API for BarrettHand, on top of a ScriptedHand."""

    def __init__(self, hand: ScriptedHand):
        self.hand = hand
        self.port = "fake://hand"
        self.timeout = None
        self.baudrate = 9600
        self.is_open = True
        self.unplugged = False
        self.interrupt_next_read = False  # a user's Ctrl-C arriving while the client waits
        self.written = bytearray()
        self._pending: list[tuple[float, bytes]] = []

    def _check(self):
        if self.unplugged:
            raise serial.SerialException("device reports readiness to read but returned no data (device disconnected?)")
        if not self.is_open:
            raise serial.PortNotOpenError()

    def write(self, data) -> int:
        self._check()
        self.written += data
        reply = self.hand.receive(bytes(data))
        delay, self.hand.delay_next_reply = self.hand.delay_next_reply, 0.0
        if reply:
            self._pending.append((time.monotonic() + delay, reply))
        return len(data)

    def _ready(self) -> bytearray:
        now = time.monotonic()
        ready = bytearray()
        while self._pending and self._pending[0][0] <= now:
            ready += self._pending.pop(0)[1]
        if ready:
            self._pending.insert(0, (now, bytes(ready)))
        return ready

    @property
    def in_waiting(self) -> int:
        self._check()
        return len(self._ready())

    def read(self, size: int = 1) -> bytes:
        self._check()
        if self.interrupt_next_read:
            self.interrupt_next_read = False
            raise KeyboardInterrupt
        if not self._ready():
            time.sleep(self.timeout or 0.0)
            if not self._ready():
                return b""
        release, data = self._pending.pop(0)
        if len(data) > size:
            self._pending.insert(0, (release, data[size:]))
        return data[:size]

    def reset_input_buffer(self):
        self._check()
        self._pending = [(t, d) for t, d in self._pending if t > time.monotonic()]

    def close(self):
        self.is_open = False

    def open(self):
        if self.unplugged:
            raise serial.SerialException("could not open port fake://hand: [Errno 2] No such file or directory")
        self.is_open = True


@pytest.fixture
def quick_resync(monkeypatch):
    """Shorter quiet period so fault tests stay fast (the fake's replies are instantaneous)."""
    monkeypatch.setattr(line_module, "RESYNC_QUIET_S", 0.03)
    monkeypatch.setattr(supervisory_module, "BAUD_SWITCH_SETTLE_S", 0.0)


@pytest.fixture
def scripted(quick_resync):
    hand = ScriptedHand()
    port = FakePort(hand)
    with BarrettHand(port, timeout=0.3, motion_timeout=1.0, firmware="4.3") as bh:
        yield bh, hand, port


# ---------------------------------------------------------------------------------------------
# Pure helpers
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "spec, prefix, motors",
    [("1", "1", (1,)), ("G", "123", (1, 2, 3)), ("GS", "1234", (1, 2, 3, 4)), ("124", "124", (1, 2, 4)),
     ("3S", "34", (3, 4)), ("gs", "1234", (1, 2, 3, 4)), (2, "2", (2,)), ([4, 1], "14", (1, 4)), (None, "", ())],
)
def test_motor_sets_follow_table_2(spec, prefix, motors):
    """Manual §5.1.2 Table 2: any mix of 1 2 3 4 G S; G = F1-F3, S = spread; none = EN motors."""
    assert parse_motors(spec) == (prefix, motors)


@pytest.mark.parametrize("bad", ["", "5", "GX", "1 2", [0], [5], [], [True], "A"])
def test_bad_motor_set_raises_value_error_naming_it(bad):
    """A bad motor set never reaches the hand: ValueError naming the value."""
    with pytest.raises(ValueError) as info:
        parse_motors(bad)
    assert repr(bad) in str(info.value)


def test_firmware_profile_from_vers():
    """SPEC.md §7: 4.4 firmware adds LCT/LFBP/LFAIN; everything else uses the 4.3 layout."""
    assert firmware_profile_of("4.34") == "4.3"
    assert firmware_profile_of("BarrettHand Firmware Version 4.40") == "4.4"
    assert firmware_profile_of("4.4.3") == "4.4"
    assert firmware_profile_of("something else") == "4.3"


# ---------------------------------------------------------------------------------------------
# Scripted hand: framing, typed results, validation
# ---------------------------------------------------------------------------------------------


def test_supervisory_framing_and_typed_results(scripted):
    """SPEC.md §2: line + CR out; echo, "\\n\\r", lines, "=> " back; FGET one line per name."""
    bh, hand, port = scripted
    assert bh.get("P MCV", "G") == {"P": [1000, 2000, 3000], "MCV": [100, 100, 100]}
    assert bh.get(["P"], "S") == {"P": [4000]}
    bh.set("13", MCV=80, MOV=60)
    assert hand.lines_received[-1] == "13FSET MCV 80 MOV 60"
    bh.set("2", {"MCV": 90}, MOV=70)
    assert hand.motor[2]["MCV"] == 90 and hand.motor[2]["MOV"] == 70
    assert bh.get_global("TEMP BAUD") == {"TEMP": 412, "BAUD": 96}
    assert bh.temperature() == pytest.approx(41.2)
    bh.set_global(LFT=1)
    assert hand.globals["LFT"] == 1
    assert bh.version() == "4.34"
    assert bh.command("1FGET P") == ["1000"]


@pytest.mark.parametrize(
    "call, line",
    [(lambda b: b.initialize(), "1234HI"), (lambda b: b.open_motors("G"), "123O"), (lambda b: b.close_motors("13"), "13C"),
     (lambda b: b.move(5000, "1"), "1M 5000"), (lambda b: b.move(), "1234M"), (lambda b: b.step_open(300, "S"), "4IO 300"),
     (lambda b: b.step_close(None, "2"), "2IC"), (lambda b: b.home("G"), "123HOME"), (lambda b: b.torque_open(), "1234TO"),
     (lambda b: b.torque_close("3"), "3TC"), (lambda b: b.terminate("S"), "4T"), (lambda b: b.save("G"), "123FSAVE"),
     (lambda b: b.load(), "1234FLOAD"), (lambda b: b.default("4"), "4FDEF"), (lambda b: b.save_global(), "PSAVE"),
     (lambda b: b.load_global(), "PLOAD"), (lambda b: b.default_global(), "PDEF")],
)
def test_each_call_sends_its_gcl_line(scripted, call, line):
    """§5.2: each API call is one GCL command with its Table 2 prefix."""
    bh, hand, _ = scripted
    call(bh)
    assert hand.lines_received[-1] == line


def test_close_releases_the_port_and_never_moves_the_hand(scripted):
    """Python's and pyserial's close() releases the port, as disconnect() does; C is close_motors()."""
    bh, hand, port = scripted
    before = list(hand.lines_received)
    with contextlib.closing(bh):
        pass
    assert hand.lines_received == before
    written = bytes(port.written)
    for call in (lambda: bh.close_motors("G"), lambda: bh.get("P"), bh.resync, lambda: bh.close_motors("G")):
        with pytest.raises(HandConnectionError, match="closed"):  # for good: never reopened
            call()
    assert hand.lines_received == before and bytes(port.written) == written


@pytest.mark.parametrize(
    "call, fragment",
    [(lambda b: b.move(20001), "20001"), (lambda b: b.move(-1), "-1"), (lambda b: b.move(1.5), "1.5"),
     (lambda b: b.step_close(True), "True"), (lambda b: b.set("G", MCV="fast"), "'fast'"),
     (lambda b: b.set("G"), "at least one"), (lambda b: b.get("P;HI"), "'P;HI'"), (lambda b: b.get([]), "at least one"),
     (lambda b: b.set_global(BAUD=384), "set_baud"), (lambda b: b.command("LOOP"), "start_loop"),
     (lambda b: b.command("PSET LFT 1 BAUD 96"), "set_baud"), (lambda b: b.command("FGET P\rHI"), "'FGET P\\rHI'"),
     (lambda b: b.set_baud(9601), "9601"), (lambda b: b.configure_loop("G", MCV=1), "MCV"),
     (lambda b: b.close_motors("7"), "'7'"), (lambda b: b.close_motors(1.5), "1.5"), (lambda b: b.get(5), "5"),
     (lambda b: b.set_baud(38400.0), "38400.0"), (lambda b: b.command("1 LOOP"), "start_loop")],
)
def test_bad_arguments_raise_value_error_naming_the_value(scripted, call, fragment):
    """Bad input to the Python API gets a specific exception naming the value, and nothing is sent."""
    bh, hand, _ = scripted
    before = list(hand.lines_received)
    with pytest.raises(ValueError) as info:
        call(bh)
    assert fragment in str(info.value)
    assert hand.lines_received == before


def test_err_reply_raises_hand_error_with_table_3_bits(scripted):
    """§5.1.3: "ERR <sum>" → HandError with the code and its Table 3 bits; no resync needed after."""
    bh, hand, port = scripted
    with pytest.raises(HandError) as info:
        bh.command("BOGUS")
    assert info.value.code == 32 and info.value.bits == [(32, "Unknown command")]
    assert bh.command("BOGUS", check=False) == ["ERR 32"]
    with pytest.raises(HandError) as info:
        bh.get("NOPE")
    assert info.value.code == 64
    sent_before = len(port.written)
    assert bh.get("P", "1") == {"P": [1000]}
    assert b"\x03" not in port.written[sent_before:]  # an ERR reply ends at a prompt: nothing to recover


@pytest.mark.parametrize("digits", ["9" * 5000, "32768", "0" * 30 + "99999999999"])
def test_an_err_code_that_is_no_status_sum_is_a_protocol_error(scripted, monkeypatch, digits):
    """Table 3's bits sum to at most 32767 (§5.1.3): "ERR" with a larger number, such as 5000
    digits (past Python's integer-string limit: a raw ValueError), is a garbled reply, a
    ProtocolError, in supervisory mode and in place of RealTime's "*"; the next call works."""
    bh, hand, _ = scripted
    execute = hand._execute
    monkeypatch.setattr(hand, "_execute", lambda line: b"\n\rERR " + digits.encode() + b"\n\r=> ")
    with pytest.raises(ProtocolError, match="not a status sum of Table 3"):
        bh.get("P", "1")
    monkeypatch.setattr(hand, "_execute", execute)
    assert bh.get("P", "1") == {"P": [1000]}
    bh.start_loop("G")
    hand.error_next_block = digits
    with pytest.raises(ProtocolError):
        bh.update([1, 1, 1], [5, 5, 5])
    assert bh.get("P", "2") == {"P": [2000]}


def test_reset_checks_banner_after_a_bare_cr(scripted):
    """Barrett's API Reset(): an empty command clears errors, then RESET; the banner names the firmware."""
    bh, hand, _ = scripted
    assert "BarrettHand Firmware" in bh.reset()
    assert hand.lines_received[-2:] == ["", "RESET"]


def test_set_baud_switches_host_after_echo(scripted):
    """Barrett's API Baud(): PSET BAUD n, echo, switch host rate, wait, clear, CR, prompt (§5.4.1)."""
    bh, hand, port = scripted
    bh.set_baud(38400)
    assert hand.baud_switches == [384] and port.baudrate == 38400 and bh.baudrate == 38400
    assert bh.get("P", "1") == {"P": [1000]}


# ---------------------------------------------------------------------------------------------
# Scripted hand: time-outs and recovery
# ---------------------------------------------------------------------------------------------


def test_hand_silent_mid_reply_times_out_then_recovers(scripted):
    """A reply cut after the echo → HandTimeout; the next call resyncs (^C, CR) and works."""
    bh, hand, port = scripted
    hand.cut_next_reply = len("1FGET P") + 3
    started = time.monotonic()
    with pytest.raises(HandTimeout):
        bh.get("P", "1")
    assert time.monotonic() - started < 2.0
    assert bh.get("P", "1") == {"P": [1000]}
    assert b"\x03\r" in port.written


def test_motion_commands_get_the_motion_budget(scripted):
    """Time-outs sized to the command: a 0.6 s motion passes (motion_timeout 1 s), also written with
    a space after the prefix as the firmware allows, a 0.6 s FGET does not (timeout 0.3 s)."""
    bh, hand, _ = scripted
    hand.delay_next_reply = 0.6
    bh.close_motors("G")
    hand.delay_next_reply = 0.6
    bh.command("G C")
    hand.delay_next_reply = 0.6
    with pytest.raises(HandTimeout):
        bh.get("P", "1")
    assert bh.get("P", "2") == {"P": [2000]}


def test_a_reply_that_trickles_without_a_prompt_cannot_hang_a_call(scripted, monkeypatch):
    """A line that keeps sending bytes but never a prompt (noise, a wrong rate) times out at the
    budget plus REPLY_STREAM_LIMIT_BYTES' transfer time (the wait was pushed on by every byte)."""
    bh, hand, port = scripted
    monkeypatch.setattr(line_module, "REPLY_STREAM_LIMIT_BYTES", 96)  # 0.1 s at 9600 baud
    answer = hand.receive

    def trickle(data: bytes) -> bytes:
        hand.receive = answer
        now = time.monotonic()
        port._pending.extend((now + 0.05 * k, b".") for k in range(1, 400))  # 20 s of dots
        return b""

    hand.receive = trickle
    started = time.monotonic()
    with pytest.raises(HandTimeout):
        bh.get("P", "1")
    assert time.monotonic() - started < 1.0  # 0.3 s budget + 0.1 s
    port._pending.clear()
    assert bh.get("P", "1") == {"P": [1000]}


def test_constructor_refuses_a_float_baud_rate():
    with pytest.raises(ValueError, match="9600.0"):
        BarrettHand(FakePort(ScriptedHand()), baudrate=9600.0)


def test_garbage_before_reply_is_a_protocol_error_then_recovers(scripted):
    """Bytes that are not the echo → ProtocolError; the client resyncs and the next call works."""
    bh, hand, _ = scripted
    hand.garbage_next_reply = b"\xff\x00junk"
    with pytest.raises(ProtocolError):
        bh.get("P", "1")
    assert bh.get("P", "3") == {"P": [3000]}


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    garbage=st.binary(max_size=12),
    cut=st.one_of(st.none(), st.integers(min_value=0, max_value=20)),
)
def test_any_corrupted_reply_leaves_a_working_client(scripted, garbage, cut):
    """Whatever a reply is corrupted into, the client raises a BH8Error (or by chance parses it)
    and never hangs; the following call returns the right value."""
    bh, hand, _ = scripted
    hand.garbage_next_reply = garbage
    hand.cut_next_reply = cut
    try:
        bh.get("P MCV", "G")
    except BH8Error:
        pass
    hand.garbage_next_reply, hand.cut_next_reply = b"", None
    assert bh.get("P", "2") == {"P": [2000]}


def test_unplugged_port_raises_connection_error_then_reopens(scripted):
    """A port that disappears (SerialException) → HandConnectionError; after replugging, the next
    call reopens the port, resyncs and works."""
    bh, hand, port = scripted
    port.unplugged = True
    with pytest.raises(HandConnectionError) as info:
        bh.get("P", "1")
    assert "fake://hand" in str(info.value)
    with pytest.raises(HandConnectionError):
        bh.get("P", "1")  # still unplugged: reopening fails clearly
    port.unplugged = False
    assert bh.get("P", "1") == {"P": [1000]}


def test_hand_that_never_answers_fails_fast_with_advice(quick_resync):
    """A hand that is off or at another baud rate: the constructor raises HandTimeout naming §8."""
    hand = ScriptedHand()
    hand.mute = True
    started = time.monotonic()
    with pytest.raises(HandTimeout) as info:
        BarrettHand(FakePort(hand), timeout=0.1)
    assert "§8" in str(info.value) and time.monotonic() - started < 3.0


def test_unopenable_port_name_raises_connection_error():
    """A port name that does not exist → HandConnectionError naming it."""
    with pytest.raises(HandConnectionError) as info:
        BarrettHand("/dev/does-not-exist-bh8")
    # Said once: not pyserial's "could not open port ...: [Errno 2] ..." after our own "cannot open".
    assert str(info.value) == "cannot open '/dev/does-not-exist-bh8': No such file or directory"
    with pytest.raises(HandConnectionError) as info:
        BarrettHand("bh8sim://?seed=x")
    assert str(info.value).count("cannot open") == 1 and "'x'" in str(info.value)


# ---------------------------------------------------------------------------------------------
# Scripted hand: RealTime
# ---------------------------------------------------------------------------------------------


def test_realtime_cycle_with_lfdp_tracking(scripted):
    """§6.2.3: the host adds LFDP × LFDPC to the reported position, which FGET P before LOOP seeds."""
    bh, hand, port = scripted
    bh.configure_loop("12", LCV=1, LCPG=1, LFDPC=2, lft=True)
    layout = bh.start_loop("12")
    assert hand.lines_received[-1] == "12LOOP" and bh.in_loop
    assert layout.control_fields == ((1, "LCV"), (1, "LCPG"), (2, "LCV"), (2, "LCPG"))
    hand.feedback_deltas = [5, -3]
    first = bh.update([10, -10], [20, 30])
    assert isinstance(first, LoopFeedback)
    assert port.written.endswith(b"C\x0a\x14\xf6\x1e")
    assert first.motors[1].tracked_position == 1000 + 10 and first.motors[2].tracked_position == 2000 + 10
    assert first.motors[1].strain == 120 and first.motors[1].velocity == -3 and first.temperature == pytest.approx(41.2)
    second = bh.update([0, 0], [0, 0])
    assert second.motors[2].tracked_position == 2000 + 10 - 6
    assert bh.update(header="a") is None and bh.update([1, 1], [1, 1], header="c") is None
    assert bh.update(header="A").block == bh.last_feedback_block
    with pytest.raises(ValueError):
        bh.update([1], [1, 1])
    with pytest.raises(RuntimeError):
        bh.get("P")
    bh.stop_loop()
    assert not bh.in_loop
    assert bh.get("P", "1") == {"P": [1000]}


def test_err_inside_realtime_raises_and_returns_to_supervisory(scripted):
    """SPEC.md §5: "\\n\\rERR n\\n\\r=> " instead of "*" → HandError; the client is in supervisory mode."""
    bh, hand, _ = scripted
    bh.start_loop("G")
    hand.error_next_block = 8192
    with pytest.raises(HandError) as info:
        bh.update([1, 1, 1], [5, 5, 5])
    assert info.value.code == 8192 and not bh.in_loop
    assert bh.get("P", "1") == {"P": [1000]}
    bh.start_loop("G")
    assert bh.update([1, 1, 1], [5, 5, 5]).motors[3].absolute_position == 3000


def test_half_read_feedback_block_times_out_and_resync_leaves_loop(scripted):
    """A feedback block cut short → HandTimeout within the block's budget; recovery sends ^C
    (RTAbort) and the hand is back at a prompt."""
    bh, hand, _ = scripted
    bh.start_loop("GS")
    hand.cut_next_reply = 4
    with pytest.raises(HandTimeout):
        bh.update([0] * 4, [0] * 4)
    assert bh.get("P", "4") == {"P": [4000]}
    assert hand.layout is None and not bh.in_loop


def test_interrupted_update_then_stop_loop_recovers(scripted):
    """Ctrl-C (KeyboardInterrupt) while waiting for a feedback block leaves the line's state unknown;
    stop_loop() then resynchronises (^C leaves LOOP, §6.1) and supervisory calls work."""
    bh, hand, port = scripted
    bh.start_loop("1")
    port.interrupt_next_read = True
    with pytest.raises(KeyboardInterrupt):
        bh.update([3], [3])
    bh.stop_loop()
    assert hand.layout is None and not bh.in_loop
    assert bh.get("P", "1") == {"P": [1000]}


def test_firmware_44_layout_from_the_hands_flags(quick_resync):
    """SPEC.md §7: on 4.4 the client queries LCT LFBP LFAIN; LCT replaces LCV/LCPG, LFT is one byte."""
    hand = ScriptedHand(firmware="4.4")
    for motor in (1, 2, 3, 4):
        hand.motor[motor].update(LCT=1 if motor == 1 else 0, LFBP=1, LFAIN=1)
    hand.globals["LFT"] = 1
    with BarrettHand(FakePort(hand), timeout=0.3) as bh:
        assert bh.firmware == "4.4"
        layout = bh.start_loop("12")
        assert layout.control_fields == ((1, "LCT"), (2, "LCV"), (2, "LCPG"))
        feedback = bh.update(velocities=[0, 5], gains=[0, 9], torques=[-300, 0])
        assert feedback.motors[1].breakaway_position == 77 and feedback.motors[2].analog_input == 9
        assert feedback.temperature == 41.0
        assert bh.last_control_block == b"C\xfe\xd4\x05\x09"


# ---------------------------------------------------------------------------------------------
# The simulated hand in this process (bh8sim://): every call
# ---------------------------------------------------------------------------------------------

MPE = 50  # §5.3.4 default maximum position error


@pytest.fixture
def sim(tmp_path):
    with BarrettHand(f"bh8sim://?seed=0&state={tmp_path / 'store'}") as bh:
        yield bh


def test_sim_a_closed_client_never_reopens_its_port(sim):
    """close() is for good also on a port the client opened itself (it used to reopen it on the
    next call after the first refusal, and move the hand)."""
    sim.close()
    for call in (lambda: sim.get("P"), sim.resync, lambda: sim.close_motors("G"), lambda: sim.get("P")):
        with pytest.raises(HandConnectionError, match="closed"):
            call()
    assert sim.port is None


def test_sim_administrative_and_parameter_calls(sim):
    """§5.2.2-§5.2.4 through the firmware: VERS, TEMP, FGET/FSET/PGET/PSET, save/load/default."""
    assert sim.version().startswith("4.3") and sim.firmware == "4.3"
    assert 0.0 < sim.temperature() < 125.0
    assert sim.get("MCV MOV", "GS") == {"MCV": [100, 100, 100, 60], "MOV": [100, 100, 100, 60]}  # §5.3.1 defaults
    sim.set("13", MCV=80, MOV=70)
    assert sim.get("MCV MOV", "GS") == {"MCV": [80, 100, 80, 60], "MOV": [70, 100, 70, 60]}
    sim.save("13")
    sim.set("1", {"MCV": 90})
    sim.load("1")
    assert sim.get("MCV", "1") == {"MCV": [80]}
    sim.default("GS")
    assert sim.get("MCV", "13") == {"MCV": [100, 100]}
    assert sim.get_global(["LFT", "BAUD"]) == {"LFT": 0, "BAUD": 96}
    sim.set_global(LFT=1)
    sim.save_global()
    sim.set_global({"LFT": 0})
    sim.load_global()
    assert sim.get_global("LFT") == {"LFT": 1}
    sim.default_global()
    assert sim.get_global("LFT") == {"LFT": 0}
    with pytest.raises(HandError) as info:
        sim.set("1", MCV=5000)
    assert info.value.code == 128
    with pytest.raises(HandError) as info:
        sim.set_global(TEMP=300)
    assert info.value.code == 256
    assert sim.command("BOGUS", check=False) == ["ERR 32"]
    assert any("HI" in line for line in sim.command("?"))
    assert sim.abort() == []  # ^C while idle only gets a prompt (SPEC.md §2)
    assert sim.get("P", "1")["P"][0] == 0


def test_sim_motion_calls(sim):
    """§5.2.1 movement commands end where the manual says: HI at 0, M/IC/IO/HOME within MPE, C near
    CT, O near OT, TC/TO against the stops; motion before HI is ERR 4 (SPEC.md §2)."""
    with pytest.raises(HandError) as info:
        sim.move(1000)
    assert info.value.code == 4
    sim.initialize()
    assert all(abs(p) <= MPE for p in sim.get("P")["P"])
    sim.close_motors("G")
    assert all(p > 10000 for p in sim.get("P", "G")["P"])
    sim.open_motors("G")
    assert all(abs(p) <= 200 for p in sim.get("P", "G")["P"])
    sim.move(5000, "1")
    assert abs(sim.get("P", "1")["P"][0] - 5000) <= MPE
    sim.step_close(1000, "1")
    assert abs(sim.get("P", "1")["P"][0] - 6000) <= MPE
    sim.step_open(500, "1")
    assert abs(sim.get("P", "1")["P"][0] - 5500) <= MPE
    sim.home("1")
    assert abs(sim.get("P", "1")["P"][0]) <= MPE
    sim.torque_close("2")
    assert sim.get("P", "2")["P"][0] > 10000
    sim.torque_open("2")
    assert sim.get("P", "2")["P"][0] < 500
    sim.move(1500, "S")
    assert abs(sim.get("P", "S")["P"][0] - 1500) <= MPE
    sim.terminate()
    banner = sim.reset()
    assert "BarrettHand Firmware" in banner
    with pytest.raises(HandError) as info:
        sim.close_motors("G")
    assert info.value.code == 4  # RESET = power cycle: motors uninitialised again


def test_sim_realtime_tracks_position_like_lfap(sim):
    """§6.2.3: FGET P before LOOP seeds the reported position; adding LFDP × LFDPC each block
    follows the absolute position LFAP exactly while no delta clips."""
    sim.initialize("G")
    sim.move(3000, "12")
    sim.configure_loop("12", LCV=1, LCVC=1, LCPG=1, LFV=1, LFS=1, LFAP=1, LFDP=1, LFDPC=1, lft=False)
    layout = sim.start_loop("12")
    assert layout.control_block_size(b"C") == 5 and layout.feedback_size == 11
    positions = []
    for _ in range(20):
        feedback = sim.update(velocities=[10, -10], gains=[60, 60])
        for motor in (1, 2):
            assert feedback.motors[motor].tracked_position == feedback.motors[motor].absolute_position
        positions.append((feedback.motors[1].absolute_position, feedback.motors[2].absolute_position))
    assert positions[-1][0] > positions[0][0] + 100  # motor 1 closes
    assert positions[-1][1] < positions[0][1] - 100  # motor 2 opens
    assert sim.update(header="a") is None
    assert sim.update([0, 0], [0, 0], header="c") is None
    assert sim.update(header="A").motors[1].strain is not None
    sim.stop_loop()
    assert not sim.in_loop and sim.get("P", "1")["P"][0] > 3100


def test_sim_manual_example_6_4_and_baud_change(sim):
    """§6.4 example through the firmware: 3-byte control, 8-byte feedback with LFT in tenths °C;
    after set_baud(38400) (§5.4.1) the hand still answers in both modes."""
    sim.initialize()
    sim.configure_loop("12", LCV=1, LCVC=1, LCPG=0, LFV=0, LFS=1, LFAP=0, LFDP=1, LFDPC=1, lft=True)
    sim.configure_loop("4", LCV=0, LCPG=0, LFV=0, LFS=0, LFAP=0, LFDP=1, LFDPC=1)
    layout = sim.start_loop("124")
    assert layout.control_block_size(b"C") == 3 and layout.feedback_size == 8
    feedback = sim.update(velocities=[5, 5, 0])
    assert len(feedback.block) == 8 and 0.0 < feedback.temperature < 125.0
    assert feedback.motors[4].strain is None and feedback.motors[4].delta_position is not None
    sim.stop_loop()
    sim.set_baud(38400)
    assert sim.get_global("BAUD") == {"BAUD": 384}
    sim.start_loop("124")
    assert len(sim.update(velocities=[0, 0, 0]).block) == 8
    sim.stop_loop()
    sim.set_baud(9600)
    assert sim.get_global("BAUD") == {"BAUD": 96}


def test_sim_firmware_44_detected_and_decoded(tmp_path):
    """SPEC.md §7: VERS 4.4x selects the 4.4 layout: LFBP and LFAIN after LFDP, LFT in whole °C."""
    with BarrettHand(f"bh8sim://?seed=0&firmware=4.4&state={tmp_path}") as bh:
        assert bh.firmware == "4.4"
        bh.initialize("1")
        bh.configure_loop("1", LCV=1, LCPG=1, LFV=0, LFS=0, LFAP=1, LFDP=0, LFBP=1, LFAIN=1, lft=True)
        layout = bh.start_loop("1")
        assert layout.feedback_fields == ((1, "LFAP"), (1, "LFBP"), (1, "LFAIN"), (None, "LFT"))
        feedback = bh.update([0], [0])
        assert feedback.motors[1].analog_input is not None and feedback.temperature == int(feedback.temperature)
        bh.stop_loop()


# ---------------------------------------------------------------------------------------------
# `bh8 serve` through a real pty
# ---------------------------------------------------------------------------------------------


@pytest.fixture
def served(tmp_path):
    from conftest import PtyLink

    link = PtyLink(tmp_path / "store")
    link.port.close()  # the client opens the device itself
    yield link
    link.close()


def test_pty_representative_calls(served):
    """The same client over `bh8 serve`'s pty: supervisory calls, a RealTime session, RESET."""
    with BarrettHand(served.device) as bh:
        assert bh.version().startswith("4.3")
        bh.initialize()
        bh.close_motors("G")
        assert all(p > 10000 for p in bh.get("P", "G")["P"])
        bh.set("G", MCV=80)
        assert bh.get("MCV", "G") == {"MCV": [80, 80, 80]}
        with pytest.raises(HandError) as info:
            bh.command("XYZ")
        assert info.value.code == 32
        bh.open_motors("G")
        bh.start_loop("GS")
        for _ in range(10):
            feedback = bh.update([5, 5, 5, 0], [50, 50, 50, 0])
            assert feedback.motors[1].tracked_position == feedback.motors[1].absolute_position
        bh.stop_loop()
        assert "BarrettHand Firmware" in bh.reset()


def test_pty_server_gone_raises_connection_error(served):
    """A port whose other end disappears (the server dies) → HandConnectionError, not a hang."""
    with BarrettHand(served.device, timeout=1.0) as bh:
        assert bh.get("P", "1")
        served.process.kill()
        served.process.wait()
        with pytest.raises((HandConnectionError, HandTimeout)):
            bh.get("P", "1")
