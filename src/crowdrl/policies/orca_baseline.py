"""The ORCA robot baseline (``SPEC.md`` §2), batched over episodes.

The robot runs its own ORCA among the humans it observes: holonomic, continuous velocity,
robot radius + 0.01, humans' radius + 0.01 + 0.2 safety space, humans' preferred velocities
zero (their goals are unknown to the robot), robot preferred velocity the unit vector to its
goal (shorter within 1 m). Only the robot's velocity is used.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.crowd import human_preferred_velocity
from crowdrl.sim.orca import orca_solve
from crowdrl.sim.state import CrowdState


@dataclass(frozen=True)
class OrcaRobotPolicy:
    """Batched ORCA robot policy: ``policy(cfg, state) -> (velocity [B, 2], heading [B] | None)``."""

    safety_space: float = 0.2
    radius_margin: float = 0.01

    def __post_init__(self) -> None:
        if self.safety_space < 0 or self.radius_margin < 0:
            raise ValueError("safety_space and radius_margin must be >= 0")

    def __call__(self, cfg: CrowdConfig, state: CrowdState) -> tuple[Tensor, Tensor | None]:
        B, N = state.batch_size, state.num_humans
        dtype, dev = state.robot_position.dtype, state.device
        positions = torch.cat((state.robot_position.unsqueeze(1), state.human_position), dim=1)
        velocities = torch.cat((state.robot_velocity.unsqueeze(1), state.human_velocity), dim=1)
        pref = torch.zeros_like(positions)
        pref[:, 0] = human_preferred_velocity(state.robot_position, state.robot_goal)
        radius = torch.full((B, N + 1), cfg.human_radius + self.radius_margin + self.safety_space, dtype=dtype, device=dev)
        radius[:, 0] = cfg.robot_radius + self.radius_margin
        max_speed = torch.full((B, N + 1), cfg.human_v_pref, dtype=dtype, device=dev)
        max_speed[:, 0] = cfg.robot_v_pref
        sol = orca_solve(
            positions, velocities, pref, radius, max_speed,
            time_step=cfg.time_step, neighbor_dist=cfg.orca_neighbor_dist,
            max_neighbors=cfg.orca_max_neighbors, time_horizon=cfg.orca_time_horizon,
        )
        return sol.velocities[:, 0], None
