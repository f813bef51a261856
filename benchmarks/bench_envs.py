"""Benchmark the environments: env steps/s, simulated s per wall s, peak memory, vectorised envs,
the overhead against raw PyBullet stepping of the same scene, and a cProfile of the step path.

    python benchmarks/bench_envs.py [--steps 3000] [--envs 2] [--profile]

Overhead ratio = wall time of env steps / wall time of bare `p.stepSimulation` calls covering the
same simulated time in the same world (hand, table, object), i.e. what the drive train model,
the HCTL emulation, the firmware's byte handling and the env add on top of PyBullet itself.
"""
from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import resource
import time

import gymnasium as gym
import numpy as np
import pybullet as p

import bh8_gym  # noqa: F401
from bh8_gym.envs.wrappers import ContinuousActions


def closing_policy(env):
    """A fixed, contact-making action: close the fingers at a moderate gain (more physics than idle)."""
    low, high = env.action_space.low, env.action_space.high
    return np.array([60 if name == "LCV" else 160 for _, name in env.unwrapped.layout.control_fields],
                    dtype=np.int16).clip(low, high)


def bench_single(env_id: str, steps: int) -> dict:
    env = gym.make(env_id).unwrapped
    action = closing_policy(env)
    env.reset(seed=0)
    resets, sim_time = 0, 0.0
    start = time.perf_counter()
    reset_wall = 0.0
    for _ in range(steps):
        _, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            sim_time += env.elapsed()
            t = time.perf_counter()
            env.reset()
            reset_wall += time.perf_counter() - t
            resets += 1
    sim_time += env.elapsed()
    wall = time.perf_counter() - start
    physics_steps = sim_time / env.plant.dt
    # Raw PyBullet stepping of the same world over the same simulated time.
    env.reset(seed=0)
    client = env.plant.client
    t = time.perf_counter()
    for _ in range(int(physics_steps)):
        p.stepSimulation(physicsClientId=client)
    raw = time.perf_counter() - t
    env.close()
    return {
        "env": env_id,
        "steps_per_s": steps / wall,
        "sim_s_per_wall_s": sim_time / wall,
        "reset_ms": 1e3 * reset_wall / max(resets, 1),
        "cycle_ms": 1e3 * env.cycle_seconds,
        "physics_steps_per_env_step": physics_steps / steps,
        "raw_pybullet_step_us": 1e6 * raw / physics_steps,
        "env_per_physics_step_us": 1e6 * wall / physics_steps,
        "overhead_ratio": wall / raw,
    }


def bench_vector(env_id: str, n_envs: int, steps: int) -> dict:
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv

    vec = make_vec_env(env_id, n_envs=n_envs, seed=0, vec_env_cls=SubprocVecEnv, wrapper_class=ContinuousActions)
    vec.reset()
    action = np.full((n_envs,) + vec.action_space.shape, 0.4, dtype=np.float32)
    start = time.perf_counter()
    for _ in range(steps):
        vec.step(action)
    wall = time.perf_counter() - start
    vec.close()
    return {"env": env_id, "n_envs": n_envs, "steps_per_s": n_envs * steps / wall}


def profile(env_id: str, steps: int) -> str:
    env = gym.make(env_id).unwrapped
    action = closing_policy(env)
    env.reset(seed=0)
    profiler = cProfile.Profile()
    profiler.enable()
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
    profiler.disable()
    env.close()
    out = io.StringIO()
    pstats.Stats(profiler, stream=out).sort_stats("tottime").print_stats(18)
    return out.getvalue()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--envs", type=int, default=2)
    parser.add_argument("--profile", action="store_true")
    args = parser.parse_args()
    for env_id in ("BH8FingerReach-v0", "BH8Grasp-v0"):
        result = bench_single(env_id, args.steps)
        print(
            f"{env_id:18s} 1 process: {result['steps_per_s']:7.0f} env steps/s, "
            f"{result['sim_s_per_wall_s']:5.2f} sim s/wall s, cycle {result['cycle_ms']:.2f} ms "
            f"({result['physics_steps_per_env_step']:.2f} physics steps), reset {result['reset_ms']:.2f} ms, "
            f"raw PyBullet {result['raw_pybullet_step_us']:.0f} us/physics step vs env "
            f"{result['env_per_physics_step_us']:.0f} us -> overhead ratio {result['overhead_ratio']:.2f}"
        )
        vector = bench_vector(env_id, args.envs, max(args.steps // args.envs, 200))
        print(f"{env_id:18s} {args.envs} SubprocVecEnv envs: {vector['steps_per_s']:7.0f} env steps/s total")
    peak_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(f"peak RSS of this process: {peak_kib / 1024:.0f} MiB")
    if args.profile:
        for env_id in ("BH8Grasp-v0",):
            print(profile(env_id, args.steps))


if __name__ == "__main__":
    main()
