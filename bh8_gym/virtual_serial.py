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

A client may close and reopen the device without losing the hand's state. Like a real port, a
closed device receives nothing and a fresh open starts empty: nothing a client left unread (the
reply to a ^C sent just before closing, a prompt it stopped reading) reaches the next open, however
fast it follows (Barrett's C++ API closes and reopens at once to discard buffers when it changes
the baud rate). A pty cannot drop bytes when its client closes it, so on Linux the printed device
is a symlink (in a private directory under /dev/shm) to a pty no client has opened yet: as soon as a
client opens it, inotify wakes the server (`_OpenWatch`), which points the symlink (and `--link`)
at a fresh pty, and the next open gets that one. The hand answers on the pty its input came from;
a pty is closed when its client closes it (the leader's hang-up tells), and what was left in it
goes with it. Elsewhere the device is the pty itself, held open by the server, and unread bytes
wait for the next reader. The hand itself keeps its state: a client killed in the middle of a
RealTime control block leaves the firmware waiting for that block's data bytes, as a real hand does
(docs/clients.md says how to recover).
"""
from __future__ import annotations

import ctypes
import ctypes.util
import errno
import os
import select
import shutil
import sys
import tempfile
import time
from pathlib import Path

from bh8_gym.protocol import BITS_PER_BYTE


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
    """Wakes the server when a client opens the pty follower (inotify IN_OPEN on the device).

    Only a wake-up: inotify merges identical events that are not yet read, so it cannot count
    clients; the leader's hang-up (the kernel's count) says whether any client has the device open.
    Linux only; `create` returns None where inotify is missing.
    """

    _IN_OPEN = 0x20

    def __init__(self, fd: int):
        self.fd = fd

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
        if libc.inotify_add_watch(fd, os.fsencode(path), cls._IN_OPEN) < 0:
            os.close(fd)
            return None
        return cls(fd)

    def drain(self) -> None:
        """Read the pending events (their content does not matter)."""
        while True:
            try:
                if not os.read(self.fd, 4096):
                    return
            except BlockingIOError:
                return

    def close(self) -> None:
        os.close(self.fd)


class _Pty:
    """One pseudo-terminal: its leader, what it owes its client, whether a client has it open.

    With an open watch (Linux) the server holds no follower fd, so the leader hangs up while no
    client has the device open; without one the follower stays open and the pty counts as
    always connected."""

    def __init__(self):
        self.leader, self.follower, self.device = open_raw_pty()
        self.backlog = bytearray()
        self.polled_events = 0  # the poll events registered for the leader while a client has it open
        self.watch = _OpenWatch.create(self.device)
        self.client = self.watch is None
        if self.watch is not None:
            self._hangup = select.poll()
            self._hangup.register(self.leader, 0)
            os.close(self.follower)
            self.follower = -1

    def client_present(self) -> bool:
        """Whether a client has the device open now (reads the open watch's wake-ups)."""
        if self.watch is None:
            return True
        self.watch.drain()
        return not self._hangup.poll(0)

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
        if self.watch is not None:
            self.watch.close()
            self.watch = None
        for fd in (self.leader, self.follower):
            try:
                os.close(fd)
            except OSError:
                pass
        self.leader = self.follower = -1


def _private_directory() -> str:
    """A new directory only its owner can enter, for the device's symlink: under /dev/shm where
    there is one (the printed device then still starts with /dev/, as pty paths do), else the
    system's temporary directory. Named after the server's pid, so the directories of servers
    that were killed (no clean exit removes them) are removed here."""
    for parent in ("/dev/shm", tempfile.gettempdir()):
        try:
            _remove_dead_servers_directories(parent)
            return tempfile.mkdtemp(prefix=f"bh8-serve-{os.getpid()}-", dir=parent)
        except OSError:
            continue
    raise OSError("cannot make a private directory for the device's symlink")


def _remove_dead_servers_directories(parent: str) -> None:
    for entry in os.scandir(parent):
        fields = entry.name.split("-")
        if len(fields) < 4 or fields[:2] != ["bh8", "serve"] or not fields[2].isdigit():
            continue
        try:
            if entry.stat(follow_symlinks=False).st_uid != os.getuid():
                continue
            os.kill(int(fields[2]), 0)
        except ProcessLookupError:
            shutil.rmtree(entry.path, ignore_errors=True)  # its server is gone
        except OSError:
            continue  # alive (another user's pid: PermissionError) or vanished meanwhile


class _Stopped(Exception):
    """Raised by the signal handler to abandon a firmware run in progress."""


class PtyServer:
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
        self._ptys: list[_Pty] = []
        self._pending_input = bytearray()  # what the client of a pty closed since wrote before closing
        self._links: list[Path] = []  # the printed device (Linux) and --link: all at self._fresh
        self._link_dir: str | None = None
        self.link = None
        try:
            self._fresh = self._add_pty()
            self._speaker: _Pty | None = self._fresh  # the pty the last input came from
            if self._fresh.watch is None:
                self.device = self._fresh.device
            else:
                self._link_dir = _private_directory()
                self.device = os.path.join(self._link_dir, "ttyBH8")
                os.symlink(self._fresh.device, self.device)
                self._links.append(Path(self.device))
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
        """Remove the device's and --link's symlinks (if still ours) and close the ptys."""
        ours = {pty.device for pty in self._ptys}
        for path in self._links:
            try:
                if os.readlink(path) in ours:
                    os.unlink(path)
            except OSError:
                pass  # already gone or replaced by someone else: leave it
        self._links = []
        self.link = None
        self._close_fds()

    def _close_fds(self) -> None:
        for pty in self._ptys:
            pty.close()
        self._ptys = []
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
        # Left behind by a server that was killed: dangling, or pointing at a pty just opened here
        # (the kernel reuses the freed pty numbers; no live server can hold these).
        if path.is_symlink() and (not path.exists() or os.readlink(path) == self._fresh.device):
            path.unlink()
        elif path.exists() or path.is_symlink():
            raise FileExistsError(f"--link {path}: already exists; remove it or choose another path")
        os.symlink(self._fresh.device, path)
        self._links.append(path)
        self.link = path

    def _add_pty(self) -> _Pty:
        pty = _Pty()
        self._ptys.append(pty)
        self._poller.register(pty.leader if pty.watch is None else pty.watch.fd, select.POLLIN)
        return pty

    def _replace_fresh_pty(self) -> None:
        """The fresh pty got a client: point the device's and --link's symlinks at a new one, so
        the next open (this client reopening to discard buffers, the next program) starts empty
        whatever this client leaves unread. Each link is replaced atomically (rename)."""
        fresh = self._add_pty()
        for path in self._links:
            temporary = path.with_name(f".{path.name}.{os.getpid()}")
            try:
                temporary.unlink(missing_ok=True)
                os.symlink(fresh.device, temporary)
                os.replace(temporary, path)
            except OSError as error:
                print(f"bh8 serve: cannot repoint {path}: {error}", file=sys.stderr, flush=True)
        self._fresh = fresh

    def _drop_pty(self, pty: _Pty) -> None:
        """Close a pty whose client closed it; what it still held for a reader goes with it. What
        the client wrote before closing still reaches the hand (the replies go nowhere)."""
        self._pending_input += pty.read(INPUT_BUFFER_BYTES - len(self._pending_input))
        for fd in (pty.leader, pty.watch.fd if pty.watch is not None else -1):
            try:
                self._poller.unregister(fd)
            except (KeyError, ValueError):
                pass
        pty.close()
        self._ptys.remove(pty)
        if self._speaker is pty:
            self._speaker = None

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
        for pty in self._ptys:
            events = (select.POLLIN if room else 0) | (select.POLLOUT if pty.backlog else 0)
            if pty.client and events != pty.polled_events:
                self._poller.modify(pty.leader, events)
                pty.polled_events = events
        self._poller.poll(None if timeout_s is None else timeout_s * 1000.0)
        try:
            os.read(self._wake_read, 64)
        except BlockingIOError:
            pass
        self._follow_clients()

    def _follow_clients(self) -> None:
        """Track which ptys a client has open: a pty that got its first client is replaced by a
        fresh one behind the symlinks; one whose client closed is closed (on a pty the unread
        bytes would wait for the next reader). While a client has it open the leader is polled
        (without a client it would report a hang-up at every poll)."""
        for pty in tuple(self._ptys):
            if pty.watch is None:
                continue
            present = pty.client_present()
            if present == pty.client:
                continue
            pty.client = present
            if present:
                self._poller.register(pty.leader, select.POLLIN)
                pty.polled_events = select.POLLIN
                if pty is self._fresh:
                    self._replace_fresh_pty()
            else:
                self._poller.unregister(pty.leader)
                self._drop_pty(pty)

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
        buffer ahead of the firmware."""
        return max(0, min(int(self._line_credit), INPUT_BUFFER_BYTES - self.firmware.pending_input))

    def _take_input(self) -> None:
        data = self._read_input()
        if data:
            self.firmware.write(data)

    def _read_input(self) -> bytes:
        """Input from one pty at a time (a closed one's last bytes first), so the hand answers on
        the pty each command came from; no more than the line delivered (`_input_room`)."""
        self._follow_clients()
        room = self._input_room()
        data = b""
        if self._pending_input:
            data = bytes(self._pending_input[:room])
            del self._pending_input[:room]
            self._speaker = None  # its pty is closed: the replies go nowhere, as on a closed port
        elif room > 0:
            for pty in self._ptys:
                data = pty.read(room)
                if data:
                    self._speaker = pty
                    break
        self._line_credit -= len(data)
        return data

    def _queue_output(self, data: bytes) -> None:
        self._follow_clients()
        pty = self._speaker
        if data and pty is not None and pty.client:
            pty.backlog += data
            overflow = len(pty.backlog) - OUTPUT_BACKLOG_LIMIT
            if overflow > 0:
                del pty.backlog[:overflow]

    def _flush_output(self) -> None:
        for pty in self._ptys:
            while pty.backlog:
                try:
                    written = os.write(pty.leader, pty.backlog)
                except BlockingIOError:
                    break
                del pty.backlog[:written]
