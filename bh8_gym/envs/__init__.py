"""Gymnasium environments; `register_envs` runs on `import bh8_gym`."""


def register_envs() -> None:
    """Register the bh8-gym environments with Gymnasium (idempotent)."""
