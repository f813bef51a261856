"""Pictures of the grasp env's approach (docs/envs.md): a flat, a tall and a round object, each as a
strip of side views (looking along the hand's x axis, F3 on the left, F1 and F2 on the right) at the
start, through the grasp, at the lift's start and lifted, with a scripted LOOP grasp of the ceiling
family. The flat one gets the table-contact grasp (envs/scenes.py), the others the rigid approach.

Run: python benchmarks/draw_approach.py [--script loop-g80] [--out docs/images]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from PIL import Image

from bh8_gym.agents.grasps import FAMILY, make_script
from bh8_gym.agents.env_factory import make_env
from bh8_gym.objects import ObjectSpec
from bh8_gym.rendering import Camera, render_frame

OBJECTS = {
    "flat": ObjectSpec("box", (0.08, 0.05, 0.015), mass=0.1),
    "tall": ObjectSpec("box", (0.06, 0.04, 0.08), mass=0.15),
    "round": ObjectSpec("sphere", (0.05,), mass=0.1),
}
STEPS = (0, 40, 80, 124, 200)  # env steps of 6.47 ms: start, closing, closed, the lift's start, lifted


def strip(spec: ObjectSpec, script: str, size=(240, 200)) -> tuple[np.ndarray, bool]:
    env = make_env("BH8Grasp-v0", {"object_files": [spec], "randomize": False, "render_mode": "rgb_array"})
    try:
        base = env.unwrapped
        grasp = make_script(script, env)
        obs, info = env.reset(seed=0)
        # A point of view fixed on the table under the palm, level with the fingers.
        camera = Camera(target=(0.0, 0.0, base.scene.table_top + 0.06), distance=0.32, yaw=90.0, pitch=-5.0)
        frames, step, done = [], 0, False
        while not done and step <= STEPS[-1]:
            if step in STEPS:
                frames.append(render_frame(base.plant, *size, camera))
            obs, _, terminated, truncated, info = env.step(grasp.act(obs, info))
            done = terminated or truncated
            step += 1
        return np.concatenate(frames, axis=1), bool(info.get("is_success"))
    finally:
        env.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--script", default="loop-g80", choices=list(FAMILY))
    parser.add_argument("--out", type=Path, default=Path("docs/images"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for name, spec in OBJECTS.items():
        image, held = strip(spec, args.script)
        path = args.out / f"approach_{name}.png"
        Image.fromarray(image).save(path)
        print(f"{path}: {spec.kind} {spec.size}, {args.script} {'held it' if held else 'did not hold it'} at step {STEPS[-1]}")


if __name__ == "__main__":
    main()
