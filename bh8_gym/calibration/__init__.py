"""Sim-to-real calibration: fit the simulated hand to a log of a real one (`bh8 calibrate`).

The lab runs a fixed excitation on its hand and logs it (`record`); the fit replays the log's
commands in the simulator and adjusts the PlantParameters that are our estimates until the
simulator answers as the hand did (`fit`); the result is a hand file the environments, `bh8 train`
and `bh8 serve` take (`hand_parameters`). docs/hardware.md has the lab's procedure,
docs/modelling.md what a log can tell.

- `excitation`: the program of motions (supervisory moves, LOOP sweeps, squeezes) and its laws;
- `recorder`: `Recorder` runs it on a `bh8_gym.client.BarrettHand` (a real hand, `bh8 serve`,
  bh8sim://), logging every command, reply and block, and leaves the hand as it found it;
- `log_format`: the JSONL log (`LogWriter`, `read_log`): chained digests, bounded strict reading;
- `scene`: the mounting and the calibration object, the same for the hand and the replay;
- `replay`: the log's commands and blocks sent to a simulated hand (`replay`), and the recorded
  hand's signals (`observed`);
- `residuals`: what the fit compares (`ResidualModel`), and the gauges' offsets;
- `fit`: the fitted parameters, SciPy's least squares, the noise probe, the uncertainties;
- `rollouts`: replays in parallel (local processes, or Ray tasks on a cluster);
- `report`: the text report, the plot, the hand file's provenance;
- the fit writes `hand.toml` through `bh8_gym.hand_file` (its strict schema and atomic write,
  `HandParameters`; outside this package because the envs and `bh8sim://` read it too);
- `practice`: practice hands drawn away from the defaults (`bh8 calibrate draw`).

`record` runs nothing but the client (it simulates nothing); `fit` needs the calibrate extra
(SciPy, matplotlib).
"""
