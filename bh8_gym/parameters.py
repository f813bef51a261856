"""Every motor and global parameter of firmware 4.3x (and the 4.4 additions), in one table.

Sources: manual §5.3.1-§5.3.4 (motor parameters), §5.4.1-§5.4.3 (global parameters), §6.3
Tables 4-5; SPEC.md §3 (coefficient ranges 0..255 with 0 scaled as 1), §7 (4.4 adds LCT, LFBP,
LFAIN), §3.1 (the breakaway parameters BS, BD, BP, BDAT, which our copy of the manual lacks; where
each fact comes from is noted there). The table order is the manual's order, which is the order
FLIST/FLISTV/PLIST print in.

List membership (§5.3.4, §5.2.5): standard parameters (§5.3.1-§5.3.3, §5.4.1-§5.4.2) are listed by
FLIST/FLISTV and PLIST/PLISTV; advanced ones (§5.3.4, §5.4.3) only by FLISTA/FLISTAV and
PLISTA/PLISTAV, which list the standard ones too.

Read-only parameters (status: BD BP OD P S SG, TEMP PTEMP UPSECS SN) are "live": the firmware computes
their values; they have no default and are not part of a stored parameter set. MSG is an alias of
HSG (§5.3.1): one stored value, both names read and write it.
"""
from __future__ import annotations

from dataclasses import dataclass

from bh8_gym.protocol import BAUD_VALUES, FIRMWARE_PROFILES, MOTORS, SPREAD_MOTOR

UINT32_MAX = 4_294_967_295  # "0 to 4 billion" counters (OD, UPSECS)
COEFFICIENTS = ("LCVC", "LFVC", "LFDPC")  # Table 4 coefficients: 0 is scaled as 1 (SPEC.md §3)
BREAKAWAY_POSITION_MAX = 20000  # BP "Values: 0 or 20000" (SPEC.md §3.1), i.e. 0 to 20000 counts
BDAT_DEFAULT = 100  # our choice (SPEC.md §3.1); the simulated hand detects breakaway from the plant


@dataclass(frozen=True)
class Parameter:
    """One parameter: its range, defaults and where it appears."""

    name: str
    description: str  # the manual's "Name:" field; FLIST/PLIST print it
    minimum: int
    maximum: int
    finger_default: int | None = None  # motor parameters: fingers F1-F3 (globals: the default)
    spread_default: int | None = None  # motor parameters: the spread motor
    read_only: bool = False
    advanced: bool = False
    allowed: tuple[int, ...] | None = None  # a value set instead of a range (BAUD)
    profiles: tuple[str, ...] = FIRMWARE_PROFILES
    alias_of: str | None = None  # MSG -> HSG

    def default_for(self, motor: int) -> int | None:
        """The factory default for `motor` (1-3 fingers, 4 spread)."""
        return self.spread_default if motor == SPREAD_MOTOR else self.finger_default

    def accepts(self, value: int) -> bool:
        """True when `value` is a valid setting (range, or the allowed set)."""
        if self.allowed is not None:
            return value in self.allowed
        return self.minimum <= value <= self.maximum

    @property
    def stored_name(self) -> str:
        """The name the value is stored under (the alias target for MSG)."""
        return self.alias_of or self.name


def _motor(name, description, minimum, maximum, finger=None, spread=None, **kw) -> Parameter:
    return Parameter(name, description, minimum, maximum, finger, finger if spread is None else spread, **kw)


_FLAG = (0, 1)
_44 = ("4.4",)

MOTOR_TABLE: tuple[Parameter, ...] = (
    # §5.3.1 Movement (BS: SPEC.md §3.1)
    _motor("BS", "Breakaway Stop", *_FLAG, 0),
    _motor("DP", "Default Position", 0, 65535, 8500, 1575),
    _motor("DS", "Default Step", 0, 65535, 1700, 315),
    _motor("HSG", "Highest Strain Gauge Value", 0, 256, 256),
    _motor("LSG", "Lowest Strain Gauge Value", 0, 256, 256),
    _motor("MOV", "Maximum Open Velocity", 16, 4080, 100, 60),
    _motor("MCV", "Maximum Close Velocity", 16, 4080, 100, 60),
    _motor("MSG", "Maximum Strain Gauge", 0, 256, 256, alias_of="HSG"),
    # §5.3.2 Status (read-only, computed by the firmware; BD, BP: SPEC.md §3.1)
    _motor("BD", "Breakaway-Detected Flag", *_FLAG, read_only=True),
    _motor("BP", "Breakaway Position", 0, BREAKAWAY_POSITION_MAX, read_only=True),
    _motor("OD", "Odometer", 0, UINT32_MAX, read_only=True),
    _motor("P", "Position", -32768, 65535, read_only=True),
    _motor("S", "Status", 0, 32767, read_only=True),
    _motor("SG", "Strain Gauge", 0, 255, read_only=True),
    # §5.3.3 RealTime (4.4 adds LCT, LFBP, LFAIN: SPEC.md §7)
    _motor("LCV", "Loop Control Velocity", *_FLAG, 1),
    _motor("LCVC", "Loop Control Velocity Coefficient", 0, 255, 1),
    _motor("LCPG", "Loop Control Proportional Gain", *_FLAG, 1),
    _motor("LCT", "Loop Control Torque", *_FLAG, 0, profiles=_44),
    _motor("LFV", "Loop Feedback Velocity", *_FLAG, 1),
    _motor("LFVC", "Loop Feedback Velocity Coefficient", 0, 255, 1),
    _motor("LFS", "Loop Feedback Strain", *_FLAG, 1),
    _motor("LFAP", "Loop Feedback Absolute Position", *_FLAG, 1),
    _motor("LFDP", "Loop Feedback Delta Position", *_FLAG, 1),
    _motor("LFDPC", "Loop Feedback Delta Position Coefficient", 0, 255, 1),
    _motor("LFBP", "Loop Feedback Breakaway Position", *_FLAG, 0, profiles=_44),
    _motor("LFAIN", "Loop Feedback Analog Input", *_FLAG, 0, profiles=_44),
    # §5.3.4 Advanced
    _motor("ACCEL", "Acceleration", 0, 65535, 4, 2, advanced=True),
    # SPEC.md §3.1: range and default are our choice (not in the sources we could read)
    _motor("BDAT", "Breakaway Detection Acceleration Threshold", 0, 65535, BDAT_DEFAULT, advanced=True),
    _motor("CT", "Close Target", 0, 65535, 17000, 3150, advanced=True),
    _motor("EN", "Enabled", *_FLAG, 1, advanced=True),
    _motor("FDZ", "Filter Derivative Zero", 0, 255, 0, advanced=True),
    _motor("FIP", "Filter Integral Pole", 0, 255, 0, advanced=True),
    _motor("FPG", "Filter Proportional Gain", 0, 255, 10, advanced=True),
    _motor("HOLD", "Hold", *_FLAG, 0, 1, advanced=True),
    _motor("IHIT", "Initialization hit count", 0, 65535, 2, 0, advanced=True),
    _motor("IOFF", "Initialization Offset", 0, 65535, 50, 0, advanced=True),
    _motor("IVEL", "Initialization Velocity", 16, 4080, 300, 150, advanced=True),
    _motor("MPE", "Maximum Position Error", 0, 65535, 50, advanced=True),
    _motor("OT", "Open Target", 0, 65535, 0, advanced=True),
    _motor("SAMPLE", "Sample Time", 15, 255, 31, advanced=True),
    # §5.3.4 gives SGFLIP no default; 0 (no flip) is the only reading that leaves SG as documented.
    _motor("SGFLIP", "Strain Gage Flip", *_FLAG, 0, advanced=True),
    _motor("TSTOP", "Time to Stop", 0, 65535, 30, advanced=True),
)

GLOBAL_TABLE: tuple[Parameter, ...] = (
    # §5.4.1 Configuration
    Parameter("BAUD", "Baud rate", min(BAUD_VALUES), max(BAUD_VALUES), 96, allowed=BAUD_VALUES),
    Parameter("LFT", "Loop Feedback Temperature", *_FLAG, 0),
    Parameter("OTEMP", "OverTemperature", 0, 1250, 0),
    # §5.4.2 Status (read-only, computed by the firmware)
    Parameter("TEMP", "Temperature", -550, 1250, read_only=True),
    Parameter("PTEMP", "Peak Temperature", 0, 1250, read_only=True),
    Parameter("UPSECS", "Uptime Seconds", 0, UINT32_MAX, read_only=True),
    Parameter("SN", "Serial Number", 0, UINT32_MAX, read_only=True),
    # §5.4.3 Advanced
    Parameter("LFDPD", "Loop Feedback Delta Position Discard", *_FLAG, 0, advanced=True),
)


def motor_parameters(profile: str = "4.3") -> dict[str, Parameter]:
    """Name -> Parameter for the motor parameters of `profile`, in listing order."""
    _check_profile(profile)
    return {p.name: p for p in MOTOR_TABLE if profile in p.profiles}


def global_parameters(profile: str = "4.3") -> dict[str, Parameter]:
    """Name -> Parameter for the global parameters of `profile`, in listing order."""
    _check_profile(profile)
    return {p.name: p for p in GLOBAL_TABLE if profile in p.profiles}


def listed(table: dict[str, Parameter], advanced: bool) -> tuple[Parameter, ...]:
    """The parameters FLIST/PLIST (advanced=False) or FLISTA/PLISTA (advanced=True) print."""
    return tuple(p for p in table.values() if advanced or not p.advanced)


def default_motor_values(motor: int, profile: str = "4.3") -> dict[str, int]:
    """Factory defaults of the stored (writable, non-alias) motor parameters of `motor`."""
    if motor not in MOTORS:
        raise ValueError(f"motor must be one of {MOTORS}, got {motor!r}")
    return {
        p.name: p.default_for(motor)
        for p in motor_parameters(profile).values()
        if not p.read_only and p.alias_of is None
    }


def default_global_values(profile: str = "4.3") -> dict[str, int]:
    """Factory defaults of the stored (writable) global parameters."""
    return {p.name: p.finger_default for p in global_parameters(profile).values() if not p.read_only}


def coefficient(value: int) -> int:
    """A Table 4 coefficient as used for scaling: 0 counts as 1 (SPEC.md §3)."""
    return value if value > 0 else 1


def _check_profile(profile: str) -> None:
    if profile not in FIRMWARE_PROFILES:
        raise ValueError(f"firmware profile must be one of {FIRMWARE_PROFILES}, got {profile!r}")
