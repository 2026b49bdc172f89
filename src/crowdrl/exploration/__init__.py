"""Exploration for off-policy RL, usable on any TorchRL env: intrinsic-reward replay-buffer
transforms (ICM, RE3), noisy-net and action-dropout surgeries of a Q network's head, and the
:class:`~crowdrl.exploration.strategy.ExplorationStrategy` interface with its registry
(``make_strategy(config)``; importing this package registers ``egreedy``, ``noisy``, ``dropout``,
``icm``, ``re3`` and ``rnd``).

Nothing here imports the crowd code (``crowdrl.sim``, ``crowdrl.envs``, ``crowdrl.models``) nor the
trainer (``crowdrl.training``): what a strategy needs from the run comes in a
:class:`~crowdrl.exploration.strategy.ReplayContext`. Keep it that way.
"""

from crowdrl.exploration.icm import ICM
from crowdrl.exploration.intrinsic import IntrinsicBonus, IntrinsicRewardTransform
from crowdrl.exploration.normalize import RunningMeanStd
from crowdrl.exploration.re3 import RE3
from crowdrl.exploration.strategy import ExplorationStrategy, ReplayContext, make_strategy, register_strategy
from crowdrl.exploration.dropout import DropoutExploration  # noqa: E402  (registers "dropout")
from crowdrl.exploration.noisy import NoisyExploration  # noqa: E402  (registers "noisy")
from crowdrl.exploration.intrinsic_strategy import IntrinsicExploration  # noqa: E402  (registers "icm", "re3")
from crowdrl.exploration.rnd import RND  # noqa: E402  (registers "rnd")

__all__ = ["ICM", "RE3", "RND", "DropoutExploration", "ExplorationStrategy", "IntrinsicBonus", "IntrinsicExploration",
           "IntrinsicRewardTransform", "NoisyExploration", "ReplayContext", "RunningMeanStd", "make_strategy",
           "register_strategy"]
