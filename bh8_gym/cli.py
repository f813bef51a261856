"""The `bh8` console command.

Each subcommand lives in its own module, which provides `configure_parser(parser)` and
`run(args) -> int`; modules are imported only when their subcommand runs, so `bh8 term` does not
pay for PyBullet and `bh8 serve` does not pay for torch.
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import json
import os
import signal
import sys

SUBCOMMANDS = {
    "serve": ("bh8_gym.commands.serve", "serve the simulated hand's firmware on a pseudo-terminal"),
    "term": ("bh8_gym.commands.term", "interactive GCL terminal for a real or simulated hand"),
    "render": ("bh8_gym.commands.render", "render the simulated hand to a PNG"),
    "calibrate": ("bh8_gym.commands.calibrate", "record a hand's calibration log and fit the simulated hand to it"),
    "train": ("bh8_gym.agents.training.train", "train a grasp policy (PPO or SAC)"),
    "sweep": ("bh8_gym.agents.sweep.command", "train seeds and hyperparameters as Ray Tune trials, locally or on a cluster"),
    "eval": ("bh8_gym.agents.evaluation.evaluate", "evaluate a policy or a scripted baseline"),
    "export": ("bh8_gym.agents.deployment.export", "export a trained policy to a numpy-only file"),
    "deploy": ("bh8_gym.agents.deployment.deploy", "run a policy closed-loop on a hand over a serial port"),
}


def json_object_argument(text: str) -> dict:
    """argparse `type=` for options such as --env-kwargs: a JSON object, else a usage error quoting it."""
    try:
        value = json.loads(text)
    except json.JSONDecodeError as error:
        raise argparse.ArgumentTypeError(f"not valid JSON ({error}): {text!r}") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"expected a JSON object of keyword arguments, got {text!r}")
    return value


def integer_argument(low: int, high: int | None = None, meaning: str = ""):
    """argparse `type=`: an integer in low..high (no upper bound if None), else a usage error quoting
    it (0 for a count is an error, not "use the default")."""
    bounds = f"at least {low}" if high is None else f"in {low}..{high}"
    bounds += f" ({meaning})" if meaning else ""

    def parse(text: str) -> int:
        try:
            value = int(text)  # more than 4300 digits: ValueError too
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer {bounds}, got {text[:100]!r}") from None
        if value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"must be {bounds}, got {value}")
        return value

    return parse


def float_argument(low: float, high: float, meaning: str = ""):
    """argparse `type=`: a finite number in low..high, else a usage error quoting it."""
    bounds = f"a number in {low:g}..{high:g}" + (f" ({meaning})" if meaning else "")

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {bounds}, got {text[:100]!r}") from None
        if not low <= value <= high:  # NaN fails too
            raise argparse.ArgumentTypeError(f"must be {bounds}, got {text[:100]}")
        return value

    return parse


@contextlib.contextmanager
def handling_signals(signums, handler):
    """Within the block, `handler` handles each signal in `signums`; the previous handlers come
    back afterwards (main thread only, as for `signal.signal`)."""
    previous = {signum: signal.signal(signum, handler) for signum in signums}
    try:
        yield
    finally:
        for signum, old in previous.items():
            signal.signal(signum, old)


def build_parser(load_subcommands: list[str] | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="bh8",
        description="BarrettHand BH8-262 simulator, firmware emulator, serial tools and grasp agents.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module_name, summary) in SUBCOMMANDS.items():
        child = sub.add_parser(name, help=summary, description=summary)
        if load_subcommands is None or name in load_subcommands:
            module = importlib.import_module(module_name)
            module.configure_parser(child)
            child.set_defaults(_module=module)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    chosen = [a for a in argv if a in SUBCOMMANDS][:1]
    # Only the chosen subcommand's module is imported; `bh8 --help` lists them all cheaply.
    parser = build_parser(load_subcommands=chosen)
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    try:
        return int(args._module.run(args) or 0)
    except KeyboardInterrupt:
        print(f"\nbh8 {args.command}: interrupted (Ctrl-C)", file=sys.stderr)
        return 130
    except (Exception, MemoryError, RecursionError) as error:  # noqa: BLE001 - the last line of defence
        # A failure no check of ours foresaw: one line and exit 1, never a raw traceback (set
        # BH8_TRACEBACK=1 to see where it came from).
        if os.environ.get("BH8_TRACEBACK"):
            raise
        text = " ".join(str(error).split())[:300] or type(error).__name__
        print(f"bh8 {args.command}: failed: {type(error).__name__}: {text} (BH8_TRACEBACK=1 shows where)",
              file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
