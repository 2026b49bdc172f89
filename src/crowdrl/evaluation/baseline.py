"""The ORCA robot baseline on fixed test cases, through the one rollout path."""

from __future__ import annotations

from dataclasses import replace

import torch

from crowdrl.envs.crowd_nav import CrowdNavEnv
from crowdrl.evaluation.metrics import EpisodeMetrics
from crowdrl.evaluation.rollout import evaluate
from crowdrl.evaluation.trajectory import Trajectory
from crowdrl.policies import OrcaRobotPolicy
from crowdrl.sim.config import CrowdConfig


def evaluate_orca(config: CrowdConfig, *, split: str = "test", seed: int = 0, episodes: int = 1000,
                  batch: int = 1000, device: torch.device | str = "cpu", record_episode: int | None = None
                  ) -> tuple[EpisodeMetrics, Trajectory | None]:
    """:class:`OrcaRobotPolicy` on episodes ``0 .. episodes-1`` of ``split``/``seed`` of ``config``'s
    scenario (the robot holonomic, whatever ``config.robot_kinematics`` says).

    >>> metrics, _ = evaluate_orca(CrowdConfig("square"), episodes=10)  # doctest: +SKIP
    """
    cfg = replace(config, robot_kinematics="holonomic")
    env = CrowdNavEnv(cfg.scenario, num_envs=min(episodes, batch), num_humans=cfg.num_humans, config=cfg,
                      split=split, seed=seed, device=device)
    return evaluate(env, OrcaRobotPolicy(cfg), num_episodes=episodes, record_episode=record_episode)
