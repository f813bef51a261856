"""`bh8 deploy` as a command: option values refused before the port is opened, the help's limits
and exit codes, a port that fails mid-run, and what the summary counts.
"""
from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import serial

import bh8_gym.urlhandler  # noqa: F401  (registers bh8sim:// with pyserial)

REACH = "BH8FingerReach-v0"


class PolicyTriggeringAtCycle3:
    """An exported policy that sets `event` (a fault on the line) when asked for policy cycle 3's action."""

    def __init__(self, policy, event: threading.Event):
        self.policy, self.event, self.calls, self.path = policy, event, 0, policy.path
        self.privileged, self.observation_dim, self.action_dim = policy.privileged, policy.observation_dim, policy.action_dim

    def predict(self, observation, deterministic=True):
        if np.ndim(observation) == 2:  # deploy's test of the policy before the port is opened, not a cycle
            return self.policy.predict(observation, deterministic=deterministic)
        self.calls += 1
        if self.calls == 3:
            self.event.set()
        return self.policy.predict(observation, deterministic=deterministic)


@pytest.fixture
def port_never_opened(monkeypatch):
    """Fails the test if deploy gets as far as connecting to the hand."""
    import bh8_gym.agents.deployment.deploy

    def refuse(*args, **kwargs):
        raise AssertionError("deploy opened the port before refusing its arguments")

    monkeypatch.setattr(bh8_gym.agents.deployment.deploy, "BarrettHand", refuse)


@pytest.mark.parametrize("option, value", [
    ("--cycles", "-5"),
    ("--cycles", "0"),  # not "one episode": that is --cycles left out
    ("--max-velocity", "128"),
    ("--max-velocity", "-1"),
    ("--max-strain", "256"),
    ("--max-strain", "-1"),
    ("--max-temperature", "nan"),
    ("--max-temperature", "inf"),
    ("--baud", "9601"),
])
def test_bad_option_values_are_usage_errors_before_the_port_is_opened(reach_policy_npz, tmp_path, capsys,
                                                                     port_never_opened, option, value):
    from bh8_gym.cli import main

    log = tmp_path / "never.jsonl"
    with pytest.raises(SystemExit) as exited:
        main(["deploy", "--port", "bh8sim://?seed=0", "--policy", str(reach_policy_npz), "--log", str(log),
              option, value])
    assert exited.value.code == 2
    last_line = capsys.readouterr().err.strip().splitlines()[-1]
    assert last_line.startswith("bh8 deploy: error: argument " + option) and value in last_line
    assert not log.exists()


def test_an_unwritable_log_is_a_usage_error_before_the_port_is_opened(reach_policy_npz, tmp_path, capsys,
                                                                      port_never_opened):
    from bh8_gym.cli import main

    log = tmp_path / "no_such_directory" / "deploy.jsonl"
    code = main(["deploy", "--port", "bh8sim://?seed=0", "--policy", str(reach_policy_npz), "--log", str(log)])
    assert code == 2
    error = capsys.readouterr().err.strip()
    assert error == f"bh8 deploy: cannot write the log: [Errno 2] No such file or directory: {str(log)!r}"


def test_help_shows_the_safety_limits_defaults_and_the_exit_codes(capsys):
    from bh8_gym.cli import main
    from bh8_gym.safety import SafetyEnvelope

    with pytest.raises(SystemExit) as exited:
        main(["deploy", "--help"])
    assert exited.value.code == 0
    text = " ".join(capsys.readouterr().out.split())  # argparse wraps lines where it likes
    envelope = SafetyEnvelope()
    for default in (envelope.max_velocity, envelope.max_strain, envelope.max_temperature):
        assert f"(default: the safety envelope the policy's env trained in, by default {default})" in text
    assert "--on-exit none --clock cycles (the default limits are the env's own safety envelope" in text
    exit_status = text.split("exit status:", 1)[1]
    for code in ("0", "1", "2", "3", "130"):
        assert f" {code} " in f" {exit_status}", code


def test_the_summary_counts_policy_cycles_and_the_log_keeps_every_block(reach_policy_npz, tmp_path, capsys):
    from bh8_gym.cli import main

    log = tmp_path / "deploy.jsonl"
    code = main(["deploy", "--port", "bh8sim://?seed=0", "--policy", str(reach_policy_npz), "--cycles", "5",
                 "--log", str(log), "--clock", "cycles"])
    assert code == 0
    assert capsys.readouterr().out.strip() == f"bh8 deploy: 5 policy cycles, stopped: done; log in {log}"
    records = [json.loads(line) for line in log.read_text().splitlines()]
    assert [r["cycle"] for r in records if "cycle" in r] == list(range(7))  # "A", 5 policy cycles, stop block
    assert records[-1]["event"] == "stop" and records[-1]["blocks"] == 7 and records[-1]["policy_cycles"] == 5


def test_a_port_failing_mid_run_is_reported_with_its_cycle_and_logged_as_a_stop(reach_policy_npz, tmp_path, capsys):
    """`bh8 serve` killed while deploy runs: the original failure with the cycle it happened at (not
    the exit action's failed reopen), a stop record, the unsent safe-exit commands, exit 1."""
    from bh8_gym.cli import main

    server = subprocess.Popen([sys.executable, "-m", "bh8_gym.cli", "serve", "--state", str(tmp_path / "state")],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    log = tmp_path / "deploy.jsonl"

    def kill_server_once_policy_cycles_run():
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline and not (log.exists() and log.read_text().count('"cycle"') > 5):
            time.sleep(0.02)
        server.kill()

    try:
        device = server.stdout.readline().strip()
        assert device.startswith("/dev/"), server.stderr.read()
        killer = threading.Thread(target=kill_server_once_policy_cycles_run, daemon=True)
        killer.start()
        code = main(["deploy", "--port", device, "--policy", str(reach_policy_npz), "--cycles", "100000000",
                     "--log", str(log), "--clock", "cycles"])
        killer.join()
    finally:
        server.kill()
        server.communicate()
    err = capsys.readouterr().err
    records = [json.loads(line) for line in log.read_text().splitlines()]
    failed_cycle = [r["cycle"] for r in records if "cycle" in r][-1] + 1  # the block that got no feedback
    stop = records[-1]
    assert code == 1, err
    assert stop["event"] == "stop" and stop["reason"].startswith(f"hand/port error at cycle {failed_cycle}: "
                                                                 f"serial port {device!r} failed")
    assert "cannot open" in stop["safe_exit_error"]
    summary, safe_exit = err.strip().splitlines()[-2:]
    assert summary == f"bh8 deploy: {failed_cycle - 1} policy cycles, stopped: {stop['reason']}; log in {log}"
    assert safe_exit.startswith("bh8 deploy: the safe-exit commands (zero-velocity block, ^C, GT) could not be sent: "
                                f"cannot open {device!r}")


def test_a_port_failure_names_the_cycle_whose_block_failed(reach_policy_npz, tmp_path):
    """The same with a port object that fails like an unplugged adapter on the third policy block:
    cycles 0 ("A"), 1 and 2 are logged, the failure is at cycle 3, and the port cannot be reopened."""
    from bh8_gym.agents.deployment.deploy import Deployment
    from bh8_gym.agents.env_factory import make_env
    from bh8_gym.agents.deployment.policy_file import load_policy
    from bh8_gym.client import BarrettHand, HandConnectionError

    port = serial.serial_for_url("bh8sim://?seed=0")
    unplugged = threading.Event()
    write = port.write

    def write_unless_unplugged(data):
        if unplugged.is_set():
            raise serial.SerialException("device disconnected")
        return write(data)

    def open_unplugged():
        raise serial.SerialException("no such device")

    port.write, port.open = write_unless_unplugged, open_unplugged

    env = make_env(REACH, {})
    log = tmp_path / "deploy.jsonl"
    try:
        with log.open("w") as log_file, BarrettHand(port) as hand:
            policy = PolicyTriggeringAtCycle3(load_policy(reach_policy_npz), unplugged)
            deployment = Deployment(hand, policy, env.unwrapped.interface, log_file, clock="cycles")
            deployment.setup(env.unwrapped.baud)
            reason = deployment.run(20)
    finally:
        env.close()
        port.close()
    assert reason == f"hand/port error at cycle 3: serial port {hand.port_name!r} failed: device disconnected"
    assert isinstance(deployment.hand_error, HandConnectionError) and deployment.policy_cycles == 2
    assert "cannot reopen" in str(deployment.safe_exit_error)
    records = [json.loads(line) for line in log.read_text().splitlines()]
    assert [r["cycle"] for r in records if "cycle" in r] == [0, 1, 2]
    assert records[-1] == {**records[-1], "event": "stop", "reason": reason, "blocks": 3, "policy_cycles": 2,
                           "safe_exit_error": str(deployment.safe_exit_error)}
    assert all(r.get("line") != "GT" for r in records)  # the exit action never reached the hand


def test_a_hand_silent_mid_run_is_sent_ctrl_c_even_without_an_exit_action(reach_policy_npz, tmp_path):
    """A RealTime block that times out leaves the line's state unknown and the client out of LOOP;
    the hand may still be in LOOP running the last velocities. finish() resyncs, which sends ^C,
    also with --on-exit none (which sent nothing before: a real hand kept moving)."""
    from bh8_gym.agents.deployment.deploy import Deployment
    from bh8_gym.agents.env_factory import make_env
    from bh8_gym.agents.deployment.policy_file import load_policy
    from bh8_gym.client import BarrettHand, HandTimeout

    port = serial.serial_for_url("bh8sim://?seed=0")
    silent, written = threading.Event(), []
    read, write = port.read, port.write

    def read_unless_silent(size=1):
        if silent.is_set():
            time.sleep(port.timeout or 0.0)
            return b""
        return read(size)

    def write_and_record(data):
        written.append(bytes(data))
        if silent.is_set() and bytes(data) == b"\x03":
            silent.clear()  # the hand answers again, as after a glitch on the line
        return write(data)

    port.read, port.write = read_unless_silent, write_and_record

    env = make_env(REACH, {})
    try:
        with (tmp_path / "deploy.jsonl").open("w") as log_file, BarrettHand(port) as hand:
            policy = PolicyTriggeringAtCycle3(load_policy(reach_policy_npz), silent)
            deployment = Deployment(hand, policy, env.unwrapped.interface, log_file, on_exit="none", clock="cycles")
            deployment.setup(env.unwrapped.baud)
            before = len(written)
            reason = deployment.run(20)
            after_failure = written[before:]
            assert isinstance(deployment.hand_error, HandTimeout) and reason.startswith("hand/port error at cycle 3")
            assert deployment.safe_exit_error is None
            assert b"\x03" in after_failure[3:]  # after the three policy blocks
            assert not hand.in_loop and hand.get("S", "G") == {"S": [0, 0, 0]}  # supervisory again
    finally:
        env.close()
        port.close()


def test_when_the_stop_block_and_the_ctrl_c_both_fail_the_stop_block_failure_is_reported_first(reach_policy_npz, tmp_path):
    """finish(): a hand that goes silent at the zero-velocity stop block and stays silent. The
    block's time-out is the safe-exit error (it came first); the failed ^C after it is a note in the
    stop record, not a replacement (before, only the ^C's failure was reported)."""
    from bh8_gym.agents.deployment.deploy import Deployment, error_text
    from bh8_gym.agents.env_factory import make_env
    from bh8_gym.agents.deployment.policy_file import load_policy
    from bh8_gym.client import BarrettHand, HandTimeout

    port = serial.serial_for_url("bh8sim://?seed=0")
    read = port.read
    deployment = None

    def read_unless_silent(size=1):
        if deployment is not None and deployment.policy_cycles >= 2:
            time.sleep(port.timeout or 0.0)
            return b""
        return read(size)

    port.read = read_unless_silent
    env = make_env(REACH, {})
    log = tmp_path / "deploy.jsonl"
    try:
        with log.open("w") as log_file, BarrettHand(port) as hand:
            deployment = Deployment(hand, load_policy(reach_policy_npz), env.unwrapped.interface, log_file, on_exit="none", clock="cycles")
            deployment.setup(env.unwrapped.baud)
            reason = deployment.run(2)
    finally:
        env.close()
        port.close()
    assert reason == "done" and deployment.hand_error is None
    error = deployment.safe_exit_error
    assert isinstance(error, HandTimeout) and str(error).startswith("RealTime reply"), error_text(error)
    assert "then leaving LOOP (^C) failed" in error_text(error)
    stop = json.loads(log.read_text().splitlines()[-1])
    assert stop["safe_exit_error"] == error_text(error)


def test_the_temperature_limit_is_checked_before_loop(reach_policy_npz, tmp_path, capsys):
    """The shipped envs' LOOP has no LFT, so a per-cycle temperature check never saw a reading:
    `--max-temperature` is checked with PGET TEMP before LOOP (a safety stop, exit 3, logged)."""
    from bh8_gym.cli import main

    log = tmp_path / "deploy.jsonl"
    code = main(["deploy", "--port", "bh8sim://?seed=0", "--policy", str(reach_policy_npz), "--log", str(log),
                 "--max-temperature", "0"])
    assert code == 3
    assert "safety stop before LOOP: temperature" in capsys.readouterr().err
    records = [json.loads(line) for line in log.read_text().splitlines()]
    assert not any("cycle" in r for r in records)  # never entered LOOP
    assert records[-1]["event"] == "stop" and "above the limit 0.0 C before LOOP" in records[-1]["reason"]
    assert records[-2] == {**records[-2], "event": "baud", "rate": 9600}  # left at the rate it was found at


def test_a_port_that_cannot_be_opened_leaves_the_old_log_alone(reach_policy_npz, tmp_path, capsys):
    """A mistyped port must not wipe the previous run's log (and its stop record)."""
    from bh8_gym.cli import main

    log = tmp_path / "deploy.jsonl"
    log.write_text('{"event": "stop", "reason": "safety stop: the last run"}\n')
    assert main(["deploy", "--port", "/dev/does-not-exist-bh8", "--policy", str(reach_policy_npz), "--log", str(log)]) == 1
    assert "cannot open" in capsys.readouterr().err
    assert log.read_text() == '{"event": "stop", "reason": "safety stop: the last run"}\n'


def test_a_firmware_44_hand_with_the_same_blocks_is_accepted(reach_policy_npz, tmp_path, capsys):
    """Without LFT the 4.3 and 4.4 blocks are byte for byte the same (SPEC.md §7): deploy runs."""
    from bh8_gym.cli import main

    log = tmp_path / "deploy.jsonl"
    code = main(["deploy", "--port", "bh8sim://?seed=0&firmware=4.4", "--policy", str(reach_policy_npz),
                 "--cycles", "3", "--log", str(log)])
    assert code == 0, capsys.readouterr().err
    assert json.loads(log.read_text().splitlines()[-1])["reason"] == "done"


def test_ctrl_c_during_the_setup_stops_the_hand_and_switches_the_rate_back(reach_policy_npz, tmp_path, capsys, monkeypatch):
    """Ctrl-C while HI runs (seconds on a hand): ^C goes to the hand (§5.5 case 4 stops a motion),
    the hand returns to the rate it was found at, the log ends with its stop record; exit 130."""
    from bh8_gym.cli import main
    from bh8_gym.client import BarrettHand

    sent = []
    command, abort = BarrettHand.command, BarrettHand.abort

    def command_interrupted_at_hi(self, line, *args, **kwargs):
        sent.append(line)
        if line == "HI":
            raise KeyboardInterrupt
        return command(self, line, *args, **kwargs)

    def recorded_abort(self):
        sent.append("^C")
        return abort(self)

    monkeypatch.setattr(BarrettHand, "command", command_interrupted_at_hi)
    monkeypatch.setattr(BarrettHand, "abort", recorded_abort)
    log = tmp_path / "deploy.jsonl"
    assert main(["deploy", "--port", "bh8sim://?seed=0", "--policy", str(reach_policy_npz), "--log", str(log)]) == 130
    assert "interrupted (Ctrl-C) during the setup" in capsys.readouterr().err
    assert sent[-2:] == ["HI", "^C"]
    records = [json.loads(line) for line in log.read_text().splitlines()]
    assert not any("cycle" in r for r in records)
    assert [r["event"] for r in records[-3:]] == ["command", "baud", "stop"]
    assert records[-2]["rate"] == 9600
    assert records[-1]["reason"] == "interrupted (Ctrl-C) during the setup"


def test_deploy_never_loads_pybullet():
    """`bh8 deploy` runs on the computer that drives a real hand: its import chain and the host's
    LoopInterface of a policy's env (built from the env id and keyword arguments) load no PyBullet."""
    script = (
        "import sys\n"
        "import bh8_gym.agents.deployment.deploy\n"
        "from bh8_gym.cli import build_parser\n"
        "from bh8_gym.envs.interfaces import interface_for\n"
        "build_parser(['deploy'])\n"
        "for env_id in ('BH8Grasp-v0', 'BH8FingerReach-v0'):\n"
        "    interface = interface_for(env_id, {'randomize': False})\n"
        "    interface.observation_from_feedback([0] * len(interface.layout.feedback_fields),\n"
        "                                        [0] * len(interface.layout.control_fields), 0.0)\n"
        "assert 'pybullet' not in sys.modules, 'deploy loaded pybullet'\n"
        "print('ok')\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0 and result.stdout.strip() == "ok", result.stderr


def test_deploy_interface_is_the_env_interface():
    """The interface deploy builds from a policy's metadata is the env's: setup script, layout,
    spaces, observation names and clock."""
    import gymnasium as gym

    from bh8_gym.envs.interfaces import interface_for

    kwargs = {"randomize": False, "lfv": True, "baud": 19200}
    env = gym.make("BH8Grasp-v0", **kwargs).unwrapped
    try:
        host = interface_for("BH8Grasp-v0", kwargs)
        mine = env.interface
        assert host.setup_commands == mine.setup_commands and host.loop_command == mine.loop_command
        assert host.baud_command == mine.baud_command == "PSET BAUD 192"
        assert host.layout == mine.layout and host.observation_fields == mine.observation_fields
        assert host.action_space == mine.action_space and host.cycle_seconds == mine.cycle_seconds
        assert host.nominal_episode_steps() == mine.nominal_episode_steps()
    finally:
        env.close()
    with pytest.raises(ValueError, match="unexpected keyword"):
        interface_for("BH8Grasp-v0", {"lcx": True})


# -- a full disk under --log (issue 32, item 5) -----------------------------------------------

_DEPLOY_RECORDING_THE_HAND = """
import sys
import bh8_gym.urlhandler
import bh8_gym.agents.deployment.deploy as deploy
from bh8_gym.cli import main

command, set_baud = deploy.BarrettHand.command, deploy.BarrettHand.set_baud
def recorded_command(self, line, *args, **kwargs):
    print("hand: " + line, file=sys.stderr, flush=True)
    return command(self, line, *args, **kwargs)
def recorded_set_baud(self, rate):
    print(f"hand: baud {rate}", file=sys.stderr, flush=True)
    return set_baud(self, rate)
deploy.BarrettHand.command, deploy.BarrettHand.set_baud = recorded_command, recorded_set_baud
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/dev/full and RLIMIT_FSIZE")
@pytest.mark.parametrize("room", ["none", 3000, 4600])
def test_a_full_disk_under_the_log_never_stops_the_safe_exit(reach_policy_npz, tmp_path, room):
    """On a full filesystem `bh8 deploy --log` died of a raw OSError: GT never sent, the baud not
    switched back, the log cut mid-record. Here the log is /dev/full (no room from the start:
    ENOSPC) or the kernel refuses it past `room` bytes (RLIMIT_FSIZE: the write that crosses it
    is cut short and the next fails, as on a full disk), mid-run or at the last records of a
    4.7 KB log (the simulated hand's 2.2 KB store fits). The run stops at the next cycle boundary
    (exit 3, also when only the last records failed); the hand still gets the zero block, ^C, GT
    and its rate back; the log holds whole records only; the summary and the log's failure are one
    line each."""
    import resource

    log = Path("/dev/full") if room == "none" else tmp_path / "deploy.jsonl"

    def limit_file_size():
        if room != "none":
            resource.setrlimit(resource.RLIMIT_FSIZE, (room, resource.RLIM_INFINITY))

    result = subprocess.run(
        [sys.executable, "-c", _DEPLOY_RECORDING_THE_HAND, "deploy", "--port", "bh8sim://?seed=0", "--policy",
         str(reach_policy_npz), "--log", str(log), "--cycles", "40", "--clock", "cycles"],
        capture_output=True, text=True, timeout=300, preexec_fn=limit_file_size)
    assert result.returncode == 3, result.stderr[-2000:]
    hand = [line.removeprefix("hand: ") for line in result.stderr.splitlines() if line.startswith("hand: ")]
    assert hand[0] == "baud 38400" and "HI" in hand and hand[-2:] == ["GT", "baud 9600"]
    reason = "No space left on device" if room == "none" else "File too large"
    if room == 4600:  # the log failed after the last cycle, leaving LOOP: the cycles all ran
        assert f"40 policy cycles, stopped: done; log in {log}" in result.stdout
    else:
        assert f"stopped: the log cannot be written ({reason}); log in {log}" in result.stdout
    assert f"bh8 deploy: the log {str(log)!r} stopped at a record it could not write" in result.stderr
    assert "Traceback" not in result.stderr
    if room != "none":
        text = log.read_text()
        assert 0 < len(text) <= room and text.endswith("\n")
        records = [json.loads(line) for line in text.splitlines()]  # whole records only
        assert records[0]["event"] == "baud" and "stop" not in [record.get("event") for record in records]


class _FillingDisk:
    """A raw file that takes `room` more bytes, the last write cut short, then fails with ENOSPC."""

    def __init__(self, file, room: int):
        self.file, self.room = file, room

    def write(self, data: bytes) -> int:
        if self.room <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        written = self.file.write(data[:self.room])
        self.room -= written
        return written

    def __getattr__(self, name):
        return getattr(self.file, name)


def test_the_log_keeps_whole_records_when_the_disk_fills(tmp_path):
    """`RecordLog`: a record the disk takes only part of is cut back off the file and its write
    raises ENOSPC; every later record raises too, and the file holds the whole records before it."""
    from bh8_gym.agents.deployment.deploy import RecordLog

    path = tmp_path / "log.jsonl"
    records = [{"cycle": index, "control": "43" + "00" * 8} for index in range(20)]
    with RecordLog(path) as log:
        log._file = _FillingDisk(log._file, room=300)
        written = []
        for record in records:
            try:
                log.write(json.dumps(record) + "\n")
            except OSError as error:
                assert error.errno == errno.ENOSPC
                break
            written.append(record)
        with pytest.raises(OSError):
            log.write(json.dumps(records[-1]) + "\n")
    assert 0 < len(written) < len(records)
    assert [json.loads(line) for line in path.read_text().splitlines()] == written
