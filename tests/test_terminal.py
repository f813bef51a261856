"""`bh8 term` sessions against `bh8 serve` on a pty: script mode through a pipe, interactive mode
through a pseudo-terminal (Ctrl-C aborts the hand's motion, Ctrl-D exits, history is saved)."""
from __future__ import annotations

import os
import select
import subprocess
import sys
import time

import pytest

from conftest import PtyLink


@pytest.fixture
def served(tmp_path):
    link = PtyLink(tmp_path / "store")
    link.port.close()  # `bh8 term` opens the device itself
    yield link
    link.close()


def term(device: str, script: str, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "bh8_gym.cli", "term", "--port", device, *extra],
        input=script, capture_output=True, text=True, timeout=120,
    )


def test_script_mode_prints_each_reply_and_succeeds(served):
    """Script mode: one GCL command per line (manual §5.1.1); transcript on stdout; exit 0 when
    nothing answered ERR. Blank and # lines are skipped."""
    result = term(served.device, "VERS\n\n# initialise first\nHI\n1FGET P\nGFSET MCV 80\nFGET MCV\n")
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines[0] == "=> VERS" and lines[1].startswith("4.3")
    assert lines[2] == "=> HI"
    assert lines[3] == "=> 1FGET P" and abs(int(lines[4])) <= 50  # HI ends at 0 (§5.2.1)
    assert lines[5:] == ["=> GFSET MCV 80", "=> FGET MCV", "80 80 80 60"]


def test_script_mode_err_sets_exit_status_and_is_explained(served):
    """An "ERR n" reply is printed as the hand sent it, explained with Table 3 on stderr, and makes
    the exit status 1; later lines still run."""
    result = term(served.device, "BOGUS\nM 1000\nPGET BAUD\n")
    assert result.returncode == 1
    assert result.stdout.splitlines() == ["=> BOGUS", "ERR 32", "=> M 1000", "ERR 4", "=> PGET BAUD", "96"]
    assert "Unknown command" in result.stderr and "Motor not initialized" in result.stderr


def test_help_passes_through_and_loop_is_refused(served):
    """`?` is the hand's own help (§5.2.4); LOOP (binary RealTime) is refused locally, not sent."""
    result = term(served.device, "?\nLOOP\nPGET LFT\n")
    assert result.returncode == 1
    out = result.stdout.splitlines()
    help_lines = out[1:out.index("=> LOOP")]
    assert any(line.split()[0] == "HI" for line in help_lines if line.split())
    assert out[out.index("=> LOOP") + 1:] == ["=> PGET LFT", "0"]
    assert "start_loop" in result.stderr


def test_pset_baud_switches_terminal_with_hand(served):
    """PSET BAUD n switches the hand and the terminal together (Barrett's API Baud() sequence)."""
    result = term(served.device, "PSET BAUD 384\nPGET BAUD\nPSET BAUD 96\nPGET BAUD\n")
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines() == ["=> PSET BAUD 384", "=> PGET BAUD", "384", "=> PSET BAUD 96", "=> PGET BAUD", "96"]


def test_an_err_code_that_is_no_status_sum_is_reported_not_a_crash():
    """A port answering "ERR" with 5000 digits (no Table 3 sum, §5.1.3) crashed `bh8 term` with
    Python's integer-string ValueError: the line is printed, called garbled, and counts as a
    failure (script mode exit 1); interactive mode prints it the same way."""
    import io

    from bh8_gym.terminal import _print_reply, explain_error, run_script

    garbled = "ERR " + "9" * 5000

    class GarblingHand:
        def command(self, line, check=True):
            return [garbled]

    out, err = io.StringIO(), io.StringIO()
    assert run_script(GarblingHand(), ["PGET TEMP\n", "VERS\n"], out, err) == 1
    assert out.getvalue().splitlines() == ["=> PGET TEMP", garbled, "=> VERS", garbled]
    assert err.getvalue().count("is not a status sum of Table 3 (0..32767)") == 2
    assert explain_error("ERR 32768") == "ERR 32768 is not a status sum of Table 3 (0..32767): a garbled reply"
    assert explain_error("ERR 16400") == "16 Couldn't reach position; 16384 Cntl-C abort command received"
    _print_reply([garbled])  # no exception


def test_missing_port_fails_cleanly(tmp_path):
    """A port that cannot be opened: a one-line error naming it, exit status 1, no traceback."""
    result = term(str(tmp_path / "nope"), "VERS\n")
    assert result.returncode == 1
    assert str(tmp_path / "nope") in result.stderr and "Traceback" not in result.stderr


def _read_until(fd: int, pattern: bytes, timeout: float, seen: bytearray, start: int = 0) -> None:
    """Read the terminal's output into `seen` until `pattern` appears at or after `start`."""
    deadline = time.monotonic() + timeout
    while seen.find(pattern, start) < 0:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise AssertionError(f"no {pattern!r} within {timeout} s; terminal showed {bytes(seen)!r}")
        ready, _, _ = select.select([fd], [], [], remaining)
        if ready:
            try:
                seen += os.read(fd, 4096)
            except OSError:
                raise AssertionError(f"terminal closed before {pattern!r}; showed {bytes(seen)!r}") from None


def test_interactive_ctrl_c_aborts_motion_and_ctrl_d_exits(tmp_path):
    """Interactive mode on a tty: Ctrl-C during a GC sends ^C to the hand, which aborts the motion
    with ERR 16384 (§5.5 case 4), and the terminal keeps running; Ctrl-D exits 0; history saved.
    The key shows as one "^C": the tty driver echoes it while the command runs (ECHOCTL), so the
    terminal does not print a second one."""
    import pty

    link = PtyLink(tmp_path / "store", ("--realtime",))  # paced: a GC takes about 1 s of wall time
    link.port.close()
    history = tmp_path / "history"
    try:
        pid, fd = pty.fork()
        if pid == 0:  # the child: `bh8 term` with this pty as its controlling terminal
            os.environ["TERM"] = "dumb"
            os.execv(sys.executable, [sys.executable, "-m", "bh8_gym.cli", "term", "--port", link.device,
                                      "--history", str(history)])
        seen = bytearray()
        try:
            _read_until(fd, b"=> ", 60, seen)
            os.write(fd, b"HI\r")
            _read_until(fd, b"HI\r\n=> ", 60, seen)
            os.write(fd, b"GFSET MCV 25\r")  # a 3 s close: room for a loaded machine's delays
            _read_until(fd, b"GFSET MCV 25\r\n=> ", 30, seen)
            os.write(fd, b"GC\r")
            _read_until(fd, b"GC\r\n", 30, seen)  # readline's echo; the line then goes to the hand
            time.sleep(0.8)
            os.write(fd, b"\x03")  # Ctrl-C: the tty turns it into SIGINT for `bh8 term`
            _read_until(fd, b"ERR 16384", 30, seen)
            _read_until(fd, b"=> ", 30, seen, seen.rfind(b"ERR 16384"))  # typing before it races readline
            after_gc = bytes(seen[seen.rfind(b"GC\r\n"):seen.rfind(b"=> ")])
            assert after_gc.count(b"^C") == 1, after_gc
            os.write(fd, b"1FGET P\r")
            _read_until(fd, b"1FGET P\r\n", 30, seen)
            mark = seen.rfind(b"1FGET P\r\n") + len(b"1FGET P\r\n")
            _read_until(fd, b"=> ", 30, seen, mark)
            position = int(bytes(seen[mark:]).split(b"\r\n")[0])
            assert 100 < position < 15000  # stopped part-way: the ^C reached the hand mid-close
            os.write(fd, b"\x04")  # Ctrl-D
            _, status = os.waitpid(pid, 0)
        finally:
            os.close(fd)
        assert os.waitstatus_to_exitcode(status) == 0
        assert "HI" in history.read_text() and "GC" in history.read_text()
    finally:
        link.close()
