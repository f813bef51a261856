"""An evaluation's episodes split over two processes: the first half here, the second in a worker
process with an env of its own.

Why: `bh8 train` evaluates its policy on 100 validation episodes at every evaluation, one env
stepped in the training process while the second core idles; at the default config's eight
evaluations that is about as many env steps as the training's own. Each episode is fixed by its
seed (a seed replays exactly whatever the env ran before, tests/test_objects.py) and the policy
is deterministic, so which process runs an episode changes nothing: the results are the ones
`run_episodes` gives in one process, in the same order.
"""
from __future__ import annotations

import multiprocessing as mp
import signal
import traceback

from bh8_gym.agents.asymmetric import HostObservationModel, host_observation_count
from bh8_gym.agents.env_factory import make_env
from bh8_gym.agents.evaluate import run_episodes


class EvaluationWorkerError(RuntimeError):
    """The evaluation worker failed (its traceback in the message) or exited."""


class _PolicyModel:
    """`predict` and `policy` of an SB3 model, from its policy alone (what the worker receives)."""

    def __init__(self, policy):
        self.policy = policy
        self.observation_space = policy.observation_space

    def predict(self, observation, state=None, episode_start=None, deterministic: bool = True):
        return self.policy.predict(observation, state, episode_start, deterministic)


def predictor(model):
    """What `run_episodes` calls for an SB3 model: host observations for an asymmetric one."""
    return HostObservationModel(model) if host_observation_count(model) else model


def _serve(remote, env_id: str, env_kwargs: dict, ignore_signals: tuple) -> None:
    """The worker: builds its env at once (ready by the first evaluation), then answers each
    (policy, n_episodes, seed) with ("ok", results) or ("error", traceback) until None."""
    import torch

    for signum in ignore_signals:
        signal.signal(signum, signal.SIG_IGN)
    torch.set_num_threads(1)  # as the training process: the same arithmetic, the same actions
    env, failure = None, None
    try:
        env = make_env(env_id, env_kwargs)
    except Exception:  # noqa: BLE001 - the answer to every request
        failure = traceback.format_exc()
    while True:
        try:
            message = remote.recv()
        except (EOFError, KeyboardInterrupt):
            break
        if message is None:
            break
        try:
            if failure is not None:
                raise RuntimeError(failure)
            policy, n_episodes, seed = message
            remote.send(("ok", run_episodes(predictor(_PolicyModel(policy)), env, n_episodes, seed=seed)))
        except Exception:  # noqa: BLE001 - reported to the training process, which raises it
            remote.send(("error", traceback.format_exc()))
    if env is not None:
        env.close()
    remote.close()


def _without_gradients(policy):
    """`policy` with the action distribution of its last forward pass dropped: after a pass with
    gradients (behaviour cloning, a PPO update) it holds tensors that are not leaves of the graph,
    which torch refuses to send to another process; the next forward pass rebuilds it."""
    for holder in (policy, getattr(policy, "actor", None)):
        distribution = getattr(holder, "action_dist", None)
        if distribution is not None and hasattr(distribution, "distribution"):
            distribution.distribution = None
    return policy


class EvaluationWorker:
    """A process that runs episodes of `env_id` (`make_env(env_id, env_kwargs)`) with a policy sent
    to it; `run` splits an evaluation between it and this process."""

    def __init__(self, env_id: str, env_kwargs: dict, ignore_signals: tuple = (), start_method: str | None = None):
        if start_method is None:
            start_method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
        context = mp.get_context(start_method)
        self._remote, work_remote = context.Pipe()
        self.process = context.Process(target=_serve, args=(work_remote, env_id, dict(env_kwargs), tuple(ignore_signals)),
                                       daemon=True)
        self.process.start()
        work_remote.close()

    def run(self, model, env, n_episodes: int, seed: int) -> list:
        """`run_episodes(predictor(model), env, n_episodes, seed)`: the first half of the episodes
        (rounded up) on `env` here, the rest in the worker at the same time; results in episode order."""
        here = (n_episodes + 1) // 2
        theirs = n_episodes - here
        if theirs:
            try:
                self._remote.send((_without_gradients(model.policy), theirs, seed + here))
            except (BrokenPipeError, ConnectionResetError):
                raise self._exited() from None
        try:
            results = run_episodes(predictor(model), env, here, seed=seed)
        finally:
            reply = self._reply() if theirs else []  # read even after a failure here: no stale reply
        return results + reply

    def _reply(self) -> list:
        try:
            status, result = self._remote.recv()
        except (EOFError, ConnectionResetError):
            raise self._exited() from None
        if status == "error":
            raise EvaluationWorkerError(f"evaluation worker failed:\n{result}")
        return result

    def _exited(self) -> EvaluationWorkerError:
        self.process.join(timeout=1)
        return EvaluationWorkerError(f"evaluation worker (pid {self.process.pid}) exited "
                                     f"(exit code {self.process.exitcode})")

    def close(self) -> None:
        try:
            self._remote.send(None)
        except OSError:
            pass
        self._remote.close()
        self.process.join(timeout=10)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join()
