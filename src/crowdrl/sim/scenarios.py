"""Episode initial states: circle- and square-crossing humans with spawn clearance.

Every random number comes from :mod:`crowdrl.sim.rng`, keyed by the episode, so an episode is
a pure function of (stream, seed, episode id), whatever the batch it is generated in.
Rejection sampling is vectorised: each human tries up to ``SPAWN_ROUNDS`` candidates and takes
the first valid one, in the order the reference simulator would have tried them; the rounds
are evaluated in chunks sized to the observed acceptance rate, for the episodes still searching.
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
GOAL_ROUNDS = 16  # candidates per new goal of a non-stop human; exhausting them keeps the last
# Chunk sizing of the spawn rejection rounds (speed only: the result does not depend on them).
_CHUNK_HITS = 1.5  # a chunk holds this many expected valid candidates per searching episode
_MIN_CANDIDATES = 512  # few episodes left: draw at least this many candidates in all
_FIRST_DRAWS = 1 << 18  # uniforms of up to 16 first rounds drawn for every human at once (small batches)
_MAX_PAIRS = 1 << 21  # candidate-agent distances per chunk, bounding its memory

# Index tags keeping the purposes of random draws apart.
_TAG_SPAWN, _TAG_NEW_GOAL, _TAG_CROWD_SIZE = range(3)
# Where absent humans (a crowd smaller than its maximum) stand: far from everything, still.
_PARKED = 1.0e4
# Components of a spawn round: 0-2 circle start (angle, x noise, y noise), 3-4 square start,
# 5-6 square goal, 7 square side (read from round 0).
_SPAWN_COMPONENTS = 8


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


def _distances(points: Tensor, others: Tensor) -> Tensor:
    """Euclidean distances ``[M, A, R]`` (others first) of ``points [A, R, 2]`` to ``others [A, M, 2]``.

    Elementwise ``sqrt(dx*dx + dy*dy)`` with the others outermost, so that the arithmetic and a reduction over
    them run along contiguous memory: on these small shapes several times cheaper than ``linalg.vector_norm``
    over a size-2 dimension (whose result can differ from this in the last bit: a clearance decision only
    changes for a candidate within rounding of the limit; none did in 80k spawned episodes). Test clearance as
    ``d.amin(0) >= limit`` (exact; a NaN fails it), which is cheaper than comparing every distance.
    """
    px, py = points.unbind(-1)
    ox, oy = others.transpose(0, 1).unsqueeze(-1).unbind(-2)  # [M, A, 1] each
    dx, dy = px - ox, py - oy
    return torch.sqrt(dx * dx + dy * dy)


def _clear_of(points: Tensor, others: Tensor, min_dist: float) -> Tensor:
    """``points [B, R, 2]`` at least ``min_dist`` from every one of ``others [B, M, 2]`` (M >= 1): ``[B, R]``."""
    return _distances(points, others).amin(0) >= min_dist


def _spawn_uniforms(
    spawn_key: Tensor, humans: Tensor | int, first_round: int, rounds: int, components: range, dtype: torch.dtype
) -> Tensor:
    """Spawn draws of ``components``, rounds ``first_round ..``: ``[B, rounds, C]`` for one human,
    ``[B, H, rounds, C]`` for ``humans [H]``.

    ``spawn_key [B]`` is ``rng.fold(episode_key, _TAG_SPAWN)``, folded once for every draw.
    """
    device = spawn_key.device
    r = torch.arange(first_round, first_round + rounds, device=device).view(rounds, 1)
    c = torch.arange(components.start, components.stop, device=device)
    if isinstance(humans, Tensor):
        humans = humans.view(-1, 1, 1)
    index = (humans * SPAWN_ROUNDS + r) * _SPAWN_COMPONENTS + c
    return rng.uniform(spawn_key.view((-1,) + (1,) * index.dim()), index, dtype=dtype)


def _first_valid(candidates: Tensor, ok: Tensor) -> tuple[Tensor, Tensor]:
    """Per episode, the first candidate ``[B, R, 2]`` flagged in ``ok [B, R]``, and whether any was."""
    first = ok.to(torch.int8).argmax(-1)
    pick = torch.gather(candidates, 1, first.view(-1, 1, 1).expand(-1, 1, 2)).squeeze(1)
    return pick, ok.any(-1)


def _chunk_rounds(searching: int, agents: int, accept: float, rounds_left: int) -> int:
    """Rounds to draw at once for ``searching`` episodes, given the acceptance rate seen so far."""
    rounds = math.ceil(_CHUNK_HITS / max(accept, 1e-3))
    searching = max(searching, 1)
    rounds = max(rounds, math.ceil(_MIN_CANDIDATES / searching))
    rounds = min(rounds, max(1, _MAX_PAIRS // (searching * agents)))
    return max(1, min(rounds, rounds_left))


def crowd_sizes(cfg: CrowdConfig, episode_key: Tensor) -> Tensor:
    """Humans present in each episode ``[B]`` int64: ``cfg.num_humans``, or with
    ``cfg.min_humans`` set, a uniform draw from ``min_humans..num_humans`` keyed by the episode."""
    if not cfg.variable_crowd:
        return torch.full(episode_key.shape, cfg.num_humans, dtype=torch.int64, device=episode_key.device)
    u = rng.uniform(episode_key, _TAG_CROWD_SIZE, dtype=torch.float64)
    span = cfg.num_humans - cfg.min_humans + 1
    return cfg.min_humans + torch.clamp((u * span).long(), max=span - 1)


def initial_states(cfg: CrowdConfig, episode_key: Tensor, dtype: torch.dtype = torch.float32) -> CrowdState:
    """Initial states of the episodes with keys ``episode_key [B]`` (see :func:`rng.episode_keys`).

    Humans are placed one after the other, each start (and goal) the first of its rejection
    rounds that keeps the clearance from everything placed before it, robot included. Rounds
    are drawn in chunks only for the human being placed and the episodes that have not found
    a valid candidate yet, so the result equals trying rounds one by one, episode by episode.

    A crowd of variable size (``cfg.min_humans``) has its first :func:`crowd_sizes` humans present;
    as each human is placed clear of those before it only, they stand exactly where the same
    episode's humans stand with a fixed crowd of that size. Absent humans are not placed: they
    stand still, far away, and ``human_mask`` marks them.
    """
    B, N = episode_key.shape[0], cfg.num_humans
    device = episode_key.device
    clearance = cfg.spawn_clearance
    robot_clear = cfg.human_radius + cfg.robot_radius + cfg.discomfort_dist

    robot_pos = torch.tensor([0.0, -cfg.circle_radius], dtype=dtype, device=device).expand(B, 2).clone()
    robot_goal = torch.tensor([0.0, cfg.circle_radius], dtype=dtype, device=device).expand(B, 2).clone()
    # Placed agents, robot first; positions and goals grow as humans are placed.
    positions = torch.zeros(B, N + 1, 2, dtype=dtype, device=device)
    goals = torch.zeros(B, N + 1, 2, dtype=dtype, device=device)
    positions[:, 0], goals[:, 0] = robot_pos, robot_goal
    spawn_key = rng.fold(episode_key, _TAG_SPAWN)  # rng.uniform(key, tag, i) == rng.uniform(fold(key, tag), i)
    humans = torch.arange(N, device=device)
    # Small batches: the first rounds of every human in one draw [B, N, R0, 8], as per-human
    # draws would cost more in call overhead than in arithmetic.
    first_rounds = min(16, _FIRST_DRAWS // max(B * N * _SPAWN_COMPONENTS, 1))
    chunk0 = None
    if first_rounds:
        chunk0 = _spawn_uniforms(spawn_key, humans, 0, first_rounds, range(_SPAWN_COMPONENTS), dtype)
        u_side = chunk0[:, :, 0, 7]
    else:
        u_side = _spawn_uniforms(spawn_key, humans, 0, 1, range(7, 8), dtype)[:, :, 0, 0]
    side = torch.where(u_side > 0.5, -1.0, 1.0).to(dtype).unsqueeze(-1)  # [B, N, 1]
    accept = 1.0  # acceptance rate in the last placement's first chunk, sizing the next first chunk

    def clear(points: Tensor, others: Tensor) -> Tensor:
        """``points [A, R, 2]`` clear of the robot (``others[:, 0]``) and the placed humans."""
        d = _distances(points, others)  # [h+1, A, R]
        ok = d[0] >= robot_clear
        return ok & (d[1:].amin(0) >= clearance) if d.shape[0] > 1 else ok

    def place(h: int, what: str, components: range, make: Callable[[Tensor | slice, Tensor], Tensor],
              others: list[Tensor], among: Tensor | None) -> Tensor:
        """The first valid of ``make(episodes, uniforms)``'s candidates, ``[B, 2]``, in the
        episodes ``among`` (all when ``None``; the others keep the parked position)."""
        nonlocal accept
        result = torch.full((B, 2), _PARKED, dtype=dtype, device=device)
        # those still searching: all (or ``among``), then an index
        episodes: Tensor | slice = slice(None) if among is None else among
        A, first, rate = (B if among is None else among.shape[0]), 0, accept
        agents = sum(o.shape[1] for o in others)
        while True:
            if first == 0 and chunk0 is not None:
                rounds, u = first_rounds, chunk0[episodes, h, :, components.start:components.stop]
            else:
                rounds = _chunk_rounds(A, agents, rate, SPAWN_ROUNDS - first)
                u = _spawn_uniforms(spawn_key[episodes], h, first, rounds, components, dtype)
            cand = make(episodes, u)
            ok = clear(cand, others[0][episodes])
            for extra in others[1:]:
                ok = ok & clear(cand, extra[episodes])
            pick, hit = _first_valid(cand, ok)
            result[episodes] = pick  # searching episodes overwrite it until they find one
            hits, valid = torch.stack((hit.sum(), ok.sum())).tolist()  # the chunk's one host sync
            rate = valid / max(A * rounds, 1)
            if first == 0:
                accept = rate
            first += rounds
            if hits == A:
                return result
            if first >= SPAWN_ROUNDS:
                raise SpawnError(
                    f"could not place the {what} of human {h} in {A - hits} episode(s) after "
                    f"{SPAWN_ROUNDS} rejection rounds: the scenario is too crowded for its spawn clearance"
                )
            # the episodes still searching, in order, without a further sync
            keep = torch.sort(hit.to(torch.uint8), stable=True).indices[: A - hits]
            episodes = keep if isinstance(episodes, slice) else episodes[keep]
            A -= hits

    sizes = crowd_sizes(cfg, episode_key)
    human_mask = torch.arange(N, device=device) < sizes.unsqueeze(-1)  # [B, N]
    min_present = cfg.min_humans if cfg.variable_crowd else N
    parked = torch.tensor(_PARKED, dtype=dtype, device=device)
    for h in range(N):
        among = None if h < min_present else human_mask[:, h].nonzero().squeeze(-1)
        if among is not None and among.shape[0] == 0:
            positions[:, h + 1] = goals[:, h + 1] = parked  # absent everywhere (stays apart from all)
            continue
        placed_pos, placed_goals = positions[:, : h + 1], goals[:, : h + 1]
        if h < cfg.num_circle_humans:
            start = place(h, "start", range(0, 3), lambda e, u: _circle_points(cfg, u[..., 0], u[..., 1], u[..., 2]),
                          [placed_pos, placed_goals], among)
            goal = -start
        else:
            start = place(h, "start", range(3, 5), lambda e, u: _square_points(cfg, side[e, h], u[..., 0], u[..., 1]),
                          [placed_pos], among)
            goal = place(h, "goal", range(5, 7), lambda e, u: _square_points(cfg, -side[e, h], u[..., 0], u[..., 1]),
                         [placed_goals], among)
        if among is not None:  # absent humans: parked, goal where they stand
            here = human_mask[:, h].unsqueeze(-1)
            start, goal = torch.where(here, start, parked), torch.where(here, goal, parked)
        positions[:, h + 1], goals[:, h + 1] = start, goal

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
        human_mask=human_mask,
    )


def new_human_goals(cfg: CrowdConfig, state: CrowdState, needs_goal: Tensor) -> Tensor:
    """Goals ``[B, N, 2]`` for non-stop humans: fresh ones where ``needs_goal [B, N]``.

    Circle scenario: a fresh circle goal for every human; square scenario: a square goal on a
    random side. A new goal keeps the spawn clearance from every agent's position and goal
    when one of ``GOAL_ROUNDS`` candidates allows it; otherwise the last candidate is used (the
    episode must go on). Only the humans that need a goal are computed.
    """
    dtype, device = state.human_goal.dtype, state.device
    env, human = needs_goal.nonzero(as_tuple=True)  # [M]
    M = env.shape[0]
    rounds = torch.arange(GOAL_ROUNDS, device=device).view(1, GOAL_ROUNDS, 1)
    comps = torch.arange(4, device=device).view(1, 1, 4)
    index = (human.view(M, 1, 1) * GOAL_ROUNDS + rounds) * 4 + comps
    draws = rng.uniform(state.episode_key[env].view(M, 1, 1), _TAG_NEW_GOAL, state.step_count[env].view(M, 1, 1),
                        index, dtype=dtype)  # [M, R, 4]
    u = draws.unbind(-1)
    if cfg.scenario == "circle":
        cand = _circle_points(cfg, u[0], u[1], u[2])  # [M, R, 2]
    else:
        side = torch.where(u[3] > 0.5, -1.0, 1.0).to(dtype)
        cand = _square_points(cfg, side, u[0], u[1])
    # clearance from every agent's position and goal, the robot's and the human's own included
    # (a goal next to where the human stands would be reached again at once)
    others = torch.cat((state.robot_position[env].unsqueeze(1), state.human_position[env],
                        state.robot_goal[env].unsqueeze(1), state.human_goal[env]), 1)  # [M, 2N+2, 2]
    ok = _clear_of(cand, others, cfg.spawn_clearance)
    ok[:, -1] = True
    first = ok.to(torch.int8).argmax(-1)
    chosen = torch.gather(cand, 1, first.view(M, 1, 1).expand(M, 1, 2)).squeeze(1)
    goals = state.human_goal.clone()
    goals[env, human] = chosen
    return goals
