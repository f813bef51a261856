"""Policy files, third round (issue 39, findings 4, 5, 7 and 9): every number a policy file gives is
range-checked before a loop uses it, no file makes us allocate more than it holds, a policy's
metadata can tighten deploy's limits but never loosen them unasked, and a damaged file is one line
and exit 2 (a policy deploy refuses), never a traceback or deploy's exit 1 (a port failure).
"""
from __future__ import annotations

import io
import json
import struct
import zipfile
import zlib

import numpy as np
import pytest

import bh8_gym.urlhandler  # noqa: F401  (registers bh8sim:// with pyserial)
from bh8_gym.cli import main
from test_policy_files_hostile import _damaged, _deploy_refused_before_the_port_opens, _metadata


def _with_metadata(reach_policy_npz, tmp_path, **changes):
    return _damaged(reach_policy_npz, tmp_path, metadata=_metadata(reach_policy_npz, **changes))


@pytest.mark.timeout(60)
def test_a_hold_of_1e300_seconds_in_a_policy_is_refused_before_the_port(reach_policy_npz, tmp_path, capsys,
                                                                        monkeypatch):
    """Finding 4: `arm.hold_seconds` 1e300 in a policy's env_kwargs made LoopInterface.episode_steps
    loop for ever: deploy hung before it opened the port. The arm's schedule is bounded now."""
    path = _with_metadata(reach_policy_npz, tmp_path, env_id="BH8Grasp-v0", env_kwargs={"arm": {"hold_seconds": 1e300}})
    err = _deploy_refused_before_the_port_opens(path, tmp_path, capsys, monkeypatch)
    assert "hold_seconds must be a number in [0, 60]" in err and err.count("\n") == 1, err


@pytest.mark.parametrize("metadata, message", [
    ({"env_id": 7}, "env_id must be a string"),
    ({"env_kwargs": [1, 2]}, "env_kwargs must be a table"),
    ({"privileged": "no"}, "privileged must be true or false"),
    ({"env_kwargs": {"episode_seconds": "long"}}, "episode_seconds"),
    ({"env_kwargs": {"safety": {"max_strain": "x"}}}, "max_strain"),
])
def test_wrong_types_in_a_policys_metadata_are_exit_2_with_one_line(reach_policy_npz, tmp_path, capsys,
                                                                     monkeypatch, metadata, message):
    """Finding 9: wrong types in an export's metadata raised TypeErrors, or passed the load and
    failed once the port was open (deploy's exit 1, which its help says is a port failure)."""
    err = _deploy_refused_before_the_port_opens(_with_metadata(reach_policy_npz, tmp_path, **metadata), tmp_path,
                                                capsys, monkeypatch)
    assert message in err and err.count("\n") == 1 and "Traceback" not in err, err


LOOSE = {"max_strain": 255, "max_velocity": 127, "max_temperature": 1e300}


def test_a_policy_cannot_loosen_deploys_limits_unless_the_command_line_says_so(reach_policy_npz, tmp_path, capsys):
    """Finding 7: metadata `safety {max_strain 255, max_velocity 127, max_temperature 1e300}` was
    applied, and deploy sent LCV 127 where its default clamp is 100. Now the policy's envelope only
    tightens deploy's defaults (it says so); --allow-looser-limits takes it; --max-* set a limit."""
    from bh8_gym.agents.deployment.deploy import DEFAULT_ENVELOPE, deploy_envelope
    from bh8_gym.envs.interfaces import interface_for

    loose = interface_for("BH8FingerReach-v0", {"safety": LOOSE})
    assert deploy_envelope(loose) == DEFAULT_ENVELOPE
    assert deploy_envelope(loose, allow_looser=True).max_velocity == 127
    tight = interface_for("BH8FingerReach-v0", {"safety": {"max_strain": 150, "max_velocity": 40}})
    assert (deploy_envelope(tight).max_strain, deploy_envelope(tight).max_velocity) == (150, 40)
    assert deploy_envelope(loose, max_velocity=120).max_velocity == 120  # the user's own flag

    # End to end: a policy that always asks for full speed, on the simulated hand.
    path = _with_metadata(reach_policy_npz, tmp_path, env_kwargs={"safety": LOOSE})
    with np.load(path, allow_pickle=False) as data:
        arrays = {name: data[name] for name in data.files}
    arrays["layer1_bias"] = np.full_like(arrays["layer1_bias"], 1e3)  # every action at its top
    np.savez(path, **arrays)
    for extra, top in (([], 100), (["--allow-looser-limits"], 127)):
        log = tmp_path / f"deploy{len(extra)}.jsonl"
        capsys.readouterr()
        code = main(["deploy", "--port", "bh8sim://?seed=0", "--policy", str(path), "--log", str(log), "--cycles",
                     "3", "--clock", "cycles", *extra])
        err = capsys.readouterr().err
        assert code == 0, err
        assert ("looser" in err) == (not extra), err
        # each "C" block: the byte 'C', then each finger's LCV as a signed byte
        sent = [struct.unpack("4b", bytes.fromhex(record["control"])[1:]) for record in
                map(json.loads, log.read_text().splitlines()) if record.get("control", "").startswith("43")]
        assert sent and max(max(values) for values in sent) == top, sent


def _zip_with(member: bytes, compress_type: int) -> bytes:
    """A zip whose one member `data` has the bytes `member` written under `compress_type` as they are."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("data", b"x" * len(member))
    raw = bytearray(buffer.getvalue())
    start = raw.index(b"x" * len(member))
    raw[start:start + len(member)] = member
    for signature, offset in ((b"PK\x03\x04", 8), (b"PK\x01\x02", 10)):
        at = raw.index(signature)
        raw[at + offset:at + offset + 2] = struct.pack("<H", compress_type)
    return bytes(raw)


@pytest.mark.parametrize("compress_type", [zipfile.ZIP_DEFLATED, zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA, 99])
def test_a_damaged_zip_member_is_one_line_not_a_traceback(tmp_path, capsys, compress_type):
    """Finding 9: zlib, bz2 and NotImplementedError escaped from damaged zip members as tracebacks."""
    path = tmp_path / "model.zip"
    path.write_bytes(_zip_with(b"garbage that is no compressed stream at all" * 4, compress_type))
    capsys.readouterr()
    assert main(["eval", str(path), "--episodes", "1", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("bh8 eval: ") and err.count("\n") == 1 and "Traceback" not in err, err


def test_an_int8_array_is_not_ballooned_and_a_zip_cannot_unpack_a_huge_tensor(reach_policy_npz, tmp_path):
    """Finding 5: an 880 KB .npz of int8 became gigabytes as float64, and a 1 MB SB3 .zip held a
    0.96 GB tensor. Only float32/float64 arrays are read from an export, and an SB3 member may
    unpack to no more than its network needs."""
    from bh8_gym.agents.deployment.policy_file import PolicyFileError, load_policy
    from bh8_gym.agents.deployment.sb3_file import _check_sb3_sizes

    path = _damaged(reach_policy_npz, tmp_path, layer0_weight=np.zeros((16, 15), dtype=np.int8))
    with pytest.raises(PolicyFileError, match="int8"):
        load_policy(path)
    data = {"observation_space": {"_shape": [15]}, "action_space": {"_shape": [4]}, "n_steps": 64, "n_envs": 1,
            "policy_kwargs": {"net_arch": [16]}}
    _check_sb3_sizes(data, {"data": 10_000, "policy.pth": 40_000}, tmp_path / "m.zip")
    with pytest.raises(PolicyFileError, match="policy.pth unpack to more than"):
        _check_sb3_sizes(data, {"data": 10_000, "policy.pth": 960 << 20}, tmp_path / "m.zip")


def test_a_replay_buffer_header_declaring_1e11_floats_is_refused_unallocated(tmp_path):
    """Finding 9: a replay-buffer .npz whose header declares 10^11 floats raised MemoryError. Each
    member's header must declare the run's buffer and hold exactly its bytes before it is read."""
    from types import SimpleNamespace

    from bh8_gym.agents.training.checkpoint_file import CheckpointError, load_replay_buffer

    buffer = SimpleNamespace(observations=np.zeros((8, 3), dtype=np.float32), pos=0, full=False, buffer_size=8)
    header = {"descr": "<f4", "fortran_order": False, "shape": (10**11,)}
    npy = io.BytesIO()
    np.lib.format.write_array_header_1_0(npy, header)
    path = tmp_path / "buffer.npz"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("observations.npy", npy.getvalue() + b"\0" * 96)
        archive.writestr("__counters__.npy", _npy(np.array([0, 0], dtype=np.int64)))
    with pytest.raises(CheckpointError, match=r"observations is float32\[100000000000\]"):
        load_replay_buffer(SimpleNamespace(replay_buffer=buffer), path)


def _npy(array: np.ndarray) -> bytes:
    handle = io.BytesIO()
    np.save(handle, array)
    return handle.getvalue()


@pytest.mark.parametrize("kind", ["a list", "a folder"])
def test_a_run_json_beside_a_model_that_is_a_list_or_a_folder_is_one_line(tmp_path, capsys, kind):
    """Finding 9: a run.json beside a policy that was a list or a folder was a raw traceback."""
    model = tmp_path / "model.zip"
    model.write_bytes(zlib.compress(b"x"))
    if kind == "a list":
        (tmp_path / "run.json").write_text("[1, 2]")
    else:
        (tmp_path / "run.json").mkdir()
    capsys.readouterr()
    assert main(["eval", str(model), "--episodes", "1", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "run.json" in err and err.count("\n") == 1 and "Traceback" not in err, err
