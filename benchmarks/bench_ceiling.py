"""The ceiling: how much room a grasp chosen per object leaves over the best fixed script.

Runs every script of the ceiling family (agents/evaluation/ceiling.py: LOOP and squeeze grasps at settings
spanning closing velocity, gain, spread, strain target and softness; all object-blind) on the same
episodes of each object set, and prints per set: each script's count, the best single script, the
best script per object family (an oracle told the family), the union (an oracle told the
episode: some script holds it), and the same on the objects lower than 3 cm at rest (the ones the
arm's table-contact grasp is for). With `--policy`, a `bh8 eval --out` report (or several) on the same
episodes is set beside them and paired with the best single script (exact McNemar test).

Run: python benchmarks/bench_ceiling.py --sets primitives-test test --episodes 1000 --jobs 2 \
         --out runs/ceiling [--randomize] [--table-contact] [--policy runs/eval/results.json]

`--out` keeps ceiling.json (which script held which episode: `agents.evaluation.ceiling.load_records`) and
ceiling.md (with --randomize: ceiling-randomized.json and .md; with --table-contact,
ceiling-table-contact.*). Rerunning with the same --out
reuses the scripts already recorded there and keeps the other sets' records. A --policy report is
paired only when it holds at least the ceiling's episodes of a set from the same seed (else it says so).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from bh8_gym.agents.grasps import FAMILY
from bh8_gym.agents.evaluation.ceiling import (
    LOW_OBJECT_HEIGHT,
    CeilingRecord,
    load_records,
    run_scripts,
    save_records,
    summarize_ceiling,
)
from bh8_gym.agents.evaluation.evaluate import paired_comparison


# The arm's table-contact grasp for objects lower than 3 cm (envs/scenes.py PlacementRanges; off
# in the env by default): --table-contact measures the family with it.
TABLE_CONTACT = {"placement": {"table_contact_below": LOW_OBJECT_HEIGHT}}


def _run(job):
    name, object_set, episodes, seed, randomize, table_contact = job
    env_kwargs = {"randomize": randomize, **(TABLE_CONTACT if table_contact else {})}
    return run_scripts([name], object_set, episodes, seed, env_kwargs).to_json()


def _policy_outcomes(path: Path, object_set: str, record: CeilingRecord) -> list[bool] | None:
    report = json.loads((path / "results.json" if path.is_dir() else path).read_text())
    rows = [e for e in report["episodes"] if e.get("object_set") == object_set]
    if report.get("seed") != record.seed or len(rows) < record.episodes:
        return None
    rows = rows[:record.episodes]
    if [r["object_name"] for r in rows] != record.objects:
        raise ValueError(f"{path}: its {object_set} episodes had other objects than the ceiling's")
    return [bool(r["success"]) for r in rows]


def markdown(summary: dict, policies: dict[str, list[bool]], record: CeilingRecord) -> str:
    n = summary["episodes"]

    def pct(k: int) -> str:
        return f"{k} ({k / n:.1%})"

    lines = [f"### {summary['object_set']}: {n} episodes from seed {summary['seed']}", "",
             "| grasp | held |", "|---|---:|"]
    for name, held in sorted(summary["scripts"].items(), key=lambda item: -item[1]):
        lines.append(f"| {name} | {pct(held)} |")
    lines += [f"| **best single script** ({summary['best_single']}) | **{pct(summary['best_single_held'])}** |",
              f"| best script per family (oracle told the family) | {pct(summary['per_family_best_held'])} |",
              f"| **union** (some script holds it) | **{pct(summary['union_held'])}** |"]
    best = record.success[summary["best_single"]]
    for label, outcomes in policies.items():
        paired = paired_comparison(outcomes, best)
        lines.append(f"| policy {label} | {pct(sum(outcomes))}; against {summary['best_single']}: "
                     f"{paired['only_ours']} only the policy, {paired['only_theirs']} only the script, "
                     f"p = {paired['mcnemar_p']:.2g} |")
    lines += ["", "| family | episodes | best script | held | best single script holds | union |",
              "|---|---:|---|---:|---:|---:|"]
    for family, row in summary["per_family"].items():
        lines.append(f"| {family} | {row['episodes']} | {row['best_script']} | {row['held']} | "
                     f"{row['best_single_held']} | {row['union']} |")
    low = summary["low_objects"]
    if low is not None:
        lines.append(f"| lower than {LOW_OBJECT_HEIGHT * 100:g} cm at rest | {low['episodes']} | {low['best_script']} | "
                     f"{low['held']} | {low['best_single_held']} | {low['union']} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sets", nargs="+", default=["primitives-test", "test"])
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=100_000)
    parser.add_argument("--scripts", nargs="+", default=list(FAMILY), choices=list(FAMILY))
    parser.add_argument("--randomize", action="store_true", help="domain randomisation on")
    parser.add_argument("--table-contact", action="store_true",
                        help="the arm's table-contact grasp for objects lower than 3 cm (off in the env by default)")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--policy", type=Path, nargs="*", default=[], help="bh8 eval --out reports to pair")
    args = parser.parse_args()

    # Nominal and randomised physics are recorded apart: a script's outcomes under one are no answer for the other.
    stem = "ceiling" + ("-randomized" if args.randomize else "") + ("-table-contact" if args.table_contact else "")
    records, others = {}, []
    if args.out is not None and (args.out / f"{stem}.json").exists():
        for record in load_records(args.out / f"{stem}.json"):
            if record.seed == args.seed and record.episodes == args.episodes and record.object_set in args.sets:
                records[record.object_set] = record
            else:
                others.append(record)  # kept in the file as it was
    jobs = [(name, object_set, args.episodes, args.seed, args.randomize, args.table_contact) for object_set in args.sets
            for name in args.scripts if object_set not in records or name not in records[object_set].success]
    start = time.perf_counter()
    with ProcessPoolExecutor(max(1, args.jobs)) as pool:
        for data in pool.map(_run, jobs):
            record = CeilingRecord.from_json(data)
            if record.object_set in records:
                records[record.object_set].merge(record)
            else:
                records[record.object_set] = record
            if args.out is not None:  # after every script: an interrupted run keeps what it measured
                args.out.mkdir(parents=True, exist_ok=True)
                save_records([*others, *records.values()], args.out / f"{stem}.json")
    print(f"{len(jobs)} script runs in {time.perf_counter() - start:.0f} s"
          f"{' (domain randomisation on)' if args.randomize else ''}")
    parts = []
    for object_set in args.sets:
        record = records[object_set]
        policies = {}
        for path in args.policy:
            outcomes = _policy_outcomes(path, object_set, record)
            if outcomes is None:
                print(f"{path}: not paired on {object_set}: its report needs at least the ceiling's "
                      f"{record.episodes} episodes of that set from seed {record.seed}", file=sys.stderr)
            else:
                policies[str(path)] = outcomes
        parts.append(markdown(summarize_ceiling(record, args.scripts), policies, record))
    text = "\n\n".join(parts)
    print(text)
    if args.out is not None:
        (args.out / f"{stem}.md").write_text(text + "\n")


if __name__ == "__main__":
    main()
