"""The grasp choice (agents/choice/): a discrete pick among named grasps after the fingers have felt the
object, labels by counterfactual from snapshot-and-branch, a policy file that carries no code, and the
same bytes in `bh8 eval` and `bh8 deploy`."""
from __future__ import annotations

import json
import sys

import numpy as np
import pytest

import bh8_gym  # noqa: F401  (registers the envs)
from bh8_gym.agents.choice.features import ChoiceFeatures
from bh8_gym.agents.choice.labels import label_context
from bh8_gym.agents.choice.model import SuccessModel
from bh8_gym.agents.choice.policy import ChoiceSettings, GraspChoicePolicy, probe_policy
from bh8_gym.agents.deployment.policy_file import PolicyFileError, load_policy
from bh8_gym.agents.env_factory import make_env
from bh8_gym.agents.grasps import make_script

ENV_ID = "BH8Grasp-v0"
SETTINGS = ChoiceSettings(probe="loop-v70", grasps=("loop-v70", "squeeze", "hold"), decision_seconds=0.6)


@pytest.fixture(scope="module")
def env():
    env = make_env(ENV_ID, {"object_set": "primitives-train", "randomize": True})
    yield env
    env.close()


@pytest.fixture(scope="module")
def n_features(env):
    base = env.unwrapped
    return len(ChoiceFeatures(base.layout.feedback_fields, base.episode_seconds).names)


def forced(settings: ChoiceSettings, n_features: int, name: str) -> GraspChoicePolicy:
    """A policy whose selector always picks `name` (its bias is the only thing it has)."""
    bias = np.array([1.0 if g == name else 0.0 for g in settings.grasps])
    return GraspChoicePolicy(settings, SuccessModel(np.zeros(n_features), np.ones(n_features),
                                                    [np.zeros((n_features, len(bias)))], [bias]))


def episode(env, actor, seed: int) -> tuple[list[bytes], bool]:
    """(control blocks, held) of one episode of `actor` (a script or a choice policy)."""
    obs, info = env.reset(seed=seed)
    actor.reset(env)
    blocks, done = [], False
    while not done:
        obs, _, terminated, truncated, info = env.step(actor.act(obs, info))
        blocks.append(info["control_block"])
        done = terminated or truncated
    return blocks, bool(info["is_success"])


def test_keeping_the_probe_is_the_probes_script_byte_for_byte(env, n_features):
    """Probing costs nothing when the choice keeps the probe: every block is loop-v70's."""
    policy = probe_policy(SETTINGS, n_features)
    script = make_script("loop-v70", env)
    ours, _ = episode(env, policy, seed=4)
    theirs, _ = episode(env, script, seed=4)
    assert ours == theirs
    assert [d["grasp"] for d in policy.decisions] == ["loop-v70"]
    assert policy.decisions[0]["at"] == pytest.approx(0.6, abs=policy.cycle_seconds)


def test_the_choice_is_one_grasp_not_an_average(env, n_features):
    """After the decision the bytes are one candidate's own: the fingers' LCV bytes of a choice of
    `hold` are 0 from the decision on, and those of a choice of loop-v70 its closing 70 (0 while the
    spread, back-driven by the grasp, is off its setting: the LOOP script's rule)."""
    for name, allowed in (("hold", {0}), ("loop-v70", {0, 70})):
        policy = forced(SETTINGS, n_features, name)
        blocks, _ = episode(env, policy, seed=5)
        layout = env.unwrapped.layout
        decided = int(round(policy.decisions[0]["at"] / policy.cycle_seconds))
        for block in blocks[decided:]:
            values = dict(zip(layout.control_fields, layout.decode_control(block[1:])))
            lcv = {values[(m, "LCV")] for m in (1, 2, 3)}
            assert len(lcv) == 1 and lcv <= allowed


@pytest.mark.parametrize("seed", [7, 12])
def test_counterfactual_labels_are_what_each_choice_does(env, n_features, seed):
    """Every branch of a context, rolled out from the snapshot, holds exactly when the policy that
    makes that choice holds the same episode run from its reset (no snapshot)."""
    features, success, stops, checks, family = label_context(env, SETTINGS, seed)
    assert features.shape == (n_features,) and checks.shape == (len(SETTINGS.grasps), n_features)
    for index, name in enumerate(SETTINGS.grasps):
        _, held = episode(env, forced(SETTINGS, n_features, name), seed)
        assert held == bool(success[index]), name
    decided = probe_policy(SETTINGS, n_features)
    episode(env, decided, seed)
    np.testing.assert_allclose(features, decided.decided_features, rtol=0, atol=1e-12)


def test_the_success_model_learns_which_grasp_holds():
    """Two kinds of context, each held by a different grasp: the fitted model picks the right one."""
    rng = np.random.default_rng(0)
    kind = rng.integers(0, 2, 200)
    features = np.c_[kind + rng.normal(0, 0.3, 200), rng.normal(0, 1, (200, 3))]
    labels = np.c_[kind == 0, kind == 1].astype(float)
    model = SuccessModel.fit(features, labels, hidden=(8,), epochs=40, learning_rate=1e-2, seed=0)
    assert (model(features).argmax(1) == kind).mean() > 0.9


def test_policy_file_round_trip_and_bad_files(tmp_path, n_features):
    rng = np.random.default_rng(1)
    selector = SuccessModel(rng.normal(size=n_features), np.ones(n_features),
                            [rng.normal(size=(n_features, 4)), rng.normal(size=(4, 3))], [np.zeros(4), np.zeros(3)])
    policy = GraspChoicePolicy(SETTINGS, selector, metadata={"env_id": ENV_ID, "env_kwargs": {}})
    path = policy.save(tmp_path / "choice.npz")
    loaded = load_policy(path)
    assert loaded.settings == SETTINGS and loaded.metadata["env_id"] == ENV_ID
    x = rng.normal(size=(5, n_features))
    np.testing.assert_array_equal(loaded.selector(x), selector(x))

    def damaged(change) -> str:
        arrays = {name: np.array(value) for name, value in policy.arrays().items()}
        change(arrays)
        bad = tmp_path / "bad.npz"
        np.savez(bad, **arrays)
        with pytest.raises(PolicyFileError) as error:
            load_policy(bad)
        return str(error.value)

    def set_settings(arrays, **changes):
        metadata = json.loads(str(arrays["metadata"]))
        metadata["settings"].update(changes)
        arrays["metadata"] = np.array(json.dumps(metadata))

    assert "unknown grasp" in damaged(lambda a: set_settings(a, grasps=["loop", "rm -rf"]))
    assert "decision_seconds" in damaged(lambda a: set_settings(a, decision_seconds=1e300))
    assert "unknown settings" in damaged(lambda a: set_settings(a, exec="print(1)"))
    assert "not finite" in damaged(lambda a: a["selector_layer0_weight"].__setitem__((0, 0), np.nan))
    assert "chain" in damaged(lambda a: a.__setitem__("selector_layer1_weight", np.zeros((5, 3))))
    assert "scores" in damaged(lambda a: a.__setitem__("selector_layer1_weight", np.zeros((4, 2))) or
                               a.__setitem__("selector_layer1_bias", np.zeros(2)))

    def set_metadata(arrays, **changes):
        metadata = json.loads(str(arrays["metadata"]))
        metadata.update(changes)
        arrays["metadata"] = np.array(json.dumps(metadata))

    # the metadata an export's schema checks (agents/policy_io.POLICY_METADATA), and the predictor's count
    assert "env_kwargs must be a table" in damaged(lambda a: set_metadata(a, env_kwargs=0))
    assert "seed" in damaged(lambda a: set_metadata(a, seed="x"))
    assert "predictor_layers" in damaged(lambda a: set_metadata(a, predictor_layers=True))
    assert "layers must be" in damaged(lambda a: set_metadata(a, selector_layers=True))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="pty tests need Linux /dev/pts")
def test_deploy_runs_the_choice_block_for_block(tmp_path, n_features):
    """`bh8 deploy` of a grasp-choice file against `bh8 serve --env BH8Grasp-v0 --seed 9` sends the
    very control blocks the policy sends in-process on the same episode (its clock counts cycles, as
    a host's does), so what it chose in simulation it chooses on the hand."""
    import subprocess

    from bh8_gym.cli import main

    env_kwargs = {"randomize": False}
    policy = forced(SETTINGS, n_features, "squeeze")
    policy.metadata.update(env_id=ENV_ID, env_kwargs=env_kwargs)
    path = policy.save(tmp_path / "choice.npz")
    env = make_env(ENV_ID, env_kwargs)
    try:
        ours, _ = episode(env, load_policy(path), seed=9)
    finally:
        env.close()
    server = subprocess.Popen([sys.executable, "-m", "bh8_gym.cli", "serve", "--env", ENV_ID, "--seed", "9",
                               "--env-kwargs", json.dumps(env_kwargs)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True)
    try:
        device = server.stdout.readline().strip()
        assert device.startswith("/dev/"), server.stderr.read()
        log = tmp_path / "log.jsonl"
        assert main(["deploy", "--port", device, "--policy", str(path), "--clock", "cycles", "--log", str(log),
                     "--on-exit", "none"]) == 0
    finally:
        server.terminate()
        server.communicate(timeout=30)
    records = [json.loads(line) for line in log.read_text().splitlines()]
    served = [bytes.fromhex(r["control"]) for r in records if "cycle" in r][1:len(ours) + 1]  # after the "A" block
    assert served == ours


def test_the_decision_env_passes_both_checkers_and_ppo_starts_as_the_selector(n_features):
    """RL over the discrete choice: `DecisionEnv` is a Gymnasium env (both checkers pass) whose
    action is the grasp; PPO warm-started from a selector picks, deterministically, what it picks."""
    import warnings

    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    from bh8_gym.agents.choice.decision_env import DecisionEnv, selector_of, warm_started_ppo

    env = DecisionEnv(env_kwargs={"object_set": "primitives-train", "randomize": False}, settings=SETTINGS)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # the features' Box is unbounded
            check_env(env, skip_render_check=True)
            sb3_check_env(env)
        rng = np.random.default_rng(2)
        selector = SuccessModel(rng.normal(size=n_features), rng.uniform(0.5, 2.0, n_features),
                                [rng.normal(size=(n_features, 8)), rng.normal(size=(8, 3))],
                                [rng.normal(size=8), rng.normal(size=3)])
        model = warm_started_ppo(selector, env, n_steps=8, batch_size=8)
        x = rng.normal(size=(64, n_features)).astype(np.float32)
        assert (model.predict(x, deterministic=True)[0] == selector(x).argmax(1)).all()
        assert (selector_of(model, n_features)(x).argmax(1) == selector(x).argmax(1)).all()
        env.reset(seed=0)
        _, reward, terminated, truncated, info = env.step(1)
        assert terminated and not truncated and reward == float(info["is_success"]) and info["grasp"] == "squeeze"
    finally:
        env.close()
