"""Kept for imports written before the Gymnasium face moved to :mod:`crowdrl.gym_env` (which, unlike
this package, does not import torchrl)."""

from crowdrl.gym_env import SPLITS, CrowdNavGymEnv

__all__ = ["CrowdNavGymEnv", "SPLITS"]
