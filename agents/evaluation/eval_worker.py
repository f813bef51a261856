"""An evaluation's episodes split over two processes: the first half here, the second in a worker
process with envs of its own; in each process several envs run episodes at once.

Why: `bh8 train` evaluates its policy on 100 validation episodes at every evaluation, and `bh8 eval`
runs hundreds of test episodes; in one process with one env the second core idles, and every env
step waits for a forward pass of the policy of its own. Each episode is fixed by
its seed (its object, placement and randomisation, tests/test_objects.py) and the policy is
deterministic, so the results are those of `run_episodes` in one process with one env, in the same
order, with one exception: an env's earlier episodes can change the order of PyBullet's contacts,
so where the worker gave an env another history, a return may differ in its last digits (2 of
400 grasp episodes, in the second or third digit; no success changed: docs/benchmarks.md,
"Evaluation").

What the worker runs is a job: `PolicyJob` (an SB3 policy, `bh8 train`), `PolicyFileJob` (a policy
file, `bh8 eval`) or `ScriptJob` (a scripted grasp, `bh8 eval --baseline`).
"""
from __future__ import annotations

import multiprocessing as mp
import signal
import sys
import traceback
from pathlib import Path

from bh8_gym.agents.env_factory import make_env
from bh8_gym.child_processes import WorkerDied, in_worker, stop, track
from bh8_gym.agents.evaluation.episodes import run_episodes

#: Envs per process that run a policy's episodes at once: a forward pass of a batch of 4
#: observations costs about what one of 1 does, so it is paid once per 4 env steps
#: (docs/benchmarks.md, "Evaluation").
BATCH_ENVS = 4


class EvaluationWorkerError(WorkerDied):
    """The evaluation worker failed (its error's last line in the message, its traceback in
    `details`) or exited."""

    def __init__(self, message: str, details: str = ""):
        super().__init__(message)
        self.details = details


def last_line(text: str) -> str:
    """A traceback's informative line (its last), for a one-line message."""
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return lines[-1][:300] if lines else "(no message)"


class _PolicyModel:
    """`predict` and `policy` of an SB3 model, from its policy alone (what the worker receives)."""

    def __init__(self, policy):
        self.policy = policy
        self.observation_space = policy.observation_space

    def predict(self, observation, state=None, episode_start=None, deterministic: bool = True):
        return self.policy.predict(observation, state, episode_start, deterministic)


def predictor(model):
    """What `run_episodes` calls for an SB3 model: host observations for an asymmetric one."""
    from bh8_gym.agents.asymmetric import HostObservationModel, host_observation_count  # torch: SB3 models only

    return HostObservationModel(model) if host_observation_count(model) else model


def one_torch_thread() -> None:
    """torch (if a policy needed it) on one thread, as in the training process: the same arithmetic,
    the same actions, and no process's second thread spinning on the other process's core."""
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(1)


def _without_gradients(policy):
    """`policy` with the action distribution of its last forward pass dropped: after a pass with
    gradients (behaviour cloning, a PPO update) it holds tensors that are not leaves of the graph,
    which torch refuses to send to another process; the next forward pass rebuilds it."""
    for holder in (policy, getattr(policy, "actor", None)):
        distribution = getattr(holder, "action_dist", None)
        if distribution is not None and hasattr(distribution, "distribution"):
            distribution.distribution = None
    return policy


class PolicyJob:
    """Episodes of an SB3 policy (a model's `policy`), deterministic."""

    batched = True

    def __init__(self, policy):
        self.policy = _without_gradients(policy)

    def episodes(self, envs, n_episodes: int, seed: int, **kwargs) -> list:
        return run_episodes(predictor(_PolicyModel(self.policy)), envs, n_episodes, seed=seed, **kwargs)


class PolicyFileJob:
    """Episodes of a policy file (`load_policy(path, trust)`), deterministic. `policy`: the file
    already loaded in this process (not sent: the worker loads the file itself)."""

    batched = True

    def __init__(self, path, trust: bool = False, policy=None):
        self.path, self.trust, self._policy = Path(path), bool(trust), policy

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_policy": None}

    def episodes(self, envs, n_episodes: int, seed: int, **kwargs) -> list:
        if self._policy is None:
            from bh8_gym.agents.deployment.policy_file import load_policy

            self._policy = load_policy(self.path, trust=self.trust)
            one_torch_thread()
        if getattr(self._policy, "needs_feedback", False):  # the grasp choice: acts on feedback blocks, like a script
            return run_episodes(None, envs[0], n_episodes, seed=seed, baseline=self._policy, **kwargs)
        return run_episodes(self._policy, envs, n_episodes, seed=seed, **kwargs)


class ScriptJob:
    """Episodes of a scripted grasp (`agents.evaluation.baselines.make_grasp(name)`), on one env (a script
    keeps per-episode state on its env)."""

    batched = False

    def __init__(self, name: str):
        self.name = name

    def episodes(self, envs, n_episodes: int, seed: int, **kwargs) -> list:
        from bh8_gym.agents.evaluation.baselines import make_grasp

        return run_episodes(None, envs[0], n_episodes, seed=seed, baseline=make_grasp(self.name, envs[0]), **kwargs)


def _serve(remote, env_id: str, env_kwargs: dict, n_envs: int, ignore_signals: tuple) -> None:
    """The worker: builds its envs at once (ready by the first evaluation), then answers each
    (job, n_episodes, seed, kwargs) with ("ok", results) or ("error", traceback) until None."""
    # Ctrl-C reaches the whole process group: the parent handles it and ends this worker (without
    # this, the worker died of KeyboardInterrupt with a traceback of its own).
    for signum in {signal.SIGINT, *ignore_signals}:
        signal.signal(signum, signal.SIG_IGN)
    in_worker()
    envs, failure = [], None
    try:
        for _ in range(n_envs):
            envs.append(make_env(env_id, env_kwargs))
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
            job, n_episodes, seed, kwargs = message
            one_torch_thread()
            remote.send(("ok", job.episodes(envs if job.batched else envs[:1], n_episodes, seed, **kwargs)))
        except Exception:  # noqa: BLE001 - reported to the training process, which raises it
            remote.send(("error", traceback.format_exc()))
    for env in envs:
        env.close()
    remote.close()


class EvaluationWorker:
    """A process that runs episodes of `env_id` (`n_envs` envs built by `make_env(env_id,
    env_kwargs)`) for a job sent to it; `run` splits an evaluation between it and this process."""

    def __init__(self, env_id: str, env_kwargs: dict, ignore_signals: tuple = (), start_method: str | None = None,
                 n_envs: int = BATCH_ENVS):
        if start_method is None:
            start_method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
        context = mp.get_context(start_method)
        self._remote, work_remote = context.Pipe()
        self.process = context.Process(target=_serve, daemon=True,
                                       args=(work_remote, env_id, dict(env_kwargs), int(n_envs), tuple(ignore_signals)))
        self.process.start()
        track(self.process, "evaluation worker")
        work_remote.close()

    def run(self, job, envs, n_episodes: int, seed: int, **kwargs) -> list:
        """`job.episodes(envs, n_episodes, seed)`: the first half of the episodes (rounded up) on
        `envs` here (an env or a list of them), the rest in the worker at the same time; results in
        episode order. `kwargs` go to `run_episodes` here and there (`object_set`; `progress` here
        only)."""
        envs = list(envs) if isinstance(envs, (list, tuple)) else [envs]
        here = (n_episodes + 1) // 2
        theirs = n_episodes - here
        if theirs:
            sent = {key: value for key, value in kwargs.items() if key != "progress"}
            try:
                self._remote.send((job, theirs, seed + here, sent))
            except (BrokenPipeError, ConnectionResetError):
                raise self._exited() from None
        try:
            results = job.episodes(envs if job.batched else envs[:1], here, seed, **kwargs)
        finally:
            reply = self._reply() if theirs else []  # read even after a failure here: no stale reply
        return results + reply

    def _reply(self) -> list:
        try:
            status, result = self._remote.recv()
        except (EOFError, ConnectionResetError):
            raise self._exited() from None
        if status == "error":
            raise EvaluationWorkerError(f"evaluation worker failed: {last_line(result)}", details=result)
        return result

    def _exited(self) -> EvaluationWorkerError:
        self.process.join(timeout=1)
        stop(self.process, wait=0.0)
        return EvaluationWorkerError(f"evaluation worker (pid {self.process.pid}) exited "
                                     f"(exit code {self.process.exitcode})")

    def close(self, graceful: bool = True) -> None:
        """End the worker: asked to finish (`graceful`, up to 10 s), else killed at once (after an
        error or Ctrl-C here it may be in the middle of its episodes, which nothing waits for)."""
        if graceful:
            try:
                self._remote.send(None)
            except OSError:
                pass
        self._remote.close()
        stop(self.process, wait=10.0 if graceful else 0.0)
