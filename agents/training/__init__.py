"""`bh8 train`: a grasp policy trained with PPO or SAC (Stable-Baselines3).

Entry points: `train.run` (the command; `train.configure_parser` its options, `train.load_config`
a config file read and checked) and `trainer.Trainer` (one run: build or resume, warm start, learn,
checkpoints, the best model). Its parts: `config_check` (every config key's kind and range, also
for `bh8 sweep`), `pretrain` (the `[pretrain]` warm start from a scripted grasp), `teacher` (a
script chosen per episode, distilled by DAgger), `callbacks` (evaluation, checkpoints, progress,
stop), `vec_env` (`ShardedVecEnv`: envs in worker processes) and `checkpoint_file` (a checkpoint
read back with nothing unpickled). Nothing is imported here, so importing one of them costs only
it (torch comes with the modules that need it).
"""
