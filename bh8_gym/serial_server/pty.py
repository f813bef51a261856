"""The pty behind `bh8 serve`'s device: one raw pseudo-terminal (`Pty`), what inotify says its
clients do with it (`OpenWatch`, `OpenHistory`), and how many descriptors hold it (`holders`).

On Linux the server holds no follower descriptor, so the leader hangs up while no client has the
device open; inotify reports every open, write and close of the follower, in order, and /proc
counts the descriptors when two events in a row merge into one. `clients` decides from these what
becomes of each pty; `server` moves the bytes.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import errno
import os
import select
import struct
import sys
import time

# Bytes taken from the pty ahead of what the firmware has consumed, as a host serial driver's
# buffer: past this the server stops reading and the pty's writer blocks (backpressure).
INPUT_BUFFER_BYTES = 4096
READ_CHUNK = 4096
# More than a pty holds for its leader to read (the kernel's 64 KiB flip buffer and 4 KiB line
# discipline): reading this much empties it.
PTY_BUFFER_BYTES = 1 << 17


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


class OpenWatch:
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
    def create(cls, path: str) -> "OpenWatch | None":
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


class OpenHistory:
    """What a pty's events say about its clients: whether any opened it, whether one closed it after
    the last open (two held it at once), and whether the clients before the last open wrote (their
    bytes would then be ahead of the last one's in the pty)."""

    def __init__(self):
        self.opens = 0
        self.closes = 0
        self.closed_since_open = False
        self.written_before_open = False
        self.written_since_open = False
        self.written_before_close = False  # since the last open: a write, then a close (whose bytes?)

    def add(self, masks: list[int]) -> None:
        for mask in masks:
            if mask & OpenWatch.IN_Q_OVERFLOW:  # events lost: assume the worst
                self.opens += 1
                self.closes += 1
                self.closed_since_open = self.written_before_open = self.written_since_open = True
                self.written_before_close = True
            if mask & OpenWatch.IN_OPEN:
                self.opens += 1
                self.written_before_open |= self.written_since_open
                self.written_since_open = self.closed_since_open = self.written_before_close = False
            if mask & OpenWatch.IN_MODIFY:
                self.written_since_open = True
            if mask & OpenWatch.IN_CLOSE:
                self.closes += 1
                self.closed_since_open = True
                self.written_before_close |= self.written_since_open


class Pty:
    """One pseudo-terminal: its leader, what it owes its client, whether a client has it open.

    With an open watch (Linux) the server holds no follower fd, so the leader hangs up while no
    client has the device open; without one the follower stays open and the pty counts as always
    held (it is then the one device all clients share)."""

    def __init__(self):
        self.leader, self.follower, self.device = open_raw_pty()
        self.backlog = bytearray()
        self.polled_events = 0  # the poll events registered for the leader while it is a session
        self.waiting = bytearray()  # the client's bytes taken from the pty, waiting for the hand
        self.history = OpenHistory()
        self.accepted_opens = 0  # the opens seen when it became the session
        self.watch = OpenWatch.create(self.device)
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
                chunk = os.read(self.leader, min(limit, READ_CHUNK))
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


def descriptors_open_on(device: str) -> list[tuple[int, int]]:
    """(pid, descriptor number) of each file descriptor that has `device` open, of the processes
    this user may look into (all, for root), from /proc (empty where there is none). A name that
    matches is checked to be the same node: a process in another container may have its own
    /dev/pts with the same numbers."""
    try:
        node = os.stat(device)
        pids = [entry for entry in os.listdir("/proc") if entry.isdigit()]
    except OSError:
        return []
    found = []
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
                    found.append((int(pid), int(descriptor)))
            except OSError:
                continue
    return found


def _ancestors(pid: int) -> list[int]:
    """The parent, grandparent, ... of `pid` (as far as /proc shows them)."""
    chain = []
    while len(chain) < _ANCESTRY_LIMIT:
        try:
            with open(f"/proc/{pid}/stat") as handle:
                pid = int(handle.read().rsplit(")", 1)[1].split()[1])  # field 4, after the name
        except (OSError, ValueError, IndexError):
            break
        if pid <= 1:
            break
        chain.append(pid)
    return chain


def clients_of(descriptors: list[tuple[int, int]]) -> list[int]:
    """One pid per client among (pid, descriptor) pairs: a descriptor that a process inherited from
    an ancestor holding the same number (fork keeps it: a client that starts a worker or a
    subprocess just after opening the port) is that client's, not a second client's. Two
    descriptors in one process are two opens (or a dup, which cannot be told from two opens)."""
    held = set(descriptors)
    return [pid for pid, number in descriptors
            if not any((ancestor, number) in held for ancestor in _ancestors(pid))]


# A descriptor appears in /proc a moment after the open that inotify reported: how often and how
# long apart the count is retried before a held pty counts as held by one client we cannot see
# (another user's: root may open our ptys).
_DESCRIPTOR_COUNT_TRIES = 5
_DESCRIPTOR_COUNT_PAUSE_S = 0.002
# How far up the process tree an inherited descriptor's first holder is looked for.
_ANCESTRY_LIMIT = 64


def holders(pty: Pty) -> list[int | None]:
    """The pid of each client that holds a held pty (at least one entry; None: a process we cannot
    see, such as another user's: root may open our ptys). Processes that inherited a client's
    descriptor are that client (`clients_of`)."""
    for _ in range(_DESCRIPTOR_COUNT_TRIES):
        found = descriptors_open_on(pty.device)
        if found:
            return clients_of(found)
        time.sleep(_DESCRIPTOR_COUNT_PAUSE_S)
    return [None]
