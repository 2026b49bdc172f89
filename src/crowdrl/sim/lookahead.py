"""The one-step model of the robot: what happens when action ``a`` is taken from an observed state,
given the humans' next state. One definition, used by the online planner (the humans predicted)
and by counterfactual experience (the humans' real next state, exact while they ignore the robot).

Pure torch on world-frame observation rows (:func:`crowdrl.sim.crowd.observe`'s layout: robot
``[..., 9]`` = px, py, vx, vy, r, gx, gy, v_pref, heading; humans ``[..., N, 5]`` = px, py, vx, vy, r).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.crowd import StepReward, step_reward
from crowdrl.sim.kinematics import decode_action, wrap_angle


class LookAhead(NamedTuple):
    """The step of ``w`` candidate actions from each of ``M`` states."""

    robot_next: Tensor  # [M, w, 9]: the robot's observation row after the step (heading unwrapped)
    judged: StepReward  # [M, w]: reward, collision, goal of the step (simulator's step_reward)


def look_ahead(cfg: CrowdConfig, table: Tensor, robot: Tensor, humans: Tensor, humans_next: Tensor, actions: Tensor,
               humans_mask: Tensor | None = None, walls: Tensor | None = None,
               walls_mask: Tensor | None = None) -> LookAhead:
    """The robot's next observation row and the step's judgement for unicycle ``actions [M, w]``
    (indices into ``table``, :func:`crowdrl.sim.kinematics.action_table`) from ``robot [M, 9]``,
    ``humans [M, N, 5]``, the humans moving to ``humans_next [M, N, 5]`` over the step.

    The robot moves by the simulator's kinematics (:func:`~crowdrl.sim.kinematics.decode_action`,
    then ``p + v·Δt``); the step is judged by :func:`~crowdrl.sim.crowd.step_reward` against the
    humans' motion: their velocity over the step is the displacement over ``Δt`` (the velocity ORCA
    gave them), or their velocity at the start when ``cfg.collision_velocity == "start"``, as the
    simulator judges collisions. ``walls [M, P, V, 2]`` with ``walls_mask [M, P, V]``: obstacle
    polygons the robot's swept disc must not touch (the episode's map for an exact step, or a
    planner's observed edges as 2-vertex polygons). The heading of ``robot_next`` is not wrapped
    (:func:`~crowdrl.sim.kinematics.wrap_angle` gives the simulator's).
    """
    if actions.dim() != 2 or actions.shape[0] != robot.shape[0]:
        raise ValueError(f"actions must be shaped [M, w] with M = {robot.shape[0]} states (robot's rows), "
                         f"got {tuple(actions.shape)}")
    dt = cfg.time_step
    M, w = actions.shape
    N = humans.shape[-2]
    velocity, heading = decode_action("unicycle", actions.reshape(-1), robot[:, 8:9].expand(M, w).reshape(-1),
                                      table.to(robot.dtype), cfg.robot_v_pref)
    velocity, heading = velocity.reshape(M, w, 2), heading.reshape(M, w, 1)
    position = robot[:, None, 0:2].expand(M, w, 2)
    robot_next = torch.cat((position + velocity * dt, velocity, robot[:, None, 4:8].expand(M, w, 4), heading), -1)
    if cfg.collision_velocity == "start":
        human_velocity = humans[..., 2:4]
    else:
        human_velocity = (humans_next[..., 0:2] - humans[..., 0:2]) / dt
    mask_w = None if humans_mask is None else humans_mask[:, None].expand(M, w, N)
    judged = step_reward(cfg, position, velocity, robot[:, None, 5:7].expand(M, w, 2),
                         humans[:, None, :, 0:2].expand(M, w, N, 2), human_velocity[:, None].expand(M, w, N, 2),
                         mask_w, walls, walls_mask)
    return LookAhead(robot_next, judged)


__all__ = ["LookAhead", "look_ahead", "wrap_angle"]
