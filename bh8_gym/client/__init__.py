"""The client side of the serial protocol: a BH8-262 over any pyserial port.

The same code drives a real hand (`/dev/ttyUSB0`, `COM3`, `socket://host:port` through a serial
server), `bh8 serve` on a pseudo-terminal, and the in-process simulator (`bh8sim://?seed=0`).
It splits as the protocol does (SPEC.md §2, §5):

- `line`: the port and the line discipline: `SerialLine` (echo, output lines, prompt, "ERR n",
  bounded reads, resynchronisation) and `HandConnectionError`;
- `hand`: `BarrettHand`, the object a program holds: it owns the line, resynchronises, aborts, and
  enters and leaves RealTime mode;
- `supervisory`: `SupervisoryCommands`, the §5.2 command set `BarrettHand` speaks (a mixin);
- `realtime`: `RealTimeSession`, one LOOP from its "*" to the ^C, which owns the block layout
  (`realtime_codec.LoopLayout`) and decodes `LoopFeedback`.

Nothing here loads PyBullet: `bh8 deploy` runs on a computer that has only the hand.
"""
from bh8_gym.client.line import PORT_ERRORS, HandConnectionError, SerialLine
from bh8_gym.client.realtime import REALTIME_MOTOR_PARAMETERS, LoopFeedback, MotorFeedback, RealTimeSession
from bh8_gym.client.hand import DEFAULT_MOTION_TIMEOUT_S, DEFAULT_TIMEOUT_S, BarrettHand
from bh8_gym.client.supervisory import SupervisoryCommands, firmware_profile_of, parse_motors
from bh8_gym.status import HandError, HandTimeout, ProtocolError  # what the client raises, named here too

__all__ = [
    "BarrettHand",
    "DEFAULT_MOTION_TIMEOUT_S",
    "DEFAULT_TIMEOUT_S",
    "HandConnectionError",
    "HandError",
    "HandTimeout",
    "LoopFeedback",
    "MotorFeedback",
    "PORT_ERRORS",
    "ProtocolError",
    "REALTIME_MOTOR_PARAMETERS",
    "RealTimeSession",
    "SerialLine",
    "SupervisoryCommands",
    "firmware_profile_of",
    "parse_motors",
]
