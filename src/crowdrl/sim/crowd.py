"""One step of B crowd-navigation episodes: ORCA humans, robot motion, events and reward.

Pure torch on :class:`CrowdState`; no TorchRL here (``crowdrl.envs`` wraps it).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.kinematics import wrap_angle
# the humans' motion models and preferred velocities (crowd's public names since before crowdrl.sim.humans)
from crowdrl.sim.humans import (doorway_waypoints, human_preferred_velocities,  # noqa: F401
                                human_preferred_velocity, human_velocities, preferred_velocities)
from crowdrl.sim.obstacles import ObstacleEdges, path_obstacle_distance
from crowdrl.sim.orca import require_finite
from crowdrl.sim.scenarios import new_human_goals
from crowdrl.sim.state import CrowdState

# Event codes of a step (``StepResult.event``).
RUNNING, SUCCESS, COLLISION, TIMEOUT = 0, 1, 2, 3
EVENT_NAMES = ("running", "success", "collision", "timeout")

ROBOT_OBS_DIM = 9  # px, py, vx, vy, radius, gx, gy, v_pref, heading
HUMAN_OBS_DIM = 5  # px, py, vx, vy, radius


class StepResult(NamedTuple):
    """What one step produced, per episode ``[B]`` (``min_separation`` in metres)."""

    reward: Tensor
    terminated: Tensor  # collision or goal
    truncated: Tensor  # time limit, not terminated
    event: Tensor  # int64: RUNNING, SUCCESS, COLLISION or TIMEOUT
    min_separation: Tensor  # closest robot-human surface distance during the step
    discomfort_count: Tensor  # int64: humans closer than discomfort_dist during the step
    human_lp_infeasible: Tensor  # [B, N] bool: a human's ORCA program fell back to 3-D
    # bool: the robot touched an obstacle during the step (a collision; None: no obstacles)
    obstacle_collision: Tensor | None = None


def closest_surface_distance(rel_position: Tensor, rel_velocity: Tensor, dt: float, radii: float) -> Tensor:
    """Closest distance of the segment ``p -> p + v*dt`` to the origin, minus ``radii``.

    ``rel_position``/``rel_velocity`` are ``[..., 2]`` (human relative to robot); the result is
    negative when the two discs touch at some time within the step.
    """
    seg = rel_velocity * dt
    seg_sq = (seg * seg).sum(-1)
    t = -(rel_position * seg).sum(-1) / torch.where(seg_sq > 0, seg_sq, torch.ones_like(seg_sq))
    t = t.clamp(0.0, 1.0)
    closest = rel_position + t.unsqueeze(-1) * seg
    return torch.linalg.vector_norm(closest, dim=-1) - radii


class StepReward(NamedTuple):
    """How one step of the robot is judged, per episode ``[...]``."""

    reward: Tensor
    collided: Tensor  # bool: the robot touched a present human (or an obstacle) during the step
    reached: Tensor  # bool: the robot ends the step within its radius of the goal
    min_separation: Tensor  # closest robot-human surface distance during the step (inf: no human present)
    discomfort_count: Tensor  # int64: present humans closer than discomfort_dist during the step
    obstacle_collision: Tensor | None = None  # bool: the robot touched an obstacle (None: none given)


def obstacle_hit(cfg: CrowdConfig, robot_position: Tensor, robot_velocity: Tensor, obstacles: Tensor,
                 obstacle_mask: Tensor) -> Tensor:
    """Continuous collision of the robot with obstacle edges over a step, ``[B]`` bool: the disc of
    ``cfg.robot_radius`` swept along ``p -> p + v * dt`` touches an edge (strictly closer than the
    radius, as with humans), so a fast robot cannot tunnel through a wall between two positions.

    ``robot_position``/``robot_velocity`` are ``[B, 2]``, or ``[B, M, 2]`` for ``M`` candidate steps
    per episode (a planner's; the result is then ``[B, M]``)."""
    single = robot_position.dim() == 2
    p0 = robot_position.unsqueeze(1) if single else robot_position
    p1 = p0 + (robot_velocity.unsqueeze(1) if single else robot_velocity) * cfg.time_step
    hit = path_obstacle_distance(p0, p1, obstacles, obstacle_mask) < cfg.robot_radius
    return hit.squeeze(1) if single else hit


def step_reward(cfg: CrowdConfig, robot_position: Tensor, robot_velocity: Tensor, robot_goal: Tensor,
                human_position: Tensor, human_velocity: Tensor, human_mask: Tensor | None = None,
                obstacles: Tensor | None = None, obstacle_mask: Tensor | None = None) -> StepReward:
    """The reward, collision and goal of a step (``docs/mdp.md``, "Reward"): the one definition
    that :func:`step` and any look-ahead (e.g. a planner's predicted crowd) use.

    Positions are at the start of the step; velocities hold over it (``dt = cfg.time_step``).
    Shapes: robot ``[..., 2]``, humans ``[..., N, 2]``, ``human_mask [..., N]`` bool (``True`` =
    present; absent humans neither collide, nor cause discomfort, nor enter the reward).
    ``obstacles [B, P, V, 2]`` with ``obstacle_mask [B, P, V]`` (robot ``[B, 2]`` or ``[B, M, 2]``): touching an
    obstacle edge during the step (:func:`obstacle_hit`) is a collision, with the same penalty.
    """
    dt = cfg.time_step
    rel_p = human_position - robot_position.unsqueeze(-2)
    rel_v = human_velocity - robot_velocity.unsqueeze(-2)
    surface = closest_surface_distance(rel_p, rel_v, dt, cfg.human_radius + cfg.robot_radius)  # [..., N]
    if human_mask is not None:
        surface = surface.masked_fill(~human_mask, float("inf"))
    min_sep = surface.amin(-1) if surface.shape[-1] else surface.new_full(surface.shape[:-1], float("inf"))
    collided = min_sep < 0
    wall = None
    if obstacles is not None and obstacles.shape[1] > 0:
        wall = obstacle_hit(cfg, robot_position, robot_velocity, obstacles, obstacle_mask)
        collided = collided | wall
    discomfort = (surface < cfg.discomfort_dist).sum(-1)
    robot_next = robot_position + robot_velocity * dt
    dist_before = torch.linalg.vector_norm(robot_position - robot_goal, dim=-1)
    dist_after = torch.linalg.vector_norm(robot_next - robot_goal, dim=-1)
    reached = dist_after < cfg.robot_radius
    # progress, discomfort (every present human, every step), and the terminal bonus/penalty
    reward = cfg.progress_factor * (dist_before - dist_after)
    reward = reward + torch.clamp(surface - cfg.discomfort_dist, max=0.0).sum(-1)
    reward = reward + torch.where(collided, cfg.collision_penalty, torch.where(reached, cfg.goal_reward, 0.0))
    return StepReward(reward, collided, reached, min_sep, discomfort, wall)


def step(cfg: CrowdConfig, state: CrowdState, robot_velocity: Tensor, robot_heading: Tensor | None = None,
         obstacle_edges: ObstacleEdges | None = None) -> tuple[CrowdState, StepResult]:
    """Advance every episode by one time step.

    Args:
        robot_velocity: ``[B, 2]`` the robot's velocity during this step (world frame).
        robot_heading: ``[B]`` the robot's heading after the step; defaults to the velocity's
            direction (unchanged when the robot stops).
        obstacle_edges: the processed edges of ``state.obstacles`` if at hand (the humans' ORCA
            processes the polygons on every step otherwise); ignored without obstacles.

    With obstacles in the state the humans' ORCA sees them and the robot collides with them
    (:func:`obstacle_hit`: the episode ends as a collision, with the collision penalty).

    Raises ``ValueError`` naming the argument for NaN or infinite ``robot_velocity`` or
    ``robot_heading`` (and, from the ORCA solver, for a non-finite humans' state).
    """
    B = state.batch_size
    if robot_velocity.shape != (B, 2):
        raise ValueError(f"robot_velocity must be shaped [{B}, 2], got {tuple(robot_velocity.shape)}")
    # NaN/inf in: a ValueError naming it (not a NaN reward with event "running"); the humans' state is
    # checked by the ORCA solver's own entry point
    given = {"robot_velocity": robot_velocity} if robot_heading is None else {"robot_velocity": robot_velocity,
                                                                             "robot_heading": robot_heading}
    require_finite(**given, **{"state.robot_position": state.robot_position, "state.robot_goal": state.robot_goal})
    if state.has_obstacles and (state.obstacles.device != state.device or state.obstacle_mask.device != state.device):
        raise ValueError(f"state.obstacles is on {state.obstacles.device} (mask on {state.obstacle_mask.device}) "
                         f"but the agents are on {state.device}")
    if robot_heading is None:
        speed = torch.linalg.vector_norm(robot_velocity, dim=-1)
        robot_heading = torch.where(
            speed > 0, torch.atan2(robot_velocity[:, 1], robot_velocity[:, 0]), state.robot_heading
        )
    # wrap to [-pi, pi): the observation stays bounded; cos/sin are unchanged
    robot_heading = wrap_angle(robot_heading)

    # absent humans (a crowd smaller than N) take no part: not in ORCA, collisions or the reward
    human_mask = state.human_mask if cfg.variable_crowd else None

    # 1. humans: ORCA from the state at the start of the step
    human_vel, lp_infeasible = human_velocities(cfg, state, obstacle_edges)

    # 2-4. move, and judge the step: collision over the relative motion, goal, reward
    check_vel = human_vel if cfg.collision_velocity == "new" else state.human_velocity
    judged = step_reward(cfg, state.robot_position, robot_velocity, state.robot_goal, state.human_position,
                         check_vel, human_mask, state.obstacles, state.obstacle_mask)
    collided, reached, reward = judged.collided, judged.reached, judged.reward
    min_sep, discomfort = judged.min_separation, judged.discomfort_count
    moved = advance(cfg, state, robot_velocity, robot_heading, human_vel)
    step_count = moved.step_count
    terminated = collided | reached
    truncated = ~terminated & (step_count >= cfg.max_steps)
    event = torch.where(
        collided, COLLISION, torch.where(reached, SUCCESS, torch.where(truncated, TIMEOUT, RUNNING))
    )
    result = StepResult(reward, terminated, truncated, event, min_sep, discomfort, lp_infeasible,
                        judged.obstacle_collision)
    return moved, result


def advance(cfg: CrowdConfig, state: CrowdState, robot_velocity: Tensor, robot_heading: Tensor,
            human_velocity: Tensor) -> CrowdState:
    """The state after a step whose velocities are known: everyone moves (``p + v·Δt``), the robot
    takes ``robot_heading`` (wrapped by the caller), and non-stop humans that stayed near their goal
    long enough get a new goal and stand still (:func:`~crowdrl.sim.scenarios.new_human_goals`).

    The one transition :func:`step` makes after the humans' velocities; a search that steps many
    robot actions against one crowd (:mod:`crowdrl.sim.oracle`) calls it too. The robot enters
    only through the new goals, which keep clear of its new position."""
    dt = cfg.time_step
    human_mask = state.human_mask if cfg.variable_crowd else None
    human_pos = state.human_position + human_velocity * dt
    # 5. non-stop humans: after enough steps near the goal, a new goal and a standstill
    near_goal = torch.linalg.vector_norm(human_pos - state.human_goal, dim=-1) < cfg.human_radius
    if human_mask is not None:
        near_goal = near_goal & human_mask
    goal_steps = state.human_goal_steps + near_goal.long()
    needs_goal = goal_steps >= cfg.goal_steps_before_new_goal
    moved = state.replace(
        robot_position=state.robot_position + robot_velocity * dt,
        robot_velocity=robot_velocity,
        robot_heading=robot_heading,
        human_position=human_pos,
        human_velocity=human_velocity,
        human_goal_steps=goal_steps,
        step_count=state.step_count + 1,
    )
    if bool(needs_goal.any()):
        moved = moved.replace(
            human_goal=new_human_goals(cfg, moved, needs_goal),
            human_velocity=torch.where(needs_goal.unsqueeze(-1), 0.0, human_velocity),
            human_goal_steps=torch.where(needs_goal, 0, goal_steps),
        )
    return moved


def observe(cfg: CrowdConfig, state: CrowdState) -> tuple[Tensor, Tensor]:
    """World-frame observation: robot ``[B, 9]`` and humans ``[B, N, 5]`` (the rows of absent
    humans are zeros, radius included; ``state.human_mask`` tells which are present)."""
    B, N = state.batch_size, state.num_humans
    dtype = state.robot_position.dtype
    robot = torch.cat(
        (
            state.robot_position,
            state.robot_velocity,
            torch.full((B, 1), cfg.robot_radius, dtype=dtype, device=state.device),
            state.robot_goal,
            torch.full((B, 1), cfg.robot_v_pref, dtype=dtype, device=state.device),
            state.robot_heading.unsqueeze(-1),
        ),
        dim=-1,
    )
    humans = torch.cat(
        (
            state.human_position,
            state.human_velocity,
            torch.full((B, N, 1), cfg.human_radius, dtype=dtype, device=state.device),
        ),
        dim=-1,
    )
    if cfg.variable_crowd:
        humans = humans * state.human_mask.unsqueeze(-1)
    return robot, humans
