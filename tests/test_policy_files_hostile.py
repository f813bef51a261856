"""Policy files as people download and share them (issue 19): nothing in one runs unless the user
says it trusts the file, and a damaged one is refused before the hand is touched.

An SB3 .zip stores non-JSON settings as cloudpickles that SB3's loader unpickles (running their
code); agents/deployment/sb3_file.py rebuilds the known ones without unpickling. An exported .npz holds
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


def _deploy_refused_before_the_port_opens(path, tmp_path, capsys, monkeypatch) -> str:
    """`bh8 deploy --policy path` exits 2 without opening the port or writing its log (the last
    run's log is left alone); returns its stderr, one line starting "bh8 deploy: "."""
    import bh8_gym.agents.deployment.deploy

    def refuse(*args, **kwargs):
        raise AssertionError(f"deploy opened the port for {path}")

    monkeypatch.setattr(bh8_gym.agents.deployment.deploy, "BarrettHand", refuse)
    log = tmp_path / "deploy.jsonl"
    capsys.readouterr()
    assert main(["deploy", "--port", "bh8sim://?seed=0", "--policy", str(path), "--log", str(log)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("bh8 deploy: "), err
    assert not log.exists()
    return err


@pytest.mark.parametrize("case, message", [
    ("layer 1 takes fewer inputs", "layer 1 takes 15 inputs but layer 0 gives 16"),
    ("bias of another size", "layer 0 has weights (16, 15) and biases (3,)"),
    ("observation mean of another size", "obs_mean has shape (5,)"),
    ("action bounds of another size", "action_low has shape (7,)"),
    ("a NaN weight", "not a finite number"),
    ("a negative variance", "not a finite number (or a variance is not positive)"),
    ("n_layers true", "n_layers must be an integer in 1..64, got True"),
    ("n_layers huge", "n_layers must be an integer in 1..64"),
    ("metadata a list", "metadata is not a policy metadata"),
])
def test_a_damaged_export_is_refused_before_the_hand_is_touched(reach_policy_npz, tmp_path, capsys, monkeypatch, case, message):
    """An .npz whose layer shapes do not chain loaded, ran HI on the hand, then failed at the first
    prediction with numpy's raw matmul error and exit 1, the log without a stop record. The shapes
    (and finiteness) are checked when the file is read: PolicyFileError, `bh8 deploy` exit 2 (a
    policy it refuses) before the port is opened, so the hand never moves."""
    from bh8_gym.agents.deployment.policy_file import PolicyFileError, load_policy

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

    err = _deploy_refused_before_the_port_opens(path, tmp_path, capsys, monkeypatch)
    assert "damaged" in err and "Traceback" not in err


@pytest.mark.parametrize("case, message", [
    ("one action too few", "the policy gives 3 actions but the env's control block has 4 fields (LCV 1, LCV 2, "
                           "LCV 3, LCV 4)"),
    ("NaN for every input", "gives a non-finite action"),
])
def test_a_policy_that_cannot_act_on_the_env_is_refused_before_the_port_opens(reach_policy_npz, tmp_path, capsys,
                                                                              monkeypatch, case, message):
    """Issue 32 item 3: an .npz with an action output too few passed the load checks (its layers
    chain) and a policy whose weights overflow to NaN for every input (weights ±1e300, obs_clip inf,
    every number finite) did too: deploy sent BAUD, HI, the LOOP setup and LOOP, then died at cycle
    0 or stopped there. Now the action size is checked against the env's control block and one
    forward pass on test observations must give finite actions of the env's shape: exit 2 before
    the port is opened."""

    with np.load(reach_policy_npz, allow_pickle=False) as data:
        w0, w1, b1 = data["layer0_weight"], data["layer1_weight"], data["layer1_bias"]
    bad = {
        "one action too few": dict(layer1_weight=w1[:3], layer1_bias=b1[:3], action_low=-np.ones(3),
                                   action_high=np.ones(3)),
        "NaN for every input": dict(layer0_weight=np.where(np.indices(w0.shape).sum(axis=0) % 2, 1e300, -1e300),
                                    obs_mean=np.full(w0.shape[1], -1e300), obs_clip=np.array(np.inf)),
    }[case]
    path = _damaged(reach_policy_npz, tmp_path, **bad)

    err = _deploy_refused_before_the_port_opens(path, tmp_path, capsys, monkeypatch)
    assert message in err and len(err.strip().splitlines()) == 1, err


class _FailingAtCycle:
    """An exported policy whose prediction raises at policy cycle `cycle` (as a mismatched layer would)."""

    def __init__(self, policy, cycle: int):
        self.policy, self.cycle, self.calls, self.path = policy, cycle, 0, policy.path
        self.privileged, self.observation_dim, self.metadata = policy.privileged, policy.observation_dim, policy.metadata
        self.action_dim = policy.action_dim

    def predict(self, observation, deterministic=True):
        if np.ndim(observation) == 2:  # deploy's test of the policy before the port is opened, not a cycle
            return self.policy.predict(observation, deterministic=deterministic)
        self.calls += 1
        if self.calls == self.cycle:
            raise ValueError("matmul: Input operand 1 has a mismatch in its core dimension 0")
        return self.policy.predict(observation, deterministic=deterministic)


def test_a_policy_failing_mid_run_is_a_stop_with_its_record_and_exit_2(reach_policy_npz, tmp_path, capsys, monkeypatch):
    """Whatever still fails in a policy mid-run is a stop like a safety limit: the zero-velocity
    block, ^C and the exit action leave the hand safe, the log's stop record names the cycle and
    the error, and the exit status is 2 (a bad policy). It was a raw traceback, exit 1, no record."""
    import bh8_gym.agents.deployment.deploy as deploy
    from bh8_gym.agents.deployment.policy_file import load_policy

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


# -- files that ask for more than they hold (issue 32, items 4 and 10) ------------------------


def _model_copy(sb3_run, tmp_path, data: dict | None = None, members: dict | None = None):
    """A copy of the run whose model's `data` JSON gets `data`'s entries and whose zip gets `members`."""
    folder = tmp_path / "edited"
    shutil.copytree(sb3_run, folder)
    path = folder / "model.zip"
    with zipfile.ZipFile(path) as archive:
        contents = {name: archive.read(name) for name in archive.namelist()}
    contents["data"] = json.dumps({**json.loads(contents["data"]), **(data or {})}).encode()
    contents.update(members or {})
    with zipfile.ZipFile(path, "w") as archive:
        for name, content in contents.items():
            archive.writestr(name, content)
    return path


class _RunsOnUnpickling:
    def __reduce__(self):
        return os.system, ("echo ran",)


def _weights_with_a_pickle() -> bytes:
    import io

    import torch

    buffer = io.BytesIO()
    torch.save({"payload": _RunsOnUnpickling(), "padding": torch.zeros(10_000)}, buffer)
    return buffer.getvalue()


@pytest.mark.parametrize("case, message", [
    ("net_arch [12000, 12000]", "net_arch must list at most 64 layer widths from 1 to 4096, got [12000, 12000]"),
    ("net_arch wider than its weights", "its net_arch makes a network of 32172005 parameters, but the file stores"),
    ("net_arch of 100 layers", "net_arch must list at most 64 layer widths"),
    ("a width of 0", "net_arch must list at most 64 layer widths from 1 to 4096, got [0]"),
    ("n_steps 1e12", "n_steps must be a whole number from 1 to 268435456, got 1000000000000"),
    ("n_envs 1e9 with n_steps 64", "n_envs must be a whole number from 1 to 268435456, got 1000000000"),
    ("a rollout of 2**27 transitions", "its rollout buffer would hold 134217728 transitions of 21 numbers"),
    ("an observation of 10**9 entries", "observation_space must have a shape of at most 65536 entries"),
    ("data nested 100k deep", "cannot read SB3 model"),
    ("weights holding a pickle", "its weights hold pickled Python objects besides tensors, which bh8-gym never "
                                 "unpickles (not even with --trust-file)"),
])
@pytest.mark.parametrize("trust", [False, True])
def test_a_policy_zip_that_asks_for_more_than_it_holds_is_refused_at_once(sb3_run, tmp_path, capsys, case, message,
                                                                         trust):
    """Item 4: a 20 KB zip whose JSON asks for net_arch [12000, 12000] kept `bh8 eval` building a
    network for minutes at 3.1 GB; n_steps 1e12 made SB3 allocate its rollout buffer (a raw
    allocation traceback). The sizes are bounded before SB3 builds anything, and the parameters
    must fit in the weights the file stores. Item 10: torch's refusal of a pickle among the
    weights advised `weights_only=False` (which would run it). Each is one line, exit 2, quickly,
    with --trust-file as without (trusting a file does not make it fit in memory)."""
    import time

    edits = {
        "net_arch [12000, 12000]": dict(data={"policy_kwargs": {"net_arch": [12000, 12000]}}),
        "net_arch wider than its weights": dict(data={"policy_kwargs": {"net_arch": [4000, 4000]}}),
        "net_arch of 100 layers": dict(data={"policy_kwargs": {"net_arch": [8] * 100}}),
        "a width of 0": dict(data={"policy_kwargs": {"net_arch": {"pi": [0]}}}),
        "n_steps 1e12": dict(data={"n_steps": 10**12}),
        "n_envs 1e9 with n_steps 64": dict(data={"n_envs": 10**9}),
        "a rollout of 2**27 transitions": dict(data={"n_steps": 2**27}),
        "an observation of 10**9 entries": dict(data={"observation_space": {"_shape": [10**9]}}),
        "data nested 100k deep": dict(data={"deep": "<placeholder>"}),
        "weights holding a pickle": dict(members={"policy.pth": _weights_with_a_pickle()}),
    }[case]
    path = _model_copy(sb3_run, tmp_path, **edits)
    if case == "data nested 100k deep":
        with zipfile.ZipFile(path) as archive:
            contents = {name: archive.read(name) for name in archive.namelist()}
        contents["data"] = contents["data"].replace(b'"<placeholder>"', b"[" * 100_000 + b"]" * 100_000)
        with zipfile.ZipFile(path, "w") as archive:
            for name, content in contents.items():
                archive.writestr(name, content)
    started = time.monotonic()
    code = main(["eval", str(path), "--episodes", "1", "--no-progress", "--gif-episodes", "0",
                 *(["--trust-file"] if trust else [])])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith("bh8 eval: ") and message in err, err
    assert "\n" not in err and "weights_only" not in err
    assert time.monotonic() - started < 30.0


def test_a_sac_zip_asking_for_a_huge_replay_buffer_is_refused(tmp_path, capsys):
    """SAC builds its replay buffer of buffer_size transitions when it loads a model: 10^12 was an
    allocation traceback."""
    from stable_baselines3 import SAC

    from bh8_gym.agents.env_factory import make_env

    env = make_env(REACH, {})
    try:
        model = SAC("MlpPolicy", env, seed=0, device="cpu", buffer_size=100, policy_kwargs={"net_arch": [16]})
    finally:
        env.close()
    folder = tmp_path / "run"
    folder.mkdir()
    model.save(folder / "model.zip")
    (folder / "run.json").write_text(json.dumps({"env_id": REACH, "env_kwargs": {}, "algorithm": "SAC"}))
    path = _model_copy(folder, tmp_path, data={"buffer_size": 10**12})
    assert main(["eval", str(path), "--episodes", "1", "--no-progress", "--gif-episodes", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert "buffer_size must be a whole number from 1 to 268435456, got 1000000000000" in err and "\n" not in err


def _npz_with_member(exported, tmp_path, name: str, member: bytes, extra: int = 0):
    """A copy of an export whose member `name` is replaced by raw .npy bytes, plus `extra` tiny members."""
    with zipfile.ZipFile(exported) as archive:
        contents = {item: archive.read(item) for item in archive.namelist()}
    contents[name] = member
    for index in range(extra):
        contents[f"extra{index}.npy"] = contents["obs_clip.npy"]
    path = tmp_path / "edited.npz"
    with zipfile.ZipFile(path, "w") as archive:
        for item, content in contents.items():
            archive.writestr(item, content)
    return path


@pytest.mark.parametrize("case, message", [
    ("metadata nested 100k deep", "its metadata is nested too deep"),
    ("a header declaring 10**12 floats", "'obs_mean.npy' declares 8000000000000 bytes of data but holds"),
    ("a header declaring fewer floats", "'obs_mean.npy' declares 8 bytes of data but holds"),
    ("thousands of members", "holds 3012 arrays, more than an export's 144"),
])
@pytest.mark.parametrize("command", ["deploy", "eval"])
def test_an_npz_that_asks_for_more_than_it_holds_is_one_line_exit_2(reach_policy_npz, tmp_path, capsys, monkeypatch,
                                                                     case, message, command):
    """Item 10: metadata JSON nested 100k deep was a RecursionError, and a member whose .npy header
    declares 10^12 floats made numpy allocate them before reading (an allocation error): raw
    tracebacks. The .npy headers are read first and must declare what each member holds; exit 2
    with one line, and deploy never opens the port."""
    import io

    import bh8_gym.agents.deployment.deploy

    def header(shape) -> bytes:
        buffer = io.BytesIO()
        np.lib.format.write_array_header_1_0(buffer, {"descr": "<f8", "fortran_order": False, "shape": shape})
        return buffer.getvalue()

    with np.load(reach_policy_npz, allow_pickle=False) as data:
        size = data["obs_mean"].size
    if case == "metadata nested 100k deep":
        path = _damaged(reach_policy_npz, tmp_path, metadata=np.array("[" * 100_000 + "]" * 100_000))
    elif case == "thousands of members":
        path = _npz_with_member(reach_policy_npz, tmp_path, "obs_clip.npy", header(()) + bytes(8), extra=3000)
    else:
        shape = (10**12,) if case == "a header declaring 10**12 floats" else (1,)
        path = _npz_with_member(reach_policy_npz, tmp_path, "obs_mean.npy", header(shape) + bytes(8 * size))

    def refuse(*args, **kwargs):
        raise AssertionError("deploy opened the port for a damaged policy")

    monkeypatch.setattr(bh8_gym.agents.deployment.deploy, "BarrettHand", refuse)
    argv = {"deploy": ["deploy", "--port", "bh8sim://?seed=0", "--policy", str(path), "--log", str(tmp_path / "log")],
            "eval": ["eval", str(path), "--episodes", "1", "--no-progress", "--gif-episodes", "0"]}[command]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"bh8 {command}: ") and message in err and "\n" not in err, err
