"""`bh8 render`: the simulated hand to a PNG (visual or collision shapes, with objects)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from bh8_gym.cli import integer_argument
from bh8_gym.objects import OBJECT_SPEC_HELP, ObjectError, add_object_from_spec
from bh8_gym.plant import HandPlant, PlantParameters
from bh8_gym.rendering import DEFAULT_CAMERA, Camera, camera_for, collision_frame, render_frame, save_png


def close_hand(plant, seconds: float = 1.5, velocity: float = 24_414.0, torque_fraction: float = 1.0) -> None:
    """Close the three fingers like a C at MCV 100 (App. A speed) for `seconds`, then leave them held."""
    for motor in (1, 2, 3):
        plant.set_drive(motor, velocity, torque_fraction)
    for _ in range(int(round(seconds / plant.dt))):
        plant.step()
    for motor in (1, 2, 3):
        plant.set_drive_off(motor)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--output", "-o", type=Path, default=Path("hand.png"),
                        help="PNG file to write (default: %(default)s)")
    parser.add_argument("--width", type=int, default=800, help="image width, pixels (default: %(default)s)")
    parser.add_argument("--height", type=int, default=600, help="image height, pixels (default: %(default)s)")
    parser.add_argument("--closed", action="store_true",
                        help="close the fingers (around the objects) first (default: open)")
    parser.add_argument("--spread", type=float, default=0.0, help="spread angle, degrees (0-180; default: %(default)s)")
    parser.add_argument(
        "--object", action="append", default=[], metavar="SPEC",
        help="add an object (repeatable; default: none): " + OBJECT_SPEC_HELP,
    )
    parser.add_argument("--wrist-height", type=float, default=None,
                        help="wrist height above the table, m (palm down; default: 0.3, or 0.2 with --object)")
    parser.add_argument("--palm-up", action="store_true", help="turn the hand palm up (default: palm down)")
    parser.add_argument("--yaw", type=float, default=DEFAULT_CAMERA.yaw,
                        help="camera yaw, degrees (default: %(default)s)")
    parser.add_argument("--pitch", type=float, default=DEFAULT_CAMERA.pitch,
                        help="camera pitch, degrees (default: %(default)s)")
    parser.add_argument("--distance", type=float, default=DEFAULT_CAMERA.distance,
                        help="camera distance from its target, m (default: %(default)s)")
    parser.add_argument("--seed", type=integer_argument(0), default=0,
                        help="seed of the plant's randomised constants (default: %(default)s)")
    parser.add_argument("--shapes", choices=("visual", "collision", "both"), default="visual",
                        help="draw the hand's visual shapes, its collision shapes (one colour per shape, "
                             "objects left out), or both side by side (default: %(default)s)")


def run(args) -> int:
    params = PlantParameters()
    if args.palm_up:
        params.wrist_orientation = (0.0, 0.0, 0.0, 1.0)
    if args.wrist_height is not None:
        params.wrist_position = (0.0, 0.0, float(args.wrist_height))
    elif args.object:
        params.wrist_position = (0.0, 0.0, 0.20)  # palm a few cm above a table-top object
    problem = None
    if not 0.0 <= args.spread <= 180.0:
        problem = f"--spread must be 0..180 degrees, got {args.spread}"
    elif not (16 <= args.width <= 4096 and 16 <= args.height <= 4096):
        problem = f"--width and --height must be 16..4096 pixels, got {args.width} x {args.height}"
    elif args.output.suffix.lower() != ".png" or args.output.is_dir():
        problem = f"--output must be a .png file, got {str(args.output)!r}"
    if problem is not None:
        print(f"bh8 render: {problem}", file=sys.stderr)
        return 2
    with HandPlant(params=params, seed=args.seed) as plant:
        try:
            for spec in args.object:
                add_object_from_spec(plant, spec)
        except ObjectError as error:
            print(f"bh8 render: {error}", file=sys.stderr)
            return 2
        plant.set_drive(4, 14_648.0 if args.spread > 0 else -14_648.0, 1.0)
        target = args.spread * 17.5
        for _ in range(500):  # settle objects; spread to its angle
            if args.spread > 0 and plant.motor_positions()[3] >= target:
                plant.set_drive(4, 0.0, 1.0)
            plant.step()
        if args.closed:
            close_hand(plant)
            for _ in range(100):
                plant.step()
        target_point = tuple(float(v) for v in camera_for(plant, None).target)
        camera = Camera(target=target_point, distance=args.distance, yaw=args.yaw, pitch=args.pitch)
        frames = []
        if args.shapes in ("visual", "both"):
            frames.append(render_frame(plant, args.width, args.height, camera))
        if args.shapes in ("collision", "both"):
            frames.append(collision_frame(plant, args.width, args.height, camera))
        try:
            save_png(args.output, np.hstack(frames))
        except OSError as error:
            print(f"bh8 render: cannot write {str(args.output)!r}: {error}", file=sys.stderr)
            return 1
    print(args.output)
    return 0
