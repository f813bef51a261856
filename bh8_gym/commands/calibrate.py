"""`bh8 calibrate`: fit the simulated hand to a log of a real one (bh8_gym/calibration/).

    bh8 calibrate record --port /dev/ttyUSB0 --mounting palm-up --object "box:0.05;mass=0.1" -o hand-log.jsonl
    bh8 calibrate fit hand-log.jsonl -o hand.toml
    bh8 calibrate draw --seed 7 -o hidden.toml      # a practice hand for `bh8 serve --hand-parameters`

docs/hardware.md has the lab's procedure. `record` simulates nothing (it talks to the hand through
bh8_gym.client); `fit` needs the calibrate extra (SciPy, matplotlib): pip install "bh8-gym[calibrate]".
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bh8_gym.cli import float_argument, integer_argument

RECORD_EXIT_HELP = """\
exit status:
  0    the whole excitation ran; the hand was left as it was found
  1    the port or the hand failed (the log's end record says where)
  2    usage error (a bad option, an unwritable log)
  3    stopped early, safely (Ctrl-C, SIGTERM, a safety limit, a full disk): the log is marked
       incomplete and `bh8 calibrate fit` refuses it unless given --partial
"""
FIT_EXIT_HELP = """\
exit status:
  0    fitted; hand.toml written and read back
  2    usage error, or a log it cannot use (not a calibration log, edited, cut short, foreign)
  3    the fit does not replay the log well enough to trust it (the report says what differs):
       no hand.toml is written
"""


def configure_parser(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    record = sub.add_parser("record", help="run the calibration excitation on a hand and log it",
                            description="Run the fixed calibration excitation (about two minutes) on a hand over a "
                                        "serial port and log every command, reply and RealTime block.",
                            epilog=RECORD_EXIT_HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    record.add_argument("--port", required=True,
                        help="serial port or pyserial URL: /dev/ttyUSB0, COM3, socket://host:port, bh8sim://?seed=0, "
                             "or the device `bh8 serve` printed")
    record.add_argument("-o", "--output", type=Path, required=True, help="the log to write (JSONL)")
    record.add_argument("--mounting", required=True, choices=("palm-up", "palm-down"),
                        help="how the hand is mounted: palm-up (standing on its base; `bh8 serve --object`) or "
                             "palm-down (hanging from an arm; `bh8 serve` without --object)")
    record.add_argument("--object", default=None, metavar="SPEC",
                        help='the calibration object resting on the palm (palm-up only), e.g. "box:0.05;mass=0.1" '
                             "(docs/hardware.md); adds squeezes of it (default: none)")
    record.add_argument("--baud", type=int, default=9600, metavar="RATE",
                        help="the hand's current rate (default 9600, after power-up); the excitation runs at 38400 "
                             "and switches back")
    record.add_argument("--scale", type=float_argument(0.05, 10.0), default=1.0,
                        help="stretch every part of the excitation (default 1.0: about two minutes at 38400 baud)")
    record.add_argument("--max-strain", type=integer_argument(0, 255), default=None,
                        help="stop when a finger's gauge reads more (default: the safety envelope's, 230)")
    record.add_argument("--force", action="store_true", help="overwrite an existing log")

    fit = sub.add_parser("fit", help="fit the simulated hand's parameters to a calibration log",
                         description="Replay a calibration log in the simulator and fit the PlantParameters the log "
                                     "can tell (docs/modelling.md: which are our estimates); write them to a hand file.",
                         epilog=FIT_EXIT_HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    fit.add_argument("log", type=Path, help="the log `bh8 calibrate record` wrote")
    fit.add_argument("-o", "--output", type=Path, required=True, help="the hand file to write (TOML)")
    fit.add_argument("--plot", type=Path, default=None,
                     help="PNG of logged against simulated traces (default: the output's name with .png)")
    fit.add_argument("--iterations", type=integer_argument(1, 200), default=30,
                     help="least-squares evaluations at most (default %(default)s)")
    fit.add_argument("--jobs", type=integer_argument(1, 256), default=None,
                     help="replays at once on this machine (default: its CPUs)")
    fit.add_argument("--address", default=None,
                     help="run the replays as Ray tasks on the cluster at HOST:PORT (or auto), as bh8 sweep does "
                          "(docs/cluster.md); needs the cluster extra")
    fit.add_argument("--partial", action="store_true",
                     help="fit a log whose excitation stopped early (what it holds; the report says what is missing)")

    draw = sub.add_parser("draw", help="write a practice hand: parameters drawn away from the defaults",
                          description="Write a hand file whose parameters are drawn within ±30 % of the defaults, "
                                      "for `bh8 serve --hand-parameters` to stand in for an unknown real hand.")
    draw.add_argument("-o", "--output", type=Path, required=True, help="the hand file to write")
    draw.add_argument("--seed", type=integer_argument(0), default=0, help="seed of the draw (default 0)")
    draw.add_argument("--everything", action="store_true",
                      help="draw also the parameters the fit holds or cannot tell (motor torque, link masses, ...)")


def run(args: argparse.Namespace) -> int:
    return {"record": _record, "fit": _fit, "draw": _draw}[args.action](args)


def _record(args: argparse.Namespace) -> int:
    from bh8_gym.calibration.recorder import Recorder
    from bh8_gym.calibration.scene import check_calibration_object
    from bh8_gym.client import BarrettHand
    from bh8_gym.protocol import BAUD_RATES
    from bh8_gym.safety import SafetyEnvelope
    from bh8_gym.status import BH8Error

    name = "bh8 calibrate record"
    if args.baud not in BAUD_RATES:
        print(f"{name}: --baud must be one of {BAUD_RATES}, got {args.baud}", file=sys.stderr)
        return 2
    if args.object is not None:
        if args.mounting != "palm-up":
            print(f"{name}: a calibration object rests on the palm: use --mounting palm-up", file=sys.stderr)
            return 2
        try:
            check_calibration_object(args.object)
        except ValueError as error:
            print(f"{name}: --object: {error}", file=sys.stderr)
            return 2
    if args.output.exists() and not args.force:
        print(f"{name}: {args.output} exists (--force overwrites it)", file=sys.stderr)
        return 2
    envelope = SafetyEnvelope() if args.max_strain is None else SafetyEnvelope(max_strain=args.max_strain)
    try:
        hand = BarrettHand(args.port, baudrate=args.baud)
    except (BH8Error, ValueError) as error:
        print(f"{name}: {error}", file=sys.stderr)
        return 1
    with hand:
        recorder = Recorder(hand, args.output, args.mounting, args.object, args.scale, envelope,
                            progress=_part_progress(name))
        try:
            complete, reason = recorder.run()
        except OSError as error:
            print(f"{name}: cannot write the log: {error}", file=sys.stderr)
            return 2
    print(f"{name}: {recorder.blocks:,} RealTime blocks; {'complete' if complete else 'stopped: ' + reason}; "
          f"log in {args.output}", file=sys.stdout if complete else sys.stderr)
    if recorder.safe_exit_error is not None or reason.startswith("hand/port error"):
        return 1
    return 0 if complete else 3


def _part_progress(name: str):
    def show(part: str, index: int, parts: int) -> None:
        if sys.stderr.isatty():
            print(f"\r{name}: part {index + 1}/{parts} ({part})\033[K", end="", file=sys.stderr, flush=True)
            if index + 1 == parts:
                print(file=sys.stderr)
    return show


def _fit(args: argparse.Namespace) -> int:
    name = "bh8 calibrate fit"
    try:
        from bh8_gym.calibration.fit import REPLAY_MISMATCH_PERCENT, FitError, fit
        from bh8_gym.calibration.report import fit_provenance, plot_traces, text_report
    except ImportError as error:
        print(f"{name}: needs the calibrate extra ({error.name} is missing): pip install \"bh8-gym[calibrate]\"",
              file=sys.stderr)
        return 2
    from bh8_gym.hand_file import HandParameters
    from bh8_gym.calibration.log_format import CalibrationLogError, MAX_LOG_BYTES, parse_log
    from bh8_gym.safe_files import read_bounded
    from bh8_gym.calibration.replay import ReplayMismatch, observed

    plot = args.plot or args.output.with_suffix(".png")
    try:
        data = read_bounded(args.log, MAX_LOG_BYTES, "calibration log", CalibrationLogError)
        log = parse_log(data, str(args.log))
    except CalibrationLogError as error:
        print(f"{name}: {error}", file=sys.stderr)
        return 2
    if not log.complete and not args.partial:
        print(f"{name}: {args.log}: the excitation did not run to its end ({log.reason}); record it again, or fit "
              "what it holds with --partial", file=sys.stderr)
        return 2
    try:
        rollouts = _rollouts(args, data, str(args.log))
    except ValueError as error:
        print(f"{name}: {error}", file=sys.stderr)
        return 2
    try:
        with _progress_bar() as bar:
            result = fit(log, rollouts, iterations=args.iterations, progress=bar)
    except (FitError, ReplayMismatch) as error:
        print(f"{name}: {error}", file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        print(f"{name}: interrupted; nothing written", file=sys.stderr)
        return 130
    except Exception as error:  # a log the simulator cannot replay (edited in ways the reader cannot see)
        print(f"{name}: the simulator could not replay {args.log} ({type(error).__name__}: {error})", file=sys.stderr)
        return 3
    finally:
        rollouts.close()
    print(text_report(log, result, rollouts.where))
    try:
        plot_traces(plot, log, observed(log), result)
        print(f"plot: {plot}")
    except OSError as error:
        print(f"{name}: cannot write the plot {plot}: {error}", file=sys.stderr)
    if not result.position_rms_after <= REPLAY_MISMATCH_PERCENT:
        print(f"{name}: the fitted simulator does not replay this log: position RMS {result.position_rms_after:.2f} % "
              f"of range (trusted below {REPLAY_MISMATCH_PERCENT} %). Check the mounting ({log.header.mounting}) and "
              f"the calibration object ({log.header.calibration_object}) the log names; nothing written",
              file=sys.stderr)
        return 3
    hand = HandParameters(result.hand_values(), result.uncertainties(), fit_provenance(log, result))
    comment = f"bh8 calibrate fit {args.log}: the hand's parameters (docs/hardware.md)"
    if not _write_hand(name, args.output, hand, comment):
        return 2
    print(f"written: {args.output} (read back and checked)")
    return 0


def _write_hand(name: str, path, hand, comment: str) -> bool:
    """Write a hand file (hand_file.write_hand_parameters: atomic, read back); False, said on stderr,
    if it cannot be."""
    from bh8_gym.hand_file import HandFileError, write_hand_parameters

    try:
        write_hand_parameters(path, hand, comment=comment)
    except (HandFileError, OSError) as error:
        print(f"{name}: cannot write {path}: {error}", file=sys.stderr)
        return False
    return True


def _rollouts(args: argparse.Namespace, data: bytes, log_name: str):
    from bh8_gym.calibration.rollouts import LocalRollouts, RayRollouts

    if args.address is None:
        return LocalRollouts(data, log_name, args.jobs)
    try:
        from bh8_gym.agents.sweep.cluster import address_argument, check_reachable
    except ImportError:
        raise ValueError('--address needs Ray: pip install "bh8-gym[cluster]"') from None
    try:
        address = address_argument(args.address)
        check_reachable(address)
    except (argparse.ArgumentTypeError, ValueError) as error:
        raise ValueError(f"--address: {error}") from None
    return RayRollouts(data, log_name, address)


class _progress_bar:
    """A tqdm bar counting replays (on stderr when it is a terminal)."""

    def __enter__(self):
        from tqdm import tqdm

        self._bar = tqdm(desc="replays", unit="replay", disable=None, leave=False, dynamic_ncols=True)
        return self._bar.update

    def __exit__(self, *exc_info):
        self._bar.close()


def _draw(args: argparse.Namespace) -> int:
    import numpy as np

    from bh8_gym.hand_file import HandParameters
    from bh8_gym.calibration.practice import draw_hand

    values = draw_hand(np.random.default_rng(args.seed), everything=args.everything)
    if not _write_hand("bh8 calibrate draw", args.output, HandParameters(values),
                       f"bh8 calibrate draw --seed {args.seed}: a practice hand for bh8 serve --hand-parameters "
                       "(docs/hardware.md)"):
        return 2
    print(f"bh8 calibrate draw: {args.output}")
    return 0
