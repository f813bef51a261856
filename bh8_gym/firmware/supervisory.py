"""The supervisory commands (manual §5.2): movement commands that start a motion task, T, LOOP,
the parameter commands (FSET/FGET/FLIST..., PSET/PGET/PLIST...), and ?, RESET, ERR, VERS.

Choices where the documents are silent (SPEC.md §2, §8):

- Over-temperature (§5.4.1 OTEMP): checked when a motor command (HI HOME M IO IC C O TC TO LOOP)
  starts: TEMP > OTEMP with OTEMP ≠ 0 fails it with ERR 8192. T is always allowed (it cools).
- T on an uninitialised motor: §5.2.1 T note: "T will return an ERR 1 if any of the selected
  motor(s) isn't initialized; it will still turn the selected and initialized motor(s)'s power off".
- FLISTV/FLISTAV/PLISTV/PLISTAV lines are "NAME v1 v2 ..."; FLIST/PLIST lines are
  "NAME<padding>description"; FGET/PGET lines are values only (SPEC.md §2 example).
- FSET/PSET are all-or-nothing: if any pair is bad nothing is set and the codes of all bad pairs
  are summed (§5.1.3: "the sum of the status codes encountered").
"""
from __future__ import annotations

import re

from bh8_gym.motion_control import HOLD
from bh8_gym.firmware.parser import COMMANDS, CommandError
from bh8_gym.parameters import (
    GLOBAL_TABLE,
    MOTOR_TABLE,
    default_global_values,
    default_motor_values,
    listed,
)
from bh8_gym.realtime_codec import LoopLayout, MotorFlags
from bh8_gym.status import STATUS_DESCRIPTIONS, Status

VERSIONS = {"4.3": "4.34", "4.4": "4.40"}  # our choice of the exact 4.3x / 4.4x version strings
BANNER_LINES = ("BarrettHand Firmware", "Version {version}")  # see module docstring
MOTION_ARGUMENT_RANGE = (0, 20000)  # §5.2.1 M, IO, IC arguments
_INTEGER = re.compile(r"[+-]?[0-9]+")
# Every parameter name -> the firmware profiles that have it (for other_profile_hook).
_PARAMETER_PROFILES = {p.name: p.profiles for p in MOTOR_TABLE + GLOBAL_TABLE}


class SupervisoryCommands:
    """The `_cmd_<NAME>` handlers `LineParser` calls, each with the selected motors and the
    argument tokens; a handler returns the reply lines, or None when a task (motion, LOOP) replies
    later, and raises CommandError for an ERR reply."""

    @staticmethod
    def _no_arguments(args) -> None:
        if args:
            raise CommandError(Status.TOO_MANY_ARGUMENTS)

    @staticmethod
    def _integer(text: str) -> int:
        if _INTEGER.fullmatch(text) is None:  # ASCII digits only: str.isdigit() accepts "²"
            raise CommandError(Status.INVALID_VALUE)
        return int(text)

    def _motion_argument(self, args) -> int | None:
        if len(args) > 1:
            raise CommandError(Status.TOO_MANY_ARGUMENTS)
        if not args:
            return None
        value = self._integer(args[0])
        if not MOTION_ARGUMENT_RANGE[0] <= value <= MOTION_ARGUMENT_RANGE[1]:
            raise CommandError(Status.INVALID_VALUE)
        return value

    def _check_motor_command(self, word: str, motors, args) -> None:
        if word in ("M", "IO", "IC"):
            self._motion_argument(args)
        else:
            self._no_arguments(args)
        otemp = self._globals["OTEMP"]
        if otemp and self._temperature_tenths() > otemp:
            raise CommandError(Status.OVER_TEMPERATURE)
        if word != "HI" and any(not self._initialized[m] for m in motors):
            raise CommandError(Status.NOT_INITIALIZED)

    # -- movement (§5.2.1)

    def _cmd_HI(self, motors, args):
        self._start_task(self._motion_task("HI", motors, {}))

    def _cmd_HOME(self, motors, args):
        self._start_position_command("HOME", motors, {m: 0.0 for m in motors})

    def _cmd_M(self, motors, args):
        value = self._motion_argument(args)
        targets = {m: float(self._motor_values[m]["DP"] if value is None else value) for m in motors}
        self._start_position_command("M", motors, targets)

    def _cmd_IC(self, motors, args):
        self._incremental("IC", motors, args, 1.0)

    def _cmd_IO(self, motors, args):
        self._incremental("IO", motors, args, -1.0)

    def _incremental(self, word, motors, args, direction):
        value = self._motion_argument(args)
        targets = {}
        for m in motors:
            step = self._motor_values[m]["DS"] if value is None else value
            # From the HCTL's commanded position: a held motor's set point (a servo still settling,
            # the back-drivable spread, is not a step short), else where the motor is.
            channel = self._channels[m]
            start = channel.set_point if channel.mode == HOLD else round(self._position(m))
            targets[m] = float(start) + direction * step
        self._start_position_command(word, motors, targets)

    def _cmd_C(self, motors, args):
        self._start_position_command("C", motors, {m: float(self._motor_values[m]["CT"]) for m in motors})

    def _cmd_O(self, motors, args):
        self._start_position_command("O", motors, {m: float(self._motor_values[m]["OT"]) for m in motors})

    def _cmd_TC(self, motors, args):
        self._start_task(self._motion_task("TC", motors, {}))

    def _cmd_TO(self, motors, args):
        self._start_task(self._motion_task("TO", motors, {}))

    def _start_position_command(self, word, motors, targets):
        self._start_task(self._motion_task(word, motors, targets))

    def _cmd_T(self, motors, args):
        self._no_arguments(args)
        for m in motors:
            if self._initialized[m]:
                self._channels[m].off()
        if any(not self._initialized[m] for m in motors):
            raise CommandError(Status.NO_MOTOR_BOARD)  # §5.2.1 T note: "ERR 1"
        return []

    def _cmd_LOOP(self, motors, args):
        if not motors:
            raise CommandError(Status.INVALID_VALUE)
        flags = {m: MotorFlags.from_parameters(self._motor_values[m]) for m in motors}
        layout = LoopLayout(motors, flags, lft=bool(self._globals["LFT"]), firmware=self.profile)
        self._enter_loop(layout)
        return None

    # -- parameters (§5.2.2, §5.2.3)

    def _motor_value(self, m: int, name: str) -> int:
        if name == "P":
            return int(round(self._position(m)))
        if name == "S":
            return self._status[m]
        if name == "SG":
            return self._strain_gauge(m)
        if name == "OD":
            return int(self._odometer[m - 1] // 1000.0)
        if name == "BD":
            return int(self._breakaway_detected(m))
        if name == "BP":
            return self._breakaway_position(m)
        return self._motor_values[m][self._motor_table[name].stored_name]

    def _strain_gauge(self, m: int) -> int:
        sg = int(self.plant.strain_gauges()[m - 1])
        return 255 - sg if self._motor_values[m]["SGFLIP"] else sg

    def _global_value(self, name: str) -> int:
        if name == "TEMP":
            return self._temperature_tenths()
        if name == "PTEMP":
            return self._update_peak_temperature()
        if name == "UPSECS":
            return int(self._uptime_seconds())
        if name == "SN":
            return self._serial_number
        return self._globals[name]

    def _parse_assignments(self, table: dict, args) -> list[tuple[str, int]]:
        if not args or len(args) % 2:
            raise CommandError(Status.INVALID_VALUE)
        error = 0
        pairs = []
        for name, text in zip(args[0::2], args[1::2]):
            parameter = table.get(name)
            if parameter is None:
                self._note_other_profile(name)
                error |= Status.UNKNOWN_PARAMETER
                continue
            if parameter.read_only:
                error |= Status.READ_ONLY
                continue
            try:
                value = self._integer(text)
            except CommandError as bad:
                error |= bad.code
                continue
            if not parameter.accepts(value):
                error |= Status.INVALID_VALUE
                continue
            pairs.append((parameter.stored_name, value))
        if error:
            raise CommandError(error)
        return pairs

    def _check_names(self, table: dict, names) -> None:
        unknown = [name for name in names if name not in table]
        for name in unknown:
            self._note_other_profile(name)
        if unknown:
            raise CommandError(Status.UNKNOWN_PARAMETER)

    def _note_other_profile(self, name: str) -> None:
        profiles = _PARAMETER_PROFILES.get(name)
        if profiles and self.profile not in profiles and self.other_profile_hook is not None:
            self.other_profile_hook(name, profiles)

    def _cmd_FSET(self, motors, args):
        pairs = self._parse_assignments(self._motor_table, args)
        for m in motors:
            for name, value in pairs:
                self._motor_values[m][name] = value
        return []

    def _cmd_FGET(self, motors, args):
        self._check_names(self._motor_table, args)
        lines = []
        for name in args:
            values = [self._motor_value(m, name) for m in motors]
            if name == "P":
                for m, value in zip(motors, values):
                    self._reported_position[m] = value  # §6.2.3
            lines.append(" ".join(str(value) for value in values))
        return lines

    def _cmd_FLOAD(self, motors, args):
        self._no_arguments(args)
        stored = self.store.load().motors
        for m in motors:
            self._motor_values[m] = dict(stored[m])
        return []

    def _cmd_FSAVE(self, motors, args):
        self._no_arguments(args)
        self._save(motors=motors)
        return []

    def _cmd_FDEF(self, motors, args):
        self._no_arguments(args)
        for m in motors:
            self._motor_values[m] = default_motor_values(m, self.profile)
        return []

    def _cmd_FLIST(self, motors, args):
        self._no_arguments(args)
        return _describe(listed(self._motor_table, advanced=False))

    def _cmd_FLISTA(self, motors, args):
        self._no_arguments(args)
        return _describe(listed(self._motor_table, advanced=True))

    def _cmd_FLISTV(self, motors, args):
        self._no_arguments(args)
        return self._motor_value_lines(motors, advanced=False)

    def _cmd_FLISTAV(self, motors, args):
        self._no_arguments(args)
        return self._motor_value_lines(motors, advanced=True)

    def _motor_value_lines(self, motors, advanced: bool):
        return [
            " ".join([p.name] + [str(self._motor_value(m, p.name)) for m in motors])
            for p in listed(self._motor_table, advanced)
        ]

    def _cmd_PSET(self, motors, args):
        for name, value in self._parse_assignments(self._global_table, args):
            self._globals[name] = value
        return []

    def _cmd_PGET(self, motors, args):
        self._check_names(self._global_table, args)
        return [str(self._global_value(name)) for name in args]

    def _cmd_PLOAD(self, motors, args):
        self._no_arguments(args)
        self._globals = dict(self.store.load().globals)
        return []

    def _cmd_PSAVE(self, motors, args):
        self._no_arguments(args)
        self._save(global_values=True)
        return []

    def _cmd_PDEF(self, motors, args):
        self._no_arguments(args)
        self._globals = default_global_values(self.profile)
        return []

    def _cmd_PLIST(self, motors, args):
        self._no_arguments(args)
        return _describe(listed(self._global_table, advanced=False))

    def _cmd_PLISTA(self, motors, args):
        self._no_arguments(args)
        return _describe(listed(self._global_table, advanced=True))

    def _cmd_PLISTV(self, motors, args):
        self._no_arguments(args)
        return [f"{p.name} {self._global_value(p.name)}" for p in listed(self._global_table, advanced=False)]

    def _cmd_PLISTAV(self, motors, args):
        self._no_arguments(args)
        return [f"{p.name} {self._global_value(p.name)}" for p in listed(self._global_table, advanced=True)]

    # -- administrative (§5.2.4, §5.2.5)

    def _cmd_HELP(self, motors, args):
        if len(args) > 1:
            raise CommandError(Status.TOO_MANY_ARGUMENTS)
        if args:
            entry = COMMANDS.get(args[0])
            if entry is None:
                raise CommandError(Status.UNKNOWN_COMMAND)
            return [_help_line(args[0], entry[0])]
        return [_help_line(name, entry[0]) for name, entry in COMMANDS.items() if not entry[1]]

    def _cmd_HELP_ALL(self, motors, args):
        self._no_arguments(args)
        return [_help_line(name, entry[0]) for name, entry in COMMANDS.items()]

    def _cmd_RESET(self, motors, args):
        self._no_arguments(args)
        self._save()
        self._power_up()
        return [line.format(version=self.version) for line in BANNER_LINES]

    def _cmd_ERR(self, motors, args):
        if len(args) > 1:
            raise CommandError(Status.TOO_MANY_ARGUMENTS)
        if not args:
            return [f"{code} {text}" for code, text in STATUS_DESCRIPTIONS.items()]
        code = self._integer(args[0])
        if code < 0:
            raise CommandError(Status.INVALID_VALUE)
        return [f"{bit} {STATUS_DESCRIPTIONS.get(bit, '(unknown status bit)')}" for bit in _bits(code)]

    def _cmd_VERS(self, motors, args):
        self._no_arguments(args)
        return [self.version]


def _describe(parameters) -> list[str]:
    return [f"{p.name:<7}{p.description}" for p in parameters]


def _help_line(name: str, description: str) -> str:
    return f"{name:<9}{description}"


def _bits(code: int):
    bit = 1
    while bit <= code:
        if code & bit:
            yield bit
        bit <<= 1
