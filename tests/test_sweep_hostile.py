"""`bh8 sweep` against hostile input (issue 32 items 2, 7 and 10): numbers out of range and deep
nesting are one-line usage errors before Ray starts (and before a seed range is expanded); an
--address that is malformed, refused or not a Ray head fails within seconds; a search space that
can give a config bh8 train refuses is refused; an edited sweep.json cannot move --resume's writes
out of the folders the command line names; Ctrl-C before any trial has reported exits 130 with
sweep.md and the resume command. Issue 39: --resume restores no pickle at all: it rebuilds the
sweep from our own JSON records (sweep.json's planned trials, each run directory's trial.json and
result.json, checked) and never restores Ray Tune's state, so a planted tuner.pkl or
experiment_state file runs nothing, and a planted symbolic link cannot redirect its writes.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import pickle
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from bh8_gym.cli import main
from conftest import sweep_finish, sweep_wait

ray = pytest.importorskip("ray")

TINY = """\
algorithm = "PPO"
env_id = "BH8FingerReach-v0"
[eval_env_kwargs]
randomize = false
[train]
total_timesteps = {total}
checkpoint_freq = 512
[eval]
freq = 1024
episodes = 2
[hyperparameters]
n_steps = 128
batch_size = 64
n_epochs = 2
[policy_kwargs]
net_arch = [16]
[sweep]
seeds = [0, 1]
{space}
"""


def _config(folder: Path, total: int = 2048, space: str = "") -> Path:
    path = folder / "tiny.toml"
    path.write_text(TINY.format(total=total, space=space))
    return path


def _sweep(*arguments) -> tuple[int, str]:
    """`bh8 sweep ARGUMENTS` in this process: exit status (argparse's too) and stderr."""
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        try:
            code = main(["sweep", *map(str, arguments)])
        except SystemExit as exit_:
            code = exit_.code
    return code, err.getvalue()


def _refused(tmp_path: Path, *arguments, within: float = 60.0) -> str:
    started = time.monotonic()
    code, err = _sweep(*arguments)
    assert time.monotonic() - started < within, "took too long to refuse"
    assert code == 2, err
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith(("bh8 sweep", "usage")) or \
        err.strip().splitlines()[-1].startswith("bh8 sweep: error"), err
    assert not (tmp_path / "sweep").exists()
    return err.strip().splitlines()[-1]


class Payload:
    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return os.mkdir, (self.marker,)


# -- usage errors before Ray starts --------------------------------------------------------------


@pytest.mark.parametrize("option, value, message", [
    ("--seeds", "0-99999999999999999999", "--seeds"),
    ("--seeds", "0-4294967295", "at most 1000 seeds"),
    ("--seeds", "0-1000000", "at most 1000 seeds"),
    ("--seeds", "9" * 5000, "--seeds"),
    ("--seeds", "3-1", "--seeds"),
    ("--timesteps", "1" + "0" * 400, "--timesteps"),
    ("--samples", "10000000000000000000", "--samples"),
    ("--test-episodes", "10000000000000000000", "--test-episodes"),
    ("--test-seed", "4294967296", "--test-seed"),
    ("--max-failures", "99999999999", "--max-failures"),
    ("--resources-per-trial", "cpu=inf", "out of range"),
    ("--resources-per-trial", "cpu=nan", "out of range"),
    ("--resources-per-trial", "gpu=1e400", "out of range"),
    ("--resources-per-trial", "cpu=1,widgets=1e300", "out of range"),
])
def test_numbers_out_of_range_are_refused_at_once(tmp_path, option, value, message):
    line = _refused(tmp_path, "--config", _config(tmp_path), "--out", tmp_path / "sweep", option, value)
    assert message in line, line


def test_a_huge_seed_range_is_refused_without_expanding_it():
    from bh8_gym.agents.sweep.space import SweepConfigError, parse_seeds

    started = time.process_time()
    for text in ("0-4294967295", "0-99999999999999999999", "0-500,600-1200"):
        with pytest.raises(SweepConfigError, match="at most 1000 seeds"):
            parse_seeds(text)
    assert time.process_time() - started < 1.0
    assert parse_seeds("0-2,7") == [0, 1, 2, 7]


@pytest.mark.parametrize("address", ["127.0.0.1:99999", "127.0.0.1:-1", "127.0.0.1:0", "nonsense", "host:",
                                     ":6379", "[::1", "[zz::1]:6379", "127.0.0.1:6379 ; rm", "[::1]:65536"])
def test_a_malformed_address_is_a_usage_error(tmp_path, address):
    line = _refused(tmp_path, "--config", _config(tmp_path), "--out", tmp_path / "sweep", "--address", address)
    assert "HOST:PORT" in line


@pytest.mark.parametrize("address", ["127.0.0.1:1", "[::1]:1"])
def test_an_address_nothing_listens_on_fails_at_once(tmp_path, address):
    line = _refused(tmp_path, "--config", _config(tmp_path), "--out", tmp_path / "sweep", "--address", address)
    assert "cannot reach the Ray cluster" in line and address in line


def test_an_address_that_is_not_a_ray_head_times_out_with_a_message(tmp_path, monkeypatch):
    from bh8_gym.agents.sweep import cluster as sweep_cluster

    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(8)
    accepted = []

    def accept_all() -> None:  # holds each connection open, saying nothing, as a stray service might
        with contextlib.suppress(OSError):
            while True:
                accepted.append(listener.accept())

    threading.Thread(target=accept_all, daemon=True).start()
    monkeypatch.setattr(sweep_cluster, "CONNECT_TIMEOUT_S", 3.0)
    address = f"127.0.0.1:{listener.getsockname()[1]}"
    try:
        line = _refused(tmp_path, "--config", _config(tmp_path), "--out", tmp_path / "sweep", "--address", address,
                        within=60.0)
    finally:
        listener.close()
    assert "no Ray cluster answered" in line and "within 3 s" in line


def test_deep_nesting_in_the_space_or_sweep_json_is_one_line(tmp_path):
    config = tmp_path / "deep.toml"
    for depth, message in ((600, "nested more than"), (3000, "larger than 1 MB")):
        headers = "\n".join("[sweep.space." + ".".join(["t"] * level) + "]" for level in range(1, depth))
        config.write_text(TINY.format(total=2048, space="") + headers + "\n")
        line = _refused(tmp_path, "--config", config, "--out", tmp_path / "sweep")
        assert message in line

    resumed = tmp_path / "resumed"
    resumed.mkdir()
    (resumed / "sweep.json").write_text('{"version": 1, "space": ' + "[" * 100_000 + "]" * 100_000 + "}")
    code, err = _sweep("--resume", resumed)
    assert code == 2 and err.count("\n") == 1 and "sweep.json" in err and "Traceback" not in err, err


@pytest.mark.parametrize("space, message", [
    ('"hyperparameters.gamma" = {grid = [0.9, 2.0]}', "[hyperparameters] gamma must be in (0, 1]"),
    ('"hyperparameters.n_steps" = {uniform = [64, 512]}', "[hyperparameters] n_steps must be an integer"),
    ('"policy_kwargs.net_arch" = {choice = [[8], [0]]}', "[policy_kwargs] net_arch"),
    ('"hyperparameters.batch_size" = {grid = [64, 1]}', "batch_size must be at least 2"),
    ('"hyperparameters.n_steps" = {grid = [' + ", ".join(["64"] * 1001) + "]}", "1..1000 values"),
])
def test_a_space_that_can_give_a_bad_config_is_refused(tmp_path, space, message):
    config = _config(tmp_path, space="[sweep.space]\n" + space)
    line = _refused(tmp_path, "--config", config, "--out", tmp_path / "sweep")
    assert message in line, line


def _resume_args(folder: Path, *extra) -> argparse.Namespace:
    from bh8_gym.cli import build_parser

    return build_parser(["sweep"]).parse_args(["sweep", "--resume", str(folder), *map(str, extra)])


def _new_sweep_json(tmp_path: Path) -> Path:
    """A sweep directory as `bh8 sweep` leaves it before Ray has saved anything: sweep.json only."""
    from bh8_gym.agents.sweep.settings import new_settings, write_settings
    from bh8_gym.cli import build_parser

    args = build_parser(["sweep"]).parse_args(["sweep", "--config", str(_config(tmp_path)), "--out",
                                               str(tmp_path / "sweep")])
    write_settings(new_settings(args))
    return tmp_path / "sweep"


def test_an_edited_sweep_json_cannot_move_resumes_writes(tmp_path):
    """sweep_dir and experiment_path in sweep.json pointing elsewhere: the resumed settings keep the
    folder given to --resume; trials stored outside it need --storage on the command line."""
    from bh8_gym.agents.sweep.settings import resumed_settings
    from bh8_gym.agents.sweep.space import SweepConfigError

    folder = _new_sweep_json(tmp_path)
    elsewhere = tmp_path / "elsewhere"
    settings = json.loads((folder / "sweep.json").read_text())
    settings.update(sweep_dir=str(elsewhere), experiment_path=str(elsewhere))
    (folder / "sweep.json").write_text(json.dumps(settings))
    resumed = resumed_settings(_resume_args(folder))
    assert resumed["sweep_dir"] == resumed["experiment_path"] == str(folder.resolve())

    settings.update(sweep_dir=str(folder), experiment_path=str(elsewhere / "sweep"))
    (folder / "sweep.json").write_text(json.dumps(settings))
    with pytest.raises(SweepConfigError, match="pass --storage"):
        resumed_settings(_resume_args(folder))
    storage = tmp_path / "storage"
    resumed = resumed_settings(_resume_args(folder, "--storage", storage))
    assert resumed["experiment_path"] == str(storage.resolve() / "sweep")
    assert not elsewhere.exists()


@pytest.mark.parametrize("field, value, message", [
    ("n_envs", 10**9, "n_envs"), ("timesteps", -1, "timesteps"), ("resources", {"cpu": 1e308}, "out of range"),
    ("max_failures", "x", "max_failures"), ("seeds", list(range(2000)), "seeds"), ("samples", 0, "samples"),
    ("config", {"algorithm": "PPO"}, "env_id"), ("space", {"hyperparameters.gamma": {"grid": [7]}}, "gamma"),
])
def test_an_edited_sweep_json_is_checked_like_a_new_sweep(tmp_path, field, value, message):
    folder = _new_sweep_json(tmp_path)
    settings = json.loads((folder / "sweep.json").read_text())
    settings[field] = value
    (folder / "sweep.json").write_text(json.dumps(settings))
    code, err = _sweep("--resume", folder)
    assert code == 2 and err.count("\n") == 1 and message in err and "Traceback" not in err, err


def _trial_files(folder: Path, name: str, seed: int, space: dict | None = None, finished: bool = False,
                 sweep_id: str | None = None) -> Path:
    sweep_id = sweep_id or json.loads((folder / "sweep.json").read_text())["sweep_id"]
    run_dir = folder / "runs" / f"{name}_seed{seed}"
    run_dir.mkdir(parents=True)
    (run_dir / "trial.json").write_text(json.dumps({"trial_id": name, "seed": seed, "space": space or {},
                                                    "attempts": 1, "wall_seconds": 3.0, "sweep_id": sweep_id}))
    if finished:
        (run_dir / "result.json").write_text(json.dumps({"metrics": {"best_validation_success": 0.5,
                                                                     "best_mean_return": 1.0},
                                                         "num_timesteps": 2048, "wall_seconds": 3.0, "attempts": 1,
                                                         "sweep_id": sweep_id}))
    return run_dir


def test_resume_is_rebuilt_from_our_records_not_from_ray(tmp_path):
    """The trials are drawn when the sweep starts (sweep.json); --resume launches the ones without a
    whole result.json, from that record. What a run directory says is checked: a trial.json naming
    a value the space cannot give, or a result.json that is damaged or holds a string for its step
    count, is not taken as finished or relaunched as it is (before: latest.json and result.json
    were read unchecked)."""
    from bh8_gym.agents.sweep.command import _launches
    from bh8_gym.agents.sweep.report import COMPLETE, PENDING, STOPPED, collect, started_trials
    from bh8_gym.agents.sweep.settings import resumed_settings

    folder = _new_sweep_json(tmp_path)
    settings = resumed_settings(_resume_args(folder))
    assert [(t["name"], t["seed"]) for t in settings["trials"]] == [("t0000", 0), ("t0001", 1)]
    assert [trials for trials, _ in _launches(settings)] == [settings["trials"]]
    _trial_files(folder, "t0000", 0, finished=True)
    assert [trials for trials, _ in _launches(settings)] == [settings["trials"][1:]]
    records = collect(settings, {})
    assert [(r.trial_id, r.seed, r.status) for r in records] == [("t0000", 0, COMPLETE), ("t0001", 1, PENDING)]
    run_dir = _trial_files(folder, "t0001", 1)
    assert [r.status for r in collect(settings, {})] == [COMPLETE, STOPPED]
    for damaged in ("[1, 2]", '{"metrics": {}, "num_timesteps": "2048"}', '{"metrics": {}, "num_timesteps": 1e308}'):
        (run_dir / "result.json").write_text(damaged)
        assert [r.status for r in collect(settings, {})] == [COMPLETE, STOPPED], damaged
    (run_dir / "trial.json").write_text(json.dumps({"trial_id": "t0001", "seed": 1, "sweep_id": settings["sweep_id"],
                                                    "space": {"hyperparameters.gamma": 7}}))
    assert [t["name"] for t in started_trials(settings)] == ["t0000"]  # not one this sweep gives


def test_a_trial_copied_from_another_sweep_is_not_taken_for_this_ones(tmp_path):
    """Finding 12: the seal was not tied to its folder, so sealed state copied between two sweeps of
    one account passed. The records are tied to their sweep now (sweep.json's sweep_id, written
    into each trial.json and result.json): a run directory from another sweep is refused by
    --resume (exit 2) and never counted as finished."""
    from bh8_gym.agents.sweep.report import collect, started_trials
    from bh8_gym.agents.sweep.settings import resumed_settings

    folder = _new_sweep_json(tmp_path)
    settings = resumed_settings(_resume_args(folder))
    _trial_files(folder, "t0000", 0, finished=True, sweep_id="0123456789abcdef")
    assert started_trials(settings) == [] and collect(settings, {})[0].status != "complete"
    code, err = _sweep("--resume", folder)
    assert code == 2 and "another sweep's trial" in err and err.count("\n") == 1, err


@pytest.mark.parametrize("planted", ["test/t0000_seed0.partial", "runs/t0001_seed1", "validation_curves.png",
                                     "runs/t0000_seed0/evaluations.csv"])
def test_a_planted_symlink_is_refused_before_resume_writes_anything(tmp_path, planted):
    """Issue 39 finding 6: test/<trial>.partial linked to another folder had bh8 eval's report written
    over that folder's results.json, table.md and eval.txt, with exit 0. A link or special file
    where --resume writes is now refused at once (exit 2, one line), and nothing is written."""
    folder = _new_sweep_json(tmp_path)
    _trial_files(folder, "t0000", 0, finished=True)
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "results.json").write_text("precious")
    link = folder / planted
    link.parent.mkdir(parents=True, exist_ok=True)
    link.symlink_to(victim)
    code, err = _sweep("--resume", folder)
    assert code == 2 and err.count("\n") == 1 and "symbolic link" in err and planted.split("/")[-1] in err, err
    assert (victim / "results.json").read_text() == "precious" and os.listdir(victim) == ["results.json"]


# -- a real sweep: Ctrl-C before any report, planted pickles, --resume ------------------------------


def _sweep_process(log: Path, *arguments) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "bh8_gym.cli", "sweep", "--num-cpus", "2", "--test-episodes", "2",
                             *map(str, arguments)], stdout=log.open("w"), stderr=subprocess.STDOUT,
                            start_new_session=True)


@pytest.mark.timeout(3600)  # two Ray starts and two short trials; the waits are hang guards (conftest.py)
def test_ctrl_c_before_any_report_then_resume_restores_no_pickle(tmp_path):
    """Issue 39 finding 1: --resume ran a payload swapped into tuner.pkl during the seal check's window,
    or planted as a newer experiment_state-*.json where the seal saw no file. Now no file of Ray
    Tune's is ever restored: every pickle and experiment state under the sweep is replaced by a
    payload, and the resumed sweep finishes without running it."""
    sweep, log = tmp_path / "sweep", tmp_path / "first.log"
    process = _sweep_process(log, "--config", _config(tmp_path, total=1024), "--out", sweep)
    sweep_wait(lambda: list(sweep.glob("runs/*/trial.json")), process, log, sweep)  # a trial has started; none has evaluated yet
    os.killpg(process.pid, signal.SIGINT)
    assert sweep_finish(process, log, sweep) == 130, log.read_text()[-3000:]
    text = log.read_text()
    assert "KeyError" not in text and "Traceback" not in text, text[-3000:]
    assert f"bh8 sweep --resume {sweep}" in text
    report = (sweep / "sweep.md").read_text()
    assert "stopped" in report or "pending" in report

    marker = tmp_path / "ran"
    payload = pickle.dumps(Payload(marker))
    pickles = [path for path in sweep.rglob("*") if path.suffix == ".pkl" or path.name.startswith("experiment_state")]
    assert pickles  # Ray Tune's own state, under ray/
    for path in [*pickles, sweep / "tuner.pkl", sweep / "experiment_state-2099-01-01_00-00-00.json",
                 next(sweep.glob("ray/*")) / "tuner.pkl"]:
        path.write_bytes(payload)
    log = tmp_path / "resumed.log"
    process = _sweep_process(log, "--resume", sweep)
    assert sweep_finish(process, log, sweep) == 0, log.read_text()[-3000:]
    assert not marker.exists()
    assert "2 complete" in (sweep / "sweep.md").read_text()
