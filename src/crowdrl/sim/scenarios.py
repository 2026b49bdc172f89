"""Episode initial states: circle- and square-crossing humans with spawn clearance.

Every random number comes from :mod:`crowdrl.sim.rng`, keyed by the episode, so an episode is
a pure function of (stream, seed, episode id), whatever the batch it is generated in.
Rejection sampling is vectorised: each human draws ``SPAWN_ROUNDS`` candidates at once and
takes the first valid one, in the order the reference simulator would have tried them.
"""

from __future__ import annotations

import math
from typing import Callable

import torch
from torch import Tensor

from crowdrl.sim import rng
from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.state import CrowdState

SPAWN_ROUNDS = 256  # candidates per human at spawn; exhausting them is an error
SPAWN_CHUNK = 16  # candidates drawn at once
GOAL_ROUNDS = 16  # candidates per new goal of a non-stop human; exhausting them keeps the last

# Index tags keeping the purposes of random draws apart.
_TAG_CIRCLE, _TAG_SQUARE_SIDE, _TAG_SQUARE_START, _TAG_SQUARE_GOAL, _TAG_NEW_GOAL = range(5)


class SpawnError(RuntimeError):
    """No valid start or goal was found within the bounded number of rejection rounds."""


def _circle_points(cfg: CrowdConfig, u_angle: Tensor, u_nx: Tensor, u_ny: Tensor) -> Tensor:
    angle = u_angle * (2 * math.pi)
    noise_x = (u_nx - 0.5) * cfg.human_v_pref
    noise_y = (u_ny - 0.5) * cfg.human_v_pref
    return torch.stack(
        (cfg.circle_radius * torch.cos(angle) + noise_x, cfg.circle_radius * torch.sin(angle) + noise_y), dim=-1
    )


def _square_points(cfg: CrowdConfig, side: Tensor, u_x: Tensor, u_y: Tensor) -> Tensor:
    half = cfg.square_width * 0.5
    return torch.stack((u_x * half * side, (u_y - 0.5) * cfg.square_width), dim=-1)


def _clear_of(points: Tensor, others: Tensor, valid_others: Tensor, min_dist: float) -> Tensor:
    """``points [B, R, 2]`` at least ``min_dist`` from every valid ``others [B, M, 2]``: ``[B, R]``."""
    if others.shape[1] == 0:
        return torch.ones(points.shape[:2], dtype=torch.bool, device=points.device)
    d = torch.linalg.vector_norm(points.unsqueeze(2) - others.unsqueeze(1), dim=-1)  # [B, R, M]
    return ((d >= min_dist) | ~valid_others.unsqueeze(1)).all(-1)


def _first_valid(
    draw: Callable[[Tensor], Tensor], is_ok: Callable[[Tensor], Tensor], what: str, human: int, device: torch.device
) -> Tensor:
    """Per episode, the first valid candidate in round order.

    ``draw(rounds)`` gives candidates ``[B, R, 2]`` for round indices ``rounds [R]``;
    ``is_ok(candidates)`` flags the valid ones ``[B, R]``. Rounds are tried in chunks so the
    common case costs one small chunk, while the answer is the same as trying them one by one.
    """
    result, found = None, None
    for first in range(0, SPAWN_ROUNDS, SPAWN_CHUNK):
        rounds = torch.arange(first, first + SPAWN_CHUNK, device=device)
        cand = draw(rounds)
        ok = is_ok(cand)
        pick = torch.gather(cand, 1, ok.to(torch.int8).argmax(-1).view(-1, 1, 1).expand(-1, 1, 2)).squeeze(1)
        hit = ok.any(-1)
        if result is None:
            result, found = pick, hit
        else:
            result = torch.where(found.unsqueeze(-1), result, pick)
            found = found | hit
        if bool(found.all()):
            return result
    n_bad = int((~found).sum())
    raise SpawnError(
        f"could not place the {what} of human {human} in {n_bad} episode(s) after {SPAWN_ROUNDS} "
        f"rejection rounds: the scenario is too crowded for its spawn clearance"
    )


def initial_states(cfg: CrowdConfig, episode_key: Tensor, dtype: torch.dtype = torch.float32) -> CrowdState:
    """Initial states of the episodes with keys ``episode_key [B]`` (see :func:`rng.episode_keys`)."""
    B, N = episode_key.shape[0], cfg.num_humans
    device = episode_key.device
    key = episode_key.view(B, 1)
    clearance = cfg.spawn_clearance

    robot_pos = torch.tensor([0.0, -cfg.circle_radius], dtype=dtype, device=device).expand(B, 2).clone()
    robot_goal = torch.tensor([0.0, cfg.circle_radius], dtype=dtype, device=device).expand(B, 2).clone()
    # Placed agents, robot first; positions and goals grow as humans are placed.
    positions = torch.zeros(B, N + 1, 2, dtype=dtype, device=device)
    goals = torch.zeros(B, N + 1, 2, dtype=dtype, device=device)
    positions[:, 0], goals[:, 0] = robot_pos, robot_goal
    placed = torch.zeros(B, N + 1, dtype=torch.bool, device=device)
    placed[:, 0] = True
    robot_clear = cfg.human_radius + cfg.robot_radius + cfg.discomfort_dist

    for h in range(N):
        # the robot needs robot_clear; other humans need clearance (both 0.8 m by default)
        def clear(points: Tensor, others: Tensor) -> Tensor:
            ok_robot = _clear_of(points, others[:, :1], placed[:, :1], robot_clear)
            return ok_robot & _clear_of(points, others[:, 1:], placed[:, 1:], clearance)

        if h < cfg.num_circle_humans:
            start = _first_valid(
                lambda r: _circle_points(cfg, *(rng.uniform(key, _TAG_CIRCLE, h, r, c, dtype=dtype) for c in range(3))),
                lambda p: clear(p, positions) & clear(p, goals),
                "start", h, device,
            )
            goal = -start
        else:
            side_u = rng.uniform(episode_key, _TAG_SQUARE_SIDE, h, dtype=dtype)
            side = torch.where(side_u > 0.5, -1.0, 1.0).to(dtype).view(B, 1)
            start = _first_valid(
                lambda r: _square_points(cfg, side, *(rng.uniform(key, _TAG_SQUARE_START, h, r, c, dtype=dtype) for c in range(2))),
                lambda p: clear(p, positions),
                "start", h, device,
            )
            goal = _first_valid(
                lambda r: _square_points(cfg, -side, *(rng.uniform(key, _TAG_SQUARE_GOAL, h, r, c, dtype=dtype) for c in range(2))),
                lambda p: clear(p, goals),
                "goal", h, device,
            )
        positions[:, h + 1], goals[:, h + 1] = start, goal
        placed[:, h + 1] = True

    return CrowdState(
        robot_position=robot_pos,
        robot_velocity=torch.zeros(B, 2, dtype=dtype, device=device),
        robot_heading=torch.full((B,), math.pi / 2, dtype=dtype, device=device),
        robot_goal=robot_goal,
        human_position=positions[:, 1:].clone(),
        human_velocity=torch.zeros(B, N, 2, dtype=dtype, device=device),
        human_goal=goals[:, 1:].clone(),
        human_goal_steps=torch.zeros(B, N, dtype=torch.int64, device=device),
        step_count=torch.zeros(B, dtype=torch.int64, device=device),
        episode_key=episode_key.clone(),
    )


def new_human_goals(cfg: CrowdConfig, state: CrowdState, needs_goal: Tensor) -> Tensor:
    """Goals ``[B, N, 2]`` for non-stop humans: fresh ones where ``needs_goal [B, N]``.

    Circle scenario: a fresh circle goal for every human; square scenario: a square goal on a
    random side. A new goal keeps the spawn clearance from every agent's position and goal
    when one of ``GOAL_ROUNDS`` candidates allows it; otherwise the last candidate is used (the
    episode must go on). Only the humans that need a goal are computed.
    """
    B, N = needs_goal.shape
    dtype, device = state.human_goal.dtype, state.device
    env, human = needs_goal.nonzero(as_tuple=True)  # [M]
    M = env.shape[0]
    rounds = torch.arange(GOAL_ROUNDS, device=device).view(1, GOAL_ROUNDS)
    key = state.episode_key[env].view(M, 1)
    step = state.step_count[env].view(M, 1)
    u = [rng.uniform(key, _TAG_NEW_GOAL, step, human.view(M, 1), rounds, c, dtype=dtype) for c in range(4)]
    if cfg.scenario == "circle":
        cand = _circle_points(cfg, u[0], u[1], u[2])  # [M, R, 2]
    else:
        side = torch.where(u[3] > 0.5, -1.0, 1.0).to(dtype)
        cand = _square_points(cfg, side, u[0], u[1])
    # clearance from every agent's position and goal, the robot's and the human's own included
    # (a goal next to where the human stands would be reached again at once)
    others_pos = torch.cat((state.robot_position.unsqueeze(1), state.human_position), 1)[env]  # [M, N+1, 2]
    others_goal = torch.cat((state.robot_goal.unsqueeze(1), state.human_goal), 1)[env]
    every = torch.ones(M, N + 1, dtype=torch.bool, device=device)
    ok = _clear_of(cand, others_pos, every, cfg.spawn_clearance) & _clear_of(cand, others_goal, every, cfg.spawn_clearance)
    ok[:, -1] = True
    first = ok.to(torch.int8).argmax(-1)
    chosen = torch.gather(cand, 1, first.view(M, 1, 1).expand(M, 1, 2)).squeeze(1)
    goals = state.human_goal.clone()
    goals[env, human] = chosen
    return goals
