"""`bh8 serve`: the simulated hand's firmware on a pseudo-terminal (docs/architecture.md Contract 3).

The server itself is `serial_server.PtyServer` (pacing, ports, reopening); the hand is
`simulator.build_firmware`'s. This module is the command: its options, the store's directory,
the start-up lines, signals, and `--env`.

`--env ID --seed N [--env-kwargs JSON]` serves a Gymnasium environment's own firmware
(`gym.make(ID, **kwargs).unwrapped.firmware`: its plant, scene, arm and fresh store), so a host
(`bh8 deploy`) sees byte for byte what an in-process evaluation of `env.reset(seed=N)` then
`env.step(...)` sees. Every time a client enters LOOP with the env's layout (the env's setup
script, then `loop_command`), the server runs the env's `prepare_episode`: restore of the env's
post-LOOP snapshot (this also undoes whatever the client's supervisory commands did to the
simulated time, baud rate and motors), randomisation (when on), and the episode's scene. The
first entry is `reset(seed=N)`'s episode, each later one the next episode of that generator, as
successive `reset()` calls give. The client's first block then plays the env's "A" block. A LOOP
with another layout is served plainly (no episode). Unpaced only: LOOP cycles then cost exactly
the simulated time the env charges.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import sys
import warnings
from pathlib import Path

import gymnasium as gym

from bh8_gym.hand_file import HandFileError, load_hand_parameters
from bh8_gym.cli import handling_signals, integer_argument, json_object_argument
from bh8_gym.envs import register_envs
from bh8_gym.nvstore import StoreError, StoreWarning
from bh8_gym.objects import OBJECT_SPEC_HELP
from bh8_gym.protocol import FIRMWARE_PROFILES
from bh8_gym.rendering import display_available
from bh8_gym.simulator import build_firmware, shutdown_firmware
from bh8_gym.serial_server import PtyServer


def default_state_dir() -> Path:
    """The per-user non-volatile store: $XDG_DATA_HOME/bh8-gym/state, else ~/.local/share/..."""
    base = os.environ.get("XDG_DATA_HOME") or os.path.join(os.path.expanduser("~"), ".local", "share")
    return Path(base) / "bh8-gym" / "state"


def build_env_firmware(env_id: str, seed: int, env_kwargs: dict | None = None, gui: bool = False):
    """(env, firmware) for `bh8 serve --env`: the env's own firmware after its setup script, out of
    LOOP again, with each LOOP entry in the env's layout starting the env's next episode (the
    first one `reset(seed=seed)`'s).

    Raises ValueError naming a bad id or keyword (before any pty is made).
    """
    register_envs()
    kwargs = dict(env_kwargs or {})
    if gui:
        kwargs["render_mode"] = "human"
    try:
        env = gym.make(env_id, **kwargs).unwrapped
    except gym.error.Error as error:
        raise ValueError(f"--env {env_id!r}: {error}") from None
    except TypeError as error:
        raise ValueError(f"--env-kwargs for {env_id}: {error}") from None
    if not hasattr(env, "prepare_episode"):
        env.close()
        raise ValueError(f"--env {env_id!r} is not a bh8-gym RealTime environment")
    start_episodes_on_loop_entry(env, seed)
    # The env left its firmware in LOOP (its snapshot's state); a client connects to a prompt.
    env.firmware.transact(b"\x03")
    return env, env.firmware


def start_episodes_on_loop_entry(env, seed: int | None) -> None:
    """Make every LOOP entry of `env.firmware` in the env's layout run `env.prepare_episode`
    (the first with `seed`, later ones continuing its generator), as if the env's reset ran there.

    Installed as `Firmware.loop_entry_hook`; the episode's restore keeps the serial bytes still
    waiting (the "*" LOOP acknowledgement and any control block sent with the LOOP command).
    """
    seeds = [seed]

    def start_episode(firmware, layout) -> None:
        if layout != env.layout:
            print(f"bh8 serve: LOOP layout {layout!r} is not {env.env_id}'s {env.layout!r}; "
                  "serving it without starting an episode", file=sys.stderr, flush=True)
            return
        env.prepare_episode(seeds.pop() if seeds else None, keep_io=True)

    env.firmware.loop_entry_hook = start_episode


def _state_directory(text: str) -> Path:
    """argparse `type=` of --state: an empty path would be "." (the store written into the working
    directory), so it is refused as bh8sim://?state= refuses it."""
    if not text.strip():
        raise argparse.ArgumentTypeError("needs a directory, got an empty value")
    return Path(text)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--state", metavar="DIR", type=_state_directory, default=None,
        help=f"non-volatile store of the simulated hand (default: {default_state_dir()})",
    )
    parser.add_argument(
        "--realtime", action="store_true",
        help="pace simulated time to the wall clock (a GC takes about 1 s; ^C aborts a motion); needed by "
             "clients that time their RealTime loop or their waits by the wall clock; default: answer as "
             "soon as the simulated motion ends (^C still aborts one; RealTime runs many times faster)",
    )
    parser.add_argument("--firmware", choices=FIRMWARE_PROFILES, default=None,
                        help="firmware profile (default 4.3). Clients written for firmware 4.4 (Barrett's C++ "
                             "API 4.4.x, drivers that use LCT, LFBP or LFAIN) need --firmware 4.4: a 4.3 hand "
                             "answers their 4.4 parameters with ERR 64. With --env use --env-kwargs firmware_profile")
    parser.add_argument(
        "--link", metavar="PATH", default=None,
        help="also make a symlink PATH (e.g. /dev/ttyUSB0, for programs with a hard-wired port name) to a "
             "pty of this hand; every open of PATH gets a fresh pty, so nothing a program left unread "
             "survives its reopening the port, however fast (docs/clients.md); removed on exit; refused if "
             "PATH exists (unless a killed bh8 serve left it)",
    )
    parser.add_argument(
        "--hand-parameters", metavar="FILE", type=Path, default=None,
        help="the hand's parameters from a hand file (`bh8 calibrate fit -o FILE`, or a practice hand from "
             "`bh8 calibrate draw`; docs/hardware.md); with --env it is the env's hand_parameters keyword",
    )
    parser.add_argument("--seed", type=integer_argument(0), default=0,
                        help="seed of the plant's randomised constants; with --env, the env's reset seed (default 0)")
    parser.add_argument("--gui", action="store_true", help="show the PyBullet GUI (needs a display)")
    parser.add_argument(
        "--object", metavar="SPEC", action="append", default=[], dest="objects",
        help="place an object in the hand (repeatable; default: none; the palm faces up): " + OBJECT_SPEC_HELP,
    )
    parser.add_argument(
        "--env", metavar="ID", default=None,
        help="serve a Gymnasium env's own hand (BH8Grasp-v0, BH8FingerReach-v0): each LOOP entry in the "
             "env's layout starts the env's next episode, the first being reset(seed=--seed)'s, so "
             "`bh8 deploy` sees byte for byte what an in-process evaluation sees; unpaced only; the "
             "store is the env's own fresh one (no --state, --object, --firmware); default: none, the "
             "simulated hand on its own",
    )
    parser.add_argument(
        "--env-kwargs", metavar="JSON", default=None, type=json_object_argument,
        help='keyword arguments of the env as a JSON object, e.g. \'{"randomize": false, "object_set": "test"}\' '
             "(default: none, the env's defaults)",
    )


@contextlib.contextmanager
def _native_stdout_to_stderr():
    """Send what native code prints to stdout (PyBullet's GUI start-up chatter) to stderr, so the
    device path stays the first line of stdout."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        os.dup2(2, 1)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def run(args: argparse.Namespace) -> int:
    if args.gui and not display_available():
        print("bh8 serve: --gui needs a display and DISPLAY is not set; run without --gui "
              "(or under xvfb-run)", file=sys.stderr)
        return 2
    if args.env is not None:
        return _run_env(args)
    if args.env_kwargs is not None:
        print("bh8 serve: --env-kwargs needs --env", file=sys.stderr)
        return 2
    state_dir = args.state if args.state is not None else default_state_dir()
    try:
        hand = None if args.hand_parameters is None else load_hand_parameters(args.hand_parameters).values
    except HandFileError as error:
        print(f"bh8 serve: --hand-parameters: {error}", file=sys.stderr)
        return 2
    with _store_warnings_on_stderr():
        try:
            with _native_stdout_to_stderr():
                firmware = build_firmware(state_dir, args.firmware or "4.3", args.seed, tuple(args.objects), args.gui,
                                          hand)
        except ValueError as error:
            print(f"bh8 serve: {error}", file=sys.stderr)
            return 2
        except StoreError as error:
            print(f"bh8 serve: {error}", file=sys.stderr)
            return 1
        except OSError as error:
            print(f"bh8 serve: cannot use the store {state_dir}: {error}", file=sys.stderr)
            return 1
        return serve(firmware, realtime=args.realtime, link=args.link, store=state_dir)


@contextlib.contextmanager
def _store_warnings_on_stderr():
    """Each StoreWarning (a save that failed, a damaged store set aside) as one line on stderr."""
    show_others = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, StoreWarning):
            print(f"bh8 serve: {message}", file=sys.stderr, flush=True)
        else:
            show_others(message, category, filename, lineno, file, line)

    with warnings.catch_warnings():
        warnings.simplefilter("always", StoreWarning)
        warnings.showwarning = show
        yield


def _run_env(args: argparse.Namespace) -> int:
    conflicts = [name for name, given in (("--state", args.state is not None), ("--object", bool(args.objects)),
                                           ("--firmware", args.firmware is not None), ("--realtime", args.realtime))
                 if given]
    if conflicts:
        print(f"bh8 serve: --env serves the env's own hand unpaced; it cannot take {', '.join(conflicts)} "
              "(set env options with --env-kwargs)", file=sys.stderr)
        return 2
    env_kwargs = dict(args.env_kwargs or {})
    if args.hand_parameters is not None:
        if "hand_parameters" in env_kwargs:
            print("bh8 serve: --hand-parameters and --env-kwargs' hand_parameters: give one", file=sys.stderr)
            return 2
        env_kwargs["hand_parameters"] = str(args.hand_parameters)
    try:
        with _native_stdout_to_stderr():
            env, firmware = build_env_firmware(args.env, args.seed, env_kwargs, args.gui)
    except ValueError as error:
        print(f"bh8 serve: {error}", file=sys.stderr)
        return 2

    def close(served) -> None:
        try:
            served.shutdown()
        finally:
            env.close()

    return serve(firmware, link=args.link, close=close,
                 description=f"{args.env} seed {args.seed} {json.dumps(args.env_kwargs or {})}")


def _other_profile_note(profile: str):
    """An `other_profile_hook` that says once per name on stderr why a client got ERR 64."""
    noted = set()

    def note(name: str, profiles) -> None:
        if name not in noted:
            noted.add(name)
            wanted = " or ".join(profiles)
            print(f"bh8 serve: the client asked for {name}, a parameter of firmware {wanted}; this hand runs "
                  f"firmware {profile} and answered ERR 64 (start bh8 serve --firmware {profiles[-1]})",
                  file=sys.stderr, flush=True)

    return note


def serve(firmware, realtime: bool = False, link: str | os.PathLike | None = None, store=None,
          close=shutdown_firmware, description: str | None = None) -> int:
    """Serve `firmware` on a new pty until SIGINT, SIGTERM or SIGHUP: print the device path as the
    first line of stdout, then `close(firmware)` (default: shut it down, persisting its counters,
    and close its plant). `description` names what is served in the start-up note on stderr.
    Returns the exit code: 0, or 1 when the pty or the link cannot be made or the simulation failed
    (a step that raised; the counters are still saved)."""
    try:
        server = PtyServer(firmware, realtime=realtime, link=link)
    except OSError as error:
        close(firmware)
        print(f"bh8 serve: {error}", file=sys.stderr)
        return 1

    firmware.other_profile_hook = _other_profile_note(firmware.profile)
    try:
        with handling_signals((signal.SIGINT, signal.SIGTERM, signal.SIGHUP), server.stop_from_signal_handler):
            print(server.device, flush=True)
            mode = "paced to the wall clock" if realtime else "unpaced"
            linked = f" (link {server.link})" if server.link else ""
            stored = f", store {store}" if store is not None else ""
            served = f" ({description})" if description else ""
            print(f"bh8 serve: firmware {firmware.profile}{served} on {server.device}{linked}, {mode}{stored}; "
                  "^C to stop", file=sys.stderr, flush=True)
            server.serve_forever()
    except Exception as error:  # a simulation step that failed: shut down all the same (the counters)
        failure = error
    else:
        failure = None
    finally:
        try:
            close(firmware)
        finally:
            server.close()
    if failure is not None:
        print(f"bh8 serve: the simulation failed ({type(failure).__name__}: {failure}); the hand's counters "
              "were saved", file=sys.stderr)
        return 1
    return 0
