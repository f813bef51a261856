"""Worker processes that never outlive the command that started them.

`bh8 train`'s env workers and the evaluation worker ignore the stop signals (Ctrl-C, SIGTERM,
SIGHUP): the training process stops on them, takes its checkpoint and closes the workers. But
multiprocessing ends a daemonic worker still alive at exit with SIGTERM and then waits for it
without a limit, so a worker that ignores SIGTERM kept `bh8 train` alive for ever after an
exception (issue 39, finding 3). So every worker is `track`ed, `stop` ends one with SIGKILL if it
has not exited in time, and at exit any still alive is killed before multiprocessing's own
exit handler runs (atexit runs handlers in reverse order of registration, and multiprocessing's
is registered when it is imported, before this module's).
"""
from __future__ import annotations

import atexit
import multiprocessing.util  # noqa: F401  (its exit handler first: ours then runs before it)
import os
import signal
import weakref

# Each worker this process started and has not stopped: what it is ("env worker 1"), the pid of the
# process that started it (a forked child inherits this dict but not the workers), its start time.
_workers: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


class WorkerDied(RuntimeError):
    """A worker process ended while its work was still expected of it (killed, or crashed)."""


def track(process, what: str = "worker") -> None:
    """Watch `process` (a started multiprocessing.Process): `check_alive` raises once it has died,
    and it is killed at exit if still alive then."""
    _workers[process] = (what, os.getpid(), _start_time(process.pid))


def _start_time(pid: int) -> str | None:
    """The process's start time (/proc/PID/stat field 22) while it runs (not a zombie), else None."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as stat:
            fields = stat.read().rsplit(b")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return None if fields[0] in (b"Z", b"X") else fields[19].decode()


def _running(process, started: str | None) -> bool:
    """Whether the worker runs. multiprocessing's answer comes from its fork server, which a SIGTERM
    to the process group ends (the workers ignore it): then it says 255 for a worker that still
    runs. So /proc has the last word: the same pid with the same start time, not a zombie."""
    if process.is_alive():
        return True
    return started is not None and _start_time(process.pid) == started


def stop(process, wait: float = 10.0) -> None:
    """Wait up to `wait` seconds for `process` to exit, then kill it (SIGKILL: it cannot be ignored)."""
    _, _, started = _workers.pop(process, (None, None, _start_time(process.pid)))
    process.join(timeout=wait)
    if _running(process, started):
        try:
            os.kill(process.pid, signal.SIGKILL)  # not process.kill(): its fork server may be gone
        except OSError:
            pass
        process.join(timeout=5.0)


def check_alive() -> None:
    """WorkerDied naming the first tracked worker of this process that has exited. Cheap (a waitpid
    with WNOHANG and a read of /proc each): the episode loops and the training steps call it at
    every step, so a worker killed while this process works on something else ends the command
    within a step, not when its reply is next awaited (an evaluation's half took half a minute)."""
    for process, (what, parent, started) in list(_workers.items()):
        if parent == os.getpid() and not _running(process, started):
            _workers.pop(process, None)
            raise WorkerDied(f"{what} (pid {process.pid}) exited (exit code {process.exitcode})")


def in_worker() -> None:
    """What a worker process does first: tqdm's bars lock with a lock of this process only (its
    default, a multiprocessing lock, is a semaphore the resource tracker reports as leaked, in a
    warning of its own, when the worker is killed)."""
    import threading

    from tqdm.std import tqdm

    tqdm.set_lock(threading.RLock())


def _kill_all() -> None:
    for process, (_, parent, _) in list(_workers.items()):
        try:
            if parent == os.getpid():
                stop(process, wait=0.0)
        except (OSError, ValueError, AssertionError):  # closed already
            pass


atexit.register(_kill_all)
