"""`bh8 serve` against hostile and clumsy input (issue 19): floods, bad stores, bad objects and
options. The server must answer with a clear error or keep serving, with bounded memory and CPU,
and must always save its never-reset counters on the way out (manual §5.3.2, §5.4.2).
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
import time

import pytest

from conftest import PtyLink, read_to_prompt
from bh8_gym.cli import main

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="pty tests need Linux /dev/pts")


@pytest.mark.parametrize("state", ["", "   "])
def test_an_empty_state_directory_is_refused_not_the_working_directory(state, tmp_path, monkeypatch, capsys):
    """`--state ""` was Path("") = ".": the store went into ./nvstore.json. Refused as
    bh8sim://?state= refuses an empty value (usage error, exit 2), before any store is made."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as stopped:
        main(["serve", "--state", state])
    assert stopped.value.code == 2
    assert "--state: needs a directory, got an empty value" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


# -- floods -----------------------------------------------------------------------------------


def _rss_bytes(pid: int) -> int:
    with open(f"/proc/{pid}/status") as handle:
        for line in handle:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    raise AssertionError("no VmRSS")


def _cpu_seconds(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as handle:
        fields = handle.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _flood(fd: int, block: bytes, seconds: float, align: bool = True) -> tuple[int, int]:
    """Write `block` 400 times per write, again and again for `seconds`, never reading, as fast as
    the pty takes it; then (`align`) complete the block a partial write left open, so the stream
    stays aligned. Returns (bytes written, writes refused)."""
    written = refused = 0
    rest = b""
    deadline = time.monotonic() + seconds
    while rest or time.monotonic() < deadline:
        if time.monotonic() >= deadline:
            if not align:
                break
            rest = rest[: len(rest) % len(block)]  # only the open block's remainder
            if not rest:
                break
        rest = rest or block * 400
        try:
            count = os.write(fd, rest)
        except BlockingIOError:
            refused += 1
            time.sleep(0.002)
            continue
        written += count
        rest = rest[count:]
    return written, refused


def _enter_loop_and_flood(link, seconds: float) -> tuple[int, int, float]:
    """HI, GSLOOP, then a flood of control blocks ("C" + LCV, LCPG per motor, SPEC.md §5; all 0:
    no motion, no torque) from a host that never reads. Returns (written, refused, RSS growth)."""
    assert link.lines("HI", timeout=60) == []
    link.write(b"GSLOOP\r")
    assert link.read_until(b"*", timeout=10) == b"GSLOOP*"
    fd = link.port.fileno()
    os.set_blocking(fd, False)
    rss_before = _rss_bytes(link.process.pid)
    written, refused = _flood(fd, b"C" + b"\0" * 8, seconds)
    os.set_blocking(fd, True)
    return written, refused, _rss_bytes(link.process.pid) - rss_before


def test_a_loop_flood_blocks_the_writer_and_memory_stays_bounded(tmp_path):
    """A host writing RealTime control blocks as fast as it can, never reading. The server takes
    input no faster than the firmware consumes it and its line delivers it (BAUD/10 bytes per
    second of the hand's time, SPEC.md §6; unpaced that is simulated time), holding at most a
    buffer ahead: the writer blocks and the server's memory stays put (it grew by ~37 MB/s, to
    GBs). When the writer stops, ^C and a command are answered within seconds and the server goes
    idle (it had queued millions of blocks and ran a core at 100 % long after)."""
    link = PtyLink(tmp_path / "store")
    pid = link.process.pid
    try:
        written, refused, grown = _enter_loop_and_flood(link, 2.0)
        assert grown < 20e6, f"server memory grew by {grown / 1e6:.0f} MB under the flood"
        assert refused > 0 and written < 1e6, (written, refused)  # it took ~100 MB in 2 s
        fd = link.port.fileno()
        os.write(fd, b"\x03" + b"1FGET P\r")  # ^C leaves LOOP after the blocks already taken
        os.set_blocking(fd, False)
        seen = bytearray()
        deadline = time.monotonic() + 60.0
        while not re.search(rb"\n\r=> 1FGET P\n\r-?\d+\n\r=> $", bytes(seen[-64:])):
            assert time.monotonic() < deadline, f"no answer within 60 s of the flood; last bytes {bytes(seen[-64:])!r}"
            try:
                seen += os.read(fd, 65536)
            except BlockingIOError:
                time.sleep(0.005)
        os.set_blocking(fd, True)
        time.sleep(0.3)
        before = _cpu_seconds(pid)
        time.sleep(1.0)
        assert _cpu_seconds(pid) - before < 0.1  # idle again
        assert link.lines("PGET BAUD") == ["96"]
    finally:
        link.close()


def test_a_client_reading_during_a_flood_gets_its_feedback_blocks(tmp_path):
    """While a writer floods control blocks, the feedback blocks (SPEC.md §5: "*" + data) flow to a
    client that reads: the server writes its output between slices of a run. It used to hold all
    output until the firmware went idle, which a flood never lets happen."""
    import threading

    link = PtyLink(tmp_path / "store")
    try:
        assert link.lines("HI", timeout=60) == []
        link.write(b"GSLOOP\r")
        assert link.read_until(b"*", timeout=10) == b"GSLOOP*"
        fd = link.port.fileno()
        writer = os.dup(fd)
        os.set_blocking(writer, False)
        flooding = threading.Thread(target=_flood, args=(writer, b"C" + b"\0" * 8, 3.0), daemon=True)
        flooding.start()
        received = bytearray()
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            received += link.port.read(4096)
        assert flooding.is_alive()  # all of that arrived while the writer was still flooding
        assert received.count(b"*") >= 50, f"{len(received)} bytes of feedback in 2 s"
        flooding.join(timeout=30)
        os.close(writer)
    finally:
        link.close()


def test_a_paced_server_takes_a_flood_at_the_line_rate(tmp_path):
    """--realtime: the hand's time is the wall clock, so once the pty and the server's buffer are
    full the server takes at most BAUD/10 bytes a second (9600 baud: 960 B/s, SPEC.md §6); the
    rest of the flood waits in the writer, as on a real line."""
    link = PtyLink(tmp_path / "store", ("--realtime",))
    try:
        written, refused, grown = _enter_loop_and_flood(link, 1.0)  # fills the pty and the buffer
        fd = link.port.fileno()
        os.set_blocking(fd, False)
        started = time.monotonic()
        later, _ = _flood(fd, b"C" + b"\0" * 8, 3.0, align=False)
        seconds = time.monotonic() - started
        assert refused > 0 and grown < 20e6
        # The pty frees room for a writer a page (4 KB) at a time, so that is the resolution here.
        assert later <= 960 * seconds + 4096, f"{later} bytes taken in {seconds:.1f} s at 9600 baud"
    finally:
        link.close()


# -- motions that do not end ------------------------------------------------------------------


def test_accel_0_then_gc_is_answered_and_the_server_idles(tmp_path):
    """`FSET ACCEL 0` (in range, manual §5.3.4) then GC: the HCTL's trapezoid never leaves its start
    (§9.2.1), so the motors stall and terminate after TSTOP (§5.5 case 1): GC answers at once. It
    never answered, and the server spun at 100 % CPU even after the client closed the port."""
    link = PtyLink(tmp_path / "store")
    try:
        assert link.lines("HI", timeout=60) == []
        assert link.lines("FSET ACCEL 0") == []
        assert link.lines("GC", timeout=10) == []
        assert link.lines("GM 5000", timeout=10) == ["ERR 16"]
        time.sleep(0.3)
        before = _cpu_seconds(link.process.pid)
        time.sleep(1.0)
        assert _cpu_seconds(link.process.pid) - before < 0.1
    finally:
        link.close()


def test_an_unpaced_server_paces_a_motion_that_never_ends(tmp_path):
    """A motion may run for minutes (TSTOP 65535: each motor drives against its open stop 65.5 s
    before it counts as stalled, §5.5 case 1). Without --realtime the server runs a command at full speed for
    `full_speed_limit` simulated seconds, then follows the wall clock, so the motion costs what a
    paced server costs instead of a whole core; ^C still ends it (§5.5 case 4)."""
    import threading

    import serial

    from bh8_gym.firmware import Firmware
    from bh8_gym.plant import HandPlant
    from bh8_gym.serial_server import PtyServer

    plant = HandPlant(seed=0)
    firmware = Firmware(plant=plant, store_dir=tmp_path / "store", seed=0)
    assert firmware.transact(b"FSET TSTOP 65535\r").endswith(b"=> ")  # HI takes minutes
    server = PtyServer(firmware)
    server.full_speed_limit = 1.0  # simulated seconds at full speed (default UNPACED_FULL_SPEED_S)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        with serial.Serial(server.device, 9600, timeout=0.05) as port:
            port.write(b"HI\r")
            deadline = time.monotonic() + 30.0
            while firmware.time < 1.5:
                assert time.monotonic() < deadline
                time.sleep(0.05)
            cpu, wall, simulated = time.process_time(), time.monotonic(), firmware.time
            time.sleep(2.0)
            cpu, wall, simulated = time.process_time() - cpu, time.monotonic() - wall, firmware.time - simulated
            assert simulated == pytest.approx(wall, abs=0.5)  # the wall clock's pace
            assert cpu < 0.5 * wall, f"{cpu:.2f} s of CPU in {wall:.2f} s"
            assert port.read(100) == b"HI"  # still initialising
            port.write(b"\x03")
            reply = b""
            while not reply.endswith(b"=> "):
                assert time.monotonic() < deadline, reply
                reply += port.read(100)
            assert reply == b"\n\rERR 16384\n\r=> "
    finally:
        server.stop()
        thread.join(timeout=10)
        server.close()
        firmware.shutdown()
        plant.close()


# -- a simulation that fails ------------------------------------------------------------------

_SERVER_WHOSE_PHYSICS_FAILS = """
import math, sys
from bh8_gym.commands.serve import serve
from bh8_gym.plant import HandPlant
from bh8_gym.simulator import build_firmware

firmware = build_firmware(sys.argv[1], "4.3", 0, ())
real_step = firmware.plant.step_with_drives
steps = []

def failing_step(velocities, fractions):
    steps.append(None)
    if len(steps) < 300:
        return real_step(velocities, fractions)
    if len(steps) == 300:  # the state of a simulation blown up to NaN, then the failure it causes
        HandPlant.temperature = property(lambda plant: math.nan)
        return [math.nan] * 4, [math.nan] * 4
    raise ValueError("cannot convert float NaN to integer")

firmware.plant.step_with_drives = failing_step
sys.exit(serve(firmware, store=sys.argv[1]))
"""


def test_a_failing_simulation_step_still_saves_the_counters(tmp_path):
    """A step that raises (PyBullet blown up to NaN) ends the server with a one-line error and
    exit 1, and the shutdown still saves the never-reset counters (§5.3.2 OD, §5.4.2 UPSECS and
    PTEMP: "maintained through power failures"), keeping the last finite values. The NaN used to
    fail the shutdown too, so nothing was saved, with a traceback."""
    import json

    import serial

    store = tmp_path / "store"
    process = subprocess.Popen([sys.executable, "-c", _SERVER_WHOSE_PHYSICS_FAILS, str(store)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        device = process.stdout.readline().strip()
        with serial.Serial(device, 9600, timeout=0.05) as port:
            port.write(b"HI\r")
            read_to_prompt(port, limit=400)
            port.write(b"GC\r")  # the steps fail half way through the close
            assert process.wait(timeout=60) == 1
        err = process.stderr.read()
        assert "bh8 serve: the simulation failed (ValueError: cannot convert float NaN to integer)" in err
        assert "Traceback" not in err
        counters = json.loads((store / "nvstore.json").read_text())["counters"]
        assert counters["uptime_seconds"] > 0.5  # HI and half a close of simulated time
        assert all(value == 0.0 for value in counters["odometer_counts"].values())  # the last finite ones
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()


def test_a_store_nested_too_deep_is_set_aside_and_the_server_serves(tmp_path):
    """`'[' * 200000 + ']' * 200000` as nvstore.json killed `bh8 serve` with a RecursionError
    traceback: it is set aside like any unreadable store (SPEC.md §3) and the hand starts from
    factory values."""
    store = tmp_path / "store"
    store.mkdir()
    (store / "nvstore.json").write_text("[" * 200_000 + "]" * 200_000)
    link = PtyLink(store)
    try:
        assert link.lines("PGET BAUD") == ["96"]
    finally:
        link.port.close()
        link.process.terminate()
        assert link.process.wait(timeout=20) == 0
    err = link.process.stderr.read()
    assert "nested too deep" in err and "starts from factory values" in err and "Traceback" not in err
    assert len(list(store.glob("nvstore.json.unreadable-*"))) == 1


# -- objects ----------------------------------------------------------------------------------

_CRASHING_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 999999\n"


@pytest.mark.parametrize("spec, message", [
    ("sphere:d1e308", "each extent must be 0.001 to 2 m"),
    ("sphere:0.03", "d<diameter> or r<radius>"),
    ("box:1e300x1e300x1e300", "each extent must be"),
    ("box:0.05;mass=1e300", "mass must be 0.001 to 10 kg"),
    ("box:0.05;friction=1e300", "friction must be 0 to 10"),
    ("box:0.05@1e300,0,0", "position must be x, y, z within"),
    ("box:nan", "positive number"),
    ("{tmp}/crash.obj:0.05", "face vertex 999999"),
    ("{tmp}/crash.obj:1e300", "face vertex 999999"),
])
def test_an_object_outside_the_physical_bounds_or_a_crashing_mesh_is_a_usage_error(tmp_path, spec, message):
    """`--object sphere:1e308` (or a 1e300 box) served, then HI died on NaN physics ("cannot convert
    float NaN to integer") and the shutdown died too; an OBJ whose face names a missing vertex
    killed the process (SIGSEGV). Both are refused up front: exit 2, one line naming the object."""
    (tmp_path / "crash.obj").write_text(_CRASHING_OBJ)
    spec = spec.format(tmp=tmp_path)
    process = subprocess.run(
        [sys.executable, "-m", "bh8_gym.cli", "serve", "--state", str(tmp_path / "store"), "--object", spec],
        capture_output=True, text=True, timeout=60,
    )
    assert process.returncode == 2 and process.stdout == ""
    assert f"bh8 serve: object {spec!r}: " in process.stderr and message in process.stderr
    assert "Traceback" not in process.stderr
