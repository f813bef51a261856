"""Benchmark the environments: env steps/s, simulated s per wall s, peak memory, vectorised envs,
the overhead against raw PyBullet stepping of the same scene, and a cProfile of the step path.

    python benchmarks/bench_envs.py [--steps 3000] [--repeats 3] [--envs 2] [--profile]

With panda-gym installed (`pip install panda-gym`; not a dependency) its PandaReach-v3 is measured
the same way, side by side.

Overhead ratio = wall time of the env steps / wall time of bare `p.stepSimulation` calls over the
same simulated time in the same world: the same episodes (same seeds, so the same objects and
placements, physics steps per episode as the env run took), the hand's joints under PyBullet's own
velocity motors closing the fingers at the benchmark action's speed with the drive's full torque
(so the fingers reach the object and the contacts load the solver as in the env run). Resets are
excluded from both. That is what the drive-train model, the HCTL emulation, the firmware's byte
handling and the env add on top of PyBullet itself. As a cross-check the env's steps are run again
with PyBullet's calls timed (the same states: the env is deterministic): that run's wall / its own
`p.stepSimulation` time is the same ratio measured on the env's very states (the raw baseline's
arm stays still; the env's lifts; the timer adds about 0.2 µs per PyBullet call, ~1 %), and the env's other PyBullet calls (joint reads every physics
step, motor commands, the reward's pose and contact queries) give the ratio the env would have if
all of our Python took no time. Each measurement is repeated (`--repeats` rounds, interleaved)
and reported as median (min-max): on a shared 2-core machine single runs scatter by ±15 %.
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
from bh8_gym.cli import json_object_argument
from bh8_gym.motion_control import VELOCITY_SCALE, sample_period
from bh8_gym.parameters import coefficient
from bh8_gym.plant import (
    FINGER_JOINTS, INNER_COUNTS_PER_RAD, INNER_GEAR_RATIO, NUM_JOINTS, SPREAD_COUNTS_PER_RAD, SPREAD_GEAR_RATIO,
    SPREAD_INDEX,
)
from bh8_gym.envs.wrappers import ContinuousActions
from physics_timer import PhysicsTimer


def closing_policy(env):
    """A fixed, contact-making action: close the fingers at a moderate gain (more physics than idle)."""
    low, high = env.action_space.low, env.action_space.high
    return np.array([60 if name == "LCV" else 160 for _, name in env.unwrapped.layout.control_fields],
                    dtype=np.int16).clip(low, high)


def pybullet_motor_targets(env, action) -> tuple[list[float], list[float]]:
    """Joint velocity targets (rad/s) and force limits (N·m) for PyBullet's own velocity motors that
    move the hand as `action` (LCV velocity bytes, saturating gains) drives it: each finger closes
    at the LCV speed (inner joint M/125 degrees, outer joint M/375 relative to it) with the drive's
    full torque; the spread likewise; F2's spread joint follows F1's through the gear constraint."""
    period = sample_period(31)
    speed = {1: 0.0, 2: 0.0, 3: 0.0, 4: 0.0}  # motor counts per second
    for (motor, name), value in zip(env.layout.control_fields, action):
        if name == "LCV":
            speed[motor] = value * coefficient(env.coefficients["LCVC"]) / VELOCITY_SCALE / period
    prm = env.plant.params
    finger_torque = prm.motor_peak_torque * INNER_GEAR_RATIO * prm.finger_drive_efficiency
    spread_torque = prm.motor_peak_torque * SPREAD_GEAR_RATIO * prm.spread_drive_efficiency
    velocities, forces = [0.0] * NUM_JOINTS, [0.0] * NUM_JOINTS
    velocities[SPREAD_INDEX[0]], forces[SPREAD_INDEX[0]] = speed[4] / SPREAD_COUNTS_PER_RAD, spread_torque
    for finger, inner, outer in FINGER_JOINTS:
        omega = speed[finger + 1] / INNER_COUNTS_PER_RAD
        velocities[inner], forces[inner] = omega, finger_torque
        velocities[outer], forces[outer] = omega / 3.0, finger_torque
    return velocities, forces


def raw_pybullet_seconds(env, action, episode_physics_steps: list[int], seed: int) -> float:
    """Wall time of bare `p.stepSimulation` over the env run's episodes (see the module docstring)."""
    plant = env.plant
    client = plant.client
    velocities, forces = pybullet_motor_targets(env, action)
    total = 0.0
    for episode, steps in enumerate(episode_physics_steps):
        env.reset(seed=seed if episode == 0 else None)
        p.setJointMotorControlArray(plant.hand_id, plant.joint_indices, p.VELOCITY_CONTROL, targetVelocities=velocities,
                                    forces=forces, physicsClientId=client)
        start = time.perf_counter()
        for _ in range(steps):
            p.stepSimulation(physicsClientId=client)
        total += time.perf_counter() - start
    return total


def run_episodes(env, action, steps: int, seed: int) -> tuple[float, float, list[int], float]:
    """(wall seconds of the steps, simulated seconds, physics steps per episode, mean reset seconds);
    the steps' wall time excludes the resets. Every reset is timed, the seeded first one included
    (a run shorter than one episode, as the grasp env's 300 steps, has no other)."""
    clock = time.perf_counter
    start = clock()
    env.reset(seed=seed)
    wall, sim_time, episode_steps, reset_wall = 0.0, 0.0, [], clock() - start
    episode_start = env.plant.time
    start = clock()
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            wall += clock() - start
            sim_time += env.elapsed()
            episode_steps.append(round((env.plant.time - episode_start) / env.plant.dt))
            start = clock()
            env.reset()
            reset_wall += clock() - start
            episode_start = env.plant.time
            start = clock()
    wall += clock() - start
    sim_time += env.elapsed()
    episode_steps.append(round((env.plant.time - episode_start) / env.plant.dt))
    return wall, sim_time, episode_steps, reset_wall / len(episode_steps)  # one reset per episode


def bench_single(env_id: str, steps: int, repeats: int, env_kwargs: dict, seed: int = 0) -> dict:
    """`repeats` rounds of: the env's steps, raw stepping of the same episodes, the env's steps again
    with PyBullet's calls timed (deterministic: the very same states). Ratios per round."""
    env = gym.make(env_id, **env_kwargs).unwrapped
    action = closing_policy(env)
    rounds = []
    for _ in range(repeats):
        wall, sim_time, episode_steps, reset_seconds = run_episodes(env, action, steps, seed)
        physics_steps = sum(episode_steps)
        raw = raw_pybullet_seconds(env, action, episode_steps, seed)
        with PhysicsTimer() as timer:
            timed_wall, _, _, _ = run_episodes(env, action, steps, seed)
        rounds.append({
            "steps_per_s": steps / wall,
            "sim_s_per_wall_s": sim_time / wall,
            "reset_ms": 1e3 * reset_seconds,
            "raw_pybullet_step_us": 1e6 * raw / physics_steps,
            "in_env_physics_step_us": 1e6 * timer.seconds / timer.calls,
            "other_pybullet_us": 1e6 * timer.other_seconds / timer.calls,
            "env_per_physics_step_us": 1e6 * wall / physics_steps,
            "overhead_ratio": wall / raw,
            "in_env_overhead_ratio": timed_wall / timer.seconds,  # one run: no drift between runs
            # What the env would cost if our Python took no time: its PyBullet calls alone.
            "pybullet_calls_ratio": (timer.seconds + timer.other_seconds) / timer.seconds,
        })
    result = {"env": env_id, "cycle_ms": 1e3 * env.cycle_seconds, "physics_dt_ms": 1e3 * env.plant.dt,
              "physics_steps_per_env_step": physics_steps / steps, "rounds": rounds}
    env.close()
    for key in rounds[0]:
        values = sorted(r[key] for r in rounds)
        result[key] = (values[len(values) // 2], values[0], values[-1])  # median, min, max
    return result


def bench_panda_gym(steps: int, repeats: int) -> dict | None:
    """panda-gym's PandaReach-v3 measured the same way as ours (its own `stepSimulation` and other
    PyBullet calls timed in the same run), for side-by-side figures; None without panda-gym."""
    try:
        import panda_gym
    except ImportError:
        return None
    env = gym.make("PandaReach-v3")
    action = np.full(env.action_space.shape, 0.3, dtype=np.float32)

    def run() -> float:
        env.reset(seed=0)
        start = time.perf_counter()
        for _ in range(steps):
            _, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                env.reset()
        return time.perf_counter() - start

    rounds = []
    for _ in range(repeats):
        wall = run()
        with PhysicsTimer() as timer:
            timed_wall = run()
        rounds.append((steps / wall, timer.calls / steps, 1e6 * timer.seconds / timer.calls, timed_wall / timer.seconds,
                       (timer.seconds + timer.other_seconds) / timer.seconds))
    env.close()
    rounds.sort(key=lambda r: r[3])
    steps_per_s, physics_per_step, physics_us, ratio, calls_ratio = rounds[len(rounds) // 2]
    return {"version": panda_gym.__version__, "steps_per_s": steps_per_s, "physics_steps_per_env_step": physics_per_step,
            "physics_step_us": physics_us, "in_env_overhead_ratio": ratio, "pybullet_calls_ratio": calls_ratio,
            "ratio_range": (rounds[0][3], rounds[-1][3])}


def bench_vector(env_id: str, n_envs: int, steps: int, env_kwargs: dict, engine: str = "sharded") -> dict:
    """Total env steps/s of `n_envs` envs stepped together: in bh8 train's ShardedVecEnv (the first
    shard in this process, one worker process per further shard) or in SB3's SubprocVecEnv (one
    worker process per env)."""
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv

    from bh8_gym.agents.training.vec_env import ShardedVecEnv

    vec_env_cls = {"sharded": ShardedVecEnv, "subproc": SubprocVecEnv}[engine]
    vec = make_vec_env(env_id, n_envs=n_envs, seed=0, vec_env_cls=vec_env_cls, wrapper_class=ContinuousActions,
                       env_kwargs=env_kwargs)
    vec.reset()
    action = np.full((n_envs,) + vec.action_space.shape, 0.4, dtype=np.float32)
    start = time.perf_counter()
    for _ in range(steps):
        vec.step(action)
    wall = time.perf_counter() - start
    worker_peaks_mib = [peak_rss_mib(process.pid) for process in vec.processes]
    vec.close()
    return {"env": env_id, "n_envs": n_envs, "steps_per_s": n_envs * steps / wall, "worker_peak_mib": worker_peaks_mib}


def peak_rss_mib(pid: int) -> float:
    """A live process's peak resident set (VmHWM), from /proc: the workers are not our children
    under SB3's forkserver start method, so getrusage cannot see them."""
    with open(f"/proc/{pid}/status") as status:
        for line in status:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    raise RuntimeError(f"no VmHWM for process {pid}")


def profile(env_id: str, steps: int, env_kwargs: dict) -> str:
    env = gym.make(env_id, **env_kwargs).unwrapped
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
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=3000,
                        help="env steps per measurement (the vectorised one splits them over its envs; default: %(default)s)")
    parser.add_argument("--envs", type=int, default=2, help="envs in the vectorised measurement (default: %(default)s)")
    parser.add_argument("--repeats", type=int, default=3,
                        help="rounds per env (the ratios' spread is the machine's noise; default: %(default)s)")
    parser.add_argument("--profile", action="store_true",
                        help="also print a cProfile of the step path (default: off)")
    parser.add_argument("--env-kwargs", type=json_object_argument, default={},
                        help='JSON keywords for both envs, e.g. \'{"plant_parameters": {"solver_iterations": 200}}\' (default: none)')
    args = parser.parse_args()
    for env_id in ("BH8FingerReach-v0", "BH8Grasp-v0"):
        r = bench_single(env_id, args.steps, args.repeats, args.env_kwargs)

        def fmt(key, spec, scale=1.0):
            median, low, high = (scale * v for v in r[key])
            return f"{median:{spec}} ({low:{spec}}-{high:{spec}})"

        print(
            f"{env_id} 1 process, median (min-max) of {args.repeats} rounds:\n"
            f"  {fmt('steps_per_s', '.0f')} env steps/s, {fmt('sim_s_per_wall_s', '.2f')} sim s/wall s; "
            f"cycle {r['cycle_ms']:.2f} ms = {r['physics_steps_per_env_step']:.2f} physics steps of "
            f"{r['physics_dt_ms']:.1f} ms; reset {fmt('reset_ms', '.2f')} ms\n"
            f"  per physics step: raw PyBullet {fmt('raw_pybullet_step_us', '.0f')} us; in the env "
            f"{fmt('in_env_physics_step_us', '.0f')} us stepSimulation + {fmt('other_pybullet_us', '.1f')} us other "
            f"PyBullet calls, {fmt('env_per_physics_step_us', '.0f')} us in all\n"
            f"  overhead ratio vs raw PyBullet {fmt('overhead_ratio', '.2f')}; vs the env's own stepSimulation "
            f"{fmt('in_env_overhead_ratio', '.2f')}, of which its other PyBullet calls alone "
            f"{fmt('pybullet_calls_ratio', '.2f')}"
        )
        # The like-for-like baseline of the vectorised rows is one env in a vector env in this process:
        # the same wrappers, actions and resets (the row above times the bare env and leaves resets out).
        engines = {("sharded", 1): "1 env in ShardedVecEnv (this process: the baseline)",
                   ("sharded", args.envs): f"{args.envs} envs in ShardedVecEnv (bh8 train's)",
                   ("subproc", args.envs): f"{args.envs} envs in SB3's SubprocVecEnv"}
        vectors = {engine: [] for engine in engines}
        for _ in range(args.repeats):  # interleaved, as the single-process rounds
            for (engine, n_envs), runs in vectors.items():
                runs.append(bench_vector(env_id, n_envs, max(args.steps // n_envs, 200), args.env_kwargs, engine))
        for engine, runs in vectors.items():
            rates = sorted(run["steps_per_s"] for run in runs)
            peaks = [peak for run in runs for peak in run["worker_peak_mib"]]
            workers = (f"{len(runs[0]['worker_peak_mib'])} worker processes, peak RSS per worker {max(peaks):.0f} MiB"
                       if peaks else "no worker process")
            print(f"{env_id} {engines[engine]}: {rates[len(rates) // 2]:.0f} "
                  f"({rates[0]:.0f}-{rates[-1]:.0f}) env steps/s total, {workers}")
    peak_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(f"peak RSS: this process (one env of each kind) {peak_kib / 1024:.0f} MiB")
    panda = bench_panda_gym(args.steps, args.repeats)
    if panda is None:
        print("PandaReach-v3: panda-gym is not installed (pip install panda-gym) - comparison skipped")
    else:
        low, high = panda["ratio_range"]
        print(f"PandaReach-v3 (panda-gym {panda['version']}), median round of {args.repeats}: "
              f"{panda['steps_per_s']:.0f} env steps/s, {panda['physics_steps_per_env_step']:.0f} physics steps "
              f"of {panda['physics_step_us']:.0f} us per env step; overhead ratio vs its own stepSimulation "
              f"{panda['in_env_overhead_ratio']:.2f} ({low:.2f}-{high:.2f}), of which its other PyBullet calls alone "
              f"{panda['pybullet_calls_ratio']:.2f}")
    if args.profile:
        for env_id in ("BH8Grasp-v0",):
            print(profile(env_id, args.steps, args.env_kwargs))


if __name__ == "__main__":
    main()
