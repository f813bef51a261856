"""kill -9 of a worker of `bh8 train` or `bh8 eval` at a random moment, over and over: how long the
command takes to end, its exit status, its stderr lines, and whether any process is left.

Issue 39's target: each run ends within 10 s of the kill with exit 1 or 2 and one line, and no
process of the command's session is left. Each command runs in a session of its own; a worker is
a process of that session other than the command itself and multiprocessing's helpers (its fork
server and resource tracker, which are Python's, not ours).

Run: python benchmarks/kill_workers.py [--rounds 10] [--command train eval]
"""
from __future__ import annotations

import argparse
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

TINY = """\
algorithm = "PPO"
env_id = "BH8FingerReach-v0"
[eval_env_kwargs]
randomize = false
[train]
total_timesteps = 4096
n_envs = 2
checkpoint_freq = 512
[eval]
freq = 512
episodes = 8
[hyperparameters]
n_steps = 128
batch_size = 64
n_epochs = 1
[policy_kwargs]
net_arch = [16]
"""


def session_processes(session: int) -> dict[int, tuple[int, str]]:
    """{pid: (parent pid, command line)} of the live processes of `session`."""
    found = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            fields = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()
            if fields[0] == "Z" or int(fields[3]) != session:
                continue
            found[int(entry)] = (int(fields[1]), Path(f"/proc/{entry}/cmdline").read_bytes().replace(b"\0", b" ").decode())
        except (OSError, IndexError, ValueError):
            continue
    return found


def workers(session: int) -> list[int]:
    """The session's workers: the fork server's children (or the command's, under spawn), not
    multiprocessing's own helpers (the fork server, the resource tracker)."""
    processes = session_processes(session)
    command = processes.get(session, (0, ""))[1]
    helpers = {pid for pid, (parent, line) in processes.items()
               if parent == session and ("forkserver" in line or "resource_tracker" in line)}
    # a child forked a moment ago still shows the command's own line until it execs: not yet known
    return [pid for pid, (parent, line) in processes.items()
            if pid != session and pid not in helpers and line != command and (parent in helpers or parent == session)]


def one_round(command: list[str], folder: Path, rng: random.Random) -> dict:
    process = subprocess.Popen(command, cwd=folder, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                               start_new_session=True)
    started = time.monotonic()
    delay = rng.uniform(0.0, 12.0)  # after the workers exist: anywhere in the run
    victim = None
    while process.poll() is None and time.monotonic() - started < 120:
        found = workers(process.pid)
        if found and time.monotonic() - started >= delay:
            victim = rng.choice(found)
            break
        time.sleep(0.05)
    if victim is None:
        process.wait()
        return {"killed": None, "code": process.returncode}
    os.kill(victim, signal.SIGKILL)
    killed = time.monotonic()
    try:
        _, err = process.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        _, err = process.communicate()
        return {"killed": victim, "code": None, "seconds": None, "lines": err.strip().splitlines(), "left": []}
    seconds = time.monotonic() - killed
    time.sleep(0.5)
    return {"killed": victim, "code": process.returncode, "seconds": seconds,
            "lines": [line for line in err.strip().splitlines() if line.strip() and "pybullet build time" not in line],
            "left": sorted(session_processes(process.pid))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=10, help="kills per command (default: %(default)s)")
    parser.add_argument("--command", nargs="+", choices=("train", "eval"), default=["train", "eval"])
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = random.Random(args.seed)
    with tempfile.TemporaryDirectory() as temporary:
        folder = Path(temporary)
        (folder / "tiny.toml").write_text(TINY)
        commands = {
            "train": lambda k: [sys.executable, "-m", "bh8_gym.cli", "train", "--config", "tiny.toml", "--out",
                                f"run{k}", "--no-progress"],
            "eval": lambda k: [sys.executable, "-m", "bh8_gym.cli", "eval", "--baseline", "loop", "--objects",
                               "primitives-test", "--episodes", "60", "--gif-episodes", "0", "--no-progress",
                               "--processes", "2", "--out", f"eval{k}"],
        }
        for name in args.command:
            outcomes = [one_round(commands[name](k), folder, rng) for k in range(args.rounds)]
            kills = [o for o in outcomes if o["killed"] is not None]
            good = [o for o in kills if o["code"] in (1, 2) and o["seconds"] is not None and o["seconds"] <= 10
                    and len(o["lines"]) == 1 and not o["left"]]
            print(f"bh8 {name}: {len(kills)} kills ({len(outcomes) - len(kills)} runs ended first); "
                  f"{len(good)} ended within 10 s with exit 1 or 2, one line and no process left; "
                  f"slowest {max((o['seconds'] or 999 for o in kills), default=0):.1f} s")
            for outcome in kills:
                if outcome not in good:
                    print(f"  not so: {outcome}")


if __name__ == "__main__":
    main()
