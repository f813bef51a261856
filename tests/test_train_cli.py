"""`bh8 train` as a command: usage errors exit 2 naming the bad value, --resume keeps the run's own
configuration, the summary tells whether an evaluation ran, SIGTERM and SIGHUP checkpoint like
Ctrl-C, and the files written are strict JSON with the umask's mode.

Kept fast: PPO on BH8FingerReach-v0 with rollouts of 32 steps, a few dozen env steps per run.
"""
from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bh8_gym.cli import main

REACH = "BH8FingerReach-v0"


def _write_config(path: Path, env_id: str = REACH, total: int = 64, eval_freq: int = 10_000,
                  checkpoint_freq: int = 10_000, hyperparameters: str = "") -> Path:
    """A tiny PPO reach config: one rollout of 32 steps per env, no evaluation unless eval_freq is small."""
    path.write_text(f"""\
algorithm = "PPO"
env_id = "{env_id}"
[eval_env_kwargs]
randomize = false
[train]
total_timesteps = {total}
checkpoint_freq = {checkpoint_freq}
[eval]
freq = {eval_freq}
episodes = 1
[hyperparameters]
n_steps = 32
batch_size = 32
n_epochs = 1
{hyperparameters}
[policy_kwargs]
net_arch = [8]
""")
    return path


def _train(*arguments) -> tuple[int, str, str]:
    """`bh8 train --no-progress --n-envs 1 ARGUMENTS` in this process: exit code, stdout, stderr."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["train", "--no-progress", "--n-envs", "1", *map(str, arguments)])
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def short_run(tmp_path_factory) -> tuple[Path, Path, str]:
    """A finished 64-step run (config, run directory, stdout) with no evaluation (eval.freq 10000),
    trained under umask 027."""
    folder = tmp_path_factory.mktemp("short")
    config = _write_config(folder / "tiny.toml")
    previous = os.umask(0o027)
    try:
        code, out, err = _train("--config", config, "--out", folder / "run")
    finally:
        os.umask(previous)
    assert code == 0, err
    return config, folder / "run", out


# -- usage errors ------------------------------------------------------------------------------


@pytest.mark.parametrize("case", ["env option", "env in config", "hyperparameter", "out is a file"])
def test_bad_values_exit_2_with_one_line_naming_them(tmp_path, case):
    """Checked before anything is built or written: no traceback, no output directory."""
    out = tmp_path / "run"
    arguments = ["--config", _write_config(tmp_path / "tiny.toml")]
    if case == "env option":
        arguments, bad = ["--env", "NoSuch-v0"], "NoSuch-v0"
    elif case == "env in config":
        arguments, bad = ["--config", _write_config(tmp_path / "bad.toml", env_id="NoSuch-v0")], "NoSuch-v0"
    elif case == "hyperparameter":
        arguments, bad = ["--config", _write_config(tmp_path / "bad.toml", hyperparameters="n_stepz = 5")], "n_stepz"
    else:
        out.write_text("not a directory")
        bad = str(out)
    code, _, err = _train(*arguments, "--out", out)
    assert code == 2
    assert err.startswith("bh8 train: ") and err.count("\n") == 1 and bad in err, err
    if case != "out is a file":
        assert not out.exists()


@pytest.mark.parametrize("option, value", [("--timesteps", "0"), ("--timesteps", "-5"), ("--n-envs", "0")])
def test_zero_or_negative_counts_are_usage_errors_not_the_default(tmp_path, capsys, option, value):
    config = _write_config(tmp_path / "tiny.toml")
    with pytest.raises(SystemExit) as exit_info:
        main(["train", "--config", str(config), "--out", str(tmp_path / "run"), option, value])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert f"{option}: must be in 1.." in err and f"got {value}" in err
    assert not (tmp_path / "run").exists()


def test_resume_refuses_an_incomplete_checkpoint(tmp_path):
    """latest.zip without latest.json (a folder this version's checkpoints never leave)."""
    (tmp_path / "run" / "checkpoints").mkdir(parents=True)
    (tmp_path / "run" / "checkpoints" / "latest.zip").write_bytes(b"PK")
    code, _, err = _train("--config", _write_config(tmp_path / "tiny.toml"), "--out", tmp_path / "run", "--resume")
    assert code == 2 and "incomplete" in err and "latest.json" in err, err


class _Killed(BaseException):
    """A kill at a chosen file operation (nothing in the trainer catches a BaseException)."""


@pytest.mark.parametrize("kill_at", range(1, 5))
def test_a_kill_during_a_checkpoint_leaves_a_model_and_state_of_the_same_step(tmp_path, monkeypatch, kill_at):
    """The checkpoint at step 64 is killed at each of its 4 renames (model staged, state staged, model
    in place, state in place). The resumed run loads a model and a state file of one step (before,
    a kill between latest.zip and latest.json paired the new model with the old step's bookkeeping),
    then finishes with no staged or temporary file left."""
    from stable_baselines3 import PPO

    from bh8_gym.agents.training.trainer import Trainer

    config = _write_config(tmp_path / "tiny.toml", checkpoint_freq=32)
    run = tmp_path / "run"
    assert _train("--config", config, "--out", run, "--timesteps", "32")[0] == 0
    checkpoints = run / "checkpoints"
    replace, renames = os.replace, []

    def killed_replace(source, destination):
        if Path(destination).parent == checkpoints:
            renames.append(Path(destination).name)
            if len(renames) == kill_at:
                raise _Killed
        replace(source, destination)

    monkeypatch.setattr(os, "replace", killed_replace)
    with pytest.raises(_Killed):
        _train("--resume", "--out", run, "--timesteps", "64")
    monkeypatch.setattr(os, "replace", replace)
    assert renames[-1] == ["latest.zip.next", "latest.json.next", "latest.zip", "latest.json"][kill_at - 1]

    loaded = {}
    read_state, resume_model = Trainer._read_checkpoint_state, Trainer._resume_model

    def spy_state(trainer):
        state = read_state(trainer)
        loaded["state"] = state["num_timesteps"]
        return state

    def spy_model(trainer, env):
        model = resume_model(trainer, env)
        loaded["model"] = model.num_timesteps
        return model

    (checkpoints / "latest.zip.next.k1ll3d.tmp").write_bytes(b"PK")  # what a SIGKILL mid-write leaves
    monkeypatch.setattr(Trainer, "_read_checkpoint_state", spy_state)
    monkeypatch.setattr(Trainer, "_resume_model", spy_model)
    code, out, err = _train("--resume", "--out", run, "--timesteps", "96")
    assert code == 0, err
    # Killed before the staged state file exists (renames 1-2): the step-32 checkpoint; after: step 64.
    expected = 32 if kill_at <= 2 else 64
    assert loaded["state"] == loaded["model"] == expected, loaded
    assert json.loads((checkpoints / "latest.json").read_text())["num_timesteps"] == 96
    assert PPO.load(checkpoints / "latest.zip", device="cpu").num_timesteps == 96
    assert not list(checkpoints.glob("*.next")) and not list(checkpoints.glob("*.tmp"))


# -- resume --------------------------------------------------------------------------------------


@pytest.mark.parametrize("arguments, message", [
    (["--algo", "SAC"], "--algo SAC contradicts"),
    (["--env", "BH8Grasp-v0"], "--env BH8Grasp-v0 contradicts"),
    (["--seed", "1"], "--seed 1 contradicts"),
    (["--config", "other"], "in hyperparameters.n_epochs"),
])
def test_resume_refuses_options_that_contradict_the_run(short_run, tmp_path, arguments, message):
    _, run, _ = short_run
    if "other" in arguments:
        other = _write_config(tmp_path / "other.toml")
        other.write_text(other.read_text().replace("n_epochs = 1", "n_epochs = 2"))
        arguments = ["--config", other]
    code, _, err = _train("--resume", "--out", run, *arguments)
    assert code == 2 and message in err, err


def test_resume_accepts_options_that_agree_with_the_run(short_run):
    config, run, _ = short_run
    code, out, err = _train("--resume", "--out", run, "--algo", "PPO", "--env", REACH, "--seed", "0",
                            "--config", config, "--timesteps", "64")
    assert code == 0, err
    assert out.startswith("trained to 64 steps; no validation evaluation ran")


def test_resume_drops_evaluations_made_after_the_checkpoint(tmp_path):
    """A run killed after an evaluation but before the next checkpoint: the resumed run makes that
    evaluation again, and evaluations.csv holds it once. The summary then names the best model."""
    from bh8_gym.agents.evaluation.run_files import read_evaluations

    config = _write_config(tmp_path / "tiny.toml", eval_freq=32)
    run = tmp_path / "run"
    assert _train("--config", config, "--out", run, "--timesteps", "32")[0] == 0
    with (run / "evaluations.csv").open("a", newline="") as handle:  # made after the checkpoint at 32
        handle.write("64,1.0,0.0,1.0,0.0,0.0,1.0,99\r\n")
    code, out, err = _train("--resume", "--out", run, "--timesteps", "64")
    assert code == 0, err
    rows = read_evaluations(run)
    assert [(row["timesteps"], row["episodes"]) for row in rows] == [(32.0, 1.0), (64.0, 1.0)]
    assert "best validation success rate" in out and str(run / "best_model.zip") in out
    assert (run / "best_model.zip").is_file()


def test_resume_without_timesteps_trains_to_the_runs_own_total(tmp_path):
    """`bh8 train --timesteps 32` interrupted, then `--resume` alone: the run's own 32 steps, not the
    config's train.total_timesteps (64 here; the README's 400 k main job would have gone on to 500 k)."""
    config = _write_config(tmp_path / "tiny.toml", total=64)
    run = tmp_path / "run"
    assert _train("--config", config, "--out", run, "--timesteps", "32")[0] == 0
    assert json.loads((run / "checkpoints" / "latest.json").read_text())["total_timesteps"] == 32
    code, out, err = _train("--resume", "--out", run)
    assert code == 0, err
    assert out.startswith("trained to 32 steps")
    code, out, err = _train("--resume", "--out", run, "--timesteps", "64")  # --timesteps extends it
    assert code == 0, err
    assert out.startswith("trained to 64 steps")


def test_resume_draws_new_scenes_deterministically(tmp_path, monkeypatch):
    """SB3's load re-seeds the envs with the run's seed, so a resumed run replayed the scenes its
    first half trained on; it now seeds them with seed + the checkpoint's step (still deterministic)."""
    import bh8_gym.envs.base as base

    seeds = []
    prepare = base.BH8LoopEnv.prepare_episode

    def logged(env, seed=None, keep_io=False):
        seeds.append(seed)
        prepare(env, seed, keep_io)

    monkeypatch.setattr(base.BH8LoopEnv, "prepare_episode", logged)
    config = _write_config(tmp_path / "tiny.toml", total=64)
    run = tmp_path / "run"
    assert _train("--config", config, "--out", run, "--timesteps", "32", "--seed", "3")[0] == 0
    first = [seed for seed in seeds if seed is not None]
    seeds.clear()
    assert _train("--resume", "--out", run, "--timesteps", "64")[0] == 0
    resumed = [seed for seed in seeds if seed is not None]
    assert 3 in first and 3 not in resumed and 3 + 32 in resumed


def test_resume_puts_back_the_checkpoints_best_model(tmp_path):
    """A run killed after an evaluation wrote best_model.zip but before the checkpoint that
    would record it: --resume restores the checkpoint's own best model (it compares against that
    best), instead of keeping a model from the discarded stretch of the run."""
    config = _write_config(tmp_path / "tiny.toml", eval_freq=32)
    run = tmp_path / "run"
    assert _train("--config", config, "--out", run, "--timesteps", "32")[0] == 0
    saved = (run / "checkpoints" / "best_model.zip").read_bytes()
    assert saved == (run / "best_model.zip").read_bytes()
    (run / "best_model.zip").write_bytes(b"written by an evaluation after the checkpoint")
    code, _, err = _train("--resume", "--out", run, "--timesteps", "32")
    assert code == 0, err
    assert (run / "best_model.zip").read_bytes() == saved


def test_resume_removes_a_best_model_written_after_a_checkpoint_without_evaluations(short_run, tmp_path):
    _, run, _ = short_run
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    (copy / "best_model.zip").write_bytes(b"written by an evaluation after the checkpoint")
    code, out, err = _train("--resume", "--out", copy, "--timesteps", "64")
    assert code == 0, err
    assert not (copy / "best_model.zip").exists() and "no validation evaluation ran" in out


def test_resume_reads_checkpoints_written_with_minus_infinity(short_run, tmp_path):
    """Checkpoints from before null was used say "no evaluation yet" as -1.0 and -Infinity."""
    _, run, _ = short_run
    copy = shutil.copytree(run, tmp_path / "run")
    state_path = copy / "checkpoints" / "latest.json"
    state = json.loads(state_path.read_text())
    state.update(best_success_rate=-1.0, best_mean_return=float("-inf"))
    state_path.write_text(json.dumps(state))
    code, out, err = _train("--resume", "--out", copy, "--timesteps", "64")
    assert code == 0, err
    assert "no validation evaluation ran" in out


# -- outputs ---------------------------------------------------------------------------------------


def test_summary_of_a_run_without_evaluation_names_the_final_model(short_run):
    _, run, out = short_run
    assert "no validation evaluation ran" in out and "best_model.zip" in out and str(run / "final_model.zip") in out
    assert "success rate" not in out
    assert not (run / "best_model.zip").exists() and (run / "final_model.zip").is_file()


def test_checkpoint_state_is_strict_json_with_null_before_any_evaluation(short_run):
    def refuse(constant):
        raise ValueError(f"not JSON: {constant}")

    _, run, _ = short_run
    state = json.loads((run / "checkpoints" / "latest.json").read_text(), parse_constant=refuse)
    assert state["best_success_rate"] is None and state["best_mean_return"] is None
    assert state["num_timesteps"] == 64


def test_written_files_get_the_umask_mode(short_run):
    _, run, _ = short_run
    for name in ("run.json", "checkpoints/latest.json", "checkpoints/latest.zip", "final_model.zip"):
        assert (run / name).stat().st_mode & 0o777 == 0o640, name  # umask 027
    assert not list(run.rglob("*.tmp*"))


# -- signals ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("signum, n_envs, to_group", [(signal.SIGTERM, 2, True), (signal.SIGHUP, 1, False)],
                         ids=["SIGTERM to the process group", "SIGHUP"])
def test_termination_signal_saves_a_checkpoint_like_ctrl_c(tmp_path, signum, n_envs, to_group):
    """`kill` from a supervisor (to the whole process group, SubprocVecEnv workers included) or a
    closed terminal: a checkpoint, a one-line note, exit status 128 + the signal number, no
    tracebacks from the workers."""
    config = _write_config(tmp_path / "tiny.toml", total=10_000_000)
    run = tmp_path / "run"
    process = subprocess.Popen(
        [sys.executable, "-m", "bh8_gym.cli", "train", "--no-progress", "--config", str(config),
         "--n-envs", str(n_envs), "--out", str(run)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 120.0
        while not list(run.glob("tb/*/events.out.tfevents*")):  # learn() has started
            assert process.poll() is None and time.monotonic() < deadline, process.communicate()
            time.sleep(0.05)
        if to_group:
            os.killpg(process.pid, signum)
        else:
            process.send_signal(signum)
        _, err = process.communicate(timeout=60)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)
    assert process.returncode == 128 + signum, err
    assert "Traceback" not in err and f"stopped by {signal.Signals(signum).name}" in err and "--resume" in err
    state = json.loads((run / "checkpoints" / "latest.json").read_text())
    assert state["num_timesteps"] >= n_envs and (run / "checkpoints" / "latest.zip").is_file()
    assert not (run / "final_model.zip").exists()


@pytest.mark.parametrize("command", [["serve"], ["render", "-o", "x.png"], ["eval", "--baseline", "loop"],
                                     ["train", "--out", "run"]])
def test_a_negative_seed_is_a_usage_error_for_every_command(command, tmp_path, monkeypatch, capsys):
    """numpy and gymnasium refuse negative seeds deep inside (tracebacks from bh8 render and eval)."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        main([*command, "--seed", "-1"])
    assert exit_info.value.code == 2
    assert "argument --seed: must be" in capsys.readouterr().err


@pytest.mark.parametrize("damaged", ["run.json", "checkpoints/latest.json"])
def test_resume_names_a_damaged_run_file(short_run, tmp_path, damaged):
    _, run, _ = short_run
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    (copy / damaged).write_text('{"config": {"algor')
    code, _, err = _train("--resume", "--out", copy, "--timesteps", "64")
    assert code == 2 and f"{str(copy / damaged)!r} is not valid JSON" in err and "Traceback" not in err
