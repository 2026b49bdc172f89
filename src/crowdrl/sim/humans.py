"""How the humans move: their preferred velocities and the motion models of ``CrowdConfig.human_model``.

* ``orca``: RVO2's ORCA among the humans (:mod:`crowdrl.sim.orca`), static obstacles included;
* ``social_force``: Helbing–Molnár social force as the ``socialforce`` package computes it
  (:mod:`crowdrl.sim.social_force`), open scenarios only;
* ``linear``: straight to the goal at the preferred speed, ignoring everyone (CrowdNav's ``linear``);
* ``mixed``: a crowd with a share of each (``CrowdConfig.social_force_share``, ``linear_share``, ORCA the
  rest), each human's model for the episode in ``CrowdState.human_model`` (drawn per episode:
  :func:`crowdrl.sim.scenarios.assign_human_models`).

A mixed crowd is what falls out of the single models naturally, in one batched step: each model that some
human of the batch follows computes its velocities over the whole crowd, exactly as it would for a crowd
of its own, and each human keeps its own model's answer. So an ORCA human treats every other present human,
whatever its model, as an ORCA neighbour with its current velocity (and, as ORCA does, expects it to take
half of the avoidance, which a linear human never does); a social-force human feels every other pedestrian
(inside the call's sub-steps the others move as social-force pedestrians, as a visible robot already does;
only the social-force humans' answers are kept); a linear human ignores everyone. A model no human of the
batch follows is not computed, so shares (0, 0) step exactly as ``orca``, (1, 0) as ``social_force`` and
(0, 1) as ``linear``.

With ``CrowdConfig.robot_visible`` the robot is one more agent to the humans: an ORCA neighbour with
its current velocity and radius (plus the ORCA margin), as CrowdNav's visible robot; one more
pedestrian to the social force, without a destination (its desired direction is its velocity's) and
with preferred speed ``robot_v_pref``. Its own answer is discarded; linear humans ignore it.
Every model computes all new velocities from the state at the start of the step; pure torch.
"""

from __future__ import annotations

import torch
from torch import Tensor

from crowdrl.sim.config import HUMAN_MODELS, MIXED, CrowdConfig
from crowdrl.sim.obstacles import ObstacleEdges
from crowdrl.sim.orca import OrcaParams, orca_solve
from crowdrl.sim.social_force import compiled_social_force_velocities, social_force_velocities
from crowdrl.sim.state import CrowdState


def human_preferred_velocity(position: Tensor, goal: Tensor) -> Tensor:
    """Vector to the goal, scaled to unit length when longer (CrowdNav's ORCA rule)."""
    to_goal = goal - position
    dist = torch.linalg.vector_norm(to_goal, dim=-1, keepdim=True)
    return torch.where(dist > 1, to_goal / dist.clamp_min(1e-12), to_goal)


def doorway_waypoints(cfg: CrowdConfig, position: Tensor, goal: Tensor) -> Tensor:
    """``doorway``: where a human heads for, ``[..., 2]``: its goal once on the goal's side of the wall,
    before that the point of the gap (``y = 0``, ``|x| <= doorway_gap / 2 - human_radius - margin``)
    nearest to where its straight line to the goal crosses the wall's line. A pure function of the
    position and goal (no state): on a straight line through the gap it is a point of that line, so
    the human walks straight as without it; a human pushed off its line walks back into the gap
    instead of pressing against the wall (ORCA avoids obstacles but does not plan around them)."""
    py, gy = position[..., 1], goal[..., 1]
    crossing = py * gy < 0
    t = py / torch.where(crossing, py - gy, torch.ones_like(py))
    x = position[..., 0] + t * (goal[..., 0] - position[..., 0])
    inner = cfg.doorway_gap / 2 - cfg.human_radius - cfg.obstacle_clearance_margin
    waypoint = torch.stack((x.clamp(-inner, inner), torch.zeros_like(x)), -1)
    return torch.where(crossing.unsqueeze(-1), waypoint, goal)


def human_preferred_velocities(cfg: CrowdConfig, state: CrowdState) -> Tensor:
    """The humans' preferred velocities in ``state``: :func:`preferred_velocities` of their positions
    and goals."""
    return preferred_velocities(cfg, state.human_position, state.human_goal)


def preferred_velocities(cfg: CrowdConfig, position: Tensor, goal: Tensor) -> Tensor:
    """Preferred velocities ``[..., 2]`` of humans at ``position`` heading for ``goal`` (``[..., 2]``):
    :func:`human_preferred_velocity` towards the goal; in ``doorway`` the same speed, towards
    :func:`doorway_waypoints` (the gap) while the wall is between a human and its goal. A pure
    function (the reference simulator of the tests calls it too, ``experiments/crowdrl_testing/reference.py``)."""
    pref = human_preferred_velocity(position, goal)
    if cfg.scenario != "doorway":
        return pref
    to = doorway_waypoints(cfg, position, goal) - position
    dist = torch.linalg.vector_norm(to, dim=-1, keepdim=True)
    speed = torch.linalg.vector_norm(pref, dim=-1, keepdim=True)
    return torch.where(dist > 1e-6, to / dist.clamp_min(1e-12) * speed, pref)



def human_velocities(cfg: CrowdConfig, state: CrowdState, obstacle_edges: ObstacleEdges | None = None
                     ) -> tuple[Tensor, Tensor]:
    """The humans' new velocities ``[B, N, 2]`` under ``cfg.human_model``, and ``[B, N]`` bool: whose ORCA
    program fell back to 3-D (all false for the other models' humans). Absent humans (``state.human_mask``)
    are nobody's neighbours and keep their velocity. ``"mixed"``: :func:`mixed_humans`.

    ``obstacle_edges``: the processed edges of ``state.obstacles`` if at hand (ORCA only; else the
    polygons are processed here)."""
    if cfg.human_model == MIXED:
        return mixed_humans(cfg, state, obstacle_edges)
    if cfg.human_model == "orca":
        return orca_humans(cfg, state, obstacle_edges)
    velocities = social_force_humans(cfg, state) if cfg.human_model == "social_force" else linear_humans(cfg, state)
    return velocities, torch.zeros(state.human_mask.shape, dtype=torch.bool, device=state.device)


def mixed_humans(cfg: CrowdConfig, state: CrowdState, obstacle_edges: ObstacleEdges | None = None
                 ) -> tuple[Tensor, Tensor]:
    """A mixed crowd's new velocities ``[B, N, 2]`` and ORCA fall-backs ``[B, N]`` (those of its ORCA humans):
    each model that a present human of the batch follows (``state.human_model``) computed over the whole
    crowd, the robot included as that model sees it (:func:`orca_humans`, :func:`social_force_humans`,
    :func:`linear_humans`), and each human given its own model's answer (module docstring)."""
    if state.human_model is None:
        raise ValueError("state.human_model is None: a crowd with human_model='mixed' needs each human's model "
                         "(crowdrl.sim.scenarios.initial_states draws it)")
    model = state.human_model
    present = state.human_mask if cfg.variable_crowd else torch.ones_like(state.human_mask)
    # which models some present human of the batch follows: one host sync, and no model computed for nobody
    used = torch.stack([(present & (model == code)).any() for code in range(len(HUMAN_MODELS))]).tolist()
    velocities = state.human_velocity
    infeasible = torch.zeros(state.human_mask.shape, dtype=torch.bool, device=state.device)
    orca, social_force, linear = (HUMAN_MODELS.index(m) for m in ("orca", "social_force", "linear"))
    if used[orca]:
        mine = (model == orca).unsqueeze(-1)
        orca_velocity, orca_infeasible = orca_humans(cfg, state, obstacle_edges)
        velocities = torch.where(mine, orca_velocity, velocities)
        infeasible = orca_infeasible & mine.squeeze(-1)
    if used[social_force]:
        velocities = torch.where((model == social_force).unsqueeze(-1), social_force_humans(cfg, state), velocities)
    if used[linear]:
        velocities = torch.where((model == linear).unsqueeze(-1), linear_humans(cfg, state), velocities)
    return velocities, infeasible


def _with_robot(humans: Tensor, robot: Tensor) -> Tensor:
    """``[B, N, ...]`` humans' values followed by the robot's ``[B, ...]``: ``[B, N + 1, ...]``."""
    return torch.cat((humans, robot.unsqueeze(1)), 1)


def orca_humans(cfg: CrowdConfig, state: CrowdState, obstacle_edges: ObstacleEdges | None = None
                ) -> tuple[Tensor, Tensor]:
    """ORCA velocities of the humans among themselves, and with ``cfg.robot_visible`` with the robot as
    agent ``N`` (last, so neighbour ties go to the humans first, as RVO2 with the robot added last).

    With obstacles in the state (``state.obstacles``, ``P > 0``) the humans' ORCA sees them too,
    with ``cfg.orca_time_horizon_obst``."""
    if cfg.orca_backend == "compiled":
        from crowdrl.sim.orca_compiled import compiled_orca_solve as solve
    else:
        solve = orca_solve
    B, N = state.batch_size, state.num_humans
    dtype, device = state.human_position.dtype, state.device
    mask = state.human_mask if cfg.variable_crowd else None
    position, velocity = state.human_position, state.human_velocity
    pref = human_preferred_velocities(cfg, state)
    radius = torch.full((B, N), cfg.human_radius + cfg.orca_radius_margin, dtype=dtype, device=device)
    max_speed = torch.full_like(radius, cfg.human_v_pref)
    if cfg.robot_visible:
        position = _with_robot(position, state.robot_position)
        velocity = _with_robot(velocity, state.robot_velocity)
        pref = _with_robot(pref, state.robot_velocity)  # the robot's own answer is discarded
        radius = _with_robot(radius, radius.new_full((B,), cfg.robot_radius + cfg.orca_radius_margin))
        max_speed = _with_robot(max_speed, max_speed.new_full((B,), cfg.robot_v_pref))
        if mask is not None:
            mask = _with_robot(mask, mask.new_ones(B))
    sol = solve(
        position, velocity, pref, radius, max_speed,
        OrcaParams.from_config(cfg),
        mask=mask,
        **_orca_obstacles(cfg, state, obstacle_edges),
    )
    return sol.velocities[:, :N], sol.lp_infeasible[:, :N]


def _orca_obstacles(cfg: CrowdConfig, state: CrowdState, edges: ObstacleEdges | None) -> dict:
    """The obstacle arguments of the ORCA solver: none for open scenarios (bit-identical to before)."""
    if not state.has_obstacles:
        return {}
    if edges is not None:
        return {"obstacles": edges}
    return {"obstacles": state.obstacles, "obstacle_mask": state.obstacle_mask}


def social_force_humans(cfg: CrowdConfig, state: CrowdState) -> Tensor:
    """Social-force velocities of the humans (:func:`crowdrl.sim.social_force.social_force_velocities`
    with ``cfg``'s ``sf_*`` parameters over one time step; its compiled form under
    ``orca_backend="compiled"``), the robot one more pedestrian when visible."""
    B, N = state.batch_size, state.num_humans
    position, velocity, goal = state.human_position, state.human_velocity, state.human_goal
    speed = torch.full((B, N), cfg.human_v_pref, dtype=position.dtype, device=state.device)
    mask = state.human_mask if cfg.variable_crowd else None
    has_goal = None
    if cfg.robot_visible:
        position = _with_robot(position, state.robot_position)
        velocity = _with_robot(velocity, state.robot_velocity)
        goal = _with_robot(goal, state.robot_position)  # unused: the robot has no destination to them
        speed = _with_robot(speed, speed.new_full((B,), cfg.robot_v_pref))
        has_goal = torch.ones(B, N + 1, dtype=torch.bool, device=state.device)
        has_goal[:, N] = False
        if mask is not None:
            mask = _with_robot(mask, mask.new_ones(B))
    solve = compiled_social_force_velocities if cfg.orca_backend == "compiled" else social_force_velocities
    velocities = solve(
        position, velocity, goal, speed, time_step=cfg.time_step, substeps=cfg.sf_substeps, tau=cfg.sf_tau,
        v0=cfg.sf_v0, sigma=cfg.sf_sigma, has_goal=has_goal, mask=mask)
    return velocities[:, :N]


def linear_humans(cfg: CrowdConfig, state: CrowdState) -> Tensor:
    """Straight to the goal at ``human_v_pref`` (in ``doorway`` through the gap, as the preferred velocity
    heads), ignoring everyone; the last step lands on the goal instead of passing it."""
    position, goal = state.human_position, state.human_goal
    pref = preferred_velocities(cfg, position, goal)
    norm = torch.linalg.vector_norm(pref, dim=-1, keepdim=True)
    direction = pref / torch.where(norm > 0, norm, torch.ones_like(norm))
    dist = torch.linalg.vector_norm(goal - position, dim=-1, keepdim=True)
    velocity = direction * torch.clamp(dist / cfg.time_step, max=cfg.human_v_pref)
    if cfg.variable_crowd:
        velocity = torch.where(state.human_mask.unsqueeze(-1), velocity, state.human_velocity)
    return velocity
