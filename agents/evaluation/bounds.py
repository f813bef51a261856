"""The bounds an evaluation's numbers are checked against, defined once for `bh8 eval`, the [eval]
table of a `bh8 train` config (training/config_check.py) and `bh8 sweep`'s test evaluation: how
many episodes, and the seeds numpy and SB3 take (a run's seed too).
"""

MAX_EPISODES = 10**6
MAX_SEED = 2**32 - 1  # numpy's and SB3's seeds
