"""`bh8 export` and `bh8 deploy`: a trained policy as a file, and that file on a hand.

Entry points: `export.run` (an SB3 model to a numpy-only policy file), `deploy.run` (the policy
closed-loop on a hand over a serial port; `deploy.Deployment` the run itself) and
`policy_file.load_policy` (any policy file, checked before use). Nothing here loads PyBullet: deploy
runs on a computer that has only the hand. Nothing is imported here, so importing one module costs
only it.
"""
