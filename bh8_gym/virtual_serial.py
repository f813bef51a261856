"""The simulated hand's firmware on a pseudo-terminal: the server behind `bh8 serve` (docs/architecture.md Contract 3).

The server owns a pty, prints the follower device path as the first line of stdout, and shovels
bytes between the pty and a `Firmware` until SIGINT, SIGTERM or SIGHUP, then `Firmware.shutdown()`
persists the never-reset counters and it exits 0. Any serial program (pyserial, screen, minicom,
Barrett's C++ API) opens the device like a USB serial adapter.

Two ways to run simulated time (SPEC.md §6):
- unpaced (default): after each read from the pty the firmware runs until it waits for input and
  its output is written back; a command answers as soon as its simulated motion ends. The line is
  read between slices of `UNPACED_SLICE_S` simulated seconds, so a ^C that arrives while a motion
  runs aborts it at the next slice. An idle server blocks in poll() with no timeout and uses no CPU.
  A supervisory command still running after `UNPACED_FULL_SPEED_S` simulated seconds (a motion
  that may never end: a finger jittering against an obstacle never stalls) is paced to the wall
  clock from then on, so it costs what a paced server costs, not a whole core, until ^C ends it.
- `--realtime`: simulated time follows the wall clock in slices of `REALTIME_SLICE_S`; bytes are
  fed to the firmware while a motion runs, so ^C (0x03) aborts it with ERR 16384 (§5.5 case 4).
  Idle time between commands costs no simulated time here either (Contract 2), so an idle paced
  server also sleeps in poll().

Input is taken no faster than the line could deliver it: at most BAUD/10 bytes per second of the
hand's time (simulated time unpaced, where waiting for input costs none, so a waiting firmware may
take a buffer's worth at once; the wall clock paced), and never more than `INPUT_BUFFER_BYTES`
ahead of what the firmware has consumed. The rest waits in the pty, whose writer then blocks, as
a host's writes block on a real serial line: a flood of RealTime blocks cannot grow the server.

A client may close and reopen the device without losing the hand's state. The device is a port:
one line, one client at a time, and every open starts a clean session (`PortClients`, the part of
`PtyServer` that keeps its ptys and clients).
- Fresh: a closed port receives nothing, and nothing a client left unread (the reply to a ^C sent
  just before closing, a prompt it stopped reading) reaches the next open, however fast it follows
  (Barrett's C++ API closes and reopens at once to discard buffers when it changes the baud rate).
  A pty cannot drop bytes when its client closes it, so on Linux the printed device is a symlink (in
  a private directory under /dev/shm) to a pty no client has opened yet. inotify tells the server
  of every open, write and close of that pty (`_OpenWatch`); once a client has opened it, the
  server points the symlink at a new pty, so the next open gets that one, and makes this pty's node
  mode 000 so that nobody else can open it by its /dev/pts name (root can: its open then ends the
  session as below). `--link` is a fixed symlink to the printed device.
- Exclusive: the server serves one pty (the session) at a time. A pty opened while another client
  has the port, or found with two clients in it (they opened the device in the instant before the
  server moved it on: two opens, or a close after the last open, or two descriptors on it in /proc),
  is hung up before anything is read from it or written to it: those clients see the port go (EOF,
  EIO; an open after the mode change fails with EACCES) and may open it again. Nothing they wrote
  reaches the hand, and neither reads the other's replies.
- Clients that came and went before the server looked (open, write, close: `echo HI > device`)
  were clients of a closed port: what they wrote reaches the hand, as bytes sent on a line do, and
  the replies go nowhere. A client that opened the same pty after them is served if the events
  tell its bytes from theirs (they wrote nothing, or it has not written yet: then all in the pty is
  theirs); otherwise it is hung up.
- The replies are the session's own: its bytes wait while the hand finishes what an earlier
  (closed) client sent, so the end of that client's motion does not reach it; a ^C does not wait
  (it aborts that motion, and the ERR 16384 is the new client's).
Elsewhere (no inotify) the device is one pty the server holds open, shared by its clients, and
unread bytes wait for the next reader. The hand itself keeps its state: a client killed in the
middle of a RealTime control block leaves the firmware waiting for that block's data bytes, as a
real hand does (docs/clients.md says how to recover).
"""
from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import errno
import os
import select
import shutil
import stat
import struct
import sys
import tempfile
import time
from pathlib import Path

from bh8_gym.protocol import BITS_PER_BYTE, CTRL_C


# Paced mode: the longest wait between firmware advances while a command or LOOP is active. One
# physics step of the plant's default dt (Contract 1), so paced output is at most a step late.
REALTIME_SLICE_S = 0.002
# Paced mode: the most simulated time run in one go, so input (^C) is looked at this often even
# when the physics runs slower than the wall clock.
REALTIME_BURST_S = 0.02
# Paced mode: when the physics falls further behind the wall clock than this, the excess is
# forgiven, so a slow machine makes the hand slow rather than jerky in catch-up bursts.
REALTIME_MAX_LAG_S = 0.25
# Without --realtime, simulated seconds a command runs between looks at the line for ^C.
UNPACED_SLICE_S = 0.25
# Without --realtime, simulated seconds a supervisory command runs at full speed; past this it is
# paced to the wall clock. Longer than the motions that end at usual settings (a full close at the
# slowest MCV takes about 4.4 s), so in practice only runaway motions are slowed.
UNPACED_FULL_SPEED_S = 10.0
# Bytes taken from the pty ahead of what the firmware has consumed, as a host serial driver's
# buffer: past this the server stops reading and the pty's writer blocks (backpressure).
INPUT_BUFFER_BYTES = 4096
# Our choice: the longest the never-reset counters (OD, PTEMP, UPSECS) go unsaved after the hand
# did something; they are "maintained through power failures" (manual §5.3.2, §5.4.2), so a kill
# of the server loses at most this much.
COUNTER_SAVE_INTERVAL_S = 10.0
# Bytes kept for a client that is not reading. Past this the oldest are dropped, as a host UART
# with nobody reading overruns; a reopening client flushes its input anyway (pyserial does).
OUTPUT_BACKLOG_LIMIT = 1 << 20
_READ_CHUNK = 4096
# More than a pty holds for its leader to read (the kernel's 64 KiB flip buffer and 4 KiB line
# discipline): reading this much empties it.
_PTY_BUFFER_BYTES = 1 << 17
# Seconds between attempts to put a new pty behind the device after one failed (out of ptys).
FRESH_PTY_RETRY_S = 1.0
_IN_USE = ("a second client opened the device while it was in use; the port is exclusive, so that "
           "client was hung up and what it wrote went nowhere")
_SHARED = ("clients opened the device at the same moment, before the server could give each its own pty; "
           "that pty was hung up before either was answered (so neither reads the other's replies); open it again")


def open_raw_pty() -> tuple[int, int, str]:
    """A new pty (leader fd, follower fd, follower path), raw and readable by its owner only.

    Raw as cfmakeraw(3): no echo, no CR/LF translation, no signals from ^C, no XON/XOFF flow
    control (RealTime data bytes may be 0x03, 0x0D, 0x11, 0x13), 8 bits, no parity.
    """
    import termios

    leader, follower = os.openpty()
    attrs = termios.tcgetattr(follower)
    iflag, oflag, cflag, lflag = attrs[0], attrs[1], attrs[2], attrs[3]
    iflag &= ~(termios.IGNBRK | termios.BRKINT | termios.PARMRK | termios.ISTRIP | termios.INLCR
               | termios.IGNCR | termios.ICRNL | termios.IXON | termios.IXOFF | termios.IXANY
               | termios.INPCK | termios.IGNPAR)
    oflag &= ~termios.OPOST
    lflag &= ~(termios.ECHO | termios.ECHONL | termios.ICANON | termios.ISIG | termios.IEXTEN)
    cflag = (cflag & ~(termios.CSIZE | termios.PARENB)) | termios.CS8 | termios.CREAD | termios.CLOCAL
    attrs[0], attrs[1], attrs[2], attrs[3] = iflag, oflag, cflag, lflag
    attrs[6][termios.VMIN] = 1
    attrs[6][termios.VTIME] = 0
    termios.tcsetattr(follower, termios.TCSANOW, attrs)
    path = os.ttyname(follower)
    os.chmod(path, 0o600)
    os.set_blocking(leader, False)
    return leader, follower, path


class _OpenWatch:
    """What clients do with a pty's follower, from inotify: opens, writes and closes, in order.

    inotify merges an event with an identical one still unread (two opens in a row read as one),
    so `PtyServer` also counts the descriptors when that matters. Linux only; `create` returns
    None where inotify is missing.
    """

    IN_MODIFY = 0x02
    IN_CLOSE = 0x08 | 0x10  # IN_CLOSE_WRITE | IN_CLOSE_NOWRITE
    IN_OPEN = 0x20
    IN_Q_OVERFLOW = 0x4000
    _EVENT = struct.Struct("iIII")  # struct inotify_event without its name (a watched file has none)

    def __init__(self, fd: int, libc, path: bytes):
        self.fd = fd
        self._libc = libc
        self._path = path

    @classmethod
    def create(cls, path: str) -> "_OpenWatch | None":
        if not sys.platform.startswith("linux"):
            return None
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
            fd = libc.inotify_init1(os.O_NONBLOCK | os.O_CLOEXEC)
        except (OSError, AttributeError):
            return None
        if fd < 0:
            return None
        watch = cls(fd, libc, os.fsencode(path))
        if not watch.watch_for(cls.IN_OPEN | cls.IN_MODIFY | cls.IN_CLOSE):
            os.close(fd)
            return None
        return watch

    def watch_for(self, mask: int) -> bool:
        """Report these events from now on (a session's pty needs only the opens)."""
        return self._libc.inotify_add_watch(self.fd, self._path, mask) >= 0

    def drain(self) -> list[int]:
        """The event masks read now, oldest first."""
        masks = []
        while True:
            try:
                data = os.read(self.fd, 4096)
            except BlockingIOError:
                return masks
            if not data:
                return masks
            masks.extend(self._EVENT.unpack_from(data, offset)[1]  # name lengths are 0
                         for offset in range(0, len(data), self._EVENT.size))

    def close(self) -> None:
        os.close(self.fd)


class _OpenHistory:
    """What a pty's events say about its clients: whether any opened it, whether one closed it after
    the last open (two held it at once), and whether the clients before the last open wrote (their
    bytes would then be ahead of the last one's in the pty)."""

    def __init__(self):
        self.opens = 0
        self.closes = 0
        self.closed_since_open = False
        self.written_before_open = False
        self.written_since_open = False

    def add(self, masks: list[int]) -> None:
        for mask in masks:
            if mask & _OpenWatch.IN_Q_OVERFLOW:  # events lost: assume the worst
                self.opens += 1
                self.closes += 1
                self.closed_since_open = self.written_before_open = self.written_since_open = True
            if mask & _OpenWatch.IN_OPEN:
                self.opens += 1
                self.written_before_open |= self.written_since_open
                self.written_since_open = self.closed_since_open = False
            if mask & _OpenWatch.IN_MODIFY:
                self.written_since_open = True
            if mask & _OpenWatch.IN_CLOSE:
                self.closes += 1
                self.closed_since_open = True


class _Pty:
    """One pseudo-terminal: its leader, what it owes its client, whether a client has it open.

    With an open watch (Linux) the server holds no follower fd, so the leader hangs up while no
    client has the device open; without one the follower stays open and the pty counts as always
    held (it is then the one device all clients share)."""

    def __init__(self):
        self.leader, self.follower, self.device = open_raw_pty()
        self.backlog = bytearray()
        self.polled_events = 0  # the poll events registered for the leader while it is a session
        self.waiting = bytearray()  # the client's bytes taken from the pty, waiting for the hand
        self.history = _OpenHistory()
        self.accepted_opens = 0  # the opens seen when it became the session
        self.watch = _OpenWatch.create(self.device)
        self.watched = self.watch is not None
        self._hangup = None
        if self.watched:
            os.close(self.follower)
            self.follower = -1
            self.watch.drain()  # our own close just now
            self._hangup = select.poll()
            self._hangup.register(self.leader, 0)

    def look(self) -> None:
        """Read the watch's new events into `history`."""
        self.history.add(self.watch.drain())

    def held(self) -> bool:
        """Whether a client has the device open now (the kernel's count: the leader's hang-up)."""
        return self._hangup is None or not self._hangup.poll(0)

    def close_to_others(self) -> None:
        """Mode 000: a further open fails with EACCES (root's passes; its open event then tells). Not
        TIOCSPTLCK: an open that fails on a locked pty leaves the pty's client with EIO too."""
        try:
            os.chmod(self.device, 0)
        except OSError:
            pass  # gone already: its client closed it

    def read(self, limit: int) -> bytes:
        """At most `limit` bytes the client wrote."""
        chunks = []
        while limit > 0:
            try:
                chunk = os.read(self.leader, min(limit, _READ_CHUNK))
            except BlockingIOError:
                break
            except OSError as error:
                if error.errno != errno.EIO:
                    raise
                break  # no client has the device open (what the last one wrote was read first)
            if not chunk:
                break
            chunks.append(chunk)
            limit -= len(chunk)
        return b"".join(chunks)

    def close(self) -> None:
        """Close the pty; a client still holding the follower is hung up (EOF, then EIO on write)."""
        if self.watch is not None:
            self.watch.close()
            self.watch = None
        for fd in (self.leader, self.follower):
            try:
                os.close(fd)
            except OSError:
                pass
        self.leader = self.follower = -1


def _descriptors_open_on(device: str) -> int:
    """How many file descriptors of the processes this user may look into (all, for root) have
    `device` open, from /proc (0 where there is none). A name that matches is checked to be the
    same node: a process in another container may have its own /dev/pts with the same numbers."""
    try:
        node = os.stat(device)
        pids = [entry for entry in os.listdir("/proc") if entry.isdigit()]
    except OSError:
        return 0
    count = 0
    for pid in pids:
        directory = f"/proc/{pid}/fd"
        try:
            descriptors = os.listdir(directory)
        except OSError:
            continue  # another user's process, or gone
        for descriptor in descriptors:
            path = f"{directory}/{descriptor}"
            try:
                if os.readlink(path) == device and os.path.samestat(os.stat(path), node):
                    count += 1
            except OSError:
                continue
    return count


# A descriptor appears in /proc a moment after the open that inotify reported: how often and how
# long apart the count is retried before a held pty counts as held by one client we cannot see
# (another user's: root may open our ptys).
_DESCRIPTOR_COUNT_TRIES = 5
_DESCRIPTOR_COUNT_PAUSE_S = 0.002


def _holders(pty: _Pty) -> int:
    """The number of descriptors a held pty is open on (at least 1)."""
    for _ in range(_DESCRIPTOR_COUNT_TRIES):
        count = _descriptors_open_on(pty.device)
        if count:
            return count
        time.sleep(_DESCRIPTOR_COUNT_PAUSE_S)
    return 1


_DEVICE_NAME = "ttyBH8"
_PRIVATE_PREFIX = "bh8-serve-"


def _private_directory() -> str:
    """A new directory only its owner can enter, for the device's symlink: under /dev/shm where
    there is one (the printed device then still starts with /dev/, as pty paths do), else the
    system's temporary directory. Named after the server's pid, so the directories of servers
    that were killed (no clean exit removes them) are removed here."""
    for parent in ("/dev/shm", tempfile.gettempdir()):
        try:
            _remove_dead_servers_directories(parent)
            return tempfile.mkdtemp(prefix=f"{_PRIVATE_PREFIX}{os.getpid()}-", dir=parent)
        except OSError:
            continue
    raise OSError("cannot make a private directory for the device's symlink")


def _server_pid(directory_name: str) -> int | None:
    """The pid in a private directory's name (bh8-serve-PID-XXXX), else None."""
    fields = directory_name.split("-")
    if len(fields) < 4 or fields[:2] != ["bh8", "serve"] or not fields[2].isdigit():
        return None
    return int(fields[2])


def _server_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True  # another user's process (PermissionError)
    return True


def _remove_dead_servers_directories(parent: str) -> None:
    for entry in os.scandir(parent):
        pid = _server_pid(entry.name)
        if pid is None:
            continue
        try:
            if entry.stat(follow_symlinks=False).st_uid != os.getuid() or _server_alive(pid):
                continue
        except OSError:
            continue  # vanished meanwhile
        shutil.rmtree(entry.path, ignore_errors=True)  # its server is gone


def _left_by_a_killed_server(path: Path) -> bool:
    """Whether `path` is a --link that a killed `bh8 serve` left behind: our own symlink to the
    device in a private directory whose server is gone (a clean exit removes the link itself)."""
    try:
        if path.lstat().st_uid != os.getuid() or not path.is_symlink():
            return False
        target = os.readlink(path)
    except OSError:
        return False
    directory, name = os.path.split(target)
    pid = _server_pid(os.path.basename(directory))
    return name == _DEVICE_NAME and pid is not None and not _server_alive(pid)


class _Stopped(Exception):
    """Raised by the signal handler to abandon a firmware run in progress."""


class PortClients:
    """The device as a serial port, a part of `PtyServer` (a mixin on its ptys, poller and
    pending input): one fresh pty behind the device's symlink, at most one session, and what
    becomes of every pty a client opens (served, a closed port's, or refused; module docstring)."""

    def _add_pty(self) -> _Pty:
        pty = _Pty()
        self._ptys.append(pty)
        if pty.watched:
            self._poller.register(pty.watch.fd, select.POLLIN)
        else:
            self._poller.register(pty.leader, select.POLLIN)
            pty.polled_events = select.POLLIN
        return pty

    def _renew_fresh_pty(self) -> None:
        """Point the device's symlink at a new pty (atomically: rename in the private directory),
        so the next open starts empty whatever the last client leaves unread. On failure (no pty
        or inotify instance left, no room) the device still leads to the last pty (mode 000: an
        open fails with EACCES) and `_wait` retries."""
        try:
            fresh = _Pty()
        except OSError as error:
            self._note(f"cannot make a new pty for the next client ({error}); retrying", once=False)
            return
        if not fresh.watched:
            fresh.close()
            self._note("cannot watch a new pty for the next client (no inotify instance left); retrying", once=False)
            return
        try:
            temporary = os.path.join(self._link_dir, f".{_DEVICE_NAME}.new")
            with contextlib.suppress(FileNotFoundError):
                os.unlink(temporary)
            os.symlink(fresh.device, temporary)
            os.replace(temporary, self.device)
        except OSError as error:
            fresh.close()
            self._note(f"cannot point {self.device} at a new pty ({error}); retrying", once=False)
            return
        self._ptys.append(fresh)
        self._poller.register(fresh.watch.fd, select.POLLIN)
        self._fresh = fresh

    def _accept(self, pty: _Pty) -> None:
        """The pty of the one client served from now on; its watch now tells only of another open."""
        pty.watch.watch_for(_OpenWatch.IN_OPEN)
        pty.accepted_opens = max(pty.history.opens, 1)  # 0: its client's own open is still to come
        self._poller.register(pty.leader, select.POLLIN)
        pty.polled_events = select.POLLIN
        self._session = pty

    def _end_session(self) -> None:
        """The session's client closed the device. What it wrote still reaches the hand (as bytes
        sent on a line do), the replies go nowhere, and what the pty held for a reader goes with it."""
        pty, self._session = self._session, None
        self._pending_input += pty.waiting
        self._pending_input += pty.read(INPUT_BUFFER_BYTES - len(self._pending_input))
        self._remove_pty(pty)

    def _orphan(self, pty: _Pty) -> None:
        """A pty whose clients opened and closed it before the server looked: a closed port's
        client, whose bytes reach the hand and whose replies go nowhere."""
        self._pending_input += pty.read(INPUT_BUFFER_BYTES - len(self._pending_input))
        self._remove_pty(pty)

    def _refuse(self, pty: _Pty, why: str) -> None:
        """Hang the pty up unread: its clients see the port go (EOF, EIO), nothing they wrote
        reaches the hand and nothing reaches them."""
        self._remove_pty(pty)
        self._note(why)

    def _remove_pty(self, pty: _Pty) -> None:
        for fd in (pty.leader, pty.watch.fd if pty.watch is not None else -1):
            try:
                self._poller.unregister(fd)
            except (KeyError, ValueError):
                pass
        pty.close()
        self._ptys.remove(pty)
        if self._speaker is pty:
            self._speaker = None

    def _note(self, message: str, once: bool = True) -> None:
        """One line on stderr (each message once, unless `once` is False)."""
        if once:
            if message in self._noted:
                return
            self._noted.add(message)
        print(f"bh8 serve: {message}", file=sys.stderr, flush=True)

    def _follow_clients(self) -> None:
        """End the session whose client closed the device (or hang it up if a second client got
        into its pty), and look at the fresh pty: once a client has opened it, put a new pty behind
        the device, close this one to further opens (mode 000), and serve it only if it is the one
        client of a free port. Otherwise hang it up unread (a second client while the port is in
        use, or clients that share the pty because they opened it before the server moved the
        device on: the events or the descriptor count tell), or, if its clients have all closed it
        again, pass what they wrote to the hand."""
        if self._link_dir is None:
            return  # one pty that every client shares (no inotify)
        session = self._session
        if session is not None:
            session.look()
            if not session.held():
                self._end_session()
            elif session.history.opens > session.accepted_opens:
                # Another open since it became the session: root's, whom mode 000 does not stop.
                self._session = None
                self._refuse(session, _SHARED)
        fresh = self._fresh
        if fresh is None:
            self._renew_fresh_pty()
            return
        fresh.look()
        if not (fresh.history.opens or fresh.history.closes or fresh.held()):
            return
        self._fresh = None
        self._renew_fresh_pty()  # first: a client that finds the device now gets the new pty
        fresh.close_to_others()
        fresh.look()  # what happened before the mode took
        # Looked at after the mode change: the session's client may have closed and reopened since.
        if self._session is not None and not self._session.held():
            self._end_session()
        self._settle(fresh)

    def _settle(self, pty: _Pty) -> None:
        """What a pty that clients have opened becomes: the session if one client holds it and the
        port was free; a closed port's pty if they have all gone; else refused."""
        history = pty.history
        if not pty.held():
            if self._session is None:
                self._orphan(pty)
            else:
                self._refuse(pty, _IN_USE)
            return
        if self._session is not None:
            self._refuse(pty, _IN_USE)
            return
        if history.closed_since_open or _holders(pty) > 1:
            self._refuse(pty, _SHARED)
            return
        if history.written_before_open:
            # Its client opened it after others had opened, written and closed it (before the server
            # looked): their bytes come first in the pty. They are all theirs unless it wrote too.
            earlier = pty.read(_PTY_BUFFER_BYTES)
            pty.look()
            if history.written_since_open or history.closed_since_open:
                self._refuse(pty, _SHARED)
                return
            self._pending_input += earlier[:max(0, INPUT_BUFFER_BYTES - len(self._pending_input))]
        self._accept(pty)


class PtyServer(PortClients):
    """Serves one `Firmware` on a new pty until `stop()`; `device` is the follower's path."""

    def __init__(self, firmware, realtime: bool = False, link: str | os.PathLike | None = None,
                 counter_save_interval: float = COUNTER_SAVE_INTERVAL_S,
                 full_speed_limit: float = UNPACED_FULL_SPEED_S):
        self.firmware = firmware
        self.realtime = bool(realtime)
        self.counter_save_interval = float(counter_save_interval)
        self.full_speed_limit = float(full_speed_limit)
        self._bits_per_byte = BITS_PER_BYTE
        self._line_credit = float(INPUT_BUFFER_BYTES)  # bytes the line may deliver now
        self._line_clock: float | None = None  # the hand's time of the last credit
        self._counters_due: float | None = None  # monotonic time by which the counters must be saved
        self._wake_read, self._wake_write = os.pipe()
        os.set_blocking(self._wake_read, False)
        os.set_blocking(self._wake_write, False)
        self._stopping = False
        self._poller = select.poll()
        self._poller.register(self._wake_read, select.POLLIN)
        self._running_firmware = False
        self._ptys: list[_Pty] = []  # the fresh pty and the session's
        self._fresh: _Pty | None = None  # behind the device's symlink, no client yet (Linux)
        self._session: _Pty | None = None  # the one client served
        self._pending_input = bytearray()  # what clients of closed ptys wrote, for the hand
        self._speaker: _Pty | None = None  # whose bytes the hand works on (None: a closed pty's)
        self._link_dir: str | None = None
        self._link_identity: tuple[int, int] | None = None  # (st_dev, st_ino) of the --link we made
        self._noted: set[str] = set()
        self.link = None
        try:
            first = self._add_pty()
            if first.watched:
                self._link_dir = _private_directory()
                self.device = os.path.join(self._link_dir, _DEVICE_NAME)
                os.symlink(first.device, self.device)
                self._fresh = first
            else:
                self.device = first.device
                self._session = self._speaker = first
            if link is not None:
                self._make_link(Path(link))
        except BaseException:
            self._close_fds()
            raise

    # -- life cycle ---------------------------------------------------------------------------

    def serve_forever(self) -> None:
        """Serve until `stop()` (from another thread) or `stop_from_signal_handler()`."""
        try:
            if self.realtime:
                self._serve_paced()
            else:
                self._serve_unpaced()
        except _Stopped:
            pass

    def stop_from_signal_handler(self, *_signal_args) -> None:
        """Signal handler (main thread): stop, abandoning a firmware run in progress, so a motion
        that never terminates cannot keep the server from exiting."""
        self.stop()
        if self._running_firmware:
            raise _Stopped()

    def stop(self) -> None:
        """Make `serve_forever` return soon; safe from a signal handler."""
        self._stopping = True
        try:
            os.write(self._wake_write, b"\0")
        except (BlockingIOError, OSError):
            pass  # the pipe is full or closed: the loop is waking up or gone already

    def close(self) -> None:
        """Remove --link if it is still the symlink this server made, remove the device's private
        directory, close the ptys."""
        if self.link is not None and self._link_identity is not None:
            try:
                info = os.lstat(self.link)
                if ((info.st_dev, info.st_ino) == self._link_identity and stat.S_ISLNK(info.st_mode)
                        and os.readlink(self.link) == self.device):
                    os.unlink(self.link)
            except OSError:
                pass  # already gone: leave whatever is there now
        self.link = None
        self._close_fds()

    def _close_fds(self) -> None:
        for pty in self._ptys:
            pty.close()
        self._ptys = []
        self._fresh = self._session = self._speaker = None
        if self._link_dir is not None:
            shutil.rmtree(self._link_dir, ignore_errors=True)
            self._link_dir = None
        for fd in (self._wake_read, self._wake_write):
            try:
                os.close(fd)
            except OSError:
                pass
        self._wake_read = self._wake_write = -1

    def _make_link(self, path: Path) -> None:
        """--link: a symlink at `path` to the device, made once (the device's own symlink is the
        one that moves from pty to pty). Only a link that a killed server left there is replaced;
        anything else at `path` is refused and left alone."""
        if os.path.lexists(path):
            if not _left_by_a_killed_server(path):
                raise FileExistsError(f"--link {path}: already exists; remove it or choose another path")
            path.unlink()
        os.symlink(self.device, path)
        info = os.lstat(path)
        self._link_identity = (info.st_dev, info.st_ino)
        self.link = path

    # -- the two serving loops -------------------------------------------------------------

    def _serve_unpaced(self) -> None:
        firmware = self.firmware
        while not self._stopping:
            # Waiting for input costs no simulated time (Contract 2): the wait stands for any
            # amount of line time, so the line's buffer is full again.
            self._line_credit, self._line_clock = float(INPUT_BUFFER_BYTES), firmware.time
            self._wait(self._seconds_to_counter_save())
            self._save_counters_if_due()
            data = self._read_input()
            if data:
                self._counters_changed()
                firmware.write(data)
                self._run_unpaced()
            self._flush_output()

    def _run_unpaced(self) -> None:
        """Run the firmware until it waits for input, in slices of UNPACED_SLICE_S, reading the
        line and writing the output between them: a ^C can abort a motion that never ends (the
        firmware drops other bytes during a motion, as the hand does), and the feedback of a
        stream of RealTime blocks flows while it lasts. A supervisory command past the full-speed
        limit is paced to the wall clock."""
        firmware = self.firmware
        started, pace = firmware.time, None
        self._running_firmware = True
        try:
            while not firmware.run_until_idle(UNPACED_SLICE_S) and not self._stopping:
                self._queue_output(firmware.read())
                self._flush_output()
                self._save_counters_if_due()
                if pace is None and not firmware.in_loop and firmware.time - started > self.full_speed_limit:
                    pace = (time.monotonic(), firmware.time)
                while pace is not None and not self._stopping:
                    ahead = (firmware.time - pace[1]) - (time.monotonic() - pace[0])
                    if ahead <= 0.0:
                        break
                    self._wait(ahead)
                    self._take_input()
                    self._flush_output()
                self._credit_line(firmware.time)
                self._take_input()
        finally:
            self._running_firmware = False
        self._queue_output(firmware.read())

    def _serve_paced(self) -> None:
        firmware = self.firmware
        anchor_wall, anchor_sim = time.monotonic(), firmware.time
        while not self._stopping:
            active = firmware.in_loop or not firmware.idle
            if active:
                self._counters_changed()
            self._wait(REALTIME_SLICE_S if active else self._seconds_to_counter_save())
            self._save_counters_if_due()
            now = time.monotonic()
            if not active:
                anchor_wall, anchor_sim = now, firmware.time  # idle time costs no simulated time
            self._credit_line(now)
            data = self._read_input()
            if data:
                firmware.write(data)
            due = anchor_sim + (now - anchor_wall) - firmware.time
            if due > REALTIME_MAX_LAG_S:
                anchor_wall += due - REALTIME_MAX_LAG_S
                due = REALTIME_MAX_LAG_S
            if due > 0.0 or data:
                firmware.run_for(min(max(due, 0.0), REALTIME_BURST_S))
            self._queue_output(firmware.read())
            self._flush_output()

    # -- the counters ------------------------------------------------------------------------

    def _counters_changed(self) -> None:
        if self._counters_due is None:
            self._counters_due = time.monotonic() + self.counter_save_interval

    def _seconds_to_counter_save(self) -> float | None:
        """How long the server may sleep before saving the counters (None: nothing to save)."""
        return None if self._counters_due is None else max(self._counters_due - time.monotonic(), 0.0)

    def _save_counters_if_due(self) -> None:
        if self._counters_due is not None and time.monotonic() >= self._counters_due:
            self._counters_due = None
            self.firmware.save_counters()

    # -- pty plumbing ------------------------------------------------------------------------

    def _wait(self, timeout_s: float | None) -> None:
        """Sleep until input can be taken, output can be written, a stop, or `timeout_s`."""
        room = self._input_room()
        if not room and self.realtime and self._line_credit < 1.0:
            # Input waits for the line's next byte (paced: the wall clock refills the credit).
            refill = (1.0 - self._line_credit) / self._line_bytes_per_second()
            timeout_s = refill if timeout_s is None else min(timeout_s, refill)
        session = self._session
        if session is not None:
            if session.waiting and self._hand_free():
                timeout_s = 0.0  # bytes that waited for the hand can go now
            events = (select.POLLIN if room else 0) | (select.POLLOUT if session.backlog else 0)
            if events != session.polled_events:
                self._poller.modify(session.leader, events)
                session.polled_events = events
        if self._link_dir is not None and self._fresh is None:
            timeout_s = FRESH_PTY_RETRY_S if timeout_s is None else min(timeout_s, FRESH_PTY_RETRY_S)
        self._poller.poll(None if timeout_s is None else timeout_s * 1000.0)
        try:
            os.read(self._wake_read, 64)
        except BlockingIOError:
            pass
        self._follow_clients()

    def _line_bytes_per_second(self) -> float:
        return self.firmware.baud / self._bits_per_byte

    def _credit_line(self, now: float) -> None:
        """The line delivers BAUD/10 bytes per second of the hand's time `now` (simulated
        unpaced, the wall clock paced), up to a buffer's worth."""
        if self._line_clock is not None and now > self._line_clock:
            self._line_credit = min(float(INPUT_BUFFER_BYTES),
                                    self._line_credit + (now - self._line_clock) * self._line_bytes_per_second())
        self._line_clock = now

    def _input_room(self) -> int:
        """Bytes that may be taken from the pty now: what the line delivered, and no more than the
        buffer ahead of the firmware (the session's waiting bytes included)."""
        waiting = len(self._session.waiting) if self._session is not None else 0
        return max(0, min(int(self._line_credit), INPUT_BUFFER_BYTES - self.firmware.pending_input - waiting))

    def _hand_free(self) -> bool:
        """Whether the hand has done all it was given (its replies are all out)."""
        return self.firmware.idle and not self.firmware.pending_input

    def _take_input(self) -> None:
        data = self._read_input()
        if data:
            self.firmware.write(data)

    def _read_input(self) -> bytes:
        """Input for the hand, no more than the line delivered (`_input_room`): first what clients
        of closed ptys wrote (their replies go nowhere), then the session's. The session's bytes
        wait while the hand works on someone else's, so that the replies it gets are its own; a
        ^C does not wait (it aborts that work, and its reply is the session's)."""
        self._follow_clients()
        room = self._input_room()
        if self._pending_input:
            data = bytes(self._pending_input[:room])
            del self._pending_input[:room]
            self._line_credit -= len(data)
            if data:
                self._speaker = None
            return data
        session = self._session
        if session is None:
            return b""
        if room > 0:
            taken = session.read(room)
            self._line_credit -= len(taken)
            session.waiting += taken
        if not session.waiting:
            return b""
        if self._speaker is not session:
            if not (self._hand_free() or CTRL_C in session.waiting):
                return b""
            self._queue_output(self.firmware.read())  # what the hand said so far was not the session's
            self._speaker = session
        data = bytes(session.waiting)
        session.waiting.clear()
        return data

    def _queue_output(self, data: bytes) -> None:
        pty = self._speaker
        if data and pty is not None and pty is self._session:
            pty.backlog += data
            overflow = len(pty.backlog) - OUTPUT_BACKLOG_LIMIT
            if overflow > 0:
                del pty.backlog[:overflow]

    def _flush_output(self) -> None:
        pty = self._session
        while pty is not None and pty.backlog:
            try:
                written = os.write(pty.leader, pty.backlog)
            except BlockingIOError:
                break
            except OSError:  # the client has just closed the device: the session ends at the next look
                pty.backlog.clear()
                break
            del pty.backlog[:written]
