"""The calibration's scene: how the hand is mounted and what rests on its palm, the same for the
hand that was recorded (`bh8 serve`, or the lab's) and for the simulator that replays the log.

- palm-down (`--mounting palm-down`): the plant's default scene, the hand hanging palm-down on its
  arm, nothing within reach of the fingers (`bh8 serve` without --object serves this);
- palm-up (`--mounting palm-up`): the hand standing on its base, palm up, free space around; with
  a calibration object (`--object SPEC`) that object rests on the palm's centre, as
  `bh8 serve --object SPEC` places it.

The calibration object is a primitive (box, sphere, cylinder or capsule with its mass): a log
names it, and nothing a log says may reach PyBullet's file parsers.
"""
from __future__ import annotations

from bh8_gym.objects import PRIMITIVE_KINDS, ObjectError, parse_object_spec

# The object docs/hardware.md asks the lab to put on the palm: a rigid 50 mm cube (a wooden or plastic
# block) standing on the palm's centre. The closing fingers meet it with their fingertips, which
# load the gauges (a can or a large cylinder meets the inner links first: the gauges barely read),
# from about 8,000 counts (F3) on, beyond the sweeps' SWEEP_HIGH.
DEFAULT_CALIBRATION_OBJECT = "box:0.05;mass=0.1"


def check_calibration_object(text: str) -> str:
    """`text` if it is a primitive object spec resting on the palm (no file, no position), else ValueError."""
    if not isinstance(text, str) or len(text) > 200:
        raise ValueError(f"a calibration object is a short spec such as {DEFAULT_CALIBRATION_OBJECT!r}")
    try:
        spec, position = parse_object_spec(text)
    except ObjectError as error:
        raise ValueError(str(error)) from None
    if spec.kind not in PRIMITIVE_KINDS:
        raise ValueError(f"a calibration object must be a box, sphere, cylinder or capsule (its size and mass given), "
                         f"not a file: {text!r}")
    if position is not None:
        raise ValueError(f"a calibration object rests on the palm's centre; give no @X,Y,Z: {text!r}")
    return text


def replay_plant(mounting: str, calibration_object: str | None, hand: dict):
    """A HandPlant in the recorded scene with the hand's PlantParameters fields `hand`."""
    from bh8_gym.simulator import build_plant

    if calibration_object is not None and mounting != "palm-up":
        raise ValueError("a calibration object rests on the palm: the hand must be mounted palm-up")
    objects = () if calibration_object is None else (check_calibration_object(calibration_object),)
    return build_plant(seed=0, objects=objects, hand=hand, palm_up=mounting == "palm-up")
