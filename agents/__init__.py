"""bh8_gym.agents: grasp policies, grouped as a user's verbs (installed from agents/).

- `training` (`bh8 train`): `train.run` and `trainer.Trainer`, the config's checks, the warm
  start, the teacher, the callbacks, the sharded envs and checkpoints.
- `evaluation` (`bh8 eval`): `evaluate.run`, running episodes (`episodes.run_episodes`), the worker
  process, `--baseline`'s names (`baselines`), the scripted family's ceiling and a run's files.
- `deployment` (`bh8 export`, `bh8 deploy`): policy files (reading and checking them, the numpy
  policy), the export and the run on a hand.
- `sweep` (`bh8 sweep`): seeds and hyperparameters as Ray Tune trials.
- `choice`: the grasp choice (features at the decision point, counterfactual labels, the selector,
  `GraspChoicePolicy`), a policy deployment loads like the others.

Directly here, because the verbs share them: `env_factory` (the envs agents act on), `asymmetric`
(the asymmetric actor-critic, which a saved model needs to load), `grasps` (the scripted LOOP
grasps, host side: an env, `bh8 deploy` and the grasp choice run them alike) and `policy_io`
(`PolicyFileError`, the size bounds of a policy file, atomic writes). Nothing is imported
here, so importing one module costs only it.
"""
