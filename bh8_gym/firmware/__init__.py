"""The BH8-262 firmware 4.3x (and 4.4) as a byte-stream machine over a simulated hand.

`Firmware` (docs/architecture.md Contract 2) takes host bytes with `write`, runs on its own
simulated clock (`run_until_idle`, `run_for`) and hands back the bytes the hand would send
(`read`). Sources: manual §4, §5 (supervisory mode, commands, parameters, termination), §6
(RealTime), §9.1-§9.2 (HCTL-1100); SPEC.md §2-§8, which decides framing, codes and timing.

The machine is split by what the firmware does, one module each (mixins of one `Firmware`, whose
state is its instance dictionary, so `snapshot` copies all of it):

- parser.py: bytes in, echo, line editing, command look-up, reply framing (SPEC.md §2);
- supervisory.py: the supervisory commands and parameters (§5.2);
- motion.py: the motion task of the motor commands and its termination (§5.5, §9.2);
- realtime.py: LOOP mode, control and feedback blocks (§6);
- clock.py: the simulated clock that runs a task and steps the plant;
- counters.py: OD, PTEMP, UPSECS and the store write that keeps them;
- snapshot.py: snapshot and restore;
- machine.py: `Firmware` itself (construction, the public API, power-up, the HCTL position and
  breakaway record).

Each module lists the choices it makes where the documents are silent (SPEC.md §8 and the firmware
brief; each is a named constant or documented there).
"""
from bh8_gym.firmware.machine import TRANSACT_LIMIT_S, Firmware, FirmwareBusyError
from bh8_gym.firmware.snapshot import FirmwareSnapshot
from bh8_gym.protocol import REALTIME_PROCESSING_S

__all__ = ["Firmware", "FirmwareBusyError", "FirmwareSnapshot", "REALTIME_PROCESSING_S", "TRANSACT_LIMIT_S"]
