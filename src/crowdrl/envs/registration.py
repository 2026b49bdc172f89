"""Kept for imports written before the ids moved to :mod:`crowdrl.registration`."""

from crowdrl.registration import GYM_IDS, register_gym_envs

__all__ = ["GYM_IDS", "register_gym_envs"]
