"""RealTime cycles per second through `bh8 serve`'s pty and through bh8sim:// (prints its figures).

The client lives in this process and speaks plain pyserial; `bh8 serve` runs as a subprocess.
Each cycle is one `C` control block out and one feedback block back (manual §6.4), encoded and
decoded with realtime_codec.LoopLayout. Figures: wall-clock cycles per second unpaced (as fast as
physics and transport allow) for each BAUD asked for, the simulated cycle time the firmware
charges (SPEC.md §6), and, with --realtime-cycles, the paced server's rate, which should match
1 / simulated cycle time.

    python benchmarks/bench_serial.py [--cycles 300] [--baud 96 384] [--realtime-cycles 60]
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import serial

import bh8_gym.urlhandler  # noqa: F401  (registers bh8sim://)
from bh8_gym.realtime_codec import LoopLayout, MotorFlags

PROMPT = b"=> "
FLAGS = MotorFlags(LCV=True, LCPG=True, LFV=True, LFS=True, LFAP=True, LFDP=True)
SETUP = ("HI", "GSFSET LCV 1 LCPG 1 LFV 1 LFS 1 LFAP 1 LFDP 1", "PSET LFT 0")


def _read_until(port, terminator: bytes, timeout_s: float = 120.0) -> bytes:
    deadline = time.monotonic() + timeout_s
    data = bytearray()
    while not data.endswith(terminator):
        if time.monotonic() > deadline:
            raise TimeoutError(f"no {terminator!r} within {timeout_s} s: {bytes(data[-80:])!r}")
        data += port.read(1)
    return bytes(data)


def _read_exact(port, count: int, timeout_s: float = 10.0) -> bytes:
    deadline = time.monotonic() + timeout_s
    data = bytearray()
    while len(data) < count:
        if time.monotonic() > deadline:
            raise TimeoutError(f"wanted {count} bytes within {timeout_s} s, got {bytes(data)!r}")
        data += port.read(count - len(data))
    return bytes(data)


def _command(port, line: str) -> bytes:
    port.write(line.encode("ascii") + b"\r")
    reply = _read_until(port, PROMPT)
    if b"ERR" in reply:
        raise RuntimeError(f"{line!r} failed: {reply!r}")
    return reply


def loop_cycles(port, baud: int, cycles: int) -> float:
    """Set up, enter LOOP at PSET BAUD `baud`, run `cycles` C blocks; wall seconds of the cycles."""
    for line in SETUP + (f"PSET BAUD {baud}",):
        _command(port, line)
    layout = LoopLayout(motors=(1, 2, 3, 4), flags=FLAGS)
    port.write(b"GSLOOP\r")
    _read_until(port, b"*")
    blocks = [layout.encode_control([20, 60, 20, 60, 20, 60, 0, 60]), layout.encode_control([-20, 60, -20, 60, -20, 60, 0, 60])]
    started = time.perf_counter()
    for i in range(cycles):
        port.write(blocks[(i // 25) % 2])
        layout.decode_feedback(_read_exact(port, layout.feedback_size))
    took = time.perf_counter() - started
    port.write(b"\x03")
    _read_until(port, PROMPT)
    return took


def cycle_time_s(baud: int) -> float:
    """The simulated seconds one C cycle costs (SPEC.md §6), measured on the in-process firmware."""
    with tempfile.TemporaryDirectory() as store, serial.serial_for_url(f"bh8sim://?state={store}", timeout=None) as port:
        for line in SETUP + (f"PSET BAUD {baud}",):
            _command(port, line)
        layout = LoopLayout(motors=(1, 2, 3, 4), flags=FLAGS)
        port.write(b"GSLOOP\r")
        _read_until(port, b"*")
        before = port.firmware.time
        port.write(layout.encode_control([0] * 8))
        _read_exact(port, layout.feedback_size)
        return port.firmware.time - before


class Served:
    """`bh8 serve` in a subprocess with a pyserial port on its device."""

    def __init__(self, store: Path, *extra: str):
        self.process = subprocess.Popen(
            [sys.executable, "-m", "bh8_gym.cli", "serve", "--state", str(store), *extra],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        )
        device = self.process.stdout.readline().strip()
        if not device:
            raise RuntimeError("bh8 serve printed no device")
        self.port = serial.Serial(device, 9600, timeout=0.05)

    def __enter__(self):
        return self.port

    def __exit__(self, *exc):
        self.port.close()
        self.process.terminate()
        self.process.wait(timeout=20)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cycles", type=int, default=300, help="cycles per measurement (default: %(default)s)")
    parser.add_argument("--baud", type=int, nargs="+", default=[96, 384], help="PSET BAUD values (default: 96 384)")
    parser.add_argument("--realtime-cycles", type=int, default=60,
                        help="cycles through `bh8 serve --realtime` (0: skip; default: %(default)s)")
    args = parser.parse_args(argv)

    print(f"{'path':<28}{'BAUD':>6}{'cycles/s':>10}{'sim ms/cycle':>14}{'sim/wall':>10}")
    for baud in args.baud:
        simulated = cycle_time_s(baud)
        with tempfile.TemporaryDirectory() as store:
            with Served(Path(store)) as port:
                wall = loop_cycles(port, baud, args.cycles)
            rate = args.cycles / wall
            print(f"{'pty (bh8 serve)':<28}{baud * 100:>6}{rate:>10.0f}{simulated * 1e3:>14.2f}{rate * simulated:>10.2f}")
        with tempfile.TemporaryDirectory() as store:
            with serial.serial_for_url(f"bh8sim://?state={store}", timeout=None) as port:
                wall = loop_cycles(port, baud, args.cycles)
            rate = args.cycles / wall
            print(f"{'in-process (bh8sim://)':<28}{baud * 100:>6}{rate:>10.0f}{simulated * 1e3:>14.2f}{rate * simulated:>10.2f}")
        if args.realtime_cycles > 0:
            with tempfile.TemporaryDirectory() as store:
                with Served(Path(store), "--realtime") as port:
                    wall = loop_cycles(port, baud, args.realtime_cycles)
                rate = args.realtime_cycles / wall
                print(f"{'pty --realtime':<28}{baud * 100:>6}{rate:>10.1f}{simulated * 1e3:>14.2f}{rate * simulated:>10.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
