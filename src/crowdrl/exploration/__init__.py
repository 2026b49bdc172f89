"""Intrinsic-reward exploration (ICM, RE3) as replay-buffer transforms, usable on any TorchRL env.

Importing this package pulls in nothing from the crowd code (``crowdrl.sim``, ``crowdrl.envs``,
``crowdrl.models``) by itself; keep it that way: crowd-specific submodules (e.g. the noisy and
dropout Q-heads) are imported by their full name, not re-exported here.
"""

from crowdrl.exploration.icm import ICM
from crowdrl.exploration.intrinsic import IntrinsicBonus, IntrinsicRewardTransform
from crowdrl.exploration.re3 import RE3, RunningStd

__all__ = ["ICM", "RE3", "IntrinsicBonus", "IntrinsicRewardTransform", "RunningStd"]
