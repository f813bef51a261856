"""bh8-gym: the BarrettHand BH8-262 in simulation, on a virtual serial port, and in Gymnasium.

Importing the package registers the environments `BH8Grasp-v0` and `BH8FingerReach-v0`.
"""
from bh8_gym.envs import register_envs as _register_envs

__version__ = "0.1.0"

_register_envs()
