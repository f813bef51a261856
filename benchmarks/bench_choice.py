"""The grasp choice against every fixed grasp on the same test episodes: the README's results table.

Trains the grasp choice for each seed (`bh8 train`, the default config), evaluates each on the
test sets with `bh8 eval` (the same episodes for every row: seed 100000 on), and beside them the
scripted grasps and the fixed switch (the choice's probe, then always the same candidate: a script
a BH8 user could write), then prints one markdown table: per set the choice's median and range over
the seeds, each fixed grasp, and per seed the paired test against the best fixed grasp of the set.

    python benchmarks/bench_choice.py --seeds 0 1 2 --episodes 1000 --out runs/choice
        [--randomize] [--scripts loop loop-v70 loop-v50 squeeze] [--skip-training]

Every run's directory is kept (`--out`/seedN, `--out`/eval-*), and a step whose report is already
there is not run again, so an interrupted benchmark continues where it stopped.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from bh8_gym.agents.choice.features import ChoiceFeatures
from bh8_gym.agents.choice.model import SuccessModel
from bh8_gym.agents.choice.policy import ChoiceSettings, GraspChoicePolicy
from bh8_gym.agents.evaluation.evaluate import paired_comparison

SETS = "test,primitives-test"
TEST_SEED = 100_000


def bh8(*arguments: str) -> None:
    command = [sys.executable, "-m", "bh8_gym.cli", *arguments]
    print("$ bh8 " + " ".join(arguments), flush=True)
    subprocess.run(command, check=True)


def evaluate(target: list[str], out: Path, episodes: int, randomize: bool) -> dict:
    if not (out / "results.json").exists():
        bh8("eval", *target, "--objects", SETS, "--episodes", str(episodes), "--seed", str(TEST_SEED),
            "--out", str(out), "--gif-episodes", "0", *(["--randomize"] if randomize else []))
    return json.loads((out / "results.json").read_text())


def fixed_switch(settings: ChoiceSettings, grasp: str, path: Path) -> Path:
    """The choice's probe, then always `grasp`: a grasp-choice file whose selector is constant."""
    from bh8_gym.agents.env_factory import make_env

    env = make_env("BH8Grasp-v0", {})
    try:
        base = env.unwrapped
        n = len(ChoiceFeatures(base.layout.feedback_fields, base.episode_seconds).names)
    finally:
        env.close()
    bias = np.array([1.0 if g == grasp else 0.0 for g in settings.grasps])
    selector = SuccessModel(np.zeros(n), np.ones(n), [np.zeros((n, len(bias)))], [bias])
    GraspChoicePolicy(settings, selector, metadata={"env_id": "BH8Grasp-v0", "env_kwargs": {}}).save(path)
    return path


def outcomes(report: dict, object_set: str) -> list[bool]:
    return [bool(e["success"]) for e in report["episodes"] if e["object_set"] == object_set]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--randomize", action="store_true", help="test with domain randomisation")
    parser.add_argument("--scripts", nargs="+", default=["loop", "loop-v70", "loop-v50", "squeeze"])
    parser.add_argument("--switch", nargs="*", default=["squeeze"],
                        help="candidates to run as fixed switches after the probe")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    tag = "-randomized" if args.randomize else ""
    choices = {}
    for seed in args.seeds:
        run = args.out / f"seed{seed}"
        if not (run / "grasp_choice.npz").exists():
            bh8("train", "--out", str(run), "--seed", str(seed), "--no-progress")
        choices[seed] = evaluate([str(run / "grasp_choice.npz")], args.out / f"eval-seed{seed}{tag}", args.episodes,
                                 args.randomize)
    fixed = {name: evaluate(["--baseline", name], args.out / f"eval-{name}{tag}", args.episodes, args.randomize)
             for name in args.scripts}
    settings = GraspChoicePolicy.from_arrays(dict(np.load(args.out / f"seed{args.seeds[0]}" / "grasp_choice.npz"))).settings
    for grasp in args.switch:
        path = fixed_switch(settings, grasp, args.out / f"switch-{grasp}.npz")
        fixed[f"{settings.probe} then {grasp} at {settings.decision_seconds} s"] = evaluate(
            [str(path)], args.out / f"eval-switch-{grasp}{tag}", args.episodes, args.randomize)
    sets = [s for s in SETS.split(",")]
    lines = [f"| grasp | {' | '.join(sets)} |", "|---|" + "---:|" * len(sets)]
    rates = {s: {seed: float(np.mean(outcomes(r, s))) for seed, r in choices.items()} for s in sets}
    cells = [f"**{np.median(list(rates[s].values())) * 100:.1f} %** ({min(rates[s].values()) * 100:.1f}-"
             f"{max(rates[s].values()) * 100:.1f})" for s in sets]
    lines.append(f"| grasp choice, median (range) of seeds {', '.join(map(str, args.seeds))} | {' | '.join(cells)} |")
    best = {}
    for name, report in fixed.items():
        row = []
        for s in sets:
            rate = float(np.mean(outcomes(report, s)))
            row.append(f"{rate * 100:.1f} %")
            if s not in best or rate > best[s][1]:
                best[s] = (name, rate)
        lines.append(f"| {name} | {' | '.join(row)} |")
    print("\n".join(lines))
    print()
    for s in sets:
        name, rate = best[s]
        for seed, report in choices.items():
            paired = paired_comparison(outcomes(report, s), outcomes(fixed[name], s))
            print(f"{s}: seed {seed} {rates[s][seed] * 100:.1f} % against {name} {rate * 100:.1f} %: "
                  f"{(rates[s][seed] - rate) * 100:+.1f} points, {paired['only_ours']} only the choice, "
                  f"{paired['only_theirs']} only the script, p = {paired['mcnemar_p']:.2g}")


if __name__ == "__main__":
    main()
