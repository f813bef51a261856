"""`bh8 eval`: a policy or a scripted grasp over episodes, with success, grasp time and strain.

Entry points: `evaluate.run` (the command; `evaluate.configure_parser` its options),
`episodes.run_episodes` (episodes of one policy on one env, and what each gives) and
`eval_worker.EvaluationWorker` (half of an evaluation's episodes in a worker process, for `bh8 eval`
and `bh8 train`). Its parts: `baselines` (the scripted grasps, `make_grasp` by name), `ceiling`
(the scripted family's per-episode records) and `run_files` (a run directory's evaluations.csv,
best model, atomic writes). Nothing is imported here: `bh8 eval` and its worker load no torch
until an SB3 model needs it.
"""
