"""`bh8 serve` through a real pty with a plain pyserial client, and the bh8sim:// URL handler.

What is checked comes from docs/architecture.md Contract 3 (the server shovels bytes between a
pty and the firmware; unpaced or paced to the wall clock), Contract 2 (identical bytes for
identical input in-process and on the pty; idle costs no simulated time, so an idle server uses
no CPU), SPEC.md §2 (framing, ^C → ERR 16384), §5 (RealTime blocks are counted bytes that may be
0x03, 0x0D, so the pty must be raw), §7 (firmware profiles) and App. A (a close takes ~1 s).
"""
from __future__ import annotations

import contextlib
import os
import select
import shutil
import signal
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import serial
from hypothesis import given, settings
from hypothesis import strategies as st

from conftest import PROMPT, PtyLink, read_to_prompt
from bh8_gym.realtime_codec import LoopLayout
from bh8_gym.commands.serve import default_state_dir
from bh8_gym.serial_server.pty import clients_of

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="pty tests need Linux /dev/pts")


def _serve(state_dir: Path, *extra: str) -> PtyLink:
    return PtyLink(state_dir, tuple(extra))


def _stop(link: PtyLink, signum: int = signal.SIGTERM) -> int:
    """Send `signum`, wait for the exit, return its code."""
    link.port.close()
    link.process.send_signal(signum)
    return link.process.wait(timeout=20)


def _cpu_seconds(pid: int) -> float:
    """utime + stime of a process from /proc (fields 14 and 15 of stat, in clock ticks)."""
    with open(f"/proc/{pid}/stat") as handle:
        fields = handle.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _check_link_serves_then_goes(link: PtyLink, link_path: Path) -> None:
    """--link is a symlink to the device, so it leads to a pty of the server (each open a fresh
    one, Contract 3), which answers as the device does; a clean exit removes the link."""
    try:
        link.port.close()  # the port is exclusive: one client at a time
        for _ in range(2):
            assert os.readlink(link_path) == link.device
            target = os.path.realpath(link_path)
            assert target.startswith("/dev/pts/") and stat.S_ISCHR(os.stat(target).st_mode)
            with serial.Serial(str(link_path), 9600, timeout=0.05) as port:
                port.write(b"\r")
                assert read_to_prompt(port) == b"\n\r=> "
        link.port = serial.Serial(link.device, 9600, timeout=0.05)
        link.write(b"\r")
        link.read_until(PROMPT, timeout=10)
    finally:
        assert _stop(link) == 0
    assert not os.path.lexists(link_path)


def _initialise(link, timeout: float = 60.0) -> None:
    assert link.lines("HI", timeout=timeout) == []


# -- the device -------------------------------------------------------------------------------


def test_device_first_line_owner_only_and_raw(tmp_path):
    """Contract 3: the first stdout line is the device; it is 0600 and a raw tty (SPEC.md §5:
    data bytes 0x03, 0x0D, 0x11, 0x13 must pass untouched), so a CR is answered per SPEC.md §2."""
    import termios

    link = _serve(tmp_path / "store")
    try:
        link.write(b"\r")
        assert link.read_until(PROMPT, timeout=10) == b"\n\r=> "
        link.port.close()  # the port is exclusive: the probe below is the next client
        info = os.stat(link.device)
        assert stat.S_ISCHR(info.st_mode)
        assert stat.S_IMODE(info.st_mode) == 0o600
        assert info.st_uid == os.getuid()
        with open(link.device, "rb", buffering=0) as probe:
            iflag, oflag, _, lflag = termios.tcgetattr(probe.fileno())[:4]
        assert not iflag & (termios.ICRNL | termios.IXON | termios.INLCR | termios.IGNCR)
        assert not oflag & termios.OPOST
        assert not lflag & (termios.ECHO | termios.ICANON | termios.ISIG)
    finally:
        link.close()


def test_link_symlink_created_and_removed(tmp_path):
    """--link PATH: a symlink to the device while serving, removed on exit. Anything already at PATH
    that a killed server did not leave there (a file, a dangling symlink of someone else's) is
    refused with a clear error and left as it was (issue 32: a dangling symlink used to be deleted)."""
    link_path = tmp_path / "ttyUSB0"
    _check_link_serves_then_goes(_serve(tmp_path / "store", "--link", str(link_path)), link_path)

    for make, check in ((lambda: link_path.write_text("not a device"), lambda: link_path.read_text() == "not a device"),
                        (lambda: os.symlink("/nonexistent/pts/99", link_path),
                         lambda: os.readlink(link_path) == "/nonexistent/pts/99")):
        make()
        process = subprocess.run(
            [sys.executable, "-m", "bh8_gym.cli", "serve", "--state", str(tmp_path / "store"), "--link", str(link_path)],
            capture_output=True, text=True, timeout=60,
        )
        assert process.returncode == 1
        assert process.stdout == ""
        assert "already exists" in process.stderr and str(link_path) in process.stderr
        assert check()
        link_path.unlink()


def test_link_left_by_a_killed_server_is_taken_over(tmp_path):
    """A server killed with SIGKILL leaves its --link behind. A restart with the same --link must
    take it over, not refuse it as 'already exists', whatever became of the killed server's pty
    numbers: here other programs hold them meanwhile (issue 31: the server recognised its
    predecessor's link by a pty number, which on a busy machine another program may have taken
    by then; the link now leads through the server's private directory, which names its pid). The
    killed server's own device symlink (and its private directory) is removed by the next server."""
    link_path = tmp_path / "ttyUSB0"
    first = _serve(tmp_path / "store1", "--link", str(link_path))
    first.port.close()
    first.process.kill()
    first.process.wait(timeout=20)
    assert os.path.islink(link_path) and os.path.islink(first.device)
    held = [os.openpty() for _ in range(8)]  # other programs take the freed pty numbers
    try:
        second = _serve(tmp_path / "store2", "--link", str(link_path))
    finally:
        for fds in held:
            for fd in fds:
                os.close(fd)
    assert not os.path.lexists(os.path.dirname(first.device))
    _check_link_serves_then_goes(second, link_path)


def test_link_touches_only_what_the_server_made(tmp_path):
    """Issue 32: the server touches only the symlink it made. --link is made once and never moved
    (the device's own symlink, in the server's private directory, is what moves from pty to pty),
    so a file that replaces it after start stays, even through the opens that used to re-point
    the link, and is not deleted at exit; a file or directory named .NAME.<pid> beside it (the
    re-point's temporary name, which was deleted or made the link fail with ENOENT) is left alone."""
    link_path = tmp_path / "ttyUSB0"
    link = _serve(tmp_path / "store", "--link", str(link_path))
    link.port.close()
    beside_file = tmp_path / f".ttyUSB0.{link.process.pid}"
    beside_file.write_text("mine")
    try:
        for _ in range(3):
            _a_fresh_session_answers(str(link_path))
        beside_file.unlink()
        beside_file.mkdir()  # a re-point through this name would fail
        for _ in range(3):
            _a_fresh_session_answers(str(link_path))
        beside_file.rmdir()
        beside_file.write_text("mine")
        link_path.unlink()
        link_path.write_text("a file of someone else's")
        for _ in range(3):
            _a_fresh_session_answers(link.device)
        assert link_path.read_text() == "a file of someone else's"
    finally:
        assert _stop(link) == 0
    assert link_path.read_text() == "a file of someone else's"
    assert beside_file.read_text() == "mine"


def test_close_and_reopen_keeps_state(tmp_path):
    """Contract 3: a client may close and reopen the device; the hand keeps its (unsaved) state."""
    link = _serve(tmp_path / "store")
    try:
        assert link.lines("1FSET DP 4321") == []
        link.port.close()
        link.port = serial.Serial(link.device, 9600, timeout=0.05)
        assert link.lines("1FGET DP") == ["4321"]
        link.port.close()
        link.port = serial.Serial(link.device, 9600, timeout=0.05)
        assert link.lines("1FGET DP") == ["4321"]
    finally:
        link.close()


def test_idle_server_uses_no_cpu(tmp_path):
    """Contract 2: idle time costs nothing, so an idle unpaced server sleeps in poll(): near zero
    CPU over a second of idleness (measured from /proc)."""
    link = _serve(tmp_path / "store")
    try:
        assert link.lines("1FGET DP") == ["8500"]
        time.sleep(0.2)
        before = _cpu_seconds(link.process.pid)
        time.sleep(1.0)
        used = _cpu_seconds(link.process.pid) - before
        assert used <= 0.02, f"idle server used {used:.3f} s of CPU in 1 s"
    finally:
        link.close()


def test_sigterm_and_sigint_save_and_exit_zero(tmp_path):
    """SPEC.md §3: FSAVE'd parameters survive restarts and UPSECS (never reset) keeps growing;
    SIGTERM and SIGINT both persist the counters (Firmware.shutdown) and exit 0."""
    store = tmp_path / "store"
    link = _serve(store)
    try:
        assert link.lines("1FSET DP 2345") == []
        assert link.lines("1FSAVE") == []
        uptime_before = int(link.lines("PGET UPSECS")[0])
        _initialise(link)  # simulated motion: powered-up time passes
        assert link.lines("GC") == [] and link.lines("GO") == []
        uptime_at_stop = int(link.lines("PGET UPSECS")[0])
        assert uptime_at_stop > uptime_before
    finally:
        assert _stop(link, signal.SIGTERM) == 0
    link = _serve(store)
    try:
        assert link.lines("1FGET DP") == ["2345"]
        assert int(link.lines("PGET UPSECS")[0]) >= uptime_at_stop
    finally:
        assert _stop(link, signal.SIGINT) == 0


def test_a_save_that_cannot_be_written_is_a_warning_and_the_server_keeps_serving(tmp_path):
    """The host's disk failing (here nvstore.json replaced by a directory) is not the hand's
    error: PSAVE still answers as on a real hand (whose EEPROM does not fail), the server says on
    stderr that the values live only in memory, and it keeps serving (it used to die with a
    traceback, the client timing out)."""
    store = tmp_path / "store"
    link = _serve(store)
    try:
        (store / "nvstore.json").unlink()
        (store / "nvstore.json").mkdir()
        assert link.lines("PSET OTEMP 111") == [] and link.lines("PSAVE") == []
        assert link.lines("PLOAD") == [] and link.lines("PGET OTEMP") == ["111"]
        assert link.lines("1FSAVE") == []
    finally:
        code = _stop(link)
    err = link.process.stderr.read()
    assert code == 0 and "Traceback" not in err, err
    assert "bh8 serve: cannot write the store" in err and "kept only until this simulated hand stops" in err


def test_a_second_server_on_the_same_state_is_refused(tmp_path):
    """Two hands on one store would undo each other's saves (each writes its whole copy)."""
    store = tmp_path / "store"
    link = _serve(store)
    try:
        second = subprocess.run([sys.executable, "-m", "bh8_gym.cli", "serve", "--state", str(store)],
                                capture_output=True, text=True, timeout=60)
        assert second.returncode == 1 and second.stdout == ""
        assert "in use by another simulated hand" in second.stderr and "Traceback" not in second.stderr
        assert link.lines("VERS") == ["4.34"]
    finally:
        assert _stop(link) == 0


def test_a_damaged_store_is_set_aside_with_a_message(tmp_path):
    store = tmp_path / "store"
    store.mkdir()
    (store / "nvstore.json").write_text('{"format": 1, "counters": {"serial_nu')
    link = _serve(store)
    try:
        assert link.lines("PGET OTEMP") == ["0"]
    finally:
        assert _stop(link) == 0
    err = link.process.stderr.read()
    assert "cannot be read" in err and "starts from factory values" in err
    aside = [p for p in store.iterdir() if p.name.startswith("nvstore.json.unreadable-")]
    assert len(aside) == 1 and aside[0].read_text().endswith("serial_nu")


_RUNAWAY_SERVER = """
import sys
from bh8_gym.commands.serve import serve

class Plant:
    def close(self):
        pass

class RunawayFirmware:
    \"\"\"Contract 2's surface, but every command runs forever (a motion that never terminates).\"\"\"
    profile, plant, idle, in_loop, time, baud, pending_input = "4.3", Plant(), True, False, 0.0, 9600, 0
    def write(self, data):
        pass
    def read(self):
        return b""
    def run_until_idle(self, max_seconds=None):
        while True:  # not even its time limit ends it
            pass
    def save_counters(self):
        pass
    def shutdown(self):
        print("shut down", file=sys.stderr, flush=True)

sys.exit(serve(RunawayFirmware()))
"""

_SERVER_SAVING_COUNTERS_EVERY_HALF_SECOND = """
import sys
from bh8_gym.simulator import build_firmware
from bh8_gym.serial_server import PtyServer

firmware = build_firmware(sys.argv[1], "4.3", 0, ())
server = PtyServer(firmware, counter_save_interval=0.5)
print(server.device, flush=True)
server.serve_forever()
"""


def test_the_counters_survive_a_kill_after_the_save_interval(tmp_path):
    """§5.3.2 OD, §5.4.2 UPSECS: "maintained through power failures". A server killed with
    SIGKILL (a power failure) keeps what the hand did up to its last periodic save; before, the
    counters were written only at a save command or a clean exit, and a kill lost them all."""
    store = tmp_path / "store"
    process = subprocess.Popen([sys.executable, "-c", _SERVER_SAVING_COUNTERS_EVERY_HALF_SECOND, str(store)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        device = process.stdout.readline().strip()
        with serial.Serial(device, 9600, timeout=0.05) as port:
            for line in (b"HI\r", b"GC\r", b"GO\r"):
                port.write(line)
                read_to_prompt(port, limit=400)
            time.sleep(1.5)  # > the save interval, idle
    finally:
        process.kill()
        process.communicate()
    link = _serve(store)
    try:
        assert all(int(value) > 10 for value in link.lines("GFGET OD")[0].split())  # thousands of counts
        assert int(link.lines("PGET UPSECS")[0]) >= 1
    finally:
        assert _stop(link) == 0


def test_sigterm_ends_a_server_stuck_in_a_runaway_command(tmp_path):
    """A command whose simulated motion never ends must not keep an unpaced server from exiting:
    SIGTERM abandons the run, shuts the firmware down and exits 0."""
    process = subprocess.Popen([sys.executable, "-c", _RUNAWAY_SERVER], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    try:
        device = process.stdout.readline().strip()
        with serial.Serial(device, 9600, timeout=0.05) as port:
            port.write(b"GC\r")
            time.sleep(0.3)
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=10) == 0
        assert "shut down" in process.stderr.read()
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()


def test_firmware_profile_option(tmp_path):
    """SPEC.md §7: --firmware 4.4 serves the 4.4 profile (VERS reports 4.4)."""
    link = _serve(tmp_path / "store", "--firmware", "4.4")
    try:
        assert "4.4" in " ".join(link.lines("VERS"))
    finally:
        link.close()


def test_gui_without_display_is_a_clear_error(tmp_path):
    """--gui on a machine without a display: exit 2 with a message, no device line."""
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    process = subprocess.run(
        [sys.executable, "-m", "bh8_gym.cli", "serve", "--state", str(tmp_path / "store"), "--gui"],
        capture_output=True, text=True, timeout=60, env=env,
    )
    assert process.returncode == 2
    assert process.stdout == ""
    assert "DISPLAY" in process.stderr


@pytest.mark.skipif(shutil.which("xvfb-run") is None, reason="needs xvfb-run (Debian package xvfb)")
def test_gui_under_a_virtual_display_keeps_the_device_first(tmp_path):
    """--gui with a display: PyBullet's GUI start-up chatter must not push the device path off
    the first stdout line, and the hand answers."""
    process = subprocess.Popen(
        ["xvfb-run", "-a", sys.executable, "-m", "bh8_gym.cli", "serve", "--state", str(tmp_path / "store"), "--gui"],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, start_new_session=True,
    )
    try:
        device = process.stdout.readline().strip()
        assert device.startswith("/dev/"), device
        with serial.Serial(device, 9600, timeout=5) as port:
            port.write(b"\r")
            assert port.read(5) == b"\n\r=> "
    finally:
        os.killpg(process.pid, signal.SIGTERM)
        process.wait(timeout=20)


def test_default_state_dir_follows_xdg(monkeypatch, tmp_path):
    """The default store is per user: $XDG_DATA_HOME/bh8-gym/state, else ~/.local/share/..."""
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path))
    assert default_state_dir() == tmp_path / "bh8-gym" / "state"
    monkeypatch.delenv("XDG_DATA_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert default_state_dir() == tmp_path / "home" / ".local" / "share" / "bh8-gym" / "state"


# -- paced serving ----------------------------------------------------------------------------


def test_realtime_paces_motion_and_ctrl_c_aborts(tmp_path):
    """--realtime paces simulated time to the wall clock: a GC takes the wall time it takes in
    simulated time (App. A: finger open→closed about 1 s), ^C arriving during a motion aborts it
    with ERR 16384 (§5.5 case 4, SPEC.md §2), and the idle paced server sleeps (Contract 2)."""
    import bh8_gym.urlhandler  # noqa: F401

    with serial.serial_for_url(f"bh8sim://?state={tmp_path / 'sim-store'}", timeout=None) as port:
        port.write(b"HI\r")
        read_to_prompt(port)
        started = port.firmware.time
        port.write(b"GC\r")
        read_to_prompt(port)
        simulated = port.firmware.time - started
    assert 0.6 <= simulated <= 1.4  # App. A, ±40 %

    link = _serve(tmp_path / "store", "--realtime")
    try:
        _initialise(link)
        started = time.monotonic()
        assert link.lines("GC", timeout=10) == []
        took = time.monotonic() - started
        assert simulated - 0.02 <= took <= simulated + 0.3, f"GC took {took:.3f} s wall, {simulated:.3f} s simulated"

        link.write(b"GO\r")
        assert link.read_until(b"GO", timeout=5) == b"GO"
        started = time.monotonic()
        time.sleep(0.3)
        link.write(b"\x03")
        reply = link.read_until(PROMPT, timeout=5)
        took = time.monotonic() - started
        assert reply == b"\n\rERR 16384\n\r=> ", reply
        assert took < 0.3 + 0.2, f"^C took effect only after {took:.2f} s"
        positions = [int(v) for v in link.lines("GFGET P")[0].split()]
        assert all(1000 < p < 16000 for p in positions), positions  # stopped part-way open

        before = _cpu_seconds(link.process.pid)
        time.sleep(0.5)
        assert _cpu_seconds(link.process.pid) - before <= 0.02
    finally:
        link.close()


def _hand_with_a_long_hi(store_dir):
    """A hand whose HI outlasts every wait here: with TSTOP 65535 each motor drives against its open
    stop for 65.5 s before it counts as stalled (§5.3.4 TSTOP, §5.5 case 1), then hits it again."""
    from bh8_gym.firmware import Firmware
    from bh8_gym.plant import HandPlant

    plant = HandPlant(seed=0)
    firmware = Firmware(plant=plant, store_dir=store_dir, seed=0)
    assert firmware.transact(b"FSET TSTOP 65535\r").endswith(b"=> ")
    return plant, firmware


def test_a_motion_that_never_ends_is_a_clear_error_in_process(tmp_path):
    """`Firmware.transact` gives up after its simulated-time limit with FirmwareBusyError instead
    of hanging; the motion runs on until ^C aborts it (§5.5 case 4)."""
    from bh8_gym.firmware import FirmwareBusyError

    plant, firmware = _hand_with_a_long_hi(tmp_path / "store")
    try:
        with pytest.raises(FirmwareBusyError, match=r"b'HI\\r' after 5 simulated seconds"):
            firmware.transact(b"HI\r", max_seconds=5.0)
        assert not firmware.idle and firmware.time == pytest.approx(5.0, abs=0.01)
        assert firmware.transact(b"\x03") == b"HI\n\rERR 16384\n\r=> "
        assert firmware.idle
    finally:
        firmware.shutdown()
        plant.close()


def test_unpaced_server_hears_ctrl_c_during_a_motion_that_never_ends(tmp_path):
    """Without --realtime the server runs a command as fast as it can but looks at the line every
    0.25 simulated s, so ^C aborts a motion that does not end (a long HI here) instead of the server
    running it to its end."""
    from bh8_gym.serial_server import PtyServer

    plant, firmware = _hand_with_a_long_hi(tmp_path / "store")
    server = PtyServer(firmware)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        with serial.Serial(server.device, 9600, timeout=0.05) as port:
            port.write(b"HI\r")
            time.sleep(0.5)
            assert port.read(100) == b"HI"  # the echo as it arrived (SPEC.md §2); still initialising
            port.write(b"\x03")
            assert read_to_prompt(port) == b"\n\rERR 16384\n\r=> "  # within 100 reads of 0.05 s
    finally:
        server.stop()
        thread.join(timeout=10)
        assert not thread.is_alive()
        server.close()
        firmware.shutdown()
        plant.close()


# -- objects ----------------------------------------------------------------------------------


def test_object_option_places_an_object_the_fingers_stall_on(tmp_path):
    """--object puts an object in the palm: a GC stalls on it (§5.5 termination case 1), so the
    fingers stop well short of CT."""
    link = _serve(tmp_path / "store", "--object", "box:0.08x0.05x0.08")
    try:
        _initialise(link)
        assert link.lines("GC", timeout=15) == []
        close_target = [int(v) for v in link.lines("GFGET CT")[0].split()]
        positions = [int(v) for v in link.lines("GFGET P")[0].split()]
        assert all(p < ct - 2000 for p, ct in zip(positions, close_target)), (positions, close_target)
    finally:
        link.close()


def test_bad_object_spec_is_a_clear_error(tmp_path):
    """A malformed --object SPEC or a missing file: exit 2 with a message naming it, no device."""
    for spec in ("banana:3", "box:0.05x-1x0.05", str(tmp_path / "missing.urdf")):
        process = subprocess.run(
            [sys.executable, "-m", "bh8_gym.cli", "serve", "--state", str(tmp_path / "store"), "--object", spec],
            capture_output=True, text=True, timeout=60,
        )
        assert process.returncode == 2, process.stderr
        assert process.stdout == ""
        assert spec in process.stderr or repr(spec) in process.stderr, process.stderr


# -- bh8sim:// --------------------------------------------------------------------------------


def test_bh8sim_url_gives_a_pyserial_port(tmp_path):
    """bh8sim:// through serial.serial_for_url: write/read/in_waiting/reset_input_buffer/close,
    the store persists across opens (SPEC.md §3), the profile option works (SPEC.md §7)."""
    import bh8_gym.urlhandler  # noqa: F401  (registers the handler package with pyserial)

    url = f"bh8sim://?seed=0&firmware=4.4&state={tmp_path / 'store'}"
    with serial.serial_for_url(url, baudrate=9600, timeout=1) as port:
        assert port.baudrate == 9600
        port.write(b"VERS\r")
        reply = read_to_prompt(port)
        assert reply.startswith(b"VERS\n\r") and b"4.4" in reply
        port.write(b"1FSET DP 3456\r1FSAVE\r")
        assert port.in_waiting > 0
        port.reset_input_buffer()
        assert port.in_waiting == 0
        port.write(b"\r")
        assert port.read(5) == b"\n\r=> "
    assert not port.is_open
    with serial.serial_for_url(url, timeout=1) as port:
        port.write(b"1FGET DP\r")
        assert read_to_prompt(port) == b"1FGET DP\n\r3456\n\r=> "


def test_bh8sim_read_timeout_is_simulated_and_never_hangs(tmp_path):
    """A read waits at most `timeout` simulated seconds: during HI (seconds of motion) a short
    timeout returns the echo only, later reads get the prompt; timeout=None returns once the
    firmware waits for input, even with fewer bytes than asked."""
    import bh8_gym.urlhandler  # noqa: F401

    with serial.serial_for_url(f"bh8sim://?state={tmp_path / 'store'}", timeout=0.05) as port:
        started = port.firmware.time
        port.write(b"HI\r")
        assert port.read(100) == b"HI"  # the motion outlasts the timeout
        assert port.firmware.time - started == pytest.approx(0.05, abs=0.003)
        assert read_to_prompt(port, limit=2000) == b"\n\r=> "
        assert port.firmware.time - started > 0.1
        port.timeout = None
        port.write(b"\r")
        assert port.read(1000) == b"\n\r=> "


def test_bh8sim_bad_urls_name_the_problem():
    """Bad options raise SerialException naming the bad value."""
    import bh8_gym.urlhandler  # noqa: F401

    for url, needle in [
        ("bh8sim://?seed=abc", "'abc'"),
        ("bh8sim://?firmware=5.0", "'5.0'"),
        ("bh8sim://?colour=red", "'colour'"),
        ("bh8sim://host", "'host'"),
        ("bh8sim://?object=banana", "banana"),
        ("bh8sim://?seed=1&seed=2", "'seed' given more than once"),  # which would win is a guess
        ("bh8sim://?state=/tmp/a&firmware=4.3&state=/tmp/b", "'state' given more than once"),
    ]:
        with pytest.raises(serial.SerialException, match=needle):
            serial.serial_for_url(url)


def test_pty_and_bh8sim_give_identical_bytes(tmp_path):
    """Contract 2: identical input gives identical bytes in-process and through the pty, including
    RealTime control blocks whose data bytes are 0x03, 0x0D, 0x11 and 0x13 (SPEC.md §5: bytes are
    counted, never parsed — a cooked tty would eat or translate them)."""
    import bh8_gym.urlhandler  # noqa: F401

    layout = LoopLayout(motors=(1, 2, 3, 4))
    awkward = [3, 0x0D, 0x11, 0x13, -3, 0x0A, 0, 0x03]  # LCV, LCPG per motor
    script = [b"HI\r", b"1FGET P\r", b"LOOP\r"]
    blocks = [layout.encode_control(awkward), layout.encode_control([], b"A")]
    link = _serve(tmp_path / "pty-store")
    try:
        pty_bytes = []
        for line in script:
            link.write(line)
            pty_bytes.append(link.read_until(b"*" if line.endswith(b"LOOP\r") else PROMPT, timeout=60))
        for block in blocks:
            link.write(block)
            pty_bytes.append(link.read_exact(layout.feedback_size, timeout=10))
        link.write(b"\x03")
        pty_bytes.append(link.read_until(PROMPT, timeout=10))
    finally:
        link.close()

    with serial.serial_for_url(f"bh8sim://?state={tmp_path / 'sim-store'}", timeout=None) as port:
        sim_bytes = []
        for line in script:
            port.write(line)
            sim_bytes.append(port.read(len(pty_bytes[len(sim_bytes)]) + 100))
        for block in blocks:
            port.write(block)
            sim_bytes.append(port.read(layout.feedback_size + 100))
        port.write(b"\x03")
        sim_bytes.append(port.read(100))
    assert sim_bytes == pty_bytes
    assert all(layout.decode_feedback(b) for b in pty_bytes[3:5])


def test_bh8sim_ctrl_c_between_reads_aborts_a_motion(tmp_path):
    """With a finite timeout the in-process hand runs only while the host reads, so a ^C written
    after a short read lands during the motion and aborts it (§5.5 case 4)."""
    import bh8_gym.urlhandler  # noqa: F401

    with serial.serial_for_url(f"bh8sim://?state={tmp_path / 'store'}", timeout=None) as port:
        port.write(b"HI\r")
        read_to_prompt(port)
        port.timeout = 0.2
        port.write(b"GC\r")
        assert port.read(100) == b"GC"
        port.write(b"\x03")
        assert read_to_prompt(port) == b"\n\rERR 16384\n\r=> "
        port.write(b"GFGET P\r")
        positions = [int(v) for v in read_to_prompt(port).split(b"\n\r")[1].split()]
        assert all(1000 < p < 15000 for p in positions), positions


_OPTION_VALUES = st.text(alphabet=st.characters(blacklist_categories=("Cs",)), max_size=12)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(["seed", "firmware", "state", "object", "gui", ""]), _OPTION_VALUES), max_size=4))
def test_bh8sim_url_options_parse_or_fail_clearly(pairs):
    """Any query string: parse_url returns the options given, or raises SerialException."""
    import urllib.parse

    from bh8_gym.urlhandler.protocol_bh8sim import parse_url

    url = "bh8sim://?" + urllib.parse.urlencode(pairs)
    try:
        options = parse_url(url)
    except serial.SerialException:
        return
    given_pairs = dict(pairs)
    assert all([n for n, _ in pairs].count(name) == 1 for name in ("seed", "firmware", "state") if name in given_pairs)
    assert options["seed"] == int(given_pairs.get("seed", 0))
    assert options["firmware"] == given_pairs.get("firmware", "4.3")
    assert options["state"] == given_pairs.get("state")
    assert options["objects"] == tuple(value for name, value in pairs if name == "object")


@pytest.fixture(scope="module")
def pty_and_sim(tmp_path_factory):
    import bh8_gym.urlhandler  # noqa: F401

    link = _serve(tmp_path_factory.mktemp("pty-store"))
    port = serial.serial_for_url(f"bh8sim://?state={tmp_path_factory.mktemp('sim-store')}", timeout=None)
    yield link, port
    port.close()
    link.close()


_TOKENS = st.sampled_from([b"\r", b"\x03", b"\n", b"\x08", b"\x11", b"\x13", b"FGET P", b"1FSET DP 77",
                           b"PGET TEMP", b"VERS", b"HI", b"SO", b"LOOP", b"C", b"A", b"ERR 16", b"x"])


@settings(max_examples=60, deadline=None)
@given(st.lists(_TOKENS | st.binary(max_size=8), min_size=1, max_size=12).map(b"".join).filter(bool))
def test_pty_carries_any_byte_stream_like_in_process(pty_and_sim, data):
    """Contract 2/3: arbitrary host bytes through the pty give exactly the bytes the in-process
    firmware gives, nothing more (the pty neither drops, adds nor translates a byte)."""
    link, port = pty_and_sim
    port.write(data)
    expected = port.read(1 << 16)  # timeout None: runs until the firmware waits for input
    link.write(data)
    assert link.read_exact(len(expected), timeout=10) == expected
    assert link.port.read(1) == b""  # nothing more within the port's 50 ms timeout


# -- what a closed port receives, and the breakaway parameters on the wire ---------------------


def _raw_open(device: str, baud: int | None = None) -> int:
    """Open the device as a C client does (open(2), cfmakeraw, the baud rate), without the input
    flush pyserial's open() adds, so bytes waiting in the pty would be read."""
    import termios
    import tty

    fd = os.open(device, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd, termios.TCSANOW)  # not TCSAFLUSH (the default), which would discard input itself
    if baud is not None:
        attrs = termios.tcgetattr(fd)
        attrs[4] = attrs[5] = getattr(termios, f"B{baud}")
        termios.tcsetattr(fd, termios.TCSANOW, attrs)
    return fd


def _raw_read(fd: int, seconds: float) -> bytes:
    """Everything that arrives on `fd` within `seconds`."""
    deadline = time.monotonic() + seconds
    data = bytearray()
    while (left := deadline - time.monotonic()) > 0:
        ready, _, _ = select.select([fd], [], [], left)
        if ready:
            data += os.read(fd, 4096)
    return bytes(data)


def _raw_read_until(fd: int, terminator: bytes, timeout: float = 10.0) -> bytes:
    deadline = time.monotonic() + timeout
    data = bytearray()
    while not data.endswith(terminator):
        left = deadline - time.monotonic()
        ready, _, _ = select.select([fd], [], [], max(left, 0.0))
        if not ready:
            raise TimeoutError(f"no {terminator!r} within {timeout}s; got {bytes(data)!r}")
        byte = os.read(fd, 1)
        if not byte:
            raise ConnectionError(f"hung up before {terminator!r}; got {bytes(data)!r}")
        data += byte
    return bytes(data)


def test_a_fresh_open_starts_empty_whatever_the_last_client_left_unread(tmp_path):
    """A real port drops what arrives while it is closed and a new open starts empty (issue 18):
    a client that sends ^C (SPEC.md §2: idle ^C gets a prompt) or a command and closes without
    reading the reply must not leave that reply for the next client, whether it closed before the
    hand answered or after. The next client then gets exactly its own replies (not even the end of
    a motion still running when it opens: see the tests of one client per port below)."""
    link = _serve(tmp_path / "store")
    link.port.close()
    try:
        for sent, wait in ((b"\x03", 0.0), (b"\x03", 0.3), (b"1FGET P\r", 0.3), (b"1FGET P\r", 0.0)):
            first = _raw_open(link.device)
            os.write(first, sent)
            time.sleep(wait)  # 0.3 s: the reply has surely arrived in the pty, unread
            os.close(first)
            time.sleep(0.3)  # the next run of a program
            second = _raw_open(link.device)
            try:
                assert _raw_read(second, 0.5) == b"", f"stale bytes after {sent!r}"
                os.write(second, b"\r")
                assert _raw_read_until(second, PROMPT, timeout=60) == b"\n\r=> "
                os.write(second, b"2FGET DP\r")
                assert _raw_read_until(second, PROMPT) == b"2FGET DP\n\r8500\n\r=> "
            finally:
                os.close(second)
    finally:
        link.close()


def test_reopening_the_port_discards_the_reply_left_unread_as_a_baud_change_does(tmp_path):
    """§5.4.1 BAUD: after PSET BAUD a client switches its own port to the new rate; Barrett's C++
    API does so by reading only the echo, waiting, closing and reopening the port at once to
    discard the buffers, then sending a CR and expecting a prompt (docs/clients.md). The reply to
    PSET BAUD must not survive the reopen, or every later reply is read one prompt late. The
    reopen follows the close within microseconds, faster than a server could flush a pty, so every
    open of the device (and of --link) is a fresh pty (Contract 3)."""
    linked = tmp_path / "ttyUSB0"
    link = _serve(tmp_path / "store", "--link", str(linked))
    link.port.close()
    try:
        for rate, device in ((38400, linked), (9600, link.device), (19200, linked), (38400, link.device), (9600, linked)):
            fd = _raw_open(str(device))
            line = f"PSET BAUD {rate // 100}".encode()
            os.write(fd, line + b"\r")
            assert _raw_read_until(fd, line) == line  # the echo only; the reply is left unread
            time.sleep(0.3)
            os.close(fd)
            fd = _raw_open(str(device), baud=rate)
            try:
                os.write(fd, b"\r")
                assert _raw_read_until(fd, PROMPT) == b"\n\r=> "
                os.write(fd, b"PGET BAUD\r")
                assert _raw_read_until(fd, PROMPT) == f"PGET BAUD\n\r{rate // 100}\n\r=> ".encode()
            finally:
                os.close(fd)
    finally:
        link.close()


def test_each_open_of_the_link_is_a_fresh_pty_on_the_same_hand(tmp_path):
    """Contract 3 / --link: the link leads to a new pty whenever a client opens it, so nothing the
    last client left unread reaches the next one however fast it reopens; the hand is the same
    (its unsaved state carries over), and a pty whose client closed is released."""
    device = tmp_path / "ttyUSB0"
    link = _serve(tmp_path / "store", "--link", str(device))
    link.port.close()
    try:
        for value in (4321, 1234, 2222, 3333):
            opened = os.path.realpath(device)
            fd = _raw_open(str(device))
            try:
                os.write(fd, f"1FSET DP {value}\r".encode())
                assert _raw_read_until(fd, PROMPT) == f"1FSET DP {value}\n\r=> ".encode()
                assert os.path.realpath(device) != opened  # moved on while this client holds `opened`
                os.write(fd, b"\x03")  # a ^C at disconnect whose prompt this client never reads
                time.sleep(0.2)  # the prompt is in the pty, unread (one still in flight could reach a reopen, as on a port)
            finally:
                os.close(fd)
            fd = _raw_open(str(device))
            try:
                os.write(fd, b"1FGET DP\r")
                assert _raw_read_until(fd, PROMPT) == f"1FGET DP\n\r{value}\n\r=> ".encode()
            finally:
                os.close(fd)
        time.sleep(0.3)
        held = [fd for fd in os.listdir(f"/proc/{link.process.pid}/fd")
                if os.readlink(f"/proc/{link.process.pid}/fd/{fd}") in ("/dev/ptmx", "/dev/pts/ptmx")]
        assert len(held) <= 2  # the fresh pty behind the device and at most one closing
        link.port = serial.Serial(link.device, 9600, timeout=0.05)
        assert link.lines("1FGET DP") == ["3333"]
    finally:
        link.close()


def test_a_second_opener_does_not_take_the_clients_output(tmp_path):
    """Output is the session's: a second opener (a terminal watching, a probe) that closes again is
    refused (the port is exclusive) and does not take the first client's replies away."""
    link = _serve(tmp_path / "store")
    try:
        assert link.lines("1FGET DP") == ["8500"]
        probe = _raw_open(link.device)
        os.close(probe)
        assert link.lines("1FGET DP") == ["8500"]
        link.write(b"1FGET DS\r")
        time.sleep(0.3)
        probe = _raw_open(link.device)
        os.close(probe)
        assert link.read_until(PROMPT, timeout=10) == b"1FGET DS\n\r1700\n\r=> "
    finally:
        link.close()


# A box between the fingers, heavy enough not to move, that the inner links meet near 37°: a GC
# at the default MCV breaks all three clutches away there (§9.3.1 TorqueSwitch).
INNER_LINK_OBSTACLE = "box:0.06x0.10x0.06;mass=10"


def _error_code(reply: bytes) -> int | None:
    """The n of an "ERR n" reply (SPEC.md §2: "\n\rERR n\n\r=> "), else None."""
    if reply.startswith(b"\n\rERR ") and reply.endswith(b"\n\r=> "):
        return int(reply[6:-5])
    return None


def _fingers(link: PtyLink, line: str) -> list[list[int]]:
    return [[int(v) for v in row.split()] for row in link.lines(line)]


def test_breakaway_parameters_across_a_breakaway_and_a_reengagement(tmp_path):
    """SPEC.md §3.1 (BD/BP: manual D3000 AF.00 §5.3.2; BS/BDAT: Barrett's API documentation),
    through the pty: before any breakaway BD and BP read 0; a GC whose inner links meet the box
    breaks away, BD reads 1 and BP the position where the inner link stopped, below P because the
    outer links closed on (§9.3.1); GO re-engages and clears BD and BP; with BS 1 the next GC stops
    each finger at its breakaway (P = BP), which also shows the clutches engaged again. BD and BP
    are read-only (ERR 256), BS is a flag (ERR 128 for 2), BDAT a stored advanced parameter; the
    spread has no breakaway."""
    link = _serve(tmp_path / "store", "--object", INNER_LINK_OBSTACLE)
    try:
        _initialise(link)
        assert _fingers(link, "GFGET BD BP BS BDAT") == [[0, 0, 0], [0, 0, 0], [0, 0, 0], [100, 100, 100]]
        assert link.lines("GC", timeout=30) == []
        detected, breakaway, position = _fingers(link, "GFGET BD BP P")
        assert detected == [1, 1, 1]
        for bp, p in zip(breakaway, position):
            assert 2000 < bp < p - 1000, (breakaway, position)  # outer links kept closing after it
        assert "BD 1 1 1" in link.lines("GFLISTV") and f"BP {' '.join(map(str, breakaway))}" in link.lines("GFLISTV")
        assert _fingers(link, "SFGET BD BP") == [[0], [0]]
        assert _error_code(link.command("1FSET BD 0")) == 256
        assert _error_code(link.command("1FSET BP 5")) == 256
        assert _error_code(link.command("GFSET BS 2")) == 128

        assert link.lines("GO", timeout=30) == []
        assert _fingers(link, "GFGET BD BP") == [[0, 0, 0], [0, 0, 0]]

        assert link.lines("GFSET BS 1 BDAT 250") == []
        assert link.lines("GC", timeout=30) == []
        detected, stopped_at, position = _fingers(link, "GFGET BD BP P")
        assert detected == [1, 1, 1]
        for bp, p, before in zip(stopped_at, position, breakaway):
            assert abs(p - bp) < 150 and abs(bp - before) < 500, (stopped_at, position, breakaway)
        assert _fingers(link, "GFGET BS BDAT") == [[1, 1, 1], [250, 250, 250]]
    finally:
        link.close()


def test_a_4_4_parameter_on_a_4_3_hand_is_err_64_and_the_server_says_why(tmp_path):
    """SPEC.md §7: LCT is a firmware 4.4 parameter; a 4.3 hand answers ERR 64 (unknown parameter),
    as a real 4.3 hand does, and `bh8 serve` tells its user on stderr to start it with
    --firmware 4.4 (once per name)."""
    link = _serve(tmp_path / "store")
    try:
        assert _error_code(link.command("1FSET LCT 1")) == 64
        assert _error_code(link.command("1FGET LCT LFBP")) == 64
        assert _error_code(link.command("1FGET LCT")) == 64
        assert _error_code(link.command("1FGET NOPE")) == 64
    finally:
        link.close()
    notes = [line for line in link.process.stderr.read().splitlines() if "a parameter of firmware" in line]
    assert len(notes) == 2 and "LCT" in notes[0] and "LFBP" in notes[1]
    assert all("--firmware 4.4" in note for note in notes)


def test_a_client_killed_mid_block_leaves_the_hand_waiting_and_repeated_ctrl_c_recovers(tmp_path):
    """SPEC.md §2 / §6 (blocks are counted bytes; 0x03 can be data): a client killed after the
    header and two of a block's six data bytes leaves the hand waiting, as a real hand does, so
    the next client's first ^C is taken as data. The documented recovery (docs/clients.md): ^C,
    read, repeat until the reply ends with the prompt; at most the block's size plus one. Our own
    client does it when it connects."""
    from bh8_gym.client import BarrettHand

    link = _serve(tmp_path / "store")
    try:
        _initialise(link)
        assert link.lines("GFSET LCV 1 LCPG 1 LFV 0 LFS 0 LFAP 0 LFDP 0") == []
        link.write(b"GLOOP\r")
        assert link.read_until(b"*", timeout=10) == b"GLOOP*"
        link.write(b"C\x05\x30")  # then killed: four data bytes never sent
        time.sleep(0.3)
        link.port.close()
        fd = _raw_open(link.device)
        try:
            replies = []
            for _ in range(7):
                os.write(fd, b"\x03")
                replies.append(_raw_read(fd, 0.5))
                if replies[-1].endswith(PROMPT):
                    break
            assert replies[0] == b"" and replies[-1] == b"\n\r=> ", replies  # the first ^C was data
            assert len(replies) <= 7
            os.write(fd, b"2FGET DP\r")
            assert _raw_read_until(fd, PROMPT) == b"2FGET DP\n\r8500\n\r=> "
            os.write(fd, b"GLOOP\r")
            assert _raw_read_until(fd, b"*") == b"GLOOP*"
            os.write(fd, b"C\x05")  # killed again
        finally:
            os.close(fd)
        with BarrettHand(link.device, timeout=2.0) as hand:
            assert hand.get("DP", "2") == {"DP": [8500]}
    finally:
        link.close()


# -- one client per port (issue 32 item 8) ----------------------------------------------------


@contextlib.contextmanager
def _server_stopped(link: PtyLink):
    """Hold the server (SIGSTOP) so that the clients' opens, writes and closes all happen before it
    can look at them: the widest form of the race between a client and the server."""
    link.process.send_signal(signal.SIGSTOP)
    try:
        yield
    finally:
        link.process.send_signal(signal.SIGCONT)


def _read_until_hangup(fd: int, seconds: float) -> tuple[bytes, bool]:
    """What arrives on `fd` within `seconds`, and whether the port was hung up (EOF or EIO)."""
    deadline = time.monotonic() + seconds
    data = bytearray()
    while (left := deadline - time.monotonic()) > 0:
        if not select.select([fd], [], [], left)[0]:
            continue
        try:
            chunk = os.read(fd, 4096)
        except OSError:
            return bytes(data), True
        if not chunk:
            return bytes(data), True
        data += chunk
    return bytes(data), False


def _a_fresh_session_answers(device: str, line: bytes = b"2FGET DP", reply: bytes = b"8500") -> None:
    """A new client gets exactly its own reply, nothing before and nothing after."""
    fd = _raw_open(device)
    try:
        os.write(fd, line + b"\r")
        assert _raw_read_until(fd, PROMPT, timeout=60) == line + b"\n\r" + reply + b"\n\r=> "
        assert _raw_read(fd, 0.3) == b""
    finally:
        os.close(fd)


def test_input_of_a_client_that_closed_before_the_server_looked_reaches_the_hand_not_the_next_client(tmp_path):
    """Contract 3, issue 32: a client that opens, writes and closes before the server has noticed
    it (here the server is stopped meanwhile) is a client of a closed port: its bytes reach the
    hand (they were sent), its replies go nowhere, and the next client gets only its own."""
    link = _serve(tmp_path / "store")
    link.port.close()
    try:
        with _server_stopped(link):
            for value in (1111, 2222, 4321):
                fd = _raw_open(link.device)
                os.write(fd, f"1FSET DP {value}\r1FGET DP\r".encode())
                os.close(fd)
        time.sleep(0.5)
        _a_fresh_session_answers(link.device, b"1FGET DP", b"4321")
    finally:
        link.close()


def test_a_client_that_opens_after_another_closed_unseen_never_gets_its_replies(tmp_path):
    """Issue 32: after a burst of open/write/close cycles that the server has not yet looked at
    (it is stopped), a new client opens the same pty. It must not receive the burst's replies:
    the server refuses a pty that was opened again after a close (hangs it up before answering,
    nothing is read), and the client's next open gets a session of its own."""
    link = _serve(tmp_path / "store")
    link.port.close()
    try:
        with _server_stopped(link):
            for _ in range(200):
                fd = _raw_open(link.device)
                os.write(fd, b"1FGET P\r")
                os.close(fd)
            late = _raw_open(link.device)
            os.write(late, b"2FGET DP\r")
        try:
            data, hung_up = _read_until_hangup(late, 5.0)
        finally:
            os.close(late)
        assert data == b"" and hung_up
        _a_fresh_session_answers(link.device)
        for _ in range(3):  # the same with the server running: its own reply, or refused unanswered
            for _ in range(300):
                fd = _raw_open(link.device)
                os.write(fd, b"1FGET P\r")
                os.close(fd)
            late = _raw_open(link.device)
            try:
                os.write(late, b"2FGET DP\r")
                data, hung_up = _read_until_hangup(late, 5.0)
            except OSError:
                data, hung_up = b"", True
            finally:
                os.close(late)
            assert data == (b"" if hung_up else b"2FGET DP\n\r8500\n\r=> "), (data, hung_up)
        _a_fresh_session_answers(link.device)
    finally:
        link.close()


def test_two_clients_opening_at_once_never_see_each_others_replies(tmp_path):
    """Issue 32 / docs/hardware.md: the port is exclusive. Two clients that open the device before
    the server has moved it on share one pty; the server hangs that pty up before answering either
    (neither can tell its bytes from the other's), so neither reads a byte meant for the other. A
    client that opens it afterwards gets a session of its own."""
    link = _serve(tmp_path / "store")
    link.port.close()
    try:
        with _server_stopped(link):
            first, second = _raw_open(link.device), _raw_open(link.device)
            os.write(first, b"1FGET DP\r")
            os.write(second, b"2FGET DS\r")
        try:
            assert _read_until_hangup(first, 5.0) == (b"", True)
            assert _read_until_hangup(second, 1.0) == (b"", True)
        finally:
            os.close(first)
            os.close(second)
        _a_fresh_session_answers(link.device)
    finally:
        link.close()


def test_a_client_that_forks_just_after_opening_keeps_its_session(tmp_path):
    """A program that starts a worker or a subprocess just after opening the port (fork: the child
    holds a copy of the descriptor until it closes it or execs) is one client, as on a real port.
    The server looks while both processes hold the pty and serves it; it once counted the copy as
    a second client and hung the pty up (the cause of a flaky test that ran a subprocess at once)."""
    link = _serve(tmp_path / "store")
    link.port.close()
    try:
        with _server_stopped(link):  # so that it looks only while the child holds the copy
            fd = _raw_open(link.device)
            release, hold = os.pipe()
            child = os.fork()
            if child == 0:
                try:
                    os.close(hold)
                    os.read(release, 1)
                finally:
                    os._exit(0)
            os.close(release)
        try:
            os.write(fd, b"1FGET DP\r")
            assert _raw_read_until(fd, PROMPT, timeout=5.0) == b"1FGET DP\n\r8500\n\r=> "
        finally:
            os.close(hold)
            os.waitpid(child, 0)
            os.close(fd)
    finally:
        link.close()


def test_a_descriptor_inherited_from_a_holder_is_not_a_second_client():
    """`clients_of`: a descriptor that a process shares by number with an ancestor holding the
    pty is that ancestor's; two descriptors in one process, or an unrelated process, stay two."""
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        me = os.getpid()
        assert clients_of([(me, 7), (child.pid, 7)]) == [me]
        assert clients_of([(child.pid, 7), (me, 7)]) == [me]
        assert clients_of([(me, 7), (child.pid, 8)]) == [me, child.pid]
        assert clients_of([(me, 7), (me, 9)]) == [me, me]
    finally:
        child.kill()
        child.wait()


def test_two_threads_opening_at_once_get_their_own_replies_or_a_hangup(tmp_path):
    """The same race without stopping the server: two threads open the device together, repeatedly.
    Each gets its own reply or a hangup (at most one of them is served at a time), never the
    other's bytes."""
    link = _serve(tmp_path / "store")
    link.port.close()
    results = {}

    def client(name: bytes, start: threading.Barrier) -> None:
        start.wait()
        results[name] = (b"", True)  # unless it gets further: refused at the open (the pty was locked)
        try:
            fd = _raw_open(link.device)
        except OSError:
            return
        try:
            os.write(fd, b"1FGET " + name + b"\r")
            results[name] = _read_until_hangup(fd, 1.0)
        except OSError:  # hung up before the write
            pass
        finally:
            os.close(fd)

    try:
        for _ in range(10):
            start = threading.Barrier(2)
            threads = [threading.Thread(target=client, args=(name, start)) for name in (b"DP", b"DS")]
            for thread in threads:
                thread.start()
            for thread in threads:
                thread.join(timeout=30)
            for name, value in ((b"DP", b"8500"), (b"DS", b"1700")):
                data, hung_up = results[name]
                assert data in (b"", b"1FGET " + name + b"\n\r" + value + b"\n\r=> "), (name, data, hung_up)
        _a_fresh_session_answers(link.device)
    finally:
        link.close()


def test_a_second_client_is_refused_while_the_port_is_in_use_and_its_bytes_go_nowhere(tmp_path):
    """A real serial port is one line: while a client has the device open, another open gets a pty
    that the server hangs up as soon as it sees it (docs/hardware.md), whatever it wrote never
    reaches the hand, and the first client's session goes on undisturbed."""
    link = _serve(tmp_path / "store")
    try:
        assert link.lines("1FGET DP") == ["8500"]
        intruder = _raw_open(link.device)
        try:
            os.write(intruder, b"1FSET DP 1234\r")
            assert _read_until_hangup(intruder, 5.0) == (b"", True)
        finally:
            os.close(intruder)
        with _server_stopped(link):  # one that the server notices only after it wrote
            intruder = _raw_open(link.device)
            os.write(intruder, b"1FSET DP 4321\r")
        try:
            assert _read_until_hangup(intruder, 5.0) == (b"", True)
        finally:
            os.close(intruder)
        assert link.lines("1FGET DP") == ["8500"]
    finally:
        link.close()


def test_a_pty_in_use_cannot_be_joined_by_its_own_name(tmp_path):
    """The device is a symlink to the pty in use; once the server has seen that pty's client, the
    pty's own /dev/pts node is mode 000, so another user process's open fails (EACCES). Root's open
    passes the permission check; the server then sees a second client in the pty and hangs it up,
    so neither reads the other's replies."""
    link = _serve(tmp_path / "store")
    try:
        assert link.lines("1FGET DP") == ["8500"]
        in_use = os.ttyname(link.port.fileno())
        assert stat.S_IMODE(os.stat(in_use).st_mode) == 0
        if os.geteuid() != 0:
            with pytest.raises(PermissionError):
                os.open(in_use, os.O_RDWR | os.O_NOCTTY)
            assert link.lines("1FGET DP") == ["8500"]
            return
        intruder = _raw_open(in_use)
        try:
            os.write(intruder, b"1FSET DP 1234\r")
            assert _read_until_hangup(intruder, 5.0) == (b"", True)
        finally:
            os.close(intruder)
        with pytest.raises(serial.SerialException):
            link.lines("1FGET DP")
        link.port.close()
        _a_fresh_session_answers(link.device, b"1FGET DP", b"8500")
    finally:
        link.close()


def _close_during_a_stall(link, tstop_ms: int) -> int:
    """`link`'s client sends SHI with TSTOP `tstop_ms` (the spread stalls that long at its open stop,
    §5.5 case 1) and closes the port while it runs; returns the next client's raw descriptor."""
    assert link.lines(f"SFSET TSTOP {tstop_ms}") == []
    link.write(b"SHI\r")
    assert link.read_until(b"SHI", timeout=10) == b"SHI"
    link.port.close()
    return _raw_open(link.device)


def test_the_reply_to_a_closed_clients_motion_does_not_reach_the_next_client(tmp_path):
    """A client sends a motion and closes while it runs; the next client's command waits for the
    hand to finish it (the hand would drop it meanwhile) and gets its own reply, not the end of
    the other client's motion. SHI with TSTOP 12000 stalls 12 simulated s at the open stop
    (§5.5 case 1), so the next client writes while it runs."""
    link = _serve(tmp_path / "store")
    try:
        fd = _close_during_a_stall(link, tstop_ms=12000)
        try:
            os.write(fd, b"2FGET DP\r")
            assert _raw_read_until(fd, PROMPT, timeout=120) == b"2FGET DP\n\r8500\n\r=> "
            os.write(fd, b"SFGET TSTOP\r")
            assert _raw_read_until(fd, PROMPT) == b"SFGET TSTOP\n\r12000\n\r=> "
        finally:
            os.close(fd)
    finally:
        link.close()


def test_a_ctrl_c_from_the_next_client_aborts_a_closed_clients_motion(tmp_path):
    """The next client's bytes wait while the hand finishes a closed client's command, but a ^C does
    not: it aborts the motion (§5.5 case 4, a motion that may never end) and its reply is the new
    client's."""
    link = _serve(tmp_path / "store")
    try:
        fd = _close_during_a_stall(link, tstop_ms=65535)
        try:
            os.write(fd, b"\x03")
            assert _raw_read_until(fd, PROMPT, timeout=30) == b"\n\rERR 16384\n\r=> "
            os.write(fd, b"2FGET DP\r")
            assert _raw_read_until(fd, PROMPT) == b"2FGET DP\n\r8500\n\r=> "
        finally:
            os.close(fd)
    finally:
        link.close()


_CLIENT_ACTIONS = st.lists(st.tuples(st.integers(0, 3), st.sampled_from(["open", "write", "close"])), max_size=30)


@settings(max_examples=300, deadline=None)
@given(_CLIENT_ACTIONS, st.lists(st.integers(1, 5), max_size=10))
def test_what_the_events_of_a_pty_say_about_its_clients(actions, drains):
    """`OpenHistory` reads a pty's inotify events (in the order of the clients' opens, writes and
    closes; inotify merges an event with an identical one before it still unread, and the server
    reads them in batches). Whenever one client holds the pty at the end: if no close came after
    the last open, that client opened after every other had closed; if then nobody wrote before
    that open, every byte in the pty is its own; and if it has written nothing, every byte is the
    others'. The server relies on these to serve it or hang it up."""
    from bh8_gym.serial_server.pty import OpenHistory, OpenWatch

    mask_of = {"open": OpenWatch.IN_OPEN, "write": OpenWatch.IN_MODIFY, "close": OpenWatch.IN_CLOSE & 0x08}
    open_clients, events, log = set(), [], []  # log: (client, action) that took effect
    for client, action in actions:
        if (action == "open") == (client in open_clients):
            continue  # a client opens only when closed, writes and closes only when open
        if action == "open":
            open_clients.add(client)
        elif action == "close":
            open_clients.discard(client)
        log.append((client, action))
        if not events or events[-1] != mask_of[action]:  # inotify merges with the last unread event
            events.append(mask_of[action])
    history, start = OpenHistory(), 0
    for size in drains + [len(events)]:  # read in batches, as the server does
        history.add(events[start:start + size])
        start += size
    if len(open_clients) != 1:
        return
    (holder,) = open_clients
    last_open = max(i for i, (client, action) in enumerate(log) if client == holder and action == "open")
    if history.closed_since_open:
        return
    assert all(action != "open" or client == holder or i < last_open for i, (client, action) in enumerate(log))
    assert all(action != "close" or i < last_open for i, (client, action) in enumerate(log))
    # "Its own" bytes are those written since that open: an earlier session of the same client
    # (open, write, close, open) wrote bytes that are not the new session's.
    if not history.written_before_open:
        assert not any(action == "write" and i < last_open for i, (client, action) in enumerate(log))
    if not history.written_since_open:
        assert not any(action == "write" and i > last_open for i, (client, action) in enumerate(log))


_HAMMER = """
import os, sys, time
device, until = sys.argv[1], time.monotonic() + float(sys.argv[2])
while time.monotonic() < until:
    try:
        os.close(os.open(device, os.O_RDWR | os.O_NOCTTY))
    except OSError:
        pass
"""


def test_clients_opening_and_closing_in_a_tight_loop_do_not_starve_another(tmp_path):
    """Issue 39, finding 11: a client that opens and closes the device in a tight loop kept a second
    client from ever getting a session (each of its opens was refused: the port in use, or a pty
    shared with the loop). Now a refused client waits in line: those that just had the port are
    hung up while it waits, and a pty whose other opener left without writing is the remaining
    client's. With three such loops, the client gets its session, and only its own reply, in seconds."""
    link = _serve(tmp_path / "store")
    link.port.close()
    hammers = [subprocess.Popen([sys.executable, "-c", _HAMMER, link.device, "60"]) for _ in range(3)]
    try:
        time.sleep(1.0)  # the loop has the port to itself for a while
        deadline, attempts = time.monotonic() + 20, 0
        while True:
            assert time.monotonic() < deadline, f"no session in {attempts} attempts"
            attempts += 1
            try:
                fd = _raw_open(link.device)
            except OSError:  # EACCES: a pty the server closed to further opens
                time.sleep(0.05)
                continue
            try:
                os.write(fd, b"1FGET DP\r")
                data, hung_up = _read_until_hangup(fd, 1.0)
            except OSError:
                data, hung_up = b"", True
            finally:
                os.close(fd)
            if not hung_up and data:
                assert data == b"1FGET DP\n\r8500\n\r=> "
                break
            time.sleep(0.05)
    finally:
        for hammer in hammers:
            hammer.kill()
            hammer.wait()
        link.close()
