"""`bh8 term`: an interactive GCL terminal for a real or simulated hand (bh8_gym.terminal)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bh8_gym.client import DEFAULT_MOTION_TIMEOUT_S, DEFAULT_TIMEOUT_S, BarrettHand
from bh8_gym.protocol import BAUD_RATES
from bh8_gym.status import BH8Error
from bh8_gym.terminal import DEFAULT_HISTORY, run_interactive, run_script


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--port", required=True,
                        help="serial port or pyserial URL: /dev/ttyUSB0, COM3, socket://host:port, bh8sim://?seed=0, "
                             "or the device `bh8 serve` printed")
    parser.add_argument("--baud", type=int, default=9600, choices=BAUD_RATES,
                        help="host baud rate; must match the hand's BAUD (default: %(default)s, the factory setting)")
    parser.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT_S,
                        help=f"seconds to wait for a non-motion reply (default {DEFAULT_TIMEOUT_S})")
    parser.add_argument("--motion-timeout", type=float, default=DEFAULT_MOTION_TIMEOUT_S,
                        help=f"seconds to wait for a motion to end (default {DEFAULT_MOTION_TIMEOUT_S})")
    parser.add_argument("--history", type=Path, default=None,
                        help=f"readline history file (default {DEFAULT_HISTORY})")


def run(args: argparse.Namespace) -> int:
    try:
        hand = BarrettHand(args.port, baudrate=args.baud, timeout=args.timeout, motion_timeout=args.motion_timeout)
    except (BH8Error, ValueError) as error:
        print(f"bh8 term: {error}", file=sys.stderr)
        return 1
    with hand:
        if sys.stdin.isatty():
            history = (args.history or DEFAULT_HISTORY).expanduser()
            return run_interactive(hand, history)
        return run_script(hand, sys.stdin, sys.stdout, sys.stderr)
