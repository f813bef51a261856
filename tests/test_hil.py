"""Hardware in the loop, simulated: `bh8 deploy` over a pty to `bh8 serve --env ID --seed N` sees
byte for byte the blocks an in-process evaluation of the same policy and seed sees.

Contract 2 (docs/architecture.md: identical bytes for identical input, in-process and on the pty)
and SPEC.md §6 (a cycle costs the block bytes at BAUD plus the processing time, which is what the
host's clock in the observation counts). With randomize=False the env's own observations equal
deploy's (`--clock cycles` sums the env's clock at the nominal latency). With randomize=True the
env draws the latency per episode, which a host cannot know: the env's clock then runs at the
drawn latency and deploy's at the nominal one, so their observations (episode fraction, arm
phase) differ in the last bits and the policy's bytes diverge. That variant therefore compares
with an in-process run that builds its observations as a host does (nominal clock); the served
hand itself (plant, latency, scene) is the env's, byte for byte.
"""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

ENV_ID = "BH8Grasp-v0"
SEED = 9
# Deploy's limits are its defaults, the env's safety envelope (bh8_gym.safety): it clamps nothing
# the env's action space allows and stops where the env's episode ends with a safety stop.
ON_EXIT = ["--on-exit", "none"]

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="pty tests need Linux /dev/pts")


def _export_random_policy(tmp_path_factory, env_kwargs: dict):
    """An untrained PPO actor exported with the real exporter; its last layer scaled up so the
    actions span the byte range (an untrained PPO's outputs are near zero) and fingers move."""
    import torch
    from stable_baselines3 import PPO

    from bh8_gym.agents.env_factory import make_env
    from bh8_gym.agents.deployment.numpy_policy import export_sb3_policy

    env = make_env(ENV_ID, {"randomize": False, **env_kwargs})
    try:
        model = PPO("MlpPolicy", env, seed=0, device="cpu", n_steps=64, batch_size=64, policy_kwargs={"net_arch": [16]})
    finally:
        env.close()
    with torch.no_grad():
        model.policy.action_net.weight.mul_(200.0)
    path = tmp_path_factory.mktemp("policy") / "random_grasp.npz"
    return export_sb3_policy(model, path, metadata={"env_id": ENV_ID, "env_kwargs": {"randomize": False, **env_kwargs},
                                                    "privileged": False})


@pytest.fixture(scope="module")
def policy_path(tmp_path_factory):
    return _export_random_policy(tmp_path_factory, {})


@pytest.fixture(scope="module")
def history_policy_path(tmp_path_factory):
    """The same, on observations that carry the haptic history (bh8_gym/haptic_history.py)."""
    return _export_random_policy(tmp_path_factory, {"history": True})


def _evaluate_in_process(policy, env_kwargs: dict, host_clock: bool) -> tuple[list[bytes], list[bytes], bool]:
    """One episode at SEED: (control blocks, feedback blocks, whether it ended with a safety stop),
    the "A" block first. With
    `host_clock`, observations are rebuilt from each feedback block on the nominal clock, as a host
    does; otherwise they are the env's own."""
    from bh8_gym.agents.env_factory import make_env

    env = make_env(ENV_ID, env_kwargs)
    base = env.unwrapped
    try:
        observation, info = env.reset(seed=SEED)
        controls, feedbacks = [info["control_block"]], [info["feedback_block"]]
        elapsed = base.next_elapsed(0.0, 1, base.nominal_processing_time)
        previous = np.zeros(len(base.layout.control_fields), dtype=np.int64)
        history = base.interface.new_history()  # the host's own, as deploy keeps it
        if host_clock:
            observation = base.observation_from_feedback(base.layout.decode_feedback(feedbacks[-1]), previous, elapsed,
                                                         history)
        done = False
        while not done:
            action, _ = policy.predict(observation, deterministic=True)
            observation, _, terminated, truncated, info = env.step(action)
            done = terminated or truncated
            controls.append(info["control_block"])
            feedbacks.append(info["feedback_block"])
            if host_clock:
                previous[:] = base.layout.decode_control(info["control_block"][1:])
                elapsed = base.next_elapsed(elapsed, len(info["control_block"]), base.nominal_processing_time)
                observation = base.observation_from_feedback(base.layout.decode_feedback(feedbacks[-1]), previous,
                                                             elapsed, history)
        stopped = "safety_stop" in info
        if not host_clock and not stopped:
            assert len(controls) - 1 == base.nominal_episode_steps()  # deploy's default cycle count
        return controls, feedbacks, stopped
    finally:
        env.close()


def _deploy_through_served_env(policy_path, env_kwargs: dict, log_path, extra: list[str], exit_code: int = 0):
    """`bh8 serve --env ... --seed SEED` as a subprocess, `bh8 deploy ... *extra` against its pty,
    expected to exit with `exit_code`: (control blocks, feedback blocks) from deploy's log."""
    from bh8_gym.cli import main

    server = subprocess.Popen(
        [sys.executable, "-m", "bh8_gym.cli", "serve", "--env", ENV_ID, "--seed", str(SEED),
         "--env-kwargs", json.dumps(env_kwargs)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        device = server.stdout.readline().strip()
        assert device.startswith("/dev/"), server.stderr.read()
        code = main(["deploy", "--port", device, "--policy", str(policy_path), "--clock", "cycles",
                     "--log", str(log_path), *ON_EXIT, *extra])
        assert code == exit_code
    finally:
        server.terminate()
        _, errors = server.communicate(timeout=30)
    assert server.returncode == 0, errors
    records = [json.loads(line) for line in log_path.read_text().splitlines()]
    blocks = [record for record in records if "cycle" in record]
    return [bytes.fromhex(b["control"]) for b in blocks], [bytes.fromhex(b["feedback"]) for b in blocks]


@pytest.mark.parametrize("randomize", [False, True], ids=["nominal", "randomized"])
def test_deploy_on_served_env_is_byte_identical_to_in_process(policy_path, tmp_path, randomize):
    """Contract 2 + SPEC.md §6: every control and feedback block of `bh8 deploy --clock cycles`
    against `bh8 serve --env BH8Grasp-v0 --seed 9` equals the in-process episode's, cycle by cycle
    (the "A" block and every policy cycle; deploy's extra stop block after the episode aside).
    This policy squeezes past the safety envelope's strain limit: deploy, with its default limits,
    stops the hand (exit 3) after the very block at which the env's episode ends with its safety stop."""
    from bh8_gym.agents.deployment.policy_file import load_policy

    env_kwargs = {"randomize": randomize}
    controls, feedbacks, stopped = _evaluate_in_process(load_policy(policy_path), env_kwargs, host_clock=randomize)
    assert stopped or randomize  # the test covers the stop (the randomised hand may squeeze less)
    # Without randomisation deploy runs its default, one episode; with it, the env's episode
    # ends on the drawn latency's clock, which the host does not know: run that many cycles.
    cycles = ["--cycles", str(len(controls) - 1)] if randomize else []
    served_controls, served_feedbacks = _deploy_through_served_env(policy_path, env_kwargs, tmp_path / "log.jsonl",
                                                                   cycles, exit_code=3 if stopped else 0)
    assert len(served_feedbacks) == len(feedbacks) + 1  # + deploy's zero-velocity stop block
    for cycle, (ours, theirs) in enumerate(zip(controls, served_controls)):
        assert ours == theirs, f"control block of cycle {cycle}"
    for cycle, (ours, theirs) in enumerate(zip(feedbacks, served_feedbacks)):
        assert ours == theirs, f"feedback block of cycle {cycle}"
    # Not a trivial episode: the policy moved the hand (the feedback changed over the episode).
    assert feedbacks[-1] != feedbacks[0]


@pytest.mark.parametrize("randomize", [False, True], ids=["nominal", "randomized"])
def test_deploy_builds_the_haptic_history_as_the_env_does(history_policy_path, tmp_path, randomize):
    """Contract 2 with `history=True`: deploy keeps its own haptic history from the blocks it
    receives, and every block of its episode equals the in-process episode's, so the history
    (which feeds the policy's every action) is the env's, entry for entry."""
    from bh8_gym.agents.deployment.policy_file import load_policy

    env_kwargs = {"randomize": randomize, "history": True}
    controls, feedbacks, stopped = _evaluate_in_process(load_policy(history_policy_path), env_kwargs,
                                                        host_clock=randomize)
    cycles = ["--cycles", str(len(controls) - 1)] if randomize else []
    served_controls, served_feedbacks = _deploy_through_served_env(history_policy_path, env_kwargs,
                                                                   tmp_path / "log.jsonl", cycles,
                                                                   exit_code=3 if stopped else 0)
    assert len(served_feedbacks) == len(feedbacks) + 1
    assert served_controls[:len(controls)] == controls
    assert served_feedbacks[:len(feedbacks)] == feedbacks
    assert feedbacks[-1] != feedbacks[0]


def _client_setup(firmware, env) -> None:
    """What a client like deploy sends before LOOP, in its order: the rate first, then the rest,
    plus a motion the env's script does not have (it must not matter: LOOP entry restores)."""
    lines = [env.baud_command, *env.setup_commands]
    lines.append("1M 3000")
    for line in lines:
        reply = firmware.transact(line.encode() + b"\r")
        assert reply.endswith(b"=> ") and b"ERR" not in reply, (line, reply)


def test_every_loop_entry_starts_the_env_next_episode(capsys):
    """Contract 2: on the served env's firmware, a client's LOOP (here sent in one write together
    with its blocks) gives reset(seed=N)'s episode, the next LOOP the env's next reset(), and a
    LOOP in another layout is served plainly with a note on stderr (SPEC.md §5 blocks)."""
    import gymnasium as gym

    from bh8_gym.commands.serve import build_env_firmware

    served_env, firmware = build_env_firmware(ENV_ID, SEED, {"randomize": True})
    env = gym.make(ENV_ID, randomize=True).unwrapped
    try:
        layout = env.layout
        rng = np.random.default_rng(0)
        actions = [rng.integers(env.action_space.low, env.action_space.high, endpoint=True) for _ in range(15)]
        c_blocks = [layout.encode_control(action.tolist()) for action in actions]
        loop = env.loop_command.encode()

        def episode(seed):
            _, info = env.reset(seed=seed)
            expected = [info["feedback_block"]]
            for action in actions:
                expected.append(env.step(action.astype(np.int16))[4]["feedback_block"])
            return b"".join(expected)

        _client_setup(firmware, env)
        reply = firmware.transact(loop + b"\r" + b"A" + b"".join(c_blocks))
        assert reply == loop + b"*" + episode(SEED)
        assert firmware.transact(b"\x03").endswith(b"=> ")

        assert firmware.transact(b"1LOOP\r") == b"1LOOP*"
        assert "without starting an episode" in capsys.readouterr().err
        assert firmware.transact(b"\x03").endswith(b"=> ")

        assert firmware.transact(loop + b"\r") == loop + b"*"
        assert firmware.transact(b"A" + b"".join(c_blocks)) == episode(None)
    finally:
        env.close()
        served_env.close()


@pytest.mark.parametrize(
    "arguments, message",
    [
        (["--env", "NoSuchEnv-v0"], "NoSuchEnv-v0"),
        (["--env", ENV_ID, "--env-kwargs", '{"no_such_option": 1}'], "no_such_option"),
        (["--env", ENV_ID, "--state", "/tmp/x"], "--state"),
        (["--env", ENV_ID, "--realtime"], "--realtime"),
        (["--env-kwargs", "{}"], "--env-kwargs needs --env"),
    ],
)
def test_serve_env_bad_options_are_clear_errors(arguments, message, capsys):
    """Bad `bh8 serve --env` options exit 2 with a message naming the problem, before any pty."""
    from bh8_gym.cli import main

    assert main(["serve", *arguments]) == 2
    captured = capsys.readouterr()
    assert message in captured.err and captured.out == ""


@pytest.mark.parametrize("text", ["{not json", "[1, 2]"])
def test_serve_env_kwargs_must_be_a_json_object(text, capsys):
    """--env-kwargs that is not a JSON object is an argparse error (exit 2) quoting it."""
    from bh8_gym.cli import main

    with pytest.raises(SystemExit) as stop:
        main(["serve", "--env", ENV_ID, "--env-kwargs", text])
    assert stop.value.code == 2
    assert text in capsys.readouterr().err
