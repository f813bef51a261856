"""`bh8 sweep`: a `bh8 train` config's seeds and hyperparameters as Ray Tune trials.

One concept in one package: `command` (the `bh8 sweep` options and `run`), `space` (the config's
`[sweep]` table), `settings` (sweep.json, new or resumed, checked), `cluster` (resources,
`--address`, starting Ray), `trial` (one trial: a `Trainer` run in a Ray worker) and `report`
(our records of the trials, sweep.md, the curves, the test evaluation). Nothing is imported here, so importing one of them costs only it.
"""
