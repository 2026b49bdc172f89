"""The ORCA robot baseline (``docs/mdp.md``), a TorchRL policy on the world-frame observation.

The robot runs its own ORCA among the humans it observes: holonomic, continuous velocity,
robot radius + 0.01, humans' radius + 0.01 + 0.2 safety space, humans' preferred velocities
zero (their goals are unknown to the robot), robot preferred velocity the unit vector to its
goal (shorter within 1 m). Only the robot's velocity is used: it is written as ``"action"`` for
a ``CrowdNavEnv`` with ``robot_kinematics="holonomic"``.

Among static obstacles (corridor, doorway, room) the robot sees them as RVO2 does: the episode's
whole map (``"obstacle_polygons"`` with its mask, as the env observes it) gives obstacle ORCA
lines before the agent lines, with ``config.orca_time_horizon_obst`` (``use_obstacles=False``
ignores them, the open-space baseline).

>>> from crowdrl.envs import CrowdNavEnv
>>> env = CrowdNavEnv("circle", num_envs=4, robot_kinematics="holonomic")
>>> rollout = env.rollout(10, OrcaRobotPolicy(env.config))
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import Tensor

from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.crowd import human_preferred_velocity
from crowdrl.sim.orca import OrcaParams, orca_solve


class OrcaRobotPolicy(TensorDictModuleBase):
    """Batched ORCA robot: reads ``"robot"`` ``[B, 9]``, ``"humans"`` ``[B, N, 5]`` (world
    frame, as ``CrowdNavEnv`` emits them) and ``"humans_mask"`` ``[B, N]`` when present, writes
    the velocity ``"action"`` ``[B, 2]``.

    ``config`` supplies the ORCA parameters (time step, neighbour distance and count, time
    horizon) and the humans' maximum speed the robot assumes; positions, velocities, radii, the
    goal and the robot's preferred speed come from the observation.
    """

    def __init__(self, config: CrowdConfig | None = None, *, safety_space: float = 0.2,
                 radius_margin: float = 0.01, use_obstacles: bool = True) -> None:
        super().__init__()
        if safety_space < 0 or radius_margin < 0:
            raise ValueError("safety_space and radius_margin must be >= 0")
        self.config = config or CrowdConfig()
        self.safety_space = safety_space
        self.radius_margin = radius_margin
        self.use_obstacles = bool(use_obstacles)
        self.in_keys = ["robot", "humans"]
        self.out_keys = ["action"]

    def velocity(self, robot: Tensor, humans: Tensor, humans_mask: Tensor | None = None,
                 obstacles: Tensor | None = None, obstacles_mask: Tensor | None = None) -> Tensor:
        """The robot's ORCA velocity ``[B, 2]`` for world-frame observations (absent humans,
        ``humans_mask [B, N]`` False, are not its neighbours); ``obstacles`` ``[B, P, V, 2]`` are
        RVO2 polygons with their vertex mask ``[B, P, V]`` (``None``: open space)."""
        cfg = self.config
        positions = torch.cat((robot[:, None, 0:2], humans[..., 0:2]), dim=1)
        velocities = torch.cat((robot[:, None, 2:4], humans[..., 2:4]), dim=1)
        pref = torch.zeros_like(positions)
        pref[:, 0] = human_preferred_velocity(robot[:, 0:2], robot[:, 5:7])
        radius = torch.cat((robot[:, None, 4] + self.radius_margin,
                            humans[..., 4] + (self.radius_margin + self.safety_space)), dim=1)
        max_speed = torch.full_like(radius, cfg.human_v_pref)
        max_speed[:, 0] = robot[:, 7]
        mask = None
        if humans_mask is not None and not bool(humans_mask.all()):
            mask = torch.cat((torch.ones_like(humans_mask[:, :1]), humans_mask), dim=1)
        sol = orca_solve(
            positions, velocities, pref, radius, max_speed, OrcaParams.from_config(cfg), mask=mask,
            obstacles=obstacles, obstacle_mask=None if obstacles is None else obstacles_mask,
        )
        return sol.velocities[:, 0]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        polygons = tensordict.get("obstacle_polygons", None) if self.use_obstacles else None
        tensordict.set("action", self.velocity(
            tensordict.get("robot"), tensordict.get("humans"), tensordict.get("humans_mask", None),
            polygons, None if polygons is None else tensordict.get("obstacle_polygons_mask")))
        return tensordict
