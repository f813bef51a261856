"""The device as a serial port: `PortClients`, the part of `PtyServer` that keeps its ptys and
clients (docs/architecture.md Contract 3).

A client may close and reopen the device without losing the hand's state. The device is a port:
one line, one client at a time, and every open starts a clean session.
- Fresh: a closed port receives nothing, and nothing a client left unread (the reply to a ^C sent
  just before closing, a prompt it stopped reading) reaches the next open, however fast it follows
  (Barrett's C++ API closes and reopens at once to discard buffers when it changes the baud rate).
  A pty cannot drop bytes when its client closes it, so on Linux the printed device is a symlink (in
  a private directory under /dev/shm) to a pty no client has opened yet. inotify tells the server
  of every open, write and close of that pty (`OpenWatch`); once a client has opened it, the
  server points the symlink at a new pty, so the next open gets that one, and makes this pty's node
  mode 000 so that nobody else can open it by its /dev/pts name (root can: its open then ends the
  session as below). `--link` is a fixed symlink to the printed device.
- Exclusive: the server serves one pty (the session) at a time. A pty opened while another client
  has the port, or found with two clients in it (they opened the device in the instant before the
  server moved it on: two opens, or a close after the last open, or two clients' descriptors on it in
  /proc; a copy a client's child inherited by fork is the client's, `pty.clients_of`),
  is hung up before anything is read from it or written to it: those clients see the port go (EOF,
  EIO; an open after the mode change fails with EACCES) and may open it again. Nothing they wrote
  reaches the hand, and neither reads the other's replies.
- Fair: a refused client waits in line (by pid, for WAITING_SECONDS): while it does, a client that
  had the port in that time is hung up when it opens the device again, and the waiting client is
  served once it alone holds its pty, even if others opened that pty in the moment before the
  server closed it to them (their bytes, if they wrote any, would come first). Clients opening and
  closing the device in a tight loop otherwise took every session, and another never got one.
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

Where a pty is handed to its client as the session: `PortClients._hand_session_to_client`, after
`_settle` has found that one client holds it and the port is free.
"""
from __future__ import annotations

import contextlib
import os
import select
import shutil
import sys
import tempfile
import time
from pathlib import Path

from bh8_gym.serial_server.pty import INPUT_BUFFER_BYTES, PTY_BUFFER_BYTES, OpenWatch, Pty, holders

# How long a refused client counts as waiting for the port (it tries again within that, or has given up).
WAITING_SECONDS = 2.0
_IN_USE = ("a second client opened the device while it was in use; the port is exclusive, so that "
           "client was hung up and what it wrote went nowhere")
_WAITING = ("a client that had the port just now opened it again while another was waiting for it; it was "
            "hung up so that the other goes first")
_SHARED = ("clients opened the device at the same moment, before the server could give each its own pty; "
           "that pty was hung up before either was answered (so neither reads the other's replies); open it again")


DEVICE_NAME = "ttyBH8"
_PRIVATE_PREFIX = "bh8-serve-"


def private_directory() -> str:
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


def left_by_a_killed_server(path: Path) -> bool:
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
    return name == DEVICE_NAME and pid is not None and not _server_alive(pid)


class PortClients:
    """The device as a serial port, a part of `PtyServer` (a mixin on its ptys, poller and
    pending input): one fresh pty behind the device's symlink, at most one session, and what
    becomes of every pty a client opens (served, a closed port's, or refused; module docstring)."""

    def _add_pty(self) -> Pty:
        pty = Pty()
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
            fresh = Pty()
        except OSError as error:
            self._note(f"cannot make a new pty for the next client ({error}); retrying", once=False)
            return
        if not fresh.watched:
            fresh.close()
            self._note("cannot watch a new pty for the next client (no inotify instance left); retrying", once=False)
            return
        try:
            temporary = os.path.join(self._link_dir, f".{DEVICE_NAME}.new")
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

    def _hand_session_to_client(self, pty: Pty) -> None:
        """The pty of the one client served from now on; its watch now tells only of another open."""
        pty.watch.watch_for(OpenWatch.IN_OPEN)
        pty.accepted_opens = max(pty.history.opens, 1)  # 0: its client's own open is still to come
        self._poller.register(pty.leader, select.POLLIN)
        pty.polled_events = select.POLLIN
        self._session = pty

    def _end_session(self) -> None:
        """The session's client closed the device. What it wrote still reaches the hand (as bytes
        sent on a line do), the replies go nowhere, and what the pty held for a reader goes with it."""
        pty, self._session = self._session, None
        if self._session_client is not None:
            self._recent[self._session_client] = time.monotonic()
        self._pending_input += pty.waiting
        self._pending_input += pty.read(INPUT_BUFFER_BYTES - len(self._pending_input))
        self._remove_pty(pty)

    def _orphan(self, pty: Pty) -> None:
        """A pty whose clients opened and closed it before the server looked: a closed port's
        client, whose bytes reach the hand and whose replies go nowhere."""
        self._pending_input += pty.read(INPUT_BUFFER_BYTES - len(self._pending_input))
        self._remove_pty(pty)

    def _refuse(self, pty: Pty, why: str) -> None:
        """Hang the pty up unread: its clients see the port go (EOF, EIO), nothing they wrote
        reaches the hand and nothing reaches them."""
        self._remove_pty(pty)
        self._note(why)

    def _remove_pty(self, pty: Pty) -> None:
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

    def _settle(self, pty: Pty) -> None:
        """What a pty that clients have opened becomes: the session if one client holds it and the
        port was free; a closed port's pty if they have all gone; else refused. A client that
        shared its pty with one that left without writing keeps it (the other left nothing in it);
        and while a refused client waits, the one that just had the port does not get it again
        (`_jumps_the_queue`)."""
        history = pty.history
        if not pty.held():
            if self._session is None:
                self._orphan(pty)
            else:
                self._refuse(pty, _IN_USE)
            return
        pids = holders(pty)
        if self._session is not None:
            self._queue(pids)
            self._refuse(pty, _IN_USE)
            return
        if len(pids) > 1:
            self._queue(pids)
            self._refuse(pty, _SHARED)
            return
        if self._jumps_the_queue(pids[0]):
            self._refuse(pty, _WAITING)
            return
        # A client refused before and alone in its pty now is served even if others opened it
        # meanwhile (clients opening the device in a loop open every pty in the moment before the
        # server closes it to them: otherwise it never gets a session). Their bytes, if they wrote
        # any, would come before its own: the price of not starving it.
        if not self._waited(pids[0]):
            if history.closed_since_open and history.written_before_close:
                self._queue(pids)
                self._refuse(pty, _SHARED)
                return
            if history.written_before_open:
                # Its client opened it after others had opened, written and closed it (before the server
                # looked): their bytes come first in the pty. They are all theirs unless it wrote too.
                earlier = pty.read(PTY_BUFFER_BYTES)
                pty.look()
                if history.written_since_open or history.closed_since_open:
                    self._queue(pids)
                    self._refuse(pty, _SHARED)
                    return
                self._pending_input += earlier[:max(0, INPUT_BUFFER_BYTES - len(self._pending_input))]
        self._waiting.pop(pids[0], None)
        self._session_client = pids[0]
        self._hand_session_to_client(pty)

    def _waited(self, pid) -> bool:
        """Whether `pid` was refused within WAITING_SECONDS and has not had the port since."""
        return pid is not None and pid in self._waiting and pid not in self._recent

    def _queue(self, pids: list) -> None:
        """Refused clients (by pid) wait for the port: `_jumps_the_queue` keeps it for them."""
        now = time.monotonic()
        for pid in pids:
            if pid is not None:
                self._waiting[pid] = now

    def _jumps_the_queue(self, pid) -> bool:
        """Whether `pid` had the port within WAITING_SECONDS while a client that has not was refused
        in that time and may still be trying: clients opening and closing the device in a tight
        loop took every session, and another never got one. A client whose pid we cannot see
        (another user's) is never held back, nor one of several threads of one process."""
        now = time.monotonic()
        self._waiting = {other: when for other, when in self._waiting.items() if now - when < WAITING_SECONDS}
        self._recent = {other: when for other, when in self._recent.items() if now - when < WAITING_SECONDS}
        return pid in self._recent and any(other not in self._recent for other in self._waiting)
