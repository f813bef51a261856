"""`bh8 term`: an interactive GCL terminal, like the supervisory window of Barrett's BHControl.

    bh8 term --port /dev/ttyUSB0            # a real hand (9600 8N1 by default)
    bh8 term --port bh8sim://?seed=0        # the simulator in this process
    echo "HI" | bh8 term --port /dev/pts/5  # script mode: one command per line

Each line typed goes to the hand (manual §5.1.1); its output lines are printed, an "ERR n" reply
with the meaning of its Table 3 bits. `?` and `?CMD` are the hand's own help. Ctrl-C sends ^C to
the hand (aborts a running motion, §5.5 case 4) instead of ending the terminal; Ctrl-D exits.
History is kept in ~/.bh8_history (--history). `PSET BAUD n` switches the hand and this terminal
together (as Barrett's API does); LOOP is refused (RealTime blocks are binary: use
`bh8_gym.client.BarrettHand.start_loop`).

When stdin is not a terminal, each input line is one command (blank lines and lines starting with
"#" are skipped); the transcript goes to stdout and the exit status is 1 if any command answered
ERR or failed, else 0.
"""
from __future__ import annotations

import re
import signal
import sys
from pathlib import Path

from bh8_gym.client import BarrettHand, HandConnectionError
from bh8_gym.protocol import BAUD_RATES, PROMPT
from bh8_gym.status import BH8Error, ProtocolError, decode_status, parse_status

HISTORY_LENGTH = 1000
DEFAULT_HISTORY = Path("~/.bh8_history")
_ERR_LINE = re.compile(r"^\s*ERR\s*(\d+)\s*$")
_LOOP = re.compile(r"^\s*[1-4GSgs]*LOOP\s*$", re.IGNORECASE)
_PSET_BAUD = re.compile(r"^\s*PSET\s+BAUD\s+(\S+)\s*$", re.IGNORECASE)


class LocalRefusal(Exception):
    """A line the terminal does not send to the hand (with the reason)."""


def explain_error(line: str) -> str | None:
    """The Table 3 meaning of an "ERR n" line, e.g. "4 Motor not initialized; 32 Unknown command"."""
    found = _ERR_LINE.match(line)
    if not found:
        return None
    try:
        bits = decode_status(parse_status(found.group(1)))
    except ProtocolError as error:
        return str(error)
    return "; ".join(f"{bit} {text}" for bit, text in bits) or "no status bits"


def execute(hand: BarrettHand, line: str) -> list[str]:
    """Send one terminal line; return the hand's output lines ("ERR n" included)."""
    if _LOOP.match(line):
        raise LocalRefusal("LOOP enters binary RealTime mode, which a text terminal cannot speak; "
                           "use bh8_gym.client.BarrettHand.start_loop()")
    baud = _PSET_BAUD.match(line)
    if baud:
        try:
            rate = int(baud.group(1)) * 100
        except ValueError:
            rate = None
        if rate not in BAUD_RATES:
            raise LocalRefusal(f"PSET BAUD takes one of {[r // 100 for r in BAUD_RATES]}, got {baud.group(1)!r}")
        hand.set_baud(rate)
        return []
    if re.match(r"^\s*PSET\b.*\bBAUD\b", line, re.IGNORECASE):
        raise LocalRefusal("set BAUD on a line of its own (PSET BAUD n), so the terminal can switch with the hand")
    return hand.command(line, check=False)


def run_script(hand: BarrettHand, lines, out, err) -> int:
    """Script mode: every line a command; 1 if any answered ERR or failed."""
    failures = 0
    for number, raw in enumerate(lines, start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        print(f"{PROMPT.decode()}{line}", file=out)
        try:
            reply = execute(hand, line)
        except LocalRefusal as refusal:
            print(f"bh8 term: line {number}: {refusal}", file=err)
            failures += 1
            continue
        except HandConnectionError as error:
            print(f"bh8 term: line {number}: {error}", file=err)
            return 1
        except (BH8Error, ValueError) as error:
            print(f"bh8 term: line {number}: {error}", file=err)
            failures += 1
            continue
        for text in reply:
            print(text, file=out)
            meaning = explain_error(text)
            if meaning:
                print(f"bh8 term: line {number}: {line!r} -> {text.strip()} ({meaning})", file=err)
                failures += 1
        out.flush()
    return 1 if failures else 0


def _load_history(path: Path):
    try:
        import readline
    except ImportError:  # Windows without pyreadline: plain input() still works
        return None
    readline.set_history_length(HISTORY_LENGTH)
    try:
        readline.read_history_file(path)
    except (FileNotFoundError, PermissionError, OSError):
        pass
    return readline


def run_interactive(hand: BarrettHand, history: Path) -> int:
    """Interactive mode: prompt, history, Ctrl-C → ^C to the hand, Ctrl-D exits."""
    readline = _load_history(history)
    # Ctrl-C must reach us as KeyboardInterrupt even when we were started with SIGINT ignored
    # (which a parent such as a background job or nohup hands down across exec).
    previous_sigint = signal.signal(signal.SIGINT, signal.default_int_handler)
    print(f"bh8 term on {hand.port_name}: "
          f"GCL commands (? for help), Ctrl-C aborts a motion, Ctrl-D exits.")
    try:
        while True:
            try:
                line = input(PROMPT.decode())
            except EOFError:
                print()
                return 0
            except KeyboardInterrupt:
                print("^C")
                _abort(hand)
                continue
            try:
                reply = execute(hand, line.strip())
            except KeyboardInterrupt:
                # Outside input() the tty is in cooked mode and its driver has already echoed the
                # key as "^C": end that line rather than show a second one.
                print("" if _tty_echoes_ctrl_c() else "^C")
                _abort(hand)
                continue
            except LocalRefusal as refusal:
                print(f"bh8 term: {refusal}")
                continue
            except HandConnectionError as error:
                print(f"bh8 term: {error}")
                continue
            except (BH8Error, ValueError) as error:
                print(f"bh8 term: {error}")
                continue
            _print_reply(reply)
    finally:
        signal.signal(signal.SIGINT, previous_sigint)
        if readline is not None:
            try:
                readline.write_history_file(history)
            except OSError as error:
                print(f"bh8 term: could not save history to {history}: {error}", file=sys.stderr)


def _tty_echoes_ctrl_c() -> bool:
    """Whether the terminal driver itself shows a Ctrl-C typed while no input() is reading (stdin's
    ECHO and ECHOCTL set, the default of Linux and macOS terminals; readline turns echo off while
    it reads, so at the prompt only our own "^C" is shown)."""
    try:
        import termios
    except ImportError:  # Windows: the console echoes nothing for Ctrl-C
        return False
    try:
        lflag = termios.tcgetattr(sys.stdin.fileno())[3]
    except (termios.error, OSError, ValueError):
        return False
    echoctl = getattr(termios, "ECHOCTL", 0)
    return bool(echoctl) and bool(lflag & termios.ECHO) and bool(lflag & echoctl)


def _print_reply(reply: list[str]) -> None:
    for text in reply:
        meaning = explain_error(text)
        print(f"{text}    ({meaning})" if meaning else text)


def _abort(hand: BarrettHand) -> None:
    """^C to the hand; show what it answered (ERR 16384 after an aborted motion)."""
    try:
        _print_reply(hand.abort())
    except BH8Error as error:
        print(f"bh8 term: {error}")
