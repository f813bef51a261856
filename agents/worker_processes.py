"""How the agents' worker processes start (the env workers of agents/vec_env.py, the evaluation
worker of agents/eval_worker.py): multiprocessing's "forkserver" by default, as SB3's (fork is
unsafe once torch runs threads), else "spawn".

A worker spends about 2.5 s importing SB3, torch, PyBullet and the envs before it builds its envs.
A forkserver imports the modules it is told to preload once and forks every worker from itself,
so a worker started after the first (the evaluation worker, `bh8 eval`'s next object set) is
ready at once (docs/benchmarks.md, "Training").
"""
from __future__ import annotations

import multiprocessing as mp


def worker_context(start_method: str | None = None, preload: tuple = ()):
    """multiprocessing's context for worker processes (`start_method` None: forkserver where there is
    one). A forkserver not yet running preloads the modules `preload` names (a module that cannot
    be imported, e.g. torch in an install without the train extras, is left to the worker)."""
    if start_method is None:
        start_method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
    context = mp.get_context(start_method)
    if start_method == "forkserver" and preload:
        context.set_forkserver_preload(list(preload))
    return context
