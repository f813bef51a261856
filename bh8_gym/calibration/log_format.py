"""The calibration log (`bh8 calibrate record -o hand-log.jsonl`): one JSON object per line, written
a record at a time and read back strictly.

Line 1 is the header: the log format's version, the excitation (its version, scale, mounting and
calibration object), the hand (VERS, firmware profile, serial number, the parameters it was found
with) and the port. Every later line is one record, in the order it happened:

- ``command``: a supervisory line sent, the hand's reply lines, its ERR code (or null), the host's
  monotonic time `t` when it was sent and `dt`, the seconds until the reply's prompt;
- ``baud``: the hand and host switched to `rate` (PSET BAUD);
- ``loop``: LOOP entered on `motors`, with the block `layout` the hand's flags give;
- ``block``: one RealTime cycle: the control block sent and the feedback block received (hex), `t`, `dt`;
- ``loop_exit``: ^C left LOOP;
- ``clock``: what the clock probe found: "wall" (the hand's motors run while the host waits, a real
  hand) or "line" (its clock stops while it waits for input, `bh8 serve`, bh8sim://);
- ``segment``: a marker naming the excitation's next part (for the report and plot);
- ``end``: the last record: `complete` true when the whole excitation ran, else the reason it stopped.

A log without its end record was cut (the recorder was killed, the disk filled); one whose end
says complete false stopped early (Ctrl-C, a safety limit). Each record carries `h`, a chained
digest of itself and the record before it: a record changed, dropped or moved after recording
breaks the chain, and the reader names the first record that does.

`read_log` bounds what it reads (a regular file, MAX_LOG_BYTES, MAX_LINE_BYTES per line) and
raises CalibrationLogError, one line naming the file and line, for anything that is not such a log.
"""
from __future__ import annotations

import errno
import hashlib
import json
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from bh8_gym.protocol import BAUD_RATES, FIRMWARE_PROFILES, MOTORS
from bh8_gym.realtime_codec import LoopLayout, MotorFlags
from bh8_gym.safe_files import parse_json, read_bounded

LOG_FORMAT = "bh8-calibration-log"
LOG_VERSION = 1
MAX_LOG_BYTES = 64 << 20  # a 2-minute excitation logs about 3 MB
MAX_LINE_BYTES = 64 << 10  # the header, the longest line, is about 4 KB
MAX_TEXT = 400  # characters of a command line, a reply line, a reason
MAX_REPLY_LINES = 64
HAND_CLOCKS = ("wall", "line")
MOUNTINGS = ("palm-up", "palm-down")
RECORD_KINDS = ("command", "baud", "loop", "block", "loop_exit", "clock", "segment", "end")
_HEX = re.compile(r"(?:[0-9a-f]{2})*")
_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_.:-]{0,63}")
_FLAG_NAMES = tuple(f.name for f in MotorFlags.__dataclass_fields__.values())


_COMMAND = re.compile(r"^\s*[1-4GSgs]*\s*([A-Za-z?]+)")  # the firmware takes "G C" as "GC" (client.supervisory)


def command_word(line: str) -> str:
    """The command of a supervisory line without its motor prefix ("123M 600" -> "M")."""
    found = _COMMAND.match(line)
    return found.group(1).upper() if found else ""


def is_motion(line: str) -> bool:
    """Whether the hand answers `line` only when a motion ends (§5.5)."""
    from bh8_gym.client.supervisory import MOTION_COMMANDS

    return command_word(line) in MOTION_COMMANDS


class CalibrationLogError(ValueError):
    """Not a calibration log this version can use (the message names the file, line and why)."""


def canonical(record: dict) -> str:
    """The record's one-line JSON as the digest covers it (sorted keys, no spaces)."""
    return json.dumps(record, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)


def chain_digest(previous: str, record: dict) -> str:
    """`h` of a record: 16 hex digits of SHA-256 over the previous record's `h` and this record
    (without its own `h`)."""
    body = {key: value for key, value in record.items() if key != "h"}
    return hashlib.sha256((previous + canonical(body)).encode("ascii")).hexdigest()[:16]


# ----------------------------------------------------------------------------------- writing


class LogWriter:
    """Writes the log a record at a time: each record one unbuffered write of one whole line, cut
    back off the file if the disk took only part of it (so the file never ends in half a record).
    `write` raises the OSError of a record it could not write."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._file = open(self.path, "wb", buffering=0)  # noqa: SIM115 (closed by close())
        self._size = 0
        self._previous = ""
        self.records = 0

    def write(self, record: dict) -> None:
        record = dict(record)
        record["i"] = self.records
        record["h"] = chain_digest(self._previous, record)
        data = memoryview((canonical(record) + "\n").encode("ascii"))
        written = 0
        try:
            while written < len(data):
                count = self._file.write(data[written:])
                if not count:
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                written += count
        except OSError:
            try:
                self._file.truncate(self._size)
                self._file.seek(self._size)
            except OSError:
                pass
            raise
        self._size += written
        self._previous = record["h"]
        self.records += 1

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> "LogWriter":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


# ----------------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class LogHeader:
    """What line 1 says about the excitation, the hand and the port."""

    excitation: str
    excitation_version: int
    scale: float
    mounting: str
    calibration_object: str | None
    version_text: str
    profile: str
    port: str
    baud_found: int
    started: str
    found: dict = field(default_factory=dict, compare=False)


@dataclass
class CalibrationLog:
    """A parsed log: the header, the records (dicts, checked) and how it ended."""

    path: str
    header: LogHeader
    records: list
    complete: bool
    reason: str
    hand_clock: str | None
    digest: str  # SHA-256 of the whole file, for the provenance of a fit

    @property
    def blocks(self) -> int:
        return sum(1 for record in self.records if record["kind"] == "block")


def read_log(path: str | os.PathLike) -> CalibrationLog:
    """Read and check a calibration log (module docstring); CalibrationLogError says what is wrong."""
    return parse_log(read_bounded(path, MAX_LOG_BYTES, "calibration log", CalibrationLogError), str(path))


def parse_log(data: bytes, name: str = "<log>") -> CalibrationLog:
    """A CalibrationLog from the bytes of a log file (CalibrationLogError if they are not one)."""
    if not isinstance(data, (bytes, bytearray)):
        raise CalibrationLogError(f"{name}: expected the bytes of a log file")
    digest = hashlib.sha256(data).hexdigest()
    lines = bytes(data).split(b"\n")
    if lines and lines[-1] == b"":
        lines.pop()
    elif lines and lines[-1]:
        # A last line without its newline: the recorder was stopped while writing it.
        lines.pop()
    if not lines:
        raise CalibrationLogError(f"{name}: empty; not a log of `bh8 calibrate record`")
    records = []
    previous = ""
    for number, raw in enumerate(lines, start=1):
        record = _decode_line(raw, number, name)
        where = f"{name}: line {number}"
        if number == 1:
            _check_is_header(record, where)
        if record.get("i") != number - 1:
            raise CalibrationLogError(f"{where}: record number {record.get('i')!r}, expected {number - 1} "
                                      "(records were removed, added or moved)")
        if record.get("h") != chain_digest(previous, record):
            raise CalibrationLogError(f"{where}: the record's digest does not match: the log was changed after "
                                      "it was recorded (record it again)")
        previous = record["h"]
        records.append(record)
    header = _header(records[0], f"{name}: line 1")
    body = records[1:]
    checker = _RecordChecker(header, name)
    for number, record in enumerate(body, start=2):
        checker.check(record, number)
    complete, reason = False, "the log was cut before its end record (the recorder was stopped or killed)"
    if body and body[-1]["kind"] == "end":
        complete, reason = body[-1]["complete"], body[-1]["reason"]
    return CalibrationLog(name, header, body, complete, reason, checker.hand_clock, digest)


def _decode_line(raw: bytes, number: int, name: str) -> dict:
    where = f"{name}: line {number}"
    if len(raw) > MAX_LINE_BYTES:
        raise CalibrationLogError(f"{where}: {len(raw):,} bytes, longer than any record ({MAX_LINE_BYTES:,})")
    try:
        text = raw.decode("ascii")
    except UnicodeDecodeError:
        raise CalibrationLogError(f"{where}: not ASCII text; not a log of `bh8 calibrate record`") from None
    try:
        record = parse_json(text, where, CalibrationLogError)
    except CalibrationLogError as error:
        if number > 1:
            raise
        raise CalibrationLogError(f"{error}; not a log of `bh8 calibrate record`") from None
    if not isinstance(record, dict):
        raise CalibrationLogError(f"{where}: a record must be a JSON object, got {type(record).__name__}")
    return record


def _check_is_header(record: dict, where: str) -> None:
    if record.get("kind") == "header" and record.get("format") == LOG_FORMAT:
        version = record.get("version")
        if isinstance(version, int) and not isinstance(version, bool) and version > LOG_VERSION:
            raise CalibrationLogError(f"{where}: log format version {version} is newer than this bh8-gym reads "
                                      f"({LOG_VERSION}); update bh8-gym")
        if version != LOG_VERSION:
            raise CalibrationLogError(f"{where}: unknown log format version {version!r} (this reads {LOG_VERSION})")
        return
    if "cycle" in record and ("control" in record or "feedback" in record) or record.get("event"):
        raise CalibrationLogError(f"{where}: this is a `bh8 deploy --log` log, not a calibration log; record one "
                                  "with `bh8 calibrate record` (docs/hardware.md)")
    raise CalibrationLogError(f"{where}: not the header of a `bh8 calibrate record` log")


# -- field checks


def _bad(where: str, key: str, expected: str, value) -> CalibrationLogError:
    return CalibrationLogError(f"{where}: {key} must be {expected}, got {json.dumps(value)[:80]}")


def _get(record: dict, key: str, where: str):
    if key not in record:
        raise CalibrationLogError(f"{where}: a {record.get('kind', 'record')} record needs {key!r}")
    return record[key]


def _int(record, key, where, low, high):
    value = _get(record, key, where)
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise _bad(where, key, f"an integer in {low}..{high}", value)
    return value


def _float(record, key, where, low=0.0, high=1e9):
    value = _get(record, key, where)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or not low <= value <= high:
        raise _bad(where, key, f"a number in {low:g}..{high:g}", value)
    return float(value)


def _text(record, key, where, choices=None, pattern=None, optional=False):
    value = _get(record, key, where)
    if value is None and optional:
        return None
    if not isinstance(value, str) or len(value) > MAX_TEXT or not value.isprintable():
        raise _bad(where, key, f"printable text of at most {MAX_TEXT} characters", value)
    if choices is not None and value not in choices:
        raise _bad(where, key, f"one of {', '.join(choices)}", value)
    if pattern is not None and not pattern.fullmatch(value):
        raise _bad(where, key, "a name", value)
    return value


def _keys(record: dict, allowed: set, where: str) -> None:
    unknown = sorted(set(record) - allowed - {"kind", "i", "h"})
    if unknown:
        raise CalibrationLogError(f"{where}: unknown field {unknown[0][:40]!r} in a {record['kind']} record")


def _header(record: dict, where: str) -> LogHeader:
    _keys(record, {"format", "version", "excitation", "hand", "port", "found", "started", "recorder"}, where)
    excitation, hand, port = (_get(record, key, where) for key in ("excitation", "hand", "port"))
    for key, value in (("excitation", excitation), ("hand", hand), ("port", port)):
        if not isinstance(value, dict):
            raise _bad(where, key, "a JSON object", value)
    _keys({**excitation, "kind": "header"}, {"name", "version", "scale", "mounting", "object"}, where + " (excitation)")
    _keys({**hand, "kind": "header"}, {"version_text", "profile", "serial_number"}, where + " (hand)")
    _keys({**port, "kind": "header"}, {"name", "baud_found"}, where + " (port)")
    found = record.get("found", {})
    if not isinstance(found, dict):
        raise _bad(where, "found", "a JSON object", found)
    calibration_object = _text(excitation, "object", where, optional=True)
    if calibration_object is not None:
        from bh8_gym.calibration.scene import check_calibration_object

        try:
            check_calibration_object(calibration_object)
        except ValueError as error:
            raise CalibrationLogError(f"{where}: excitation object: {error}") from None
    header = LogHeader(
        excitation=_text(excitation, "name", where, pattern=_NAME),
        excitation_version=_int(excitation, "version", where, 1, 10**6),
        scale=_float(excitation, "scale", where, 0.01, 100.0),
        mounting=_text(excitation, "mounting", where, choices=MOUNTINGS),
        calibration_object=calibration_object,
        version_text=_text(hand, "version_text", where),
        profile=_text(hand, "profile", where, choices=FIRMWARE_PROFILES),
        port=_text(port, "name", where),
        baud_found=_int(port, "baud_found", where, min(BAUD_RATES), max(BAUD_RATES)),
        started=_text(record, "started", where) if "started" in record else "",
        found=found,
    )
    from bh8_gym.client.supervisory import firmware_profile_of

    try:
        said = firmware_profile_of(header.version_text)
    except ValueError:
        said = None
    if said != header.profile:
        raise CalibrationLogError(f"{where}: the header says firmware profile {header.profile} but the hand answered "
                                  f"VERS {header.version_text!r}; the log was edited")
    return header


class _RecordChecker:
    """Checks each record after the header: fields, kinds and the order of LOOP records."""

    def __init__(self, header: LogHeader, name: str):
        self.header = header
        self.name = name
        self.layout: LoopLayout | None = None
        self.ended = False
        self.hand_clock = None
        self.last_time = -math.inf

    def check(self, record: dict, number: int) -> None:
        where = f"{self.name}: line {number}"
        kind = record.get("kind")
        if kind not in RECORD_KINDS:
            raise CalibrationLogError(f"{where}: unknown record kind {json.dumps(kind)[:40]}")
        if self.ended:
            raise CalibrationLogError(f"{where}: a record after the end record")
        getattr(self, "_" + kind)(record, where)
        if "t" in record:
            t = _float(record, "t", where, -1e12, 1e12)
            if t < self.last_time:
                raise CalibrationLogError(f"{where}: time {t} runs backwards (the record before was at {self.last_time})")
            self.last_time = t

    def _in_loop(self, record, where, expected: bool) -> None:
        if (self.layout is not None) != expected:
            state = "inside LOOP" if self.layout is not None else "outside LOOP"
            raise CalibrationLogError(f"{where}: a {record['kind']} record {state}")

    def _command(self, record, where):
        self._in_loop(record, where, False)
        _keys(record, {"line", "reply", "error", "t", "dt"}, where)
        line = _text(record, "line", where)
        if "LOOP" in line.upper().replace(" ", "") or "\r" in line:
            raise _bad(where, "line", "a supervisory command (LOOP has its own record)", line)
        reply = _get(record, "reply", where)
        if not isinstance(reply, list) or len(reply) > MAX_REPLY_LINES or not all(
                isinstance(item, str) and len(item) <= MAX_TEXT for item in reply):
            raise _bad(where, "reply", f"a list of at most {MAX_REPLY_LINES} lines", reply)
        if _get(record, "error", where) is not None:
            _int(record, "error", where, 1, 65535)
        _float(record, "dt", where, 0.0, 1e6)

    def _baud(self, record, where):
        self._in_loop(record, where, False)
        _keys(record, {"rate", "t"}, where)
        rate = _get(record, "rate", where)
        if rate not in BAUD_RATES or isinstance(rate, bool):
            raise _bad(where, "rate", f"one of {BAUD_RATES}", rate)

    def _loop(self, record, where):
        self._in_loop(record, where, False)
        _keys(record, {"motors", "layout", "t"}, where)
        layout = _get(record, "layout", where)
        if not isinstance(layout, dict) or set(layout) != {"motors", "flags", "lft", "firmware"}:
            raise _bad(where, "layout", "an object of motors, flags, lft, firmware", layout)
        motors, flags = layout["motors"], layout["flags"]
        if (not isinstance(motors, list) or not motors or len(motors) > 4 or len(set(motors)) != len(motors)
                or any(isinstance(m, bool) or m not in MOTORS for m in motors)):
            raise _bad(where, "layout motors", "distinct motor numbers 1..4", motors)
        if not isinstance(flags, dict) or set(flags) != {str(m) for m in motors}:
            raise _bad(where, "layout flags", "one object of flags per LOOP motor", flags)
        built = {}
        for motor in motors:
            values = flags[str(motor)]
            if not isinstance(values, dict) or not set(values) <= set(_FLAG_NAMES) or not all(
                    isinstance(v, bool) for v in values.values()):
                raise _bad(where, f"flags of motor {motor}", f"booleans named {', '.join(_FLAG_NAMES)}", values)
            built[motor] = MotorFlags(**values)
        if layout["firmware"] != self.header.profile or not isinstance(layout["lft"], bool):
            raise _bad(where, "layout firmware", f"the header's profile {self.header.profile}", layout["firmware"])
        self.layout = LoopLayout(motors, built, lft=layout["lft"], firmware=layout["firmware"])
        _text(record, "motors", where, pattern=re.compile(r"[1-4GS]{1,6}"))

    def _block(self, record, where):
        self._in_loop(record, where, True)
        _keys(record, {"control", "feedback", "t", "dt"}, where)
        control, feedback = _text(record, "control", where), _text(record, "feedback", where)
        if not _HEX.fullmatch(control) or not _HEX.fullmatch(feedback):
            raise _bad(where, "control/feedback", "lower-case hex bytes", [control[:20], feedback[:20]])
        layout = self.layout
        block = bytes.fromhex(control)
        if not block or block[:1] not in (b"C", b"A") or len(block) != layout.control_block_size(block[:1]):
            raise CalibrationLogError(f"{where}: control block {control[:40]} does not fit the LOOP's layout")
        try:
            layout.decode_feedback(bytes.fromhex(feedback))
        except ValueError as error:
            raise CalibrationLogError(f"{where}: feedback block does not fit the LOOP's layout: {error}") from None
        _float(record, "dt", where, 0.0, 1e6)

    def _loop_exit(self, record, where):
        self._in_loop(record, where, True)
        _keys(record, {"t"}, where)
        self.layout = None

    def _clock(self, record, where):
        _keys(record, {"hand_clock", "moved", "waited", "t"}, where)
        self.hand_clock = _text(record, "hand_clock", where, choices=HAND_CLOCKS)
        _float(record, "moved", where, 0.0, 1e6)
        _float(record, "waited", where, 0.0, 1e3)

    def _segment(self, record, where):
        _keys(record, {"name", "t"}, where)
        _text(record, "name", where, pattern=_NAME)

    def _end(self, record, where):
        _keys(record, {"complete", "reason", "t"}, where)
        if not isinstance(_get(record, "complete", where), bool):
            raise _bad(where, "complete", "true or false", record["complete"])
        _text(record, "reason", where)
        self.ended = True
