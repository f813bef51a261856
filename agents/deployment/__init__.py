"""`bh8 export` and `bh8 deploy`: a trained policy as a file, and that file on a hand.

Entry points: `export.run` (an SB3 model to a numpy-only policy file), `deploy.run` (the policy
closed-loop on a hand over a serial port: `deploy.Deployment`, which stops on strain in
`Deployment._stop_on_strain_or_temperature`) and `policy_file.load_policy` (any policy file,
checked before use). Its parts: `numpy_policy` (the numpy-only file: `export_sb3_policy` writes
it, `NumpyPolicy` runs it) and `sb3_file` (an SB3 .zip read with nothing unpickled: `SB3Policy`);
what every policy file shares (`PolicyFileError`, the size bounds, atomic writes) is
`agents/policy_io.py`, which every verb writes its files with.
Nothing here loads PyBullet: deploy runs on a computer that has only the hand. Nothing is imported
here, so importing one module costs only it.
"""
