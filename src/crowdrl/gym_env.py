"""A single-episode Gymnasium face of the simulator (``crowdrl/CircleCrossing-v0``, ...)."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch

from crowdrl.sim import rng
from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.crowd import EVENT_NAMES, HUMAN_OBS_DIM, ROBOT_OBS_DIM, observe, step
from crowdrl.sim.kinematics import NUM_ACTIONS, action_table, unicycle_step
from crowdrl.sim.scenarios import initial_states

SPLITS = tuple(rng.STREAMS)


class CrowdNavGymEnv(gym.Env):
    """One crowd-navigation episode at a time, for tools that speak Gymnasium.

    Observation: ``{"robot": (9,), "humans": (N, 5)}`` float32, world frame. Action: one of 81
    unicycle actions. ``reset(seed=s)`` selects scenario stream ``s`` of ``split`` and restarts
    its episode counter; ``reset(options={"episode_id": i})`` loads episode ``i``.
    """

    metadata = {"render_modes": []}

    def __init__(self, scenario: str = "circle", num_humans: int = 10, split: str = "train") -> None:
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        self.config = CrowdConfig(scenario=scenario, num_humans=num_humans)
        self.split = split
        N = self.config.num_humans
        self.observation_space = gym.spaces.Dict(
            {
                "robot": gym.spaces.Box(-np.inf, np.inf, (ROBOT_OBS_DIM,), np.float32),
                "humans": gym.spaces.Box(-np.inf, np.inf, (N, HUMAN_OBS_DIM), np.float32),
            }
        )
        self.action_space = gym.spaces.Discrete(NUM_ACTIONS)
        self._actions = action_table(self.config.robot_v_pref)
        self._stream_seed = 0
        self._next_episode = 0
        self._state = None

    def _obs(self) -> dict[str, np.ndarray]:
        robot, humans = observe(self.config, self._state)
        return {"robot": robot[0].numpy().astype(np.float32), "humans": humans[0].numpy().astype(np.float32)}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        if seed is not None:
            if seed < 0:
                raise ValueError(f"seed must be >= 0, got {seed}")
            self._stream_seed = int(seed)
            self._next_episode = 0
        episode = self._next_episode
        if options and "episode_id" in options:
            episode = int(options["episode_id"])
            if episode < 0:
                raise ValueError(f"episode_id must be >= 0, got {episode}")
        else:
            self._next_episode += 1
        key = rng.episode_keys(self.split, self._stream_seed, torch.tensor([episode]))
        self._state = initial_states(self.config, key)
        self._episode = episode
        return self._obs(), {"episode_id": episode}

    def step(self, action):
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        if not self.action_space.contains(action) and not (
            isinstance(action, (int, np.integer)) and 0 <= int(action) < NUM_ACTIONS
        ):
            raise ValueError(f"action must be an integer in 0..{NUM_ACTIONS - 1}, got {action!r}")
        speed, rot = self._actions[int(action)]
        heading, velocity = unicycle_step(self._state.robot_heading, speed.view(1), rot.view(1))
        self._state, res = step(self.config, self._state, velocity, heading)
        info = {
            "event": EVENT_NAMES[int(res.event[0])],
            "min_separation": float(res.min_separation[0]),
            "discomfort_count": int(res.discomfort_count[0]),
            "episode_id": self._episode,
        }
        return self._obs(), float(res.reward[0]), bool(res.terminated[0]), bool(res.truncated[0]), info
