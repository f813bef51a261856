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
The device as a port (one client at a time, every open a clean session) is `clients.PortClients`,
the pty itself `pty.Pty`.
"""
from __future__ import annotations

import os
import select
import shutil
import stat
import time
from pathlib import Path

from bh8_gym.protocol import BITS_PER_BYTE, CTRL_C
from bh8_gym.serial_server.clients import DEVICE_NAME, PortClients, left_by_a_killed_server, private_directory
from bh8_gym.serial_server.pty import INPUT_BUFFER_BYTES, Pty



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
# Our choice: the longest the never-reset counters (OD, PTEMP, UPSECS) go unsaved after the hand
# did something; they are "maintained through power failures" (manual §5.3.2, §5.4.2), so a kill
# of the server loses at most this much.
COUNTER_SAVE_INTERVAL_S = 10.0
# Bytes kept for a client that is not reading. Past this the oldest are dropped, as a host UART
# with nobody reading overruns; a reopening client flushes its input anyway (pyserial does).
OUTPUT_BACKLOG_LIMIT = 1 << 20
# Seconds between attempts to put a new pty behind the device after one failed (out of ptys).
FRESH_PTY_RETRY_S = 1.0


class _Stopped(Exception):
    """Raised by the signal handler to abandon a firmware run in progress."""



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
        self._ptys: list[Pty] = []  # the fresh pty and the session's
        self._fresh: Pty | None = None  # behind the device's symlink, no client yet (Linux)
        self._session: Pty | None = None  # the one client served
        self._pending_input = bytearray()  # what clients of closed ptys wrote, for the hand
        self._speaker: Pty | None = None  # whose bytes the hand works on (None: a closed pty's)
        self._link_dir: str | None = None
        self._link_identity: tuple[int, int] | None = None  # (st_dev, st_ino) of the --link we made
        self._noted: set[str] = set()
        self._waiting: dict[int, float] = {}  # refused clients' pids, when each was last refused
        self._recent: dict[int, float] = {}  # pids of recent sessions, when each ended
        self._session_client: int | None = None  # the session's pid (None: unknown)
        self.link = None
        try:
            first = self._add_pty()
            if first.watched:
                self._link_dir = private_directory()
                self.device = os.path.join(self._link_dir, DEVICE_NAME)
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
            if not left_by_a_killed_server(path):
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
