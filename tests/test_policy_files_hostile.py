"""Policy files as people download and share them (issue 19): nothing in one runs unless the user
says it trusts the file, and a damaged one is refused before the hand is touched.

An SB3 .zip stores non-JSON settings as cloudpickles that SB3's loader unpickles (running their
code); agents/policy_file.py rebuilds the known ones without unpickling. An exported .npz holds
only arrays (np.load with allow_pickle=False); its layers must chain. `bh8 deploy` exit status 2
is "a policy deploy refuses" (its --help).
"""
from __future__ import annotations

import base64
import json
import os
import pickle
import shutil
import zipfile

import numpy as np
import pytest

import bh8_gym.urlhandler  # noqa: F401  (registers bh8sim:// with pyserial)
from bh8_gym.cli import main

REACH = "BH8FingerReach-v0"


class _MakesADirectory:
    """A pickle whose loading calls os.mkdir(path): proof, if the directory appears, that it ran."""

    def __init__(self, path: str):
        self.path = path

    def __reduce__(self):
        return os.mkdir, (self.path,)


@pytest.fixture(scope="module")
def sb3_run(tmp_path_factory):
    """An untrained PPO reach model saved by SB3, with the run.json `bh8 train` writes beside it."""
    from stable_baselines3 import PPO

    from bh8_gym.agents.env_factory import make_env

    env = make_env(REACH, {})
    try:
        model = PPO("MlpPolicy", env, seed=0, device="cpu", n_steps=64, batch_size=64,
                    policy_kwargs={"net_arch": [16]})
        model.learn(64)  # a trained model also pickles its last observations and episode buffers
    finally:
        env.close()
    folder = tmp_path_factory.mktemp("run")
    model.save(folder / "model.zip")
    (folder / "run.json").write_text(json.dumps({"env_id": REACH, "env_kwargs": {}, "algorithm": "PPO"}))
    return folder


def _hostile_copy(sb3_run, tmp_path, key: str, marker) -> "os.PathLike":
    """A copy of the run whose model's `data` carries the payload as the pickle of entry `key` (the
    plain fields SB3 writes beside a pickle are kept, as an attacker editing a real model would)."""
    folder = tmp_path / f"hostile-{key}"
    shutil.copytree(sb3_run, folder)
    path = folder / "model.zip"
    with zipfile.ZipFile(path) as archive:
        members = {name: archive.read(name) for name in archive.namelist()}
    data = json.loads(members["data"])
    payload = base64.b64encode(pickle.dumps(_MakesADirectory(str(marker)))).decode()
    data[key] = {**data.get(key, {":type:": "<class 'function'>"}), ":serialized:": payload}
    members["data"] = json.dumps(data).encode()
    with zipfile.ZipFile(path, "w") as archive:
        for name, content in members.items():
            archive.writestr(name, content)
    return path


@pytest.mark.parametrize("key", ["lr_schedule", "observation_space", "policy_class", "evil"])
@pytest.mark.parametrize("command", ["eval", "export", "deploy"])
def test_a_policy_zip_carrying_a_pickle_runs_nothing(sb3_run, tmp_path, capsys, command, key):
    """A pickled payload in the model's data ran on `bh8 eval`, `bh8 export` and `bh8 deploy`
    (SB3 unpickles every such entry). Now nothing is unpickled: in an entry the loader knows
    (lr_schedule, the spaces, the policy class) a stand-in rebuilt from plain JSON takes its
    place, so the command works; any other pickled entry is refused, exit 2, naming --trust-file.
    Either way the payload's directory never appears."""
    marker = tmp_path / "pwned"
    model = _hostile_copy(sb3_run, tmp_path, key, marker)
    argv = {"eval": ["eval", str(model), "--episodes", "1", "--no-progress", "--gif-episodes", "0"],
            "export": ["export", str(model), "--check", "8"],
            "deploy": ["deploy", "--port", "bh8sim://?seed=0", "--policy", str(model), "--cycles", "2",
                       "--log", str(tmp_path / "deploy.jsonl")]}[command]
    code = main(argv)
    assert not marker.exists(), "the pickled payload ran"
    err = capsys.readouterr().err
    if key == "evil":
        assert code == 2 and "pickled Python objects in ['evil']" in err and "--trust-file" in err
    else:
        assert code == 0, err


def test_trust_file_lets_sb3_unpickle_the_file(sb3_run, tmp_path):
    """--trust-file is the user saying the file is theirs: SB3 then unpickles it (and its payload
    runs; here it only makes a directory)."""
    marker = tmp_path / "ran"
    model = _hostile_copy(sb3_run, tmp_path, "evil", marker)
    main(["export", str(model), "--check", "8", "--trust-file"])
    assert marker.is_dir()


def test_a_class_outside_the_allowlist_in_policy_kwargs_is_refused(sb3_run, tmp_path, capsys):
    """policy_kwargs pickled (an activation class) is rebuilt from its JSON fields, classes from an
    allowlist; any other class name means the file needs --trust-file."""
    folder = tmp_path / "run"
    shutil.copytree(sb3_run, folder)
    path = folder / "model.zip"
    with zipfile.ZipFile(path) as archive:
        members = {name: archive.read(name) for name in archive.namelist()}
    data = json.loads(members["data"])
    data["policy_kwargs"] = {":type:": "<class 'dict'>", ":serialized:": "AAAA", "net_arch": [16],
                             "activation_fn": "<class 'subprocess.Popen'>"}
    members["data"] = json.dumps(data).encode()
    with zipfile.ZipFile(path, "w") as archive:
        for name, content in members.items():
            archive.writestr(name, content)
    assert main(["export", str(path), "--check", "8"]) == 2
    assert "the class subprocess.Popen in its policy_kwargs" in capsys.readouterr().err


def test_deploy_prefers_the_pickle_free_export_beside_a_zip(sb3_run, tmp_path, capsys):
    """`bh8 deploy --policy MODEL.zip` deploys MODEL.npz, `bh8 export`'s pickle-free output, when it
    is there and not older than the .zip (numpy only, no torch, no pickles)."""
    folder = tmp_path / "run"
    shutil.copytree(sb3_run, folder)
    assert main(["export", str(folder / "model.zip"), "--check", "0"]) == 0
    capsys.readouterr()
    log = tmp_path / "deploy.jsonl"
    assert main(["deploy", "--port", "bh8sim://?seed=0", "--policy", str(folder / "model.zip"),
                 "--cycles", "2", "--log", str(log)]) == 0
    assert "model.npz', the pickle-free export of" in capsys.readouterr().err
    os.utime(folder / "model.npz", (0, 0))  # an export older than the model: not taken
    assert main(["deploy", "--port", "bh8sim://?seed=0", "--policy", str(folder / "model.zip"),
                 "--cycles", "2", "--log", str(log)]) == 0
    assert "pickle-free export" not in capsys.readouterr().err


# -- damaged exports --------------------------------------------------------------------------


def _damaged(exported, tmp_path, **changes):
    with np.load(exported, allow_pickle=False) as data:
        arrays = {name: data[name] for name in data.files}
    arrays.update(changes)
    path = tmp_path / "damaged.npz"
    np.savez(path, **arrays)
    return path


def _metadata(exported, **changes):
    with np.load(exported, allow_pickle=False) as data:
        return np.array(json.dumps({**json.loads(str(data["metadata"])), **changes}))


@pytest.mark.parametrize("case, message", [
    ("layer 1 takes fewer inputs", "layer 1 takes 15 inputs but layer 0 gives 16"),
    ("bias of another size", "layer 0 has weights (16, 15) and biases (3,)"),
    ("observation mean of another size", "obs_mean has shape (5,)"),
    ("action bounds of another size", "action_low has shape (7,)"),
    ("a NaN weight", "not a finite number"),
    ("a negative variance", "not a finite number (or a variance is not positive)"),
    ("n_layers true", "n_layers must be 1..64, got True"),
    ("n_layers huge", "n_layers must be 1..64"),
    ("metadata a list", "metadata is not a JSON object"),
])
def test_a_damaged_export_is_refused_before_the_hand_is_touched(reach_policy_npz, tmp_path, capsys, monkeypatch, case, message):
    """An .npz whose layer shapes do not chain loaded, ran HI on the hand, then failed at the first
    prediction with numpy's raw matmul error and exit 1, the log without a stop record. The shapes
    (and finiteness) are checked when the file is read: PolicyFileError, `bh8 deploy` exit 2 (a
    policy it refuses) before the port is opened, so the hand never moves."""
    import bh8_gym.client
    from bh8_gym.agents.policy_file import PolicyFileError, load_policy

    with np.load(reach_policy_npz, allow_pickle=False) as data:
        w0, w1 = data["layer0_weight"], data["layer1_weight"]
    bad = {
        "layer 1 takes fewer inputs": dict(layer1_weight=w1[:, :15]),
        "bias of another size": dict(layer0_weight=w0[:, :15], layer0_bias=np.zeros(3)),
        "observation mean of another size": dict(obs_mean=np.zeros(5)),
        "action bounds of another size": dict(action_low=-np.ones(7)),
        "a NaN weight": dict(layer1_weight=np.where(np.eye(*w1.shape) > 0, np.nan, w1)),
        "a negative variance": dict(obs_var=-np.ones(w0.shape[1]), obs_epsilon=np.array(0.0)),
        "n_layers true": dict(metadata=_metadata(reach_policy_npz, n_layers=True)),
        "n_layers huge": dict(metadata=_metadata(reach_policy_npz, n_layers=10**9)),
        "metadata a list": dict(metadata=np.array("[1, 2]")),
    }[case]
    if case == "bias of another size":
        message = f"layer 0 has weights ({w0.shape[0]}, 15) and biases (3,)"
    path = _damaged(reach_policy_npz, tmp_path, **bad)
    with pytest.raises(PolicyFileError, match=message.replace("(", r"\(").replace(")", r"\)")):
        load_policy(path)

    def refuse(*args, **kwargs):
        raise AssertionError("deploy opened the port for a damaged policy")

    monkeypatch.setattr(bh8_gym.agents.deploy, "BarrettHand", refuse)
    log = tmp_path / "deploy.jsonl"
    capsys.readouterr()
    assert main(["deploy", "--port", "bh8sim://?seed=0", "--policy", str(path), "--log", str(log)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("bh8 deploy: ") and "damaged" in err and "Traceback" not in err
    assert not log.exists()  # refused before anything was sent: the last run's log is left alone


class _FailingAtCycle:
    """An exported policy whose prediction raises at policy cycle `cycle` (as a mismatched layer would)."""

    def __init__(self, policy, cycle: int):
        self.policy, self.cycle, self.calls = policy, cycle, 0
        self.privileged, self.observation_dim, self.metadata = policy.privileged, policy.observation_dim, policy.metadata

    def predict(self, observation, deterministic=True):
        self.calls += 1
        if self.calls == self.cycle:
            raise ValueError("matmul: Input operand 1 has a mismatch in its core dimension 0")
        return self.policy.predict(observation, deterministic=deterministic)


def test_a_policy_failing_mid_run_is_a_stop_with_its_record_and_exit_2(reach_policy_npz, tmp_path, capsys, monkeypatch):
    """Whatever still fails in a policy mid-run is a stop like a safety limit: the zero-velocity
    block, ^C and the exit action leave the hand safe, the log's stop record names the cycle and
    the error, and the exit status is 2 (a bad policy). It was a raw traceback, exit 1, no record."""
    import bh8_gym.agents.deploy as deploy
    from bh8_gym.agents.policy_file import load_policy

    monkeypatch.setattr(deploy, "load_policy", lambda path, trust=False: _FailingAtCycle(load_policy(path), 3))
    log = tmp_path / "deploy.jsonl"
    assert main(["deploy", "--port", "bh8sim://?seed=0", "--policy", str(reach_policy_npz), "--log", str(log),
                 "--clock", "cycles"]) == 2
    err = capsys.readouterr().err
    assert "stopped: policy error at cycle 3: ValueError: matmul" in err and "Traceback" not in err
    records = [json.loads(line) for line in log.read_text().splitlines()]
    stop = records[-1]
    assert stop["event"] == "stop" and stop["reason"].startswith("policy error at cycle 3: ValueError")
    assert stop["policy_cycles"] == 2
    assert [r["line"] for r in records if r.get("event") == "command"][-1] == "GT"  # the exit action ran
    stop_block = [r for r in records if "cycle" in r][-1]
    assert stop_block["control"][2:] == "00" * (len(stop_block["control"]) // 2 - 1)  # zero velocity, gain 0
