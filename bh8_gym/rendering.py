"""Headless rendering of the simulated hand: TinyRenderer frames, PNG, GIF/MP4, and the display probe.

TinyRenderer (PyBullet's software renderer) needs no display or GPU, so frames render the same on
CI, in subprocess vector environments and on a laptop.
"""
from __future__ import annotations

import io
import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pybullet as p



@dataclass(frozen=True)
class Camera:
    """An orbit camera looking at `target` (world metres) from `distance` at `yaw`/`pitch` degrees."""

    target: tuple[float, float, float] = (0.0, 0.0, 0.14)
    distance: float = 0.42
    yaw: float = 40.0
    pitch: float = -22.0
    fov: float = 45.0
    light_direction: tuple[float, float, float] = (0.4, -0.6, 1.0)


DEFAULT_CAMERA = Camera()


def camera_for(plant, camera) -> Camera:
    if camera is None:
        # Frame the hand: look at a point between the wrist and the fingers.
        position, orientation = plant.wrist_pose()
        rotation = np.array(p.getMatrixFromQuaternion(orientation)).reshape(3, 3)
        target = position + rotation @ np.array([0.0, 0.0, 0.10])
        return Camera(target=tuple(float(v) for v in target))
    if isinstance(camera, Camera):
        return camera
    if isinstance(camera, dict):
        return Camera(**camera)
    raise ValueError(f"camera must be None, a rendering.Camera or a dict of its fields, got {camera!r}")


def check_image_size(width, height) -> None:
    """The image sizes render_frame takes: integers in 16..4096 pixels (ValueError otherwise)."""
    if not (isinstance(width, int) and isinstance(height, int) and 16 <= width <= 4096 and 16 <= height <= 4096):
        raise ValueError(f"width and height must be integers in 16..4096, got {width!r} x {height!r}")


def render_frame(plant, width: int = 640, height: int = 480, camera=None) -> np.ndarray:
    """An RGB image (height, width, 3) uint8 of the plant's world, rendered headless (TinyRenderer)."""
    check_image_size(width, height)
    cam = camera_for(plant, camera)
    view = p.computeViewMatrixFromYawPitchRoll(cam.target, cam.distance, cam.yaw, cam.pitch, 0.0, 2, physicsClientId=plant.client)
    projection = p.computeProjectionMatrixFOV(cam.fov, width / height, 0.01, 5.0, physicsClientId=plant.client)
    _, _, rgba, _, _ = p.getCameraImage(
        width, height, view, projection, renderer=p.ER_TINY_RENDERER, shadow=1,
        lightDirection=list(cam.light_direction), lightAmbientCoeff=0.55, lightDiffuseCoeff=0.5,
        lightSpecularCoeff=0.15, physicsClientId=plant.client,
    )
    return np.asarray(rgba, dtype=np.uint8).reshape(height, width, 4)[:, :, :3].copy()


# A colour per kind of link (palm, knuckle, inner, outer), each piece of a compound shape a shade of it.
_LINK_COLOURS = {"palm": (0.30, 0.45, 0.75), "knuckle": (0.35, 0.35, 0.38), "inner": (0.85, 0.45, 0.15),
                 "outer": (0.25, 0.65, 0.30)}


def collision_frame(plant, width: int = 640, height: int = 480, camera=None) -> np.ndarray:
    """Like `render_frame`, but of the hand's collision shapes (what PyBullet computes contacts with),
    each drawn in its own colour, posed as the hand is now; the table and objects are left out."""
    check_image_size(width, height)
    cam = camera_for(plant, camera)
    client, hand = plant.client, plant.hand_id
    scratch = p.connect(p.DIRECT)
    try:
        for link in range(-1, p.getNumJoints(hand, physicsClientId=client)):
            if link == -1:
                frame = p.getBasePositionAndOrientation(hand, physicsClientId=client)
            else:
                frame = p.getLinkState(hand, link, computeForwardKinematics=True, physicsClientId=client)[:2]
            name = "palm" if link == -1 else p.getJointInfo(hand, link, physicsClientId=client)[12].decode()
            base = _LINK_COLOURS.get(name.split("_")[-1], (0.5, 0.5, 0.5))
            for index, shape in enumerate(p.getCollisionShapeData(hand, link, physicsClientId=client)):
                kind, size, local_position, local_orientation = shape[2], shape[3], shape[5], shape[6]
                shade = 1.0 - 0.18 * (index % 4)
                rgba = (*(shade * c for c in base), 1.0)
                if kind == p.GEOM_BOX:
                    visual = p.createVisualShape(p.GEOM_BOX, halfExtents=[v / 2.0 for v in size], rgbaColor=rgba,
                                                 physicsClientId=scratch)
                elif kind == p.GEOM_CYLINDER:
                    visual = p.createVisualShape(p.GEOM_CYLINDER, radius=size[1], length=size[0], rgbaColor=rgba,
                                                 physicsClientId=scratch)
                elif kind == p.GEOM_SPHERE:
                    visual = p.createVisualShape(p.GEOM_SPHERE, radius=size[0], rgbaColor=rgba, physicsClientId=scratch)
                else:
                    continue  # the hand is built of boxes and cylinders only
                position, orientation = p.multiplyTransforms(frame[0], frame[1], local_position, local_orientation)
                p.createMultiBody(0.0, -1, visual, position, orientation, physicsClientId=scratch)
        view = p.computeViewMatrixFromYawPitchRoll(cam.target, cam.distance, cam.yaw, cam.pitch, 0.0, 2,
                                                   physicsClientId=scratch)
        projection = p.computeProjectionMatrixFOV(cam.fov, width / height, 0.01, 5.0, physicsClientId=scratch)
        image = p.getCameraImage(width, height, view, projection, renderer=p.ER_TINY_RENDERER, shadow=1,
                                 lightDirection=list(cam.light_direction), lightAmbientCoeff=0.55,
                                 lightDiffuseCoeff=0.5, lightSpecularCoeff=0.15, physicsClientId=scratch)[2]
    finally:
        p.disconnect(scratch)
    return np.reshape(np.asarray(image, dtype=np.uint8), (height, width, 4))[:, :, :3].copy()


def save_png(path, rgb: np.ndarray) -> Path:
    """Write an (H, W, 3) uint8 image as PNG."""
    import imageio.v2 as imageio

    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 3) uint8 image, got shape {rgb.shape} dtype {rgb.dtype}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    imageio.imwrite(path, rgb, format="png")
    return path


MIN_GIF_FRAME_MS = 20  # browsers play GIF frames of 10 ms or less at 100 ms


def steps_per_frame(step_seconds: float) -> int:
    """The fewest env steps of `step_seconds` that make a frame of at least MIN_GIF_FRAME_MS, so an
    animation of every n-th step plays in real time (one frame per 6.5 ms step would play 15x slow)."""
    return max(1, math.ceil(MIN_GIF_FRAME_MS / (1000.0 * step_seconds) - 1e-9))


def gif_durations(count: int, fps: float) -> list[int]:
    """Per-frame GIF durations (ms) for `count` frames at `fps`.

    A GIF stores whole centiseconds, so one fixed duration would play a 25.9 ms frame as 20 ms. Each
    frame ends at its true time rounded to 10 ms instead, and the clip keeps its length. Frames are at
    least MIN_GIF_FRAME_MS: browsers show shorter ones at 100 ms (so above 50 fps a clip plays slow).
    """
    frame_ms = 1000.0 / fps
    durations, shown = [], 0
    for index in range(1, count + 1):
        duration = max(MIN_GIF_FRAME_MS, int(round(index * frame_ms / 10.0)) * 10 - shown)
        durations.append(duration)
        shown += duration
    return durations


def encode_gif(frames, fps: float = 20.0) -> bytes:
    """Frames as the bytes of a GIF that plays in real time at `fps` (`gif_durations`)."""
    import imageio.v2 as imageio

    frames = _checked_frames(frames, fps)
    buffer = io.BytesIO()
    imageio.mimsave(buffer, frames, format="GIF", duration=gif_durations(len(frames), fps), loop=0)
    return buffer.getvalue()


def _checked_frames(frames, fps: float) -> list[np.ndarray]:
    frames = [np.asarray(frame, dtype=np.uint8) for frame in frames]
    if not frames:
        raise ValueError("an animation needs at least one frame")
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be positive, got {fps!r}")
    return frames


def write_animation(frames, path, fps: float = 20.0) -> Path:
    """Write frames as a GIF (`.gif`) or MP4 (`.mp4`, needs the `video` extra: imageio-ffmpeg)."""
    import imageio.v2 as imageio

    frames = _checked_frames(frames, fps)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = path.suffix.lower()
    if suffix == ".gif":
        path.write_bytes(encode_gif(frames, fps))
    elif suffix == ".mp4":
        try:
            import imageio_ffmpeg  # noqa: F401  (only checks that the backend exists)
        except ImportError:
            raise RuntimeError("writing MP4 needs imageio-ffmpeg: pip install 'bh8-gym[video]', or write a .gif") from None
        imageio.mimsave(path, frames, format="FFMPEG", fps=fps, macro_block_size=1)
    else:
        raise ValueError(f"animation path must end in .gif or .mp4, got {str(path)!r}")
    return path


def display_available() -> bool:
    """False on Linux and the BSDs when DISPLAY is not set. PyBullet's GUI then ends the whole
    process (exit status 1, no exception), so it is checked before connecting."""
    if sys.platform.startswith("linux") or "bsd" in sys.platform:
        return bool(os.environ.get("DISPLAY"))
    return True
