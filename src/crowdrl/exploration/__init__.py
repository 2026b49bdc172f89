"""Intrinsic-reward exploration (ICM, RE3) as replay-buffer transforms, usable on any TorchRL env.

Nothing here imports the crowd code (``crowdrl.sim``, ``crowdrl.envs``, ``crowdrl.models``): the
intrinsic bonuses work on any TorchRL env, and the noisy and dropout surgeries
(:mod:`crowdrl.exploration.noisy`, :mod:`crowdrl.exploration.dropout`, imported by their full
name) work on any ``nn.Module`` head. Keep it that way.
"""

from crowdrl.exploration.icm import ICM
from crowdrl.exploration.intrinsic import IntrinsicBonus, IntrinsicRewardTransform
from crowdrl.exploration.normalize import RunningMeanStd
from crowdrl.exploration.re3 import RE3

__all__ = ["ICM", "RE3", "IntrinsicBonus", "IntrinsicRewardTransform", "RunningMeanStd"]
