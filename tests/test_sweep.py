"""`bh8 sweep` on a real local Ray (num_cpus=2, no mocks of Ray): two trials of a few thousand steps
of PPO on BH8FingerReach-v0. A sweep stopped by Ctrl-C exits 130 and `--resume` finishes it from
the trials' checkpoints; the table, the plot and the chosen model's test evaluation agree with the
run directories and with `bh8 eval`; a worker killed mid-trial is retried from its checkpoint and a
trial that crashes for good is reported. Usage errors exit 2 before Ray starts, and without Ray
the command says how to install it.
"""
from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from bh8_gym.cli import main
from conftest import sweep_finish, sweep_wait

TINY = """\
algorithm = "PPO"
env_id = "BH8FingerReach-v0"
[eval_env_kwargs]
randomize = false
[train]
total_timesteps = {total}
checkpoint_freq = 512
[eval]
freq = {eval_freq}
episodes = 2
[hyperparameters]
n_steps = 128
batch_size = 64
n_epochs = 2
[policy_kwargs]
net_arch = [16]
[sweep]
seeds = {seeds}
{space}
"""
TEST_EPISODES = 3


def _config(folder: Path, total: int = 4096, eval_freq: int = 1024, seeds: str = "[0, 1]", space: str = "") -> Path:
    path = folder / "tiny.toml"
    path.write_text(TINY.format(total=total, eval_freq=eval_freq, seeds=seeds, space=space))
    return path


def _sweep_in_process(*arguments) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["sweep", *map(str, arguments)])
    return code, out.getvalue(), err.getvalue()


def _sweep_process(log: Path, *arguments) -> subprocess.Popen:
    """`bh8 sweep` as a terminal would run it: its own process group (Ctrl-C reaches all of it)."""
    return subprocess.Popen([sys.executable, "-m", "bh8_gym.cli", "sweep", "--num-cpus", "2",
                             "--test-episodes", str(TEST_EPISODES), *map(str, arguments)],
                            stdout=log.open("w"), stderr=subprocess.STDOUT, start_new_session=True)


# Each test's own limit (pytest-timeout) covers its waits (conftest.py's sweep_wait).
SWEEP_TEST_TIMEOUT = 3600


def _table(report: str) -> dict[str, dict[str, str]]:
    """sweep.md's trial table as {trial id: {column: cell}}."""
    lines = [line for line in report.splitlines() if line.startswith("|")]
    header = [cell.strip() for cell in lines[0].strip("|").split("|")]
    rows = {}
    for line in lines[2:]:
        cells = [cell.strip() for cell in line.strip("|").split("|")]
        if len(cells) == len(header) and re.fullmatch(r"t\d{4}|[0-9a-f]+_\d+", cells[1]):
            rows[cells[1]] = dict(zip(header, cells))
    return rows


def _evaluations(run_dir: Path) -> list[dict[str, float]]:
    with (run_dir / "evaluations.csv").open(newline="") as handle:
        return [{key: float(value) for key, value in row.items()} for row in csv.DictReader(handle)]


# -- without Ray, and usage errors ---------------------------------------------------------------


def test_without_ray_it_says_how_to_install_it(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    code, out, err = _sweep_in_process("--config", _config(tmp_path), "--out", tmp_path / "sweep")
    assert code == 2
    assert 'pip install "bh8-gym[cluster]"' in err and "Traceback" not in err
    assert not (tmp_path / "sweep").exists()


def test_help_explains_every_option(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["sweep", "--help"])
    assert exit_.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    for option in ("--config", "--seeds", "--timesteps", "--address", "--resources-per-trial", "--max-concurrent",
                   "--storage", "--max-failures", "--resume", "--out", "--test-episodes", "--search", "--samples"):
        assert option in text
    assert "ray start --head" in text and "validation" in text and "test split" in text


@pytest.mark.parametrize("train_table, options, n_envs", [("", ["--resources-per-trial", "cpu=2"], 2),
                                                          ("n_envs = 8", ["--resources-per-trial", "cpu=2"], 8),
                                                          ("n_envs = 8", ["--n-envs", "3"], 3)])
def test_a_trial_trains_the_configs_envs_unless_told_otherwise(tmp_path, train_table, options, n_envs):
    """A trial's envs: --n-envs, else the config's train.n_envs (the grasp config's 8 share each
    process's per-step costs), else one per CPU of the trial (docs/cluster.md)."""
    import argparse

    from bh8_gym.agents.sweep.command import configure_parser
    from bh8_gym.agents.sweep.settings import new_settings

    config = _config(tmp_path)
    config.write_text(config.read_text().replace("[train]\n", f"[train]\n{train_table}\n"))
    parser = argparse.ArgumentParser()
    configure_parser(parser)
    settings = new_settings(parser.parse_args(["--config", str(config), "--out", str(tmp_path / "sweep"), *options]))
    assert settings["n_envs"] == n_envs


@pytest.mark.parametrize("case", ["unknown space key", "space key in an unknown table", "bad spec", "bad seeds",
                                  "no evaluation", "missing resume dir", "resume with a new config",
                                  "optuna with a grid", "bad resources"])
def test_bad_input_exits_2_with_a_message_before_ray_starts(tmp_path, case):
    pytest.importorskip("ray")
    arguments = ["--out", tmp_path / "sweep"]
    space = {"unknown space key": '"hyperparameters.learnin_rate" = {grid = [1e-3, 3e-4]}',
             "space key in an unknown table": '"hyperparams.learning_rate" = {grid = [1e-3]}',
             "bad spec": '"hyperparameters.learning_rate" = {loguniform = [1e-3, 1e-4]}',
             "optuna with a grid": 'search = "optuna"\n"hyperparameters.gamma" = {grid = [0.9, 0.99]}'}.get(case, "")
    if case == "optuna with a grid":
        space = 'search = "optuna"\n[sweep.space]\n"hyperparameters.gamma" = {grid = [0.9, 0.99]}'
    elif space:
        space = "[sweep.space]\n" + space
    config = _config(tmp_path, space=space, eval_freq=10_000 if case == "no evaluation" else 1024)
    expected = {"unknown space key": "unknown config key", "space key in an unknown table": "unknown config key",
                "bad spec": "low < high", "bad seeds": "--seeds", "no evaluation": "eval.freq",
                "missing resume dir": "no such directory", "resume with a new config": "drop --config",
                "optuna with a grid": "no grid", "bad resources": "--resources-per-trial"}[case]
    if case == "bad seeds":
        arguments += ["--seeds", "0,x"]
    elif case == "missing resume dir":
        arguments = ["--resume", tmp_path / "nothing"]
    elif case == "resume with a new config":
        (tmp_path / "sweep").mkdir()
        arguments = ["--resume", tmp_path / "sweep"]
    elif case == "bad resources":
        arguments += ["--resources-per-trial", "cpu=two"]
    if case == "bad resources":
        with pytest.raises(SystemExit) as exit_, contextlib.redirect_stderr(io.StringIO()) as err:
            main(["sweep", "--config", str(config), *map(str, arguments)])
        assert exit_.value.code == 2 and expected in err.getvalue() and "cpu=two" in err.getvalue()
        return
    if case != "missing resume dir":
        arguments = ["--config", config, *arguments]
    code, out, err = _sweep_in_process(*arguments)
    assert code == 2, err
    assert expected in err and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1, err
    if case not in ("resume with a new config",):
        assert not (tmp_path / "sweep").exists()


def test_sweep_table_nested_or_dotted_keys_cross_grids_with_seeds():
    """[sweep.space.hyperparameters] and quoted dotted keys name the same dimensions; grids cross
    each other and the seeds; a trial's values land in its copy of the config only."""
    import tomllib

    from bh8_gym.agents.sweep.space import apply_space, count_trials, describe, read_sweep_table

    text = TINY.format(total=4096, eval_freq=1024, seeds="[3, 4, 5]", space="""\
samples = 2
[sweep.space]
"policy_kwargs.net_arch" = {choice = [[16], [32, 32]]}
[sweep.space.hyperparameters]
n_steps = {grid = [64, 128]}
learning_rate = {loguniform = [1e-4, 1e-3]}
""")
    config = tomllib.loads(text)
    for table in ("env_kwargs", "eval_env_kwargs", "train", "eval", "hyperparameters", "policy_kwargs"):
        config.setdefault(table, {})
    sweep = read_sweep_table(config)
    assert "sweep" not in config  # each trial's run.json holds a plain bh8 train config
    assert sweep["seeds"] == [3, 4, 5] and sweep["samples"] == 2
    assert set(sweep["space"]) == {"hyperparameters.n_steps", "hyperparameters.learning_rate", "policy_kwargs.net_arch"}
    assert count_trials(sweep) == 3 * 2 * 2
    trial = apply_space(config, {"hyperparameters.n_steps": 64, "policy_kwargs.net_arch": [32, 32]})
    assert trial["hyperparameters"]["n_steps"] == 64 and trial["policy_kwargs"]["net_arch"] == [32, 32]
    assert config["hyperparameters"]["n_steps"] == 128 and config["policy_kwargs"]["net_arch"] == [16]
    assert describe({"hyperparameters.learning_rate": 0.000316227, "hyperparameters.n_steps": 64}) == \
        "learning_rate=0.000316, n_steps=64"


# -- real sweeps --------------------------------------------------------------------------------


@pytest.mark.timeout(SWEEP_TEST_TIMEOUT)
def test_sweep_stopped_by_ctrl_c_resumes_and_reports_what_bh8_eval_measures(tmp_path):
    """Two seeds; Ctrl-C once a trial has a checkpoint; --resume finishes both; the report's test
    numbers are bh8 eval's of the chosen model, which is the best on validation."""
    pytest.importorskip("ray")
    config, sweep = _config(tmp_path, total=4096), tmp_path / "sweep"
    log = tmp_path / "first.log"
    process = _sweep_process(log, "--config", config, "--out", sweep)
    sweep_wait(lambda: list(sweep.glob("runs/*/checkpoints/latest.json")), process, log, sweep)
    os.killpg(process.pid, signal.SIGINT)
    assert sweep_finish(process, log, sweep) == 130, log.read_text()[-3000:]
    stopped = (sweep / "sweep.md").read_text()
    assert "stopped" in stopped and "bh8 sweep --resume" in stopped
    assert not (sweep / "test").exists()  # no test evaluation of an unfinished sweep

    log = tmp_path / "resumed.log"
    process = _sweep_process(log, "--resume", sweep)
    assert sweep_finish(process, log, sweep) == 0, log.read_text()[-3000:]
    report = (sweep / "sweep.md").read_text()
    rows = _table(report)
    run_dirs = sorted((sweep / "runs").iterdir())
    assert len(rows) == 2 and len(run_dirs) == 2
    starts = []
    for run_dir in run_dirs:
        for name in ("run.json", "evaluations.csv", "best_model.zip", "final_model.zip", "checkpoints/latest.zip",
                     "result.json", "tb"):
            assert (run_dir / name).exists(), (run_dir, name)
        trial = json.loads((run_dir / "trial.json").read_text())
        starts += trial["starts"]
        evaluations = _evaluations(run_dir)
        steps = [row["timesteps"] for row in evaluations]
        assert steps == [1024, 2048, 3072, 4096]  # each evaluation once, resumed or not
        row = rows[trial["trial_id"]]
        best = max(evaluations, key=lambda r: (r["success_rate"], r["mean_return"]))
        assert row["status"] == "complete" and row["steps"] == "4096" and row["seed"] == str(trial["seed"])
        assert row["best validation success"].startswith(f"{best['success_rate']:.3f}")
        assert row["95% CI (Wilson)"] == f"{best['success_ci_low']:.3f}-{best['success_ci_high']:.3f}"
        assert json.loads((run_dir / "run.json").read_text())["seed"] == trial["seed"]
    assert any(start > 0 for start in starts), starts  # a trial went on from its checkpoint

    chosen = next(row for row in rows.values() if row["rank"] == "1")
    model = next(d for d in run_dirs if d.name.startswith(chosen["trial"])) / "best_model.zip"
    best = {d.name.split("_seed")[0]: max((r["success_rate"], r["mean_return"]) for r in _evaluations(d))
            for d in run_dirs}
    assert best[chosen["trial"]] == max(best.values())  # selected on validation
    assert f"`{model}`" in report
    png = sweep / "validation_curves.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["eval", str(model), "--episodes", str(TEST_EPISODES), "--no-progress"]) == 0
    measured = re.search(r"success rate (\d\.\d{3}) \(95% Wilson CI (\d\.\d{3})-(\d\.\d{3})\) over (\d+) episodes",
                         out.getvalue())
    assert measured, out.getvalue()
    rate, low, high, episodes = measured.groups()
    assert f"success rate {rate} (" in report and f"95% Wilson CI {low}-{high});" in report
    mean_return = re.search(r"mean return (-?\d+\.\d\d);", out.getvalue()).group(1)
    assert f"mean return {mean_return}" in report
    results = json.loads(next((sweep / "test").glob("*/results.json")).read_text())
    assert results["summary"]["episodes"] == int(episodes)


@pytest.mark.timeout(SWEEP_TEST_TIMEOUT)
def test_killed_worker_is_retried_from_its_checkpoint_and_a_crash_is_reported(tmp_path):
    """`kill -9` of the worker running one trial: with --max-failures 1 it goes on from its last
    checkpoint and completes; a trial whose env cannot be built (a nested env setting the sweep
    leaves to the env to check) fails both attempts and is reported (exit 1), and the sweep still
    ranks and tests the other."""
    pytest.importorskip("ray")
    config = _config(tmp_path, total=6144, seeds="[0]",
                     space='[sweep.space]\n"env_kwargs.targets" = {grid = [{}, {bogus = 1}]}')
    sweep, log = tmp_path / "sweep", tmp_path / "sweep.log"
    process = _sweep_process(log, "--config", config, "--out", sweep, "--max-failures", "1")
    checkpoint = sweep_wait(lambda: list(sweep.glob("runs/*/checkpoints/latest.json")), process, log, sweep)[0]
    run_dir = checkpoint.parent.parent
    trial = json.loads((run_dir / "trial.json").read_text())
    os.kill(trial["pid"], signal.SIGKILL)
    assert sweep_finish(process, log, sweep) == 1, log.read_text()[-3000:]

    rows = _table((sweep / "sweep.md").read_text())
    killed = rows[trial["trial_id"]]
    assert killed["status"] == "complete" and killed["attempts"] == "2" and killed["rank"] == "1"
    record = json.loads((run_dir / "trial.json").read_text())
    assert record["starts"][0] == 0 and record["starts"][1] >= 512 and record["starts"][1] % 512 == 0
    steps = [row["timesteps"] for row in _evaluations(run_dir)]
    assert steps == sorted(set(steps)) and steps[-1] == 6144
    crashed = next(row for trial_id, row in rows.items() if trial_id != trial["trial_id"])
    assert crashed["config"] == "targets={'bogus': 1}" and crashed["attempts"] == "2"
    assert crashed["status"].startswith("error:") and "bogus" in crashed["status"]
    assert list((sweep / "test").glob(f"{run_dir.name}/results.json"))
