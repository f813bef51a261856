"""The simulated hand's firmware on a pseudo-terminal: the server behind `bh8 serve`.

Three rooms (docs/architecture.md Contract 3): `server` (`PtyServer`: the serving loops, simulated
time against the line's pace, the bytes between pty and firmware), `clients` (`PortClients`: the
device as a port, one fresh pty behind it, at most one session; `_hand_session_to_client` is where
a pty becomes the session) and `pty` (`Pty`: one raw pseudo-terminal and what inotify tells of its
clients).
"""
from bh8_gym.serial_server.server import PtyServer

__all__ = ["PtyServer"]
