"""Gymnasium ids of the crowd scenarios (registered on ``import crowdrl``; imports only gymnasium, so
``import crowdrl`` stays light and pulls in no simulator code)."""

from __future__ import annotations

import gymnasium as gym

GYM_IDS = {"crowdrl/CircleCrossing-v0": "circle", "crowdrl/SquareCrossing-v0": "square",
           "crowdrl/Corridor-v0": "corridor", "crowdrl/Doorway-v0": "doorway", "crowdrl/Room-v0": "room"}


def register_gym_envs() -> None:
    """Register the ids once; a second call is a no-op."""
    for env_id, scenario in GYM_IDS.items():
        if env_id not in gym.registry:
            gym.register(
                id=env_id,
                entry_point="crowdrl.gym_env:CrowdNavGymEnv",
                kwargs={"scenario": scenario},
                max_episode_steps=None,
            )
