"""How well `bh8 calibrate` finds a hand's parameters, and how long its fit takes (issue 40).

Per drawn hand (`bh8 calibrate draw --seed K`: each fitted parameter and the gauges' gain within
±30 % of its default, the gauges' offsets in 100..140; with `--everything` also the motor's peak torque, the links' mass,
the worm's slack and the no-load speed): `bh8 serve --hand-parameters hidden.toml` serves it (palm
up with the calibration object, as docs/hardware.md asks, or `--mounting palm-down` without one),
`bh8 calibrate record` runs the full excitation on it through the pty, and `bh8 calibrate fit` on
`--jobs` processes fits it from the defaults; all three as a user runs them (subprocesses).

Printed: per hand, each parameter's error against the hidden value (the identifiable products with
--everything: a drive's efficiency times the peak torque over Table 7's; its strength over the links'
mass), how many standard deviations that is, the replay's position RMS at the defaults and fitted
(% of range), the log's blocks and the fit's seconds; then per parameter the median and largest
error and the share within 10 %.

`--free-running DIR` then replays each hand of that run without the replay's anchors (the open-loop
replay of the whole log) at the defaults and fitted.

Run: python benchmarks/bench_calibrate.py [--hands 10] [--first-seed 1] [--jobs 2] [--mounting palm-up|palm-down]
     [--everything] [--scale 1.0] [--out DIR]
     python benchmarks/bench_calibrate.py --free-running DIR
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bh8_gym.hand_file import load_hand_parameters
from bh8_gym.calibration.log_format import read_log
from bh8_gym.calibration.scene import DEFAULT_CALIBRATION_OBJECT
from bh8_gym.plant import PlantParameters

FITTED = ("finger_drive_efficiency", "spread_drive_efficiency", "spread_friction_torque", "strain_gain")
BH8 = [sys.executable, "-m", "bh8_gym.cli"]


def effective(values: dict, name: str) -> float:
    """What the log can tell of `name`: efficiencies times the peak torque over Table 7's; with the
    links' mass drawn, forces over mass (the spread's friction too)."""
    defaults = PlantParameters()
    value = values.get(name, getattr(defaults, name))
    torque = values.get("motor_peak_torque", defaults.motor_peak_torque) / defaults.motor_peak_torque
    mass = values.get("link_mass_scale", defaults.link_mass_scale)
    if name in ("finger_drive_efficiency", "spread_drive_efficiency"):
        return value * torque / mass
    if name == "spread_friction_torque":
        return value / mass
    if name == "strain_gain":
        return value * mass
    return value


def one_hand(seed: int, args, work: Path) -> dict:
    hidden, log, hand = work / f"hidden{seed}.toml", work / f"log{seed}.jsonl", work / f"hand{seed}.toml"
    draw = [*BH8, "calibrate", "draw", "--seed", str(seed), "-o", str(hidden)] + (["--everything"] if args.everything else [])
    subprocess.run(draw, check=True, stdout=subprocess.DEVNULL)
    scene = ["--object", DEFAULT_CALIBRATION_OBJECT] if args.mounting == "palm-up" else []
    server = subprocess.Popen([*BH8, "serve", "--state", str(work / f"state{seed}"), "--hand-parameters", str(hidden),
                               *scene], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        device = server.stdout.readline().strip()
        started = time.monotonic()
        subprocess.run([*BH8, "calibrate", "record", "--port", device, "--mounting", args.mounting, *scene,
                        "--scale", str(args.scale), "-o", str(log), "--force"], check=True, stdout=subprocess.DEVNULL)
        recorded = time.monotonic() - started
    finally:
        server.terminate()
        server.wait()
    started = time.monotonic()
    fitted = subprocess.run([*BH8, "calibrate", "fit", str(log), "-o", str(hand), "--jobs", str(args.jobs)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seconds = time.monotonic() - started
    truth = load_hand_parameters(hidden).values
    parsed = read_log(log)
    row = {"seed": seed, "blocks": parsed.blocks, "record_s": recorded, "fit_s": seconds, "exit": fitted.returncode,
           "simulated_s": None}
    if fitted.returncode != 0:
        row["error"] = fitted.stderr.strip().splitlines()[-1] if fitted.stderr.strip() else "?"
        return row
    result = load_hand_parameters(hand)
    row["rms_before"], row["rms_after"] = result.fit["position_rms_percent_before"], result.fit["position_rms_percent"]
    for name in FITTED:
        if name in result.values:
            true = effective(truth, name)
            row[name] = (result.values[name] / true - 1.0, abs(result.values[name] - true) / result.uncertainty[name])
        else:
            row[name] = None
    row["offsets"] = max(abs(a - b) for a, b in zip(result.values["strain_offsets"], truth["strain_offsets"]))
    return row


def free_running(work: Path) -> None:
    """The replays without anchors (the simulated hand left to itself from the first block to the
    last, as an open-loop replay of the log), at the defaults and fitted, for every hand in `work`:
    the position RMS over the same phases the fit compares, % of range."""
    from bh8_gym.calibration.replay import observed, replay
    from bh8_gym.calibration.residuals import REPLAY_OFFSETS, ResidualModel

    before, after = [], []
    for hand in sorted(work.glob("hand*.toml"), key=lambda p: int(p.stem[4:])):
        log = read_log(work / f"log{hand.stem[4:]}.jsonl")
        model = ResidualModel(observed(log), log.hand_clock)
        fitted = {k: v for k, v in load_hand_parameters(hand).values.items() if k != "strain_offsets"}
        rms = [model.position_rms(replay(log, {**values, "strain_offsets": REPLAY_OFFSETS}, anchored=False))
               for values in ({}, fitted)]
        before.append(rms[0])
        after.append(rms[1])
        print(f"hand {hand.stem[4:]}: free-running replay RMS {rms[0]:.2f} -> {rms[1]:.2f} % of range", flush=True)
    print(f"free-running: defaults median {np.median(before):.2f} (min {min(before):.2f}), fitted median "
          f"{np.median(after):.2f} (max {max(after):.2f}) % of range")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--free-running", type=Path, default=None, metavar="DIR",
                        help="only: the free-running replays of an earlier run's --out DIR")
    parser.add_argument("--hands", type=int, default=10)
    parser.add_argument("--first-seed", type=int, default=1)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--mounting", choices=("palm-up", "palm-down"), default="palm-up")
    parser.add_argument("--everything", action="store_true")
    parser.add_argument("--scale", type=float, default=1.0)
    parser.add_argument("--out", type=Path, default=None, help="keep the logs and hand files here")
    args = parser.parse_args()
    if args.free_running is not None:
        free_running(args.free_running)
        return
    work = args.out or Path(tempfile.mkdtemp(prefix="bench-calibrate-"))
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    for seed in range(args.first_seed, args.first_seed + args.hands):
        row = one_hand(seed, args, work)
        rows.append(row)
        if row["exit"] != 0:
            print(f"hand {seed}: fit exit {row['exit']}: {row.get('error')}", flush=True)
            continue
        errors = "  ".join(f"{name.split('_')[0][:6]}.{name.split('_')[1][:4]} "
                           + ("-" if row[name] is None else f"{100 * row[name][0]:+5.1f}% ({row[name][1]:.1f} sd)")
                           for name in FITTED)
        print(f"hand {seed}: {errors}  offsets ±{row['offsets']}  RMS {row['rms_before']:.2f} -> {row['rms_after']:.2f} % "
              f"of range; {row['blocks']} blocks, record {row['record_s']:.0f} s, fit {row['fit_s']:.0f} s", flush=True)
    done = [row for row in rows if row["exit"] == 0]
    print(f"\n{len(done)} of {len(rows)} hands fitted ({args.mounting}{', everything drawn' if args.everything else ''}, "
          f"scale {args.scale}, --jobs {args.jobs}); logs in {work}")
    for name in FITTED:
        errors = np.array([abs(row[name][0]) for row in done if row[name] is not None])
        sds = np.array([row[name][1] for row in done if row[name] is not None])
        if errors.size:
            print(f"{name:26s} identified in {errors.size:2d}: error median {100 * np.median(errors):.1f} %, "
                  f"max {100 * errors.max():.1f} %, within 10 %: {np.mean(errors <= 0.10):.0%}; "
                  f"|error|/sd median {np.median(sds):.1f}")
        else:
            print(f"{name:26s} identified in  0")
    if done:
        before = np.array([row["rms_before"] for row in done])
        after = np.array([row["rms_after"] for row in done])
        fit_s = np.array([row["fit_s"] for row in done])
        print(f"position RMS, % of range: defaults median {np.median(before):.2f} (min {before.min():.2f}), fitted "
              f"median {np.median(after):.2f} (max {after.max():.2f})")
        print(f"fit: median {np.median(fit_s):.0f} s, max {fit_s.max():.0f} s; log blocks median "
              f"{np.median([row['blocks'] for row in done]):.0f}")


if __name__ == "__main__":
    main()
