"""`ShardedVecEnv`: SB3's vectorised env with the envs split into shards, one shard per process,
the first shard stepped in the training process itself.

Why (docs/benchmarks.md, "Training"): SB3's `SubprocVecEnv` puts each env in a process of its own,
so every vector step is a pipe round trip per env (pickled actions out, pickled observations and
infos back, two wake-ups) while the training process sleeps, and then the workers sleep while it
computes the next actions: two grasp envs in SubprocVecEnv stepped fewer env steps per second in
all than one env in one process. Here each worker process holds a shard of envs and answers a
step with one message, and the training process steps its own shard meanwhile instead of waiting:
on 2 cores with 2 envs, one env is stepped here and one in the single worker.

Env i is the same env built by the same factory and seeded the same way as in `SubprocVecEnv`
(`VecEnv.seed` gives env i seed + i), and each step goes through the same
step-then-reset-on-done sequence, so a training run is the same run with either: only where the
envs live differs.
"""
from __future__ import annotations

import multiprocessing as mp
import os
import signal
import traceback
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from stable_baselines3.common.env_util import is_wrapped
from stable_baselines3.common.vec_env.base_vec_env import CloudpickleWrapper, VecEnv, VecEnvIndices

from bh8_gym.agents.evaluation.eval_worker import EvaluationWorkerError, last_line
from bh8_gym.child_processes import in_worker, stop, track


class WorkerError(EvaluationWorkerError):
    """An env worker process raised (its error's last line in the message, its traceback in
    `details`) or exited."""


def _step(env: gym.Env, action) -> tuple:
    """One env step the way SB3's vectorised envs report it: done = terminated or truncated, the
    last observation kept in info["terminal_observation"] and the env reset in its place."""
    observation, reward, terminated, truncated, info = env.step(action)
    done = terminated or truncated
    info["TimeLimit.truncated"] = truncated and not terminated
    reset_info = {}
    if done:
        info["terminal_observation"] = observation
        observation, reset_info = env.reset()
    return observation, reward, done, info, reset_info


def _reset(env: gym.Env, seed: int | None, options: dict) -> tuple:
    return env.reset(seed=seed, **({"options": options} if options else {}))


class _Shard:
    """A list of envs and the commands a worker (or the training process) runs on them. A command
    with `indices` acts on those envs of the shard (positions within it)."""

    def __init__(self, env_fns: Sequence[Callable[[], gym.Env]]):
        self.envs = [env_fn() for env_fn in env_fns]
        # SB3 keeps each env's last reset info: a step that did not reset reports the previous one.
        self.reset_infos: list[dict] = [{} for _ in self.envs]

    def step(self, actions) -> list[tuple]:
        results = []
        for index, (env, action) in enumerate(zip(self.envs, actions, strict=True)):
            observation, reward, done, info, reset_info = _step(env, action)
            if done:
                self.reset_infos[index] = reset_info
            results.append((observation, reward, done, info, self.reset_infos[index]))
        return results

    def reset(self, seeds_and_options) -> list[tuple]:
        results = [_reset(env, seed, options) for env, (seed, options) in zip(self.envs, seeds_and_options, strict=True)]
        self.reset_infos = [reset_info for _, reset_info in results]
        return results

    def spaces(self) -> tuple:
        return self.envs[0].observation_space, self.envs[0].action_space

    def render(self, indices) -> list:
        return [self.envs[i].render() for i in indices]

    def env_method(self, indices, name: str, args: tuple, kwargs: dict) -> list:
        return [self.envs[i].get_wrapper_attr(name)(*args, **kwargs) for i in indices]

    def get_attr(self, indices, name: str) -> list:
        return [self.envs[i].get_wrapper_attr(name) for i in indices]

    def has_attr(self, name: str) -> bool:
        try:
            for env in self.envs:
                env.get_wrapper_attr(name)
        except AttributeError:
            return False
        return True

    def set_attr(self, indices, name: str, value) -> list[None]:
        return [setattr(self.envs[i], name, value) for i in indices]

    def is_wrapped(self, indices, wrapper_class) -> list[bool]:
        return [is_wrapped(self.envs[i], wrapper_class) for i in indices]

    def close(self) -> None:
        for env in self.envs:
            env.close()


# What a worker does for the training process: the `_Shard` methods of these names.
COMMANDS = ("step", "reset", "spaces", "render", "env_method", "get_attr", "has_attr", "set_attr", "is_wrapped")


def _worker(remote, parent_remote, env_fns: CloudpickleWrapper, ignore_signals: tuple) -> None:
    """A worker process: builds its shard, then answers (command, args) messages with ("ok", result)
    or ("error", traceback) until "close" or the pipe closes."""
    for signum in ignore_signals:
        signal.signal(signum, signal.SIG_IGN)
    in_worker()
    parent_remote.close()
    try:
        shard = _Shard(env_fns.var)
    except Exception:  # noqa: BLE001 - reported to the training process, which raises it
        remote.send(("error", traceback.format_exc()))
        remote.close()
        return
    remote.send(("ok", None))
    while True:
        try:
            command, args = remote.recv()
        except (EOFError, KeyboardInterrupt):
            break
        if command == "close":
            shard.close()
            remote.send(("ok", None))
            break
        try:
            if command not in COMMANDS:
                raise ValueError(f"unknown command {command!r}")
            remote.send(("ok", getattr(shard, command)(*args)))
        except Exception:  # noqa: BLE001 - as above
            remote.send(("error", traceback.format_exc()))
    remote.close()


def _stack(observations: Sequence, space: spaces.Space):
    """Per-env observations as one batch, env index first (dict and tuple spaces per entry)."""
    if isinstance(space, spaces.Dict):
        return {key: np.stack([obs[key] for obs in observations]) for key in space.spaces}
    if isinstance(space, spaces.Tuple):
        return tuple(np.stack([obs[i] for obs in observations]) for i in range(len(space.spaces)))
    return np.stack(observations)


def shard_sizes(n_envs: int, n_processes: int) -> list[int]:
    """Envs per process, as even as can be, the larger shards first (this process's first)."""
    if n_envs < 1 or n_processes < 1:
        raise ValueError(f"need at least one env and one process, got {n_envs} envs, {n_processes} processes")
    n_processes = min(n_processes, n_envs)
    return [n_envs // n_processes + (1 if i < n_envs % n_processes else 0) for i in range(n_processes)]


class ShardedVecEnv(VecEnv):
    """`n_envs` envs in `n_processes` processes (default: one per core, at most one per env), each
    holding a contiguous shard of them; the first shard lives in this process.

    `ignore_signals`: signals the worker processes ignore (`bh8 train` stops on them through this
    process, which then closes the workers). `start_method`: multiprocessing's, "forkserver" by
    default as SB3's (fork is unsafe once torch runs threads).
    """

    def __init__(self, env_fns: Sequence[Callable[[], gym.Env]], n_processes: int | None = None,
                 ignore_signals: tuple = (), start_method: str | None = None):
        self.closed = False
        n_envs = len(env_fns)
        sizes = shard_sizes(n_envs, n_processes if n_processes is not None else (os.cpu_count() or 1))
        bounds = np.cumsum([0, *sizes])
        #: env indices of each shard: shard 0 here, shard k in worker k - 1
        self.shards = [list(range(bounds[k], bounds[k + 1])) for k in range(len(sizes))]
        if start_method is None:
            start_method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
        context = mp.get_context(start_method)
        self.remotes, self.processes = [], []
        self._pending: set[int] = set()  # workers whose reply to a command is still to be read
        try:
            for shard in self.shards[1:]:
                remote, work_remote = context.Pipe()
                process = context.Process(target=_worker, daemon=True, args=(
                    work_remote, remote, CloudpickleWrapper([env_fns[i] for i in shard]), tuple(ignore_signals)))
                process.start()
                track(process, f"env worker {len(self.processes) + 1}")
                work_remote.close()
                self.remotes.append(remote)
                self.processes.append(process)
            self.local = _Shard([env_fns[i] for i in self.shards[0]])
            for worker in range(len(self.remotes)):
                self._pending.add(worker)
                self._receive(worker)  # its envs are built
        except BaseException:
            self._terminate()
            raise
        observation_space, action_space = self.local.spaces()
        super().__init__(n_envs, observation_space, action_space)

    # -- messages ---------------------------------------------------------------------------------
    def _send(self, worker: int, command: str, args: tuple) -> None:
        try:
            self.remotes[worker].send((command, args))
        except (BrokenPipeError, ConnectionResetError):
            raise self._exited(worker) from None
        self._pending.add(worker)

    def _receive(self, worker: int):
        self._pending.discard(worker)
        try:
            status, result = self.remotes[worker].recv()
        except (EOFError, ConnectionResetError):
            raise self._exited(worker) from None
        if status == "error":
            raise WorkerError(f"env worker {worker + 1} failed: {last_line(result)}", details=result)
        return result

    def _exited(self, worker: int) -> WorkerError:
        process = self.processes[worker]
        process.join(timeout=1)
        stop(process, wait=0.0)
        return WorkerError(f"env worker {worker + 1} (pid {process.pid}) exited (exit code {process.exitcode})")

    def _call(self, command: str, per_shard: Callable[[int], tuple], shards: Sequence[int] | None = None) -> list:
        """Run `command` on `shards` (default all; the workers' concurrently with this process's),
        `per_shard(k)` giving shard k's arguments; each shard's result, in the order of `shards`."""
        shards = range(len(self.shards)) if shards is None else shards
        for k in shards:
            if k > 0:
                self._send(k - 1, command, per_shard(k))
        local = getattr(self.local, command)(*per_shard(0)) if 0 in shards else None
        return [local if k == 0 else self._receive(k - 1) for k in shards]

    def _call_indices(self, command: str, indices: VecEnvIndices, *args) -> list:
        """`command(shard_positions, *args)` on the shards holding `indices`; results in env order."""
        wanted = self._get_indices(indices)
        positions = [[i - shard[0] for i in wanted if i in shard] for shard in self.shards]
        involved = [k for k in range(len(self.shards)) if positions[k]]
        results = {}
        for k, values in zip(involved, self._call(command, lambda k: (positions[k], *args), involved), strict=True):
            results.update({self.shards[k][p]: value for p, value in zip(positions[k], values, strict=True)})
        return [results[i] for i in wanted]

    # -- VecEnv -----------------------------------------------------------------------------------
    def step_async(self, actions: np.ndarray) -> None:
        for worker in range(len(self.remotes)):
            self._send(worker, "step", (actions[self.shards[worker + 1]],))
        self._actions = actions[self.shards[0]]

    def step_wait(self):
        results = self.local.step(self._actions)
        for worker in range(len(self.remotes)):
            results += self._receive(worker)
        observations, rewards, dones, infos, self.reset_infos = zip(*results, strict=True)
        return _stack(observations, self.observation_space), np.stack(rewards), np.stack(dones), infos

    def reset(self):
        seeds_and_options = list(zip(self._seeds, self._options, strict=True))
        by_shard = self._call("reset", lambda k: ([seeds_and_options[i] for i in self.shards[k]],))
        observations, self.reset_infos = zip(*(result for shard in by_shard for result in shard), strict=True)
        self._reset_seeds()
        self._reset_options()
        return _stack(observations, self.observation_space)

    def get_images(self) -> Sequence[np.ndarray | None]:
        if self.render_mode != "rgb_array":
            return [None] * self.num_envs
        return self._call_indices("render", None)

    def has_attr(self, attr_name: str) -> bool:
        return all(self._call("has_attr", lambda k: (attr_name,)))

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return self._call_indices("get_attr", indices, attr_name)

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        self._call_indices("set_attr", indices, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices: VecEnvIndices = None, **method_kwargs) -> list[Any]:
        return self._call_indices("env_method", indices, method_name, method_args, method_kwargs)

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        return self._call_indices("is_wrapped", indices, wrapper_class)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            for worker in sorted(self._pending):  # replies to a command in flight (or one that failed)
                try:
                    self._receive(worker)
                except WorkerError:
                    pass
            for worker in range(len(self.remotes)):
                self._send(worker, "close", ())
            for worker in range(len(self.remotes)):
                self._receive(worker)
        except (WorkerError, OSError):
            pass  # a worker already gone: nothing of it to close
        finally:
            if hasattr(self, "local"):
                self.local.close()
            self._terminate()

    def _terminate(self) -> None:
        """Close the pipes (a worker still waiting for a command then exits) and join the workers,
        ending any that do not exit."""
        for remote in self.remotes:
            remote.close()
        for process in self.processes:
            stop(process)  # they ignore SIGTERM (ignore_signals): SIGKILL after 10 s
