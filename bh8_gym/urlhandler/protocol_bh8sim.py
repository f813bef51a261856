"""pyserial handler for `bh8sim://`: a simulated BarrettHand in this process, no pty needed.

URL: ``bh8sim://[?option=value[&option=value...]]`` with options

- ``seed=N``: seed of the plant's randomised constants (default 0);
- ``firmware=4.3|4.4``: firmware profile (default 4.3, SPEC.md §7);
- ``state=DIR``: the non-volatile store (default: a temporary directory made on open and removed
  on close, so every open without ``state`` is a factory-fresh hand and tests stay independent);
- ``object=SPEC`` (repeatable): an object placed as by ``bh8 serve --object SPEC`` (percent-encode
  any ``&``, ``#`` or ``%`` in it);
- ``hand=FILE``: the hand's parameters from a hand file, as ``bh8 serve --hand-parameters FILE``.

Time: the simulated clock advances only while the host waits for the hand and the hand is busy,
so replies come as fast as the physics runs and are reproducible for a given sequence of calls;
an idle hand's clock stands still, as `bh8 serve`'s does. ``read(n)`` runs the
firmware until n bytes exist, the firmware waits for input (no further byte can come), or the
port's ``timeout`` has passed in SIMULATED seconds; it never blocks on the wall clock, so it cannot
hang. With ``timeout=None`` a read that lacks bytes runs the firmware until it waits for input,
exactly as `bh8 serve` does after each read, so both give identical bytes. With a finite timeout
a ^C written between reads aborts a running motion (§5.5 case 4), as on the wire. A poll that
finds nothing (``in_waiting``, or ``read`` with timeout 0) lets a busy hand run
``POLL_ADVANCE_S`` of simulated time, so polling loops progress too. The port's baudrate is not
checked against the hand's BAUD (a real mismatch would garble bytes); the RealTime cycle time
follows the hand's BAUD (PSET BAUD), as on the wire.
"""
from __future__ import annotations

import math
import shutil
import tempfile
import urllib.parse

from serial.serialutil import PortNotOpenError, SerialBase, SerialException, to_bytes

from bh8_gym.protocol import FIRMWARE_PROFILES
from bh8_gym.simulator import build_firmware, shutdown_firmware

SCHEME = "bh8sim"
# Simulated seconds run per firmware call while a read with a timeout waits for bytes: a reply is
# picked up within this of being sent; short enough to be negligible, long enough to keep call
# overhead small.
RUN_CHUNK_S = 0.005
# Simulated seconds an empty poll (in_waiting, read with timeout 0) lets a busy hand run.
POLL_ADVANCE_S = 0.01


def parse_url(url: str) -> dict:
    """The options of a bh8sim:// URL: {"seed": int, "firmware": str, "state": str|None, "objects": tuple,
    "hand": str|None}.

    Raises SerialException naming the offending part.
    """
    parts = urllib.parse.urlsplit(url)
    if parts.scheme.lower() != SCHEME:
        raise SerialException(f"expected a URL of the form {SCHEME}://?seed=N&firmware=4.3&state=DIR, got {url!r}")
    if parts.netloc or parts.path not in ("", "/"):
        raise SerialException(f"{SCHEME}:// takes options only (after '?'), got {parts.netloc + parts.path!r} in {url!r}")
    options = {"seed": 0, "firmware": "4.3", "state": None, "objects": (), "hand": None}
    objects = []
    try:
        pairs = urllib.parse.parse_qsl(parts.query, keep_blank_values=True, strict_parsing=bool(parts.query))
    except ValueError as error:
        raise SerialException(f"malformed options in {url!r}: {error}") from None
    repeated = sorted({name for name, _ in pairs if name != "object" and [n for n, _ in pairs].count(name) > 1})
    if repeated:  # which one would win is a guess the user should not have to make
        raise SerialException(f"option {repeated[0]!r} given more than once in {url!r}; only object may repeat")
    for name, value in pairs:
        if name == "seed":
            try:
                options["seed"] = int(value)
            except ValueError:
                options["seed"] = -1
            if options["seed"] < 0:
                raise SerialException(f"seed must be a non-negative integer, got {value!r} in {url!r}")
        elif name == "firmware":
            if value not in FIRMWARE_PROFILES:
                raise SerialException(f"firmware must be one of {FIRMWARE_PROFILES}, got {value!r} in {url!r}")
            options["firmware"] = value
        elif name == "state":
            if not value:
                raise SerialException(f"state needs a directory, got an empty value in {url!r}")
            options["state"] = value
        elif name == "object":
            objects.append(value)
        elif name == "hand":
            if not value:
                raise SerialException(f"hand needs a hand file, got an empty value in {url!r}")
            options["hand"] = value
        else:
            raise SerialException(
                f"unknown option {name!r} in {url!r}; known: seed, firmware, state, object, hand"
            )
    options["objects"] = tuple(objects)
    return options


class Serial(SerialBase):
    """A pyserial port whose other end is an in-process `Firmware` (attribute `firmware`)."""

    def __init__(self, *args, **kwargs):
        self.firmware = None
        self._received = bytearray()
        self._temporary_state = None
        super().__init__(*args, **kwargs)

    def open(self):
        if self.is_open:
            raise SerialException("Port is already open.")
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        options = parse_url(self._port)
        state = options["state"]
        if state is None:
            self._temporary_state = tempfile.mkdtemp(prefix="bh8sim-")
            state = self._temporary_state
        try:
            hand = None
            if options["hand"] is not None:
                from bh8_gym.hand_file import load_hand_parameters

                hand = load_hand_parameters(options["hand"]).values
            self.firmware = build_firmware(state, options["firmware"], options["seed"], options["objects"], hand=hand)
        except (ValueError, OSError) as error:
            self._remove_temporary_state()
            raise SerialException(f"cannot open {self._port!r}: {error}") from error
        except BaseException:
            self._remove_temporary_state()
            raise
        self._received.clear()
        self.is_open = True

    def close(self):
        if self.is_open:
            self.is_open = False
            try:
                shutdown_firmware(self.firmware)
            finally:
                self.firmware = None
                self._remove_temporary_state()

    def _remove_temporary_state(self):
        if self._temporary_state is not None:
            shutil.rmtree(self._temporary_state, ignore_errors=True)
            self._temporary_state = None

    def _reconfigure_port(self, *args, **kwargs):
        """Line settings do not reach the simulated hand (see the module docstring)."""

    # -- data ------------------------------------------------------------------------------

    def _run(self, budget_s: float, wanted: int) -> None:
        """Let the hand produce bytes until `wanted` are buffered, it waits for input, or
        `budget_s` simulated seconds have passed (math.inf: run until it waits for input)."""
        firmware = self.firmware
        received = self._received
        received += firmware.read()
        if len(received) >= wanted or firmware.idle:
            return
        if budget_s == math.inf:
            firmware.run_until_idle()
            received += firmware.read()
            return
        firmware.run_for(0.0)  # commands without motion answer at once, costing no time
        received += firmware.read()
        while len(received) < wanted and budget_s > 0.0 and not firmware.idle:
            step = RUN_CHUNK_S if budget_s > RUN_CHUNK_S else budget_s
            # Up to `step`, but not past the moment the hand waits for input: its clock then stands
            # still until the host writes, as `bh8 serve`'s does, so polls cost no simulated time
            # and a log recorded here replays exactly (bh8 calibrate).
            firmware.run_until_idle(step)
            budget_s -= step
            received += firmware.read()

    @property
    def in_waiting(self):
        if not self.is_open:
            raise PortNotOpenError()
        self._run(POLL_ADVANCE_S if not self._received else 0.0, 1)
        return len(self._received)

    def read(self, size=1):
        if not self.is_open:
            raise PortNotOpenError()
        if size <= 0:
            return b""
        timeout = self._timeout
        budget = math.inf if timeout is None else (POLL_ADVANCE_S if timeout == 0 else float(timeout))
        self._run(budget, size)
        data = bytes(self._received[:size])
        del self._received[:size]
        return data

    def write(self, data):
        if not self.is_open:
            raise PortNotOpenError()
        data = to_bytes(data)
        self.firmware.write(data)
        return len(data)

    def flush(self):
        """Written bytes reach the firmware at once; nothing to wait for."""

    def reset_input_buffer(self):
        if not self.is_open:
            raise PortNotOpenError()
        self.firmware.read()
        self._received.clear()

    def reset_output_buffer(self):
        """Written bytes reach the firmware at once; nothing is ever pending."""
        if not self.is_open:
            raise PortNotOpenError()

    @property
    def out_waiting(self):
        if not self.is_open:
            raise PortNotOpenError()
        return 0

    # Modem lines: the manual documents no handshaking (§9.1: RS-232C, 8N1), so none is emulated.
    def _update_rts_state(self):
        pass

    def _update_dtr_state(self):
        pass

    def _update_break_state(self):
        pass

    @property
    def cts(self):
        return True

    @property
    def dsr(self):
        return True

    @property
    def ri(self):
        return False

    @property
    def cd(self):
        return True
