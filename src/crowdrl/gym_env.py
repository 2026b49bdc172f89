"""A single-episode Gymnasium face of the simulator (``crowdrl/CircleCrossing-v0``, ...).

Imports only gymnasium, numpy, torch and :mod:`crowdrl.sim`, never torchrl: importing torchrl
sets multiprocessing's start method to ``"spawn"`` for the whole process, which a Gymnasium
user (``AsyncVectorEnv`` in an unguarded script) must not get from ``gym.make``.
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from crowdrl.sim import rng
from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.crowd import HUMAN_OBS_DIM, ROBOT_OBS_DIM, observe, step
from crowdrl.sim.obstacles import nearest_edges
from crowdrl.sim.kinematics import NUM_ACTIONS, action_table, decode_action
from crowdrl.sim.lidar import observe_lidar
from crowdrl.sim.scenarios import initial_states

SPLITS = tuple(rng.STREAMS)
RESET_OPTIONS = ("episode_id",)  # the keys reset(options=...) reads
MAX_EPISODE_ID = rng.MAX_SEED  # episode ids are int64: 0..2**63-1


class CrowdNavGymEnv(gym.Env):
    """One crowd-navigation episode at a time, for tools that speak Gymnasium.

    Observation: ``{"robot": (9,), "humans": (N, 5)}`` float32, world frame (in the obstacle scenarios also
    ``"obstacles"`` ``(K, 4)``, the nearest edges, and ``"obstacles_mask"`` ``(K,)``, as in ``CrowdNavEnv``; with
    ``lidar_rays = R > 0`` also ``"lidar"`` ``(R,)``, the robot's scan clipped at ``lidar_range``, as in
    ``CrowdNavEnv``: ``gym.make(id, lidar_rays=16)``). Action: one of 81
    unicycle actions, or with ``robot_kinematics="holonomic"`` a velocity in ``[-v_pref, v_pref]^2``
    (scaled down to ``v_pref`` if faster), both through :func:`crowdrl.sim.kinematics.decode_action`.
    Info (numbers only): ``event`` (0 running, 1 success, 2 collision, 3 timeout),
    ``min_separation``, ``discomfort_count``, ``episode_id``.
    The humans' model and whether they see the robot: ``gym.make(id, human_model="social_force",
    robot_visible=True)``, or a mixed crowd: ``gym.make(id, human_model="mixed", social_force_share=0.3,
    linear_share=0.2)`` (``CrowdConfig``'s keys; ORCA humans blind to the robot by default).

    ``reset(seed=s)`` selects scenario stream ``s`` of ``split`` and restarts its episode counter;
    the first reset without a seed draws the stream from ``self.np_random`` (OS entropy), so the
    sub-envs of an unseeded vector env play different episodes. Later resets take the stream's
    next episode; ``reset(options={"episode_id": i})`` loads episode ``i`` (``0 <= i <= 2**63-1``); any other
    option (a misspelt key, options that are no dict) is refused, naming it and the keys allowed.
    ``render_mode="rgb_array"``: :meth:`render` returns an ``HxWx3`` uint8 frame.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(
        self,
        scenario: str = "circle",
        num_humans: int = 10,
        split: str = "train",
        robot_kinematics: str = "unicycle",
        render_mode: str | None = None,
        lidar_rays: int = CrowdConfig.lidar_rays,
        lidar_range: float = CrowdConfig.lidar_range,
        human_model: str = CrowdConfig.human_model,
        robot_visible: bool = CrowdConfig.robot_visible,
        social_force_share: float = CrowdConfig.social_force_share,
        linear_share: float = CrowdConfig.linear_share,
    ) -> None:
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        self.config = CrowdConfig(scenario=scenario, num_humans=num_humans, robot_kinematics=robot_kinematics,
                                  lidar_rays=lidar_rays, lidar_range=lidar_range, human_model=human_model,
                                  robot_visible=robot_visible, social_force_share=social_force_share,
                                  linear_share=linear_share)
        self.split = split
        self.render_mode = render_mode
        N, v = self.config.num_humans, self.config.robot_v_pref
        self.observation_space = gym.spaces.Dict(
            {
                "robot": gym.spaces.Box(-np.inf, np.inf, (ROBOT_OBS_DIM,), np.float32),
                "humans": gym.spaces.Box(-np.inf, np.inf, (N, HUMAN_OBS_DIM), np.float32),
            }
        )
        K = self.config.num_obstacle_tokens
        if K > 0:  # obstacle scenarios: the edges nearest to the robot, as CrowdNavEnv's "obstacles"
            self.observation_space["obstacles"] = gym.spaces.Box(-np.inf, np.inf, (K, 4), np.float32)
            self.observation_space["obstacles_mask"] = gym.spaces.MultiBinary(K)
        if self.config.lidar_rays > 0:
            self.observation_space["lidar"] = gym.spaces.Box(0.0, self.config.lidar_range, (int(self.config.lidar_rays),),
                                                             np.float32)
        if self.config.robot_kinematics == "unicycle":
            self.action_space = gym.spaces.Discrete(NUM_ACTIONS)
        else:
            self.action_space = gym.spaces.Box(-v, v, (2,), np.float32)
        self._actions = action_table(v)
        self._stream_seed: int | None = None
        self._next_episode = 0
        self._episode = 0
        self._state = None
        self._ended: str | None = None  # "terminated" / "truncated": the episode is over until reset()

    def _obs(self) -> dict[str, np.ndarray]:
        robot, humans = observe(self.config, self._state)
        obs = {"robot": robot[0].numpy().astype(np.float32), "humans": humans[0].numpy().astype(np.float32)}
        s = self._state
        if s.has_obstacles:
            edges, mask = nearest_edges(s.robot_position, s.obstacles, s.obstacle_mask, self.config.num_obstacle_tokens)
            obs["obstacles"] = edges[0].numpy().astype(np.float32)
            obs["obstacles_mask"] = mask[0].numpy().astype(np.int8)
        if self.config.lidar_rays > 0:
            obs["lidar"] = observe_lidar(self.config, s)[0].numpy().astype(np.float32)
        return obs

    def _info(self, event: int = 0, min_separation: float = math.inf, discomfort_count: int = 0) -> dict[str, Any]:
        return {"event": event, "min_separation": min_separation, "discomfort_count": discomfort_count,
                "episode_id": self._episode}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer))
                                 or not 0 <= seed <= rng.MAX_SEED):  # never reduced modulo 2**64
            raise ValueError(f"seed must be None or an integer in 0..2**63-1, got {seed!r}")
        episode_option = self._episode_option(options)
        super().reset(seed=seed)
        if seed is not None:
            self._stream_seed = int(seed)
            self._next_episode = 0
        elif self._stream_seed is None:
            self._stream_seed = int(self.np_random.integers(rng.MAX_SEED))
            self._next_episode = 0
        episode = self._next_episode
        if episode_option is not None:
            episode = episode_option
        else:
            self._next_episode += 1
        key = rng.episode_keys(self.split, self._stream_seed, torch.tensor([episode]))
        self._state = initial_states(self.config, key)
        self._episode = episode
        self._ended = None
        return self._obs(), self._info()

    @staticmethod
    def _episode_option(options: Any) -> int | None:
        """``options["episode_id"]`` checked (``None``: not given); options that are no dict, or hold a key
        other than :data:`RESET_OPTIONS`, are refused naming it."""
        if options is None:
            return None
        allowed = ", ".join(RESET_OPTIONS)
        if not isinstance(options, dict):
            raise ValueError(f"options must be None or a dict with the keys {allowed}, got {options!r}")
        unknown = [key for key in options if key not in RESET_OPTIONS]
        if unknown:
            raise ValueError(f"options: unknown key(s) {', '.join(map(repr, unknown))}; allowed: {allowed}")
        if "episode_id" not in options:
            return None
        episode = options["episode_id"]
        if (isinstance(episode, (bool, np.bool_)) or not isinstance(episode, (int, np.integer))
                or not 0 <= episode <= MAX_EPISODE_ID):
            raise ValueError(f"options['episode_id'] must be an integer in 0..2**63-1 ({MAX_EPISODE_ID}), got {episode!r}")
        return int(episode)

    def _action_tensor(self, action: Any) -> torch.Tensor:
        """The action as the ``[1]`` index or ``[1, 2]`` velocity :func:`decode_action` takes."""
        if self.config.robot_kinematics == "unicycle":
            a = np.asarray(action)
            if a.shape != () or not np.issubdtype(a.dtype, np.integer) or not 0 <= int(a) < NUM_ACTIONS:
                raise ValueError(f"action must be an integer in 0..{NUM_ACTIONS - 1}, got {action!r}")
            return torch.tensor([int(a)])
        v = self.config.robot_v_pref
        try:
            a = np.asarray(action)
        except (TypeError, ValueError):  # a ragged sequence
            a = None
        # real numbers only: a complex velocity would lose its imaginary part to float64, a bool is no speed
        a = a.astype(np.float64) if a is not None and a.dtype.kind in "iuf" else None
        if a is None or a.shape != (2,) or not np.isfinite(a).all() or float(np.abs(a).max()) > v:
            raise ValueError(f"action must be a finite real velocity of shape (2,) in [-{v}, {v}]^2, got {action!r}")
        return torch.as_tensor(a, dtype=torch.float32).view(1, 2)

    def step(self, action):
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        if self._ended is not None:  # Gymnasium's contract: an ended episode is not stepped on
            raise RuntimeError(f"episode {self._episode} has {self._ended}: call reset() before step() "
                               f"(step() after the end of an episode is not defined)")
        velocity, heading = decode_action(self.config.robot_kinematics, self._action_tensor(action),
                                          self._state.robot_heading, self._actions, self.config.robot_v_pref)
        self._state, res = step(self.config, self._state, velocity, heading)
        info = self._info(int(res.event[0]), float(res.min_separation[0]), int(res.discomfort_count[0]))
        terminated, truncated = bool(res.terminated[0]), bool(res.truncated[0])
        if terminated or truncated:
            self._ended = "terminated" if terminated else "truncated"
        return self._obs(), float(res.reward[0]), terminated, truncated, info

    def render(self) -> np.ndarray | None:
        """The current state as an ``HxWx3`` uint8 frame (``render_mode="rgb_array"``), else ``None``."""
        if self.render_mode is None:
            return None
        if self._state is None:
            raise RuntimeError("call reset() before render()")
        from crowdrl.viz.frame import render_frame  # matplotlib only when rendering

        s, cfg = self._state, self.config
        return render_frame(
            s.robot_position[0].numpy(), s.robot_goal[0].numpy(), cfg.robot_radius,
            s.human_position[0].numpy(), cfg.human_radius, robot_heading=float(s.robot_heading[0]),
            half_width=max(cfg.circle_radius, cfg.square_width / 2) + 1.0,
            title=f"t = {int(s.step_count[0]) * cfg.time_step:.2f} s",
            obstacles=s.obstacle_polygons(0),
        )
