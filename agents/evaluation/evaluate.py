"""`bh8 eval`: success rate (95% Wilson CI) per object set and per object family, a per-object
table, grasp time, peak strain, safety stops, a training-curve plot and a GIF of sample episodes,
for a trained policy (SB3 .zip or exported .npz) or a scripted baseline (`--baseline
supervisory|loop|squeeze`), on one or more object sets (default: the test splits of the random_urdfs
and of the primitives, bh8_gym.envs.objects) or on object files the user names. The metrics of
an episode: agents/evaluation/episodes.py. The episodes run in two processes (agents/evaluation/eval_worker.py).

`--compare REPORT` pairs this evaluation with another one on the same episodes (same seeds, so the
same objects and placements) and prints the exact McNemar test of the two success records.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from bh8_gym.agents.evaluation.baselines import BASELINES, make_grasp
from bh8_gym.agents.grasps import FAMILY
from bh8_gym.agents.env_factory import make_env
from bh8_gym.agents.evaluation.episodes import EpisodeResult
from bh8_gym.child_processes import WorkerDied
from bh8_gym.safe_files import read_json_bounded
from bh8_gym.agents.evaluation.eval_worker import (
    BATCH_ENVS,
    EvaluationWorker,
    PolicyFileJob,
    ScriptJob,
    one_torch_thread,
)
from bh8_gym.agents.deployment.policy_file import PolicyFileError, add_trust_argument, load_policy
from bh8_gym.agents.policy_io import atomic_write
from bh8_gym.agents.evaluation.run_files import EVALUATIONS_FILE, read_evaluations, write_text_atomic
from bh8_gym.agents.evaluation.bounds import MAX_EPISODES, MAX_SEED
from bh8_gym.cli import integer_argument, json_object_argument
from bh8_gym.rendering import encode_gif, steps_per_frame

# 95% two-sided normal quantile
Z_95 = 1.959963984540054
# The object sets a report gives by default: the test splits (bh8_gym.envs.objects).
DEFAULT_EVALUATION_SETS = "test,primitives-test"


def percent(*fractions: float) -> str:
    """Fractions as the reports print them, one decimal: percent(0.425) is "42.5 %", percent(low,
    high) "35.9-49.4 %". Every table rounds through here, so 85/200 reads the same in each."""
    return "-".join(f"{100 * fraction:.1f}" for fraction in fractions) + " %"


def wilson_interval(successes: int, trials: int, z: float = Z_95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion (default 95%)."""
    if isinstance(trials, bool) or not isinstance(trials, (int, np.integer)) or trials < 1:
        raise ValueError(f"trials must be a positive integer, got {trials!r}")
    if isinstance(successes, bool) or not isinstance(successes, (int, np.integer)) or not 0 <= successes <= trials:
        raise ValueError(f"successes must be an integer in 0..{trials}, got {successes!r}")
    if not (z > 0 and math.isfinite(z)):
        raise ValueError(f"z must be positive and finite, got {z!r}")
    p = successes / trials
    z2 = z * z
    denominator = 1.0 + z2 / trials
    centre = (p + z2 / (2 * trials)) / denominator
    half = z * math.sqrt(p * (1 - p) / trials + z2 / (4 * trials * trials)) / denominator
    # The ends are exact at 0 and n successes; the formula would leave rounding residue there.
    low = 0.0 if successes == 0 else max(0.0, centre - half)
    high = 1.0 if successes == trials else min(1.0, centre + half)
    return low, high


def summarize(results: Sequence[EpisodeResult]) -> dict[str, Any]:
    """Success rate with its 95% Wilson CI, return, length, grasp time and strain statistics."""
    n = len(results)
    successes = sum(r.success for r in results)
    low, high = wilson_interval(successes, n)
    returns = np.array([r.episode_return for r in results], dtype=float)
    grasp_times = [r.grasp_time for r in results if r.grasp_time is not None]
    strains = [r.peak_strain for r in results if r.peak_strain is not None]
    return {
        "episodes": n,
        "successes": successes,
        "success_rate": successes / n,
        "success_ci_low": low,
        "success_ci_high": high,
        "mean_return": float(returns.mean()),
        "std_return": float(returns.std()),
        "mean_length": float(np.mean([r.length for r in results])),
        "mean_grasp_time": float(np.mean(grasp_times)) if grasp_times else None,
        "grasped_episodes": len(grasp_times),
        "mean_peak_strain": float(np.mean(strains)) if strains else None,
        "max_peak_strain": int(max(strains)) if strains else None,
        "safety_stops": sum(r.safety_stop for r in results),
    }


def summaries_by(results: Sequence[EpisodeResult], key: str) -> dict[str, dict[str, Any]]:
    """`summarize` of the results grouped by an EpisodeResult field ("object_set", "family")."""
    groups: dict[str, list[EpisodeResult]] = {}
    for r in results:
        groups.setdefault(getattr(r, key), []).append(r)
    return {name: summarize(rows) for name, rows in groups.items()}


def group_table(results: Sequence[EpisodeResult]) -> str:
    """A Markdown table: each object set, each family within it, then all episodes."""
    lines = ["| object set | family | episodes | success | 95% CI | safety stops | mean peak strain |",
             "|---|---|---:|---:|---|---:|---:|"]

    def row(object_set: str, family: str, s: dict) -> str:
        strain = "-" if s["mean_peak_strain"] is None else f"{s['mean_peak_strain']:.1f}"
        return (f"| {object_set} | {family} | {s['episodes']} | {s['successes']}/{s['episodes']} "
                f"({percent(s['success_rate'])}) | {percent(s['success_ci_low'], s['success_ci_high'])} | "
                f"{s['safety_stops']} | {strain} |")

    for object_set, summary in summaries_by(results, "object_set").items():
        in_set = [r for r in results if r.object_set == object_set]
        families = summaries_by(in_set, "family")
        lines.append(row(f"**{object_set or '(no objects)'}**", "all", summary))
        if len(families) > 1:
            lines += [row(object_set, family, families[family]) for family in sorted(families)]
    if len({r.object_set for r in results}) > 1:
        lines.append(row("**all**", "all", summarize(results)))
    return "\n".join(lines)


def paired_comparison(ours: Sequence[bool], theirs: Sequence[bool]) -> dict[str, Any]:
    """Two policies' successes on the same episodes: the discordant counts and the two-sided exact
    McNemar p-value (binomial test of "ours only" against "theirs only" at 1/2). Pairing removes the
    episode-to-episode difficulty that makes two separate confidence intervals wide."""
    if len(ours) != len(theirs) or not ours:
        raise ValueError(f"paired comparison needs two equally long, non-empty outcome lists, got "
                         f"{len(ours)} and {len(theirs)}")
    only_ours = sum(1 for a, b in zip(ours, theirs) if a and not b)
    only_theirs = sum(1 for a, b in zip(ours, theirs) if b and not a)
    both = sum(1 for a, b in zip(ours, theirs) if a and b)
    discordant = only_ours + only_theirs
    tail = sum(math.comb(discordant, i) for i in range(min(only_ours, only_theirs) + 1))
    p_value = min(1.0, 2 * tail / 2 ** discordant)  # exact integers until this one division
    return {"episodes": len(ours), "only_ours": only_ours, "only_theirs": only_theirs, "both": both,
            "neither": len(ours) - discordant - both, "mcnemar_p": p_value}


def paired_line(label: str, paired: dict[str, Any]) -> str:
    """One line of `paired_comparison`'s counts and p-value for the console."""
    return (f"{label} on the same {paired['episodes']} episodes: only this one succeeded {paired['only_ours']}, "
            f"only that one {paired['only_theirs']}, both {paired['both']}, neither {paired['neither']}; "
            f"exact McNemar p = {paired['mcnemar_p']:.3g}")


COMPARISON_LIMIT_BYTES = 256 << 20  # another report's results.json: a record per episode


def load_comparison_report(path: Path, seed: int, n_episodes: int) -> tuple[str, list[dict]]:
    """(its path, its episodes) of another `bh8 eval --out` report (a directory or results.json),
    checked before any episode runs to cover the same episodes: same first seed, same count."""
    path = Path(path)
    if path.is_dir():
        path = path / "results.json"
    try:
        report = read_json_bounded(path, COMPARISON_LIMIT_BYTES, "report")
        episodes = report["episodes"]
        if not isinstance(episodes, list) or not all(isinstance(e, dict) for e in episodes):
            raise ValueError("its episodes are not a list of records")
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"--compare {str(path)!r}: not a bh8 eval report ({exc})") from None
    if report.get("seed") != seed or len(episodes) != n_episodes:
        raise ValueError(f"--compare {str(path)!r}: {len(episodes)} episodes from seed {report.get('seed')}, "
                         f"this evaluation has {n_episodes} from seed {seed}; compare the same episodes")
    return str(path), episodes


def paired_outcomes(path: str, episodes: Sequence[dict], results: Sequence[EpisodeResult]) -> list[bool]:
    """The other report's per-episode successes, checked to have had the same object in each episode."""
    for index, (theirs, mine) in enumerate(zip(episodes, results)):
        if theirs["object_name"] != mine.object_name:
            raise ValueError(f"--compare {path!r}: episode {index} had object {theirs['object_name']!r}, "
                             f"this evaluation {mine.object_name!r}; compare the same objects")
    return [bool(e["success"]) for e in episodes]


def per_object_table(results: Sequence[EpisodeResult]) -> str:
    """A Markdown table: one row per object, then the total."""
    groups: dict[str, list[EpisodeResult]] = {}
    for r in results:
        groups.setdefault(r.object_name, []).append(r)
    lines = ["| object | episodes | success | 95% CI | mean grasp time (s) | mean peak strain |",
             "|---|---:|---:|---|---:|---:|"]

    def row(name: str, rows: Sequence[EpisodeResult]) -> str:
        s = summarize(rows)
        grasp = "-" if s["mean_grasp_time"] is None else f"{s['mean_grasp_time']:.3f}"
        strain = "-" if s["mean_peak_strain"] is None else f"{s['mean_peak_strain']:.1f}"
        return (f"| {name} | {s['episodes']} | {s['successes']}/{s['episodes']} ({percent(s['success_rate'])}) | "
                f"{percent(s['success_ci_low'], s['success_ci_high'])} | {grasp} | {strain} |")

    for name in sorted(groups):
        lines.append(row(name, groups[name]))
    lines.append(row("**all**", results))
    return "\n".join(lines)


def plot_training_curve(rows: Sequence[dict[str, float]], path: Path) -> Path:
    """Held-out success rate (with its CI band) and mean return against env steps, to a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not rows:
        raise ValueError("no evaluation rows to plot")
    steps = np.array([r["timesteps"] for r in rows])
    figure, (top, bottom) = plt.subplots(2, 1, sharex=True, figsize=(7, 5.5))
    top.plot(steps, [r["success_rate"] for r in rows], marker="o", label="success rate")
    top.fill_between(steps, [r["success_ci_low"] for r in rows], [r["success_ci_high"] for r in rows],
                     alpha=0.25, label="95% Wilson CI")
    top.set_ylim(-0.02, 1.02)
    top.set_ylabel("validation success")
    top.legend(loc="lower right")
    bottom.plot(steps, [r["mean_return"] for r in rows], marker="o", color="tab:orange")
    bottom.set_ylabel("mean return")
    bottom.set_xlabel("env steps")
    figure.tight_layout()
    path = Path(path)
    try:
        atomic_write(path, lambda handle: figure.savefig(handle, format="png", dpi=100))
    finally:
        plt.close(figure)
    return path


def record_gif(policy, env_id: str, env_kwargs: dict, path: Path, episodes: int, seed: int,
               script: str | None = None, every: int | None = None) -> Path:
    """Render `episodes` sample episodes (headless TinyRenderer) of `policy` or of the scripted grasp
    `script` (`make_grasp`'s name) into one real-time GIF, a frame every `every` steps (default
    `rendering.steps_per_frame`: frames of at least 20 ms)."""
    env = make_env(env_id, env_kwargs, render_mode="rgb_array")
    frames = []
    try:
        baseline = make_grasp(script, env) if script is not None else None
        if getattr(policy, "needs_feedback", False):  # the grasp choice acts like a script
            baseline = policy
        base = env.unwrapped
        if every is None:
            every = steps_per_frame(base.cycle_seconds)
        fps = 1.0 / (float(base.cycle_seconds) * every)
        for episode in range(episodes):
            if baseline is not None and hasattr(baseline, "run_episode"):
                baseline.run_episode(env, seed + episode, None, frames=frames, every=every)
                continue
            obs, info = env.reset(seed=seed + episode)
            if baseline is not None:
                baseline.reset(env)
            frames.append(env.render())
            done, step = False, 0
            while not done:
                action = baseline.act(obs, info) if baseline is not None else policy.predict(obs, deterministic=True)[0]
                obs, _, terminated, truncated, info = env.step(action)
                step += 1
                done = terminated or truncated
                if step % every == 0 or done:
                    frames.append(env.render())
    finally:
        env.close()
    gif = encode_gif(frames, fps)
    atomic_write(Path(path), lambda handle: handle.write(gif))
    return Path(path)


def scripted_grasps() -> tuple[str, ...]:
    """What `--baseline` takes: the baselines, then the ceiling family's scripts."""
    return tuple(dict.fromkeys((*BASELINES, *FAMILY)))


def configure_parser(parser: argparse.ArgumentParser) -> None:
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("policy", nargs="?", type=Path, help="policy file: SB3 .zip or exported .npz")
    source.add_argument("--baseline", choices=scripted_grasps(), metavar="SCRIPT",
                        help="evaluate a scripted baseline: supervisory, loop, squeeze, or any script of the "
                             "ceiling family (agents/evaluation/ceiling.py: " + ", ".join(FAMILY) + ")")
    parser.add_argument("--env", default=None, help="env id (default: the policy's, else BH8Grasp-v0)")
    parser.add_argument("--episodes", type=integer_argument(1, MAX_EPISODES), default=50,
                        help="episodes per object set (default: %(default)s)")
    parser.add_argument("--objects", default=DEFAULT_EVALUATION_SETS,
                        help="object sets, comma-separated, --episodes each: test, validation, train (random_urdfs), "
                             "primitives-test, primitives-validation, primitives-train, mixed-test, mixed-validation, "
                             "mixed, primitives, all (default: %(default)s)")
    parser.add_argument("--object-files", nargs="+", default=None, metavar="FILE",
                        help="your own objects: PATH.urdf[:SCALE] or PATH.obj:SCALE:MASS_KG[:FRICTION] "
                             "(default: none, the --objects set)")
    parser.add_argument("--seed", type=integer_argument(0, MAX_SEED), default=100_000,
                        help="seed of the first episode (default: %(default)s)")
    parser.add_argument("--randomize", action="store_true", help="keep domain randomisation on (default: off)")
    parser.add_argument("--env-kwargs", type=json_object_argument, default={}, metavar="JSON",
                        help='env keywords on top of the policy\'s, e.g. \'{"plant_parameters": {"solver_iterations": 200}}\' '
                             "(default: none)")
    parser.add_argument("--out", type=Path, default=None, help="report directory (default: print only)")
    add_trust_argument(parser)
    parser.add_argument("--curve", type=Path, default=None,
                        help="training run directory whose evaluations.csv to plot (default: the policy's)")
    parser.add_argument("--gif-episodes", type=integer_argument(0, 100), default=2,
                        help="episodes rendered to the GIF in --out (0: none; default: %(default)s)")
    parser.add_argument("--processes", type=int, choices=(1, 2), default=2 if (os.cpu_count() or 1) > 1 else 1,
                        help="run half of the episodes in a second process (the same episodes; default: "
                             "%(default)s, 2 on a machine with more than one core)")
    parser.add_argument("--no-progress", action="store_true",
                        help="no progress bar (as `bh8 train --no-progress`; none is drawn off a terminal anyway)")
    parser.add_argument("--compare", type=Path, default=None, metavar="REPORT",
                        help="another evaluation's --out directory on the same episodes: print the paired "
                             "comparison (exact McNemar test; default: none)")


def evaluation_env_kwargs(env_id: str, base_kwargs: dict, objects: str, object_files: list[str] | None,
                          randomize: bool) -> dict:
    """The env kwargs for evaluation: the policy's env kwargs with the chosen objects (grasp envs
    only; the reach env has none), domain randomisation off unless asked for."""
    kwargs = dict(base_kwargs)
    kwargs["randomize"] = bool(randomize)
    if not env_id.startswith("BH8Grasp"):
        if object_files:
            raise ValueError(f"{env_id} has no objects; --object-files applies to BH8Grasp-v0")
        return kwargs
    kwargs.pop("object_files", None)
    if object_files:
        kwargs["object_files"] = list(object_files)
        kwargs.pop("object_set", None)
    elif objects:
        kwargs["object_set"] = objects
    return kwargs


def run(args: argparse.Namespace) -> int:
    policy, metadata = None, {}
    try:
        if args.policy is not None:
            policy = load_policy(args.policy, trust=args.trust_file)
            metadata = policy.metadata
            one_torch_thread()  # an SB3 file: as in the worker
        env_id = args.env or metadata.get("env_id") or "BH8Grasp-v0"
        if metadata.get("env_id") and env_id != metadata["env_id"]:
            raise ValueError(f"--env {env_id} but the policy was trained on {metadata['env_id']}")
        if not env_id.startswith("BH8Grasp"):
            object_sets = [""]  # no objects
        elif args.object_files:
            object_sets = ["files"]
        else:
            object_sets = [name.strip() for name in args.objects.split(",") if name.strip()]
        if not object_sets:
            raise ValueError(f"--objects {args.objects!r} names no object set")
        set_kwargs = {name: {**evaluation_env_kwargs(env_id, metadata.get("env_kwargs", {}), name, args.object_files,
                                                     args.randomize), **args.env_kwargs} for name in object_sets}
        env_kwargs = set_kwargs[object_sets[0]]
        comparison = (None if args.compare is None
                      else load_comparison_report(args.compare, args.seed, args.episodes * len(object_sets)))
        if args.out is not None:  # before the episodes, not after them
            try:
                args.out.mkdir(parents=True, exist_ok=True)
            except OSError as error:
                raise ValueError(f"--out {str(args.out)!r} cannot be a report directory: {error}") from None
        if args.baseline is not None:
            job = ScriptJob(args.baseline)
        else:
            job = PolicyFileJob(args.policy, trust=args.trust_file, policy=policy)
        n_envs = BATCH_ENVS if job.batched else 1
        results = []
        for name in object_sets:
            # The second half of the episodes in a worker process (agents/evaluation/eval_worker.py), started
            # first: it builds its envs while this process builds its own.
            worker = (EvaluationWorker(env_id, set_kwargs[name], n_envs=n_envs)
                      if args.processes > 1 and args.episodes > 1 else None)
            envs, finished = [], False
            try:
                envs += [make_env(env_id, set_kwargs[name]) for _ in range(n_envs)]
                kwargs = {"progress": not args.no_progress, "object_set": name}
                results += (worker.run(job, envs, args.episodes, args.seed, **kwargs) if worker is not None
                            else job.episodes(envs, args.episodes, args.seed, **kwargs))
                finished = True
            finally:
                for env in envs:
                    env.close()
                if worker is not None:
                    worker.close(graceful=finished)  # after an error or Ctrl-C: killed, not waited for
        paired = None
        if comparison is not None:
            theirs = paired_outcomes(*comparison, results)
            paired = paired_comparison([r.success for r in results], theirs)
    except (PolicyFileError, FileNotFoundError, ValueError, WorkerDied) as exc:
        print(f"bh8 eval: {exc}", file=sys.stderr)
        return 2
    summary = summarize(results)
    table = per_object_table(results)
    label = f"baseline {args.baseline}" if args.baseline is not None else str(args.policy)
    grasp = "n/a" if summary["mean_grasp_time"] is None else f"{summary['mean_grasp_time']:.3f} s"
    objects = f" ({args.object_files or ', '.join(object_sets)})" if env_id.startswith("BH8Grasp") else ""
    print(f"{label} on {env_id}{objects}, {summary['episodes']} episodes")
    for name, part in summaries_by(results, "object_set").items():
        print(f"{name or env_id}: success rate {part['success_rate']:.3f} (95% Wilson CI {part['success_ci_low']:.3f}-"
              f"{part['success_ci_high']:.3f}) over {part['episodes']} episodes; safety stops {part['safety_stops']}")
    strain = ("n/a" if summary["mean_peak_strain"] is None
              else f"mean {summary['mean_peak_strain']:.1f} max {summary['max_peak_strain']}")
    print(f"mean return {summary['mean_return']:.2f}; mean grasp time {grasp}; peak strain {strain}")
    print(group_table(results))
    # The per-object rows (about 85 per object set) would bury the summary: they go to table.md only.
    print(f"per-object table: {args.out / 'table.md'}" if args.out is not None
          else "per-object table: pass --out DIR (written to DIR/table.md)")
    if paired is not None:
        if len(object_sets) > 1:
            for name in object_sets:
                episodes = [i for i, r in enumerate(results) if r.object_set == name]
                print(paired_line(f"{name}: paired", paired_comparison([results[i].success for i in episodes],
                                                                       [theirs[i] for i in episodes])))
        print(paired_line(f"paired with {args.compare}", paired))
    if args.out is not None:
        # Each report file is replaced whole or not at all (a full disk cut results.json and lost the last report).
        try:
            write_text_atomic(args.out / "table.md", group_table(results) + "\n\n" + table + "\n")
            write_text_atomic(args.out / "results.json", json.dumps(
                {"summary": summary, "by_object_set": summaries_by(results, "object_set"),
                 "by_family": summaries_by(results, "family"), "episodes": [asdict(r) for r in results],
                 "env_id": env_id, "seed": args.seed, "object_sets": object_sets,
                 "env_kwargs": env_kwargs,  # the first object set's (the others differ in object_set only)
                 "policy": label, "paired": paired}, indent=2, default=str))
            curve_dir = args.curve or (args.policy.parent if args.policy is not None else None)
            if curve_dir is not None:
                plot_run_curve(curve_dir, args.out / "training_curve.png")
            if args.gif_episodes > 0:
                record_gif(policy, env_id, env_kwargs, args.out / "episodes.gif", args.gif_episodes, args.seed,
                           script=args.baseline)
        except OSError as error:
            print(f"bh8 eval: cannot write the report in {str(args.out)!r}: {error}", file=sys.stderr)
            return 1
        print(f"report written to {args.out}")
    return 0


def plot_run_curve(curve_dir: Path, path: Path) -> None:
    """The training curve of the run in `curve_dir` (or its parent) to `path`, if it has one; its
    rows cut short are left out, and said so on stderr."""
    for folder in (curve_dir, curve_dir.parent):
        if (folder / EVALUATIONS_FILE).exists():
            skipped: list[int] = []
            rows = read_evaluations(folder, skipped)
            if skipped:
                print(f"bh8 eval: {str(folder / EVALUATIONS_FILE)!r}: left out line(s) "
                      f"{', '.join(map(str, skipped))}, cut short (a kill or a full disk mid-write)", file=sys.stderr)
            if rows:
                plot_training_curve(rows, path)
            return
