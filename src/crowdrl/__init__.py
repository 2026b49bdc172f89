"""crowdrl: batched, TorchRL-native robot navigation in crowds.

Importing the package registers the Gymnasium ids ``crowdrl/CircleCrossing-v0`` and
``crowdrl/SquareCrossing-v0``.
"""

from crowdrl.registration import register_gym_envs

__version__ = "0.1.0"

register_gym_envs()
