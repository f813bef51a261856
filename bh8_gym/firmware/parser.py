"""The firmware's line parser: bytes in, echo, line editing, command look-up and reply framing.

Choices where the documents are silent (SPEC.md §2, §8):

- Framing (SPEC.md §2): every character is echoed as it arrives, the CR is not; the reply is
  "\\n\\r", output lines each ending "\\n\\r", then the prompt "=> ". An error reply is
  "\\n\\rERR <n>\\n\\r=> ". Lines may be lower case (ASCII letters; 0xDF is not "SS"), numbers are
  ASCII digits with an optional sign. LF (0x0A) is ignored in supervisory mode, so a terminal sending
  CR LF works, but not after LOOP: there the LF is the first block header (ERR 2048). Backspace
  (0x08) and DEL (0x7F) remove the last character of the line and echo "\\b \\b". A line longer
  than `MAX_LINE_LENGTH` characters keeps being echoed but its excess is dropped, and the line then
  fails with ERR 128 (invalid value).
- ^C (0x03) in supervisory mode while no command runs discards the partial line and replies
  "\\n\\r=> ". While a motion runs the firmware only looks for ^C (§5.5 case 4): every motor
  terminates and the reply is "ERR 16384"; other bytes arriving during a motion are discarded (the
  68HC811 polls its serial port for ^C while it supervises the motors; typed-ahead text is lost).

The command handlers themselves are `SupervisoryCommands` (supervisory.py); RealTime blocks go to
`RealTimeLoop` (realtime.py) while in LOOP.
"""
from __future__ import annotations

from bh8_gym.protocol import CTRL_C, LINE_END, MOTOR_PREFIXES, MOTORS, PROMPT
from bh8_gym.realtime_codec import HEADERS_WITH_DATA
from bh8_gym.status import Status

MAX_LINE_LENGTH = 255  # our choice: longer lines fail with ERR 128

CR = 0x0D
LF = 0x0A
BACKSPACES = (0x08, 0x7F)

# name: (description, advanced, takes a motor prefix) — §5.2.1-§5.2.5
COMMANDS = {
    "C": ("Close", False, True),
    "HI": ("Hand Initialize", False, True),
    "HOME": ("Home", False, True),
    "IO": ("Incremental Open", False, True),
    "IC": ("Incremental Close", False, True),
    "LOOP": ("Loop", False, True),
    "M": ("Move", False, True),
    "O": ("Open", False, True),
    "T": ("Terminate power", False, True),
    "TC": ("Torque-Controlled Close", False, True),
    "TO": ("Torque-Controlled Open", False, True),
    "FSET": ("Finger Set", False, True),
    "FGET": ("Finger Get", False, True),
    "FLOAD": ("Finger Load", False, True),
    "FSAVE": ("Finger Save", False, True),
    "FDEF": ("Finger Default", False, True),
    "FLIST": ("Finger List", False, False),
    "FLISTV": ("Finger List Value", False, True),
    "PSET": ("Parameter Set", False, False),
    "PGET": ("Parameter Get", False, False),
    "PLOAD": ("Parameter Load", False, False),
    "PSAVE": ("Parameter Save", False, False),
    "PDEF": ("Parameter Default", False, False),
    "PLIST": ("Parameter List", False, False),
    "PLISTV": ("Parameter List Value", False, False),
    "?": ("Help", False, False),
    "RESET": ("Reset", False, False),
    "ERR": ("Error", False, False),
    "VERS": ("Version", False, False),
    "A?": ("Help All", True, False),
    "FLISTA": ("Finger List All", True, False),
    "FLISTAV": ("Finger List All Value", True, True),
    "PLISTA": ("Parameter List All", True, False),
    "PLISTAV": ("Parameter List All Value", True, False),
}
MOTOR_COMMANDS = frozenset(("C", "HI", "HOME", "IO", "IC", "LOOP", "M", "O", "TC", "TO"))
MOVEMENT_COMMANDS = MOTOR_COMMANDS | {"T"}  # §5.2.1; without a prefix they act on the EN=1 motors
_HANDLER_NAMES = {"?": "HELP", "A?": "HELP_ALL"}  # handler method names of the commands that are not identifiers


class CommandError(Exception):
    """A command failed with a Table 3 status sum."""

    def __init__(self, code: int):
        super().__init__(code)
        self.code = int(code)


class LineParser:
    """Input handling of `Firmware`: consumes `_input`, echoes into `_output`, runs one command per
    CR through its `_cmd_<NAME>` handler and frames the reply (uses `_line`, `_line_overflow`,
    `_task`, `_loop_layout`, `_motor_values`)."""

    def _input_ready(self) -> bool:
        data = self._input
        if not data:
            return False
        layout = self._loop_layout
        if layout is None:
            return True
        header = data[0]
        if header in HEADERS_WITH_DATA:
            return len(data) >= layout.control_block_size(header)
        return True

    def _consume_input(self) -> None:
        """Process arrived bytes until a task starts or the input runs dry."""
        data = self._input
        while data and self._task is None:
            if self._loop_layout is not None:
                if not self._consume_loop_block():
                    return
                continue
            byte = data[0]
            del data[0]
            if byte == CR:
                line = bytes(self._line)
                overflow = self._line_overflow
                self._line.clear()
                self._line_overflow = False
                self._execute(line, overflow)
            elif byte == CTRL_C:
                self._line.clear()
                self._line_overflow = False
                self._output += LINE_END + PROMPT
            elif byte == LF:
                continue
            elif byte in BACKSPACES:
                if self._line:
                    self._line.pop()
                    self._output += b"\b \b"
            else:
                self._output.append(byte)
                if len(self._line) < MAX_LINE_LENGTH:
                    self._line.append(byte)
                else:
                    self._line_overflow = True

    def _reply(self, lines=(), error: int = 0) -> None:
        out = self._output
        out += LINE_END
        if error:
            out += b"ERR %d" % error + LINE_END
        else:
            for line in lines:
                out += line.encode("latin-1") + LINE_END
        out += PROMPT

    def _execute(self, raw: bytes, overflow: bool) -> None:
        # Case and whitespace by the bytes' ASCII rules, as the hand's 8-bit parser: str rules would
        # make 0xDF ("ß") upper-case to "SS", a spread prefix, and 0xA0 a separator.
        line = raw.strip().upper()
        text = line.decode("latin-1")
        if overflow:
            self._reply(error=Status.INVALID_VALUE)
            return
        if not text:
            self._reply()
            return
        i = 0
        while i < len(text) and text[i] in MOTOR_PREFIXES:
            i += 1
        prefix = text[:i]
        tokens = [token.decode("latin-1") for token in line[i:].split()]
        word = tokens[0] if tokens else ""
        args = tokens[1:]
        if word.startswith("?") and word != "?":
            args = [word[1:]] + args
            word = "?"
        entry = COMMANDS.get(word)
        if entry is None:
            self._reply(error=Status.UNKNOWN_COMMAND)
            return
        if prefix and not entry[2]:
            self._reply(error=Status.NO_PREFIX_ALLOWED)
            return
        if prefix:
            motors = tuple(sorted({m for c in prefix for m in MOTOR_PREFIXES[c]}))
        elif word in MOVEMENT_COMMANDS:  # §5.3.4 EN: "a motion command with no motor prefix"
            motors = tuple(m for m in MOTORS if self._motor_values[m]["EN"])
        else:  # §5.2: "By default, all four motors are affected"
            motors = MOTORS
        handler = getattr(self, "_cmd_" + _HANDLER_NAMES.get(word, word))
        try:
            if word in MOTOR_COMMANDS:
                self._check_motor_command(word, motors, args)
            lines = handler(motors, args)
        except CommandError as error:
            self._reply(error=error.code)
            return
        if lines is not None:
            self._reply(lines)
