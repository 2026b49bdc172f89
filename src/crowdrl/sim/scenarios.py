"""Episode initial states: circle- and square-crossing humans with spawn clearance, and the
scenarios with static obstacles (corridor, doorway, room).

Every random number comes from :mod:`crowdrl.sim.rng`, keyed by the episode, so an episode is
a pure function of (stream, seed, episode id), whatever the batch it is generated in.
Rejection sampling is vectorised: each human tries up to ``SPAWN_ROUNDS`` candidates and takes
the first valid one, in the order the reference simulator would have tried them; the rounds
are evaluated in chunks sized to the observed acceptance rate, for the episodes still searching.

Obstacle scenarios (the robot still goes from ``(0, -circle_radius)`` to ``(0, circle_radius)``,
``(0, -4)`` to ``(0, 4)`` by default; the keys are :class:`~crowdrl.sim.config.CrowdConfig`'s):

* ``corridor``: two parallel walls (2-vertex segments) at ``x = -/+ corridor_width / 2`` (4 m apart),
  ``corridor_length`` long (10 m) centred on the origin. Each human walks one way (up or down, a
  fair draw): it starts inside the corridor in the half behind it and heads for the last quarter
  of the corridor ahead.
* ``doorway``: a wall across the path at ``y = 0``, ``doorway_width`` long (10 m), with a gap of
  ``doorway_gap`` (2 m) centred on ``x = 0``. Each human starts on one side (within the
  ``square_width`` square, clear of the wall) and heads for the other side; the sides alternate as
  in ``corridor``.
* ``room``: ``room_pillars`` (4) rectangular pillars, sides uniform in ``[room_pillar_min,
  room_pillar_max]`` (0.5..1.5 m), rotated uniformly, counter-clockwise, centred in the square of
  ``square_width - 2`` m; each clear of the robot's start and goal and of the others (centres apart
  by their circumradii plus a passage of ``2 * (human_radius + margin)``). Humans cross the square
  as in ``square``.

Reachability: the humans' ORCA avoids obstacles but does not plan around them, so a human's start
and goal (and every later goal of a non-stop human) are drawn such that the straight line between
them keeps ``human_radius + margin`` from every obstacle edge (``margin`` =
``CrowdConfig.obstacle_clearance_margin``, the discomfort distance): in ``doorway`` that line goes
through the gap. In ``doorway`` a human pushed off that line (by the crowd at the door) would press
against the wall, so until it has crossed the wall's line it heads for a waypoint in the gap
(:func:`crowdrl.sim.crowd.doorway_waypoints`, a pure function of its position and goal; on the
straight line it is a point of that line, so an unhindered human walks straight as before). Spawns
and goals keep the same clearance from the obstacles (the robot's start and
goal ``robot_radius + margin``). A draw failing after the bounded number of rounds raises
:class:`SpawnError` naming the scenario and its keys.
"""

from __future__ import annotations

import math
from typing import Callable

import torch
from torch import Tensor

from crowdrl.sim import rng
from crowdrl.sim.config import HUMAN_MODELS, MIXED, OBSTACLE_SCENARIOS, CrowdConfig
from crowdrl.sim.obstacles import Segments, path_obstacle_distance, point_obstacle_distance, segments_of
from crowdrl.sim.state import CrowdState

SPAWN_ROUNDS = 256  # candidates per human at spawn; exhausting them is an error
GOAL_ROUNDS = 16  # candidates per new goal of a non-stop human; exhausting them keeps the last
# Chunk sizing of the spawn rejection rounds (speed only: the result does not depend on them).
_CHUNK_HITS = 1.5  # a chunk holds this many expected valid candidates per searching episode
_MIN_CANDIDATES = 512  # few episodes left: draw at least this many candidates in all
_FIRST_DRAWS = 1 << 18  # uniforms of up to 16 first rounds drawn for every human at once (small batches)
_MAX_PAIRS = 1 << 21  # candidate-agent distances per chunk, bounding its memory

# Index tags keeping the purposes of random draws apart.
_TAG_SPAWN, _TAG_NEW_GOAL, _TAG_CROWD_SIZE, _TAG_OBSTACLES = range(4)
_TAG_HUMAN_MODEL = 4  # human_model="mixed": which human follows which model (assign_human_models)
PILLAR_ROUNDS = 64  # candidates per room pillar; exhausting them is an error
OBSTACLE_GOAL_ROUNDS = 64  # candidates per new goal in the obstacle scenarios (a clear straight path is rarer)
_OBSTACLE_CHUNK = 32  # spawn rounds evaluated at once in the obstacle scenarios (speed only)
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


def assign_human_models(cfg: CrowdConfig, episode_key: Tensor, human_mask: Tensor) -> Tensor:
    """Each human's model for the episodes ``episode_key [B]`` with present humans ``human_mask [B, N]``:
    ``[B, N]`` int8, indices into :data:`~crowdrl.sim.config.HUMAN_MODELS` (0 orca, 1 social_force, 2 linear).

    A single-model config: its model for every human (no random draw). ``human_model="mixed"``: each present
    human ``i`` gets a 63-bit draw keyed by the episode and ``i`` (tag ``_TAG_HUMAN_MODEL``: no other draw of the
    episode changes); ranked by it (ties, of probability ~2**-63, by index), the first of the episode's ``n``
    present humans follow the social force and the next the linear model, as many as
    :meth:`~crowdrl.sim.config.CrowdConfig.model_counts` says, the rest ORCA. A pure function of each episode's key
    and crowd size (whatever the batch, device or maximum crowd), so the train, validation and test streams draw
    their own; absent humans are marked ORCA (they take no part in anything)."""
    B, N = human_mask.shape
    device = episode_key.device
    if cfg.human_model != MIXED:
        return torch.full((B, N), HUMAN_MODELS.index(cfg.human_model), dtype=torch.int8, device=device)
    draw = rng.fold(episode_key.view(B, 1), _TAG_HUMAN_MODEL, torch.arange(N, device=device))  # [B, N]
    draw = draw.masked_fill(~human_mask, torch.iinfo(torch.int64).max)  # absent humans rank last
    rank = torch.argsort(torch.argsort(draw, dim=-1, stable=True), dim=-1, stable=True)
    social_force, linear = cfg.model_counts(human_mask.sum(-1))
    code = torch.where(rank < social_force.unsqueeze(-1), HUMAN_MODELS.index("social_force"),
                       torch.where(rank < (social_force + linear).unsqueeze(-1), HUMAN_MODELS.index("linear"),
                                   HUMAN_MODELS.index("orca")))
    return code.to(torch.int8)


def _start_state(robot_pos: Tensor, robot_goal: Tensor, positions: Tensor, goals: Tensor, episode_key: Tensor,
                 human_mask: Tensor | None, obstacles: Tensor, obstacle_mask: Tensor, human_model: Tensor) -> CrowdState:
    """An episode's first state: everyone at rest, the robot facing +y; ``positions`` / ``goals``
    ``[B, 1 + N, 2]`` hold the robot's row first, then the humans'; ``human_model``: :func:`assign_human_models`."""
    B, N = positions.shape[0], positions.shape[1] - 1
    dtype, device = positions.dtype, positions.device
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
        obstacles=obstacles,
        obstacle_mask=obstacle_mask,
        human_model=human_model,
    )


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
    if cfg.scenario in OBSTACLE_SCENARIOS:
        return _obstacle_initial_states(cfg, episode_key, dtype)
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

    no_obstacles = torch.zeros(B, 0, 2, 2, dtype=dtype, device=device), torch.zeros(B, 0, 2, dtype=torch.bool, device=device)
    return _start_state(robot_pos, robot_goal, positions, goals, episode_key, human_mask, *no_obstacles,
                        assign_human_models(cfg, episode_key, human_mask))


def _goal_draws(state: CrowdState, env: Tensor, human: Tensor, rounds: int) -> tuple[Tensor, ...]:
    """Four uniforms ``[M, rounds]`` per candidate new goal of humans ``(env, human)`` (``[M]`` each),
    a pure function of the episode key, the step and the human."""
    M, device = env.shape[0], state.device
    r = torch.arange(rounds, device=device).view(1, rounds, 1)
    comps = torch.arange(4, device=device).view(1, 1, 4)
    index = (human.view(M, 1, 1) * rounds + r) * 4 + comps
    return rng.uniform(state.episode_key[env].view(M, 1, 1), _TAG_NEW_GOAL, state.step_count[env].view(M, 1, 1),
                       index, dtype=state.human_goal.dtype).unbind(-1)


def new_human_goals(cfg: CrowdConfig, state: CrowdState, needs_goal: Tensor) -> Tensor:
    """Goals ``[B, N, 2]`` for non-stop humans: fresh ones where ``needs_goal [B, N]``.

    Circle scenario: a fresh circle goal for every human; square scenario: a square goal on a
    random side. A new goal keeps the spawn clearance from every agent's position and goal
    when one of ``GOAL_ROUNDS`` candidates allows it; otherwise the last candidate is used (the
    episode must go on). Only the humans that need a goal are computed.
    """
    if cfg.scenario in OBSTACLE_SCENARIOS:
        return _obstacle_new_goals(cfg, state, needs_goal)
    dtype = state.human_goal.dtype
    env, human = needs_goal.nonzero(as_tuple=True)  # [M]
    M = env.shape[0]
    u = _goal_draws(state, env, human, GOAL_ROUNDS)
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


# --- scenarios with static obstacles ---------------------------------------------------------------

def _keys_of(cfg: CrowdConfig) -> str:
    keys = {"corridor": ("corridor_width", "corridor_length"), "doorway": ("doorway_gap", "doorway_width"),
            "room": ("room_pillars", "room_pillar_min", "room_pillar_max")}[cfg.scenario]
    keys = keys + ("num_humans", "square_width") if cfg.scenario != "corridor" else keys + ("num_humans",)
    return ", ".join(f"{k}={getattr(cfg, k)}" for k in keys)


def _rectangles(center: Tensor, half: Tensor, angle: Tensor) -> Tensor:
    """Counter-clockwise corners ``[..., 4, 2]`` of rectangles (``center``/``half`` ``[..., 2]``, ``angle [...]``)."""
    signs = torch.tensor([[1.0, -1.0], [1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0]], dtype=center.dtype,
                         device=center.device)
    local = signs * half.unsqueeze(-2)  # [..., 4, 2]
    c, s = torch.cos(angle).unsqueeze(-1), torch.sin(angle).unsqueeze(-1)
    x, y = local[..., 0], local[..., 1]
    return torch.stack((c * x - s * y, s * x + c * y), -1) + center.unsqueeze(-2)


def _rectangle_distance(points: Tensor, center: Tensor, half: Tensor, angle: Tensor) -> Tensor:
    """Distance of ``points [..., 2]`` to rectangles (broadcast), 0 inside."""
    d = points - center
    c, s = torch.cos(angle), torch.sin(angle)
    q = torch.stack((c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]), -1).abs() - half
    return torch.linalg.vector_norm(q.clamp_min(0.0), dim=-1)


def scenario_obstacles(cfg: CrowdConfig, episode_key: Tensor, dtype: torch.dtype = torch.float32
                       ) -> tuple[Tensor, Tensor]:
    """The obstacles of the episodes ``episode_key [B]``: ``[B, P, V, 2]`` polygons and their vertex
    mask ``[B, P, V]`` (``P, V = cfg.obstacles_shape``), a pure function of each episode's key."""
    B, device = episode_key.shape[0], episode_key.device
    P, V = cfg.obstacles_shape
    mask = torch.ones(B, P, V, dtype=torch.bool, device=device)
    if cfg.scenario == "corridor":
        x, y = cfg.corridor_width / 2, cfg.corridor_length / 2
        walls = [[[-x, -y], [-x, y]], [[x, y], [x, -y]]]
    elif cfg.scenario == "doorway":
        x, g = cfg.doorway_width / 2, cfg.doorway_gap / 2
        walls = [[[-x, 0.0], [-g, 0.0]], [[g, 0.0], [x, 0.0]]]
    elif cfg.scenario == "room":
        return _room_pillars(cfg, episode_key, dtype), mask
    else:
        return torch.zeros(B, 0, 2, 2, dtype=dtype, device=device), torch.zeros(B, 0, 2, dtype=torch.bool,
                                                                                 device=device)
    return torch.tensor(walls, dtype=dtype, device=device).expand(B, P, V, 2).clone(), mask


def _room_pillars(cfg: CrowdConfig, episode_key: Tensor, dtype: torch.dtype) -> Tensor:
    """``room``: ``cfg.room_pillars`` rectangles ``[B, K, 4, 2]``, each the first of its rounds clear of
    the robot's start and goal and of the pillars placed before it (the first 8 rounds are tried for
    every episode, all of them only where those fail: the same result, cheaper)."""
    B, K, device = episode_key.shape[0], cfg.room_pillars, episode_key.device
    key = rng.fold(episode_key, _TAG_OBSTACLES)
    span = cfg.square_width / 2 - 1.0
    lo, hi = cfg.room_pillar_min, cfg.room_pillar_max
    robot = torch.tensor([[0.0, -cfg.circle_radius], [0.0, cfg.circle_radius]], dtype=dtype, device=device)
    robot_clear = cfg.robot_radius + cfg.obstacle_clearance_margin
    passage = 2 * (cfg.human_radius + cfg.obstacle_clearance_margin)
    centers = torch.zeros(B, K, 2, dtype=dtype, device=device)
    halves = torch.zeros(B, K, 2, dtype=dtype, device=device)
    angles = torch.zeros(B, K, dtype=dtype, device=device)

    def candidates(k: int, episodes: Tensor | slice, rounds: int):
        r = torch.arange(rounds, device=device).view(1, rounds, 1)
        c = torch.arange(5, device=device).view(1, 1, 5)
        u = rng.uniform(key[episodes].view(-1, 1, 1), (k * PILLAR_ROUNDS + r) * 5 + c, dtype=dtype)  # [A, R, 5]
        center = (u[..., 0:2] * 2 - 1) * span
        half = 0.5 * (lo + (hi - lo) * u[..., 2:4])
        angle = u[..., 4] * math.pi  # a rectangle is symmetric under a half turn
        ok = (_rectangle_distance(robot.view(1, 1, 2, 2), center.unsqueeze(2), half.unsqueeze(2),
                                  angle.unsqueeze(2)) >= robot_clear).all(-1)  # [A, R]
        if k:
            gap = torch.linalg.vector_norm(center.unsqueeze(2) - centers[episodes, None, :k], dim=-1)  # [A, R, k]
            need = (torch.linalg.vector_norm(half, dim=-1).unsqueeze(2)
                    + torch.linalg.vector_norm(halves[episodes, None, :k], dim=-1) + passage)
            ok = ok & (gap >= need).all(-1)
        first = ok.to(torch.int8).argmax(-1)
        take = lambda t: t.gather(1, first.view(-1, 1, *([1] * (t.dim() - 2))).expand(-1, 1, *t.shape[2:])).squeeze(1)  # noqa: E731
        return take(center), take(half), take(angle), ok.any(-1)

    for k in range(K):
        center, half, angle, hit = candidates(k, slice(None), min(8, PILLAR_ROUNDS))
        centers[:, k], halves[:, k], angles[:, k] = center, half, angle
        if not bool(hit.all()):
            again = (~hit).nonzero().squeeze(-1)
            center, half, angle, hit = candidates(k, again, PILLAR_ROUNDS)
            if not bool(hit.all()):
                raise SpawnError(
                    f"scenario room ({_keys_of(cfg)}): could not place pillar {k} clear of the robot's start and "
                    f"goal and of the other pillars in {int((~hit).sum())} episode(s) after {PILLAR_ROUNDS} draws; "
                    "use fewer or smaller pillars (room_pillars, room_pillar_max) or a larger square_width")
            centers[again, k], halves[again, k], angles[again, k] = center, half, angle
    return _rectangles(centers, halves, angles)


def _human_region(cfg: CrowdConfig, side: Tensor, ux: Tensor, uy: Tensor, goal: bool) -> Tensor:
    """A start (``goal=False``) or goal point ``[..., 2]`` of a human walking towards ``side`` (+1: +y)."""
    clear = cfg.human_radius + cfg.obstacle_clearance_margin
    if cfg.scenario == "corridor":
        half_w, half_l = cfg.corridor_width / 2 - clear, cfg.corridor_length / 2
        x = (ux * 2 - 1) * half_w
        y = side * half_l * (0.2 + 0.8 * uy) if goal else -side * half_l * uy  # the far 40 % / the half behind
        return torch.stack((x, y), -1)
    if cfg.scenario == "doorway":
        half_w = min(cfg.doorway_width, cfg.square_width) / 2 - clear
        half_h = cfg.square_width / 2
        x = (ux * 2 - 1) * half_w
        y = (clear + uy * (half_h - clear)) * (side if goal else -side)
        return torch.stack((x, y), -1)
    return _square_points(cfg, side if goal else -side, ux, uy)  # room: square crossing (side of x)


def _clear_of_obstacles(cfg: CrowdConfig, start: Tensor, goal: Tensor, seg: Segments, episodes: Tensor,
                        candidates: Tensor, clear: float) -> Tensor:
    """``[A, R]``: the start and goal ``[A, R, 2]`` of the ``episodes [A]`` and the straight path between
    them keep ``clear`` from the obstacles (``seg``: of all episodes), evaluated only where
    ``candidates [A, R]`` (the others: False).

    By construction a corridor's points lie ``clear`` inside its walls (a convex region: the path too),
    and a doorway's ``clear`` off the wall's line within its length, so only the path is checked there."""
    if cfg.scenario == "corridor":
        return candidates
    a, r = candidates.nonzero(as_tuple=True)
    s, g = start[a, r].unsqueeze(1), goal[a, r].unsqueeze(1)  # [C, 1, 2]
    seg = seg.select(episodes[a])
    ok = path_obstacle_distance(s, g, None, None, seg) >= clear
    if cfg.scenario != "doorway":
        ok = ok & (point_obstacle_distance(s, None, None, seg) >= clear) & (
            point_obstacle_distance(g, None, None, seg) >= clear)
    out = torch.zeros_like(candidates)
    out[a, r] = ok.squeeze(1)
    return out


def _obstacle_initial_states(cfg: CrowdConfig, episode_key: Tensor, dtype: torch.dtype) -> CrowdState:
    """:func:`initial_states` of the obstacle scenarios (module docstring): each human's start and goal
    are drawn together, the first of its rounds that keeps every clearance (agents, obstacles, and the
    straight path from start to goal)."""
    B, N = episode_key.shape[0], cfg.num_humans
    device = episode_key.device
    obstacles, obstacle_mask = scenario_obstacles(cfg, episode_key, dtype)
    clearance, robot_clear = cfg.spawn_clearance, cfg.human_radius + cfg.robot_radius + cfg.discomfort_dist
    obst_clear = cfg.human_radius + cfg.obstacle_clearance_margin
    robot_pos = torch.tensor([0.0, -cfg.circle_radius], dtype=dtype, device=device).expand(B, 2).clone()
    robot_goal = torch.tensor([0.0, cfg.circle_radius], dtype=dtype, device=device).expand(B, 2).clone()
    positions = torch.full((B, N + 1, 2), _PARKED, dtype=dtype, device=device)
    goals = torch.full((B, N + 1, 2), _PARKED, dtype=dtype, device=device)
    positions[:, 0], goals[:, 0] = robot_pos, robot_goal
    spawn_key = rng.fold(episode_key, _TAG_SPAWN)
    seg = segments_of(obstacles, obstacle_mask)
    human_mask = torch.arange(N, device=device) < crowd_sizes(cfg, episode_key).unsqueeze(-1)
    humans = torch.arange(N, device=device)
    # the direction of each human (room: of x, as in square; corridor and doorway: of y), drawn in round
    # 0; in corridor and doorway humans alternate directions from human 0's draw
    # Small batches: the first rounds of every human in one draw [B, N, R0, 8] (the same uniforms as
    # per-human draws), as per-human draws would cost more in call overhead than in arithmetic.
    first_rounds = min(_OBSTACLE_CHUNK, _FIRST_DRAWS // max(B * N * _SPAWN_COMPONENTS, 1))
    chunk0 = None
    if first_rounds >= _OBSTACLE_CHUNK // 2:
        chunk0 = _spawn_uniforms(spawn_key, humans, 0, first_rounds, range(_SPAWN_COMPONENTS), dtype)
        side_draw = chunk0[:, :, 0, 7]
    else:
        side_draw = _spawn_uniforms(spawn_key, humans, 0, 1, range(7, 8), dtype)[:, :, 0, 0]  # [B, N]
    if cfg.scenario != "room":
        side_draw = side_draw[:, :1].expand(B, N)
    for h in range(N):
        side_draw_h = side_draw[:, h]
        episodes = human_mask[:, h].nonzero().squeeze(-1)
        first = 0
        rate = 0.25  # acceptance rate guessed for the first chunk, then the first chunk's
        while episodes.numel():
            if first >= SPAWN_ROUNDS:
                raise SpawnError(
                    f"scenario {cfg.scenario} ({_keys_of(cfg)}): could not place the start and goal of human {h} "
                    f"in {episodes.numel()} episode(s) after {SPAWN_ROUNDS} rejection rounds, clear of the other "
                    "agents and of the obstacles with a clear straight path; use fewer humans or roomier obstacles")
            A = episodes.numel()
            if first == 0 and chunk0 is not None:
                rounds, u = first_rounds, chunk0[episodes, h]
            else:
                rounds = min(_OBSTACLE_CHUNK, _chunk_rounds(A, h + 1, rate, SPAWN_ROUNDS - first))
                u = _spawn_uniforms(spawn_key[episodes], h, first, rounds, range(_SPAWN_COMPONENTS), dtype)  # [A, R, 8]
            side = torch.where(side_draw_h[episodes] > 0.5, -1.0, 1.0).to(dtype).unsqueeze(-1)  # [A, 1]
            if cfg.scenario != "room":  # corridor, doorway: alternate, half the crowd each way
                side = side * (1.0 - 2.0 * (h % 2))
            start = _human_region(cfg, side, u[..., 3], u[..., 4], goal=False)
            goal = _human_region(cfg, side, u[..., 5], u[..., 6], goal=True)
            d_start = _distances(start, positions[episodes, : h + 1])
            d_goal = _distances(goal, goals[episodes, : h + 1])
            ok = (d_start[0] >= robot_clear) & (d_goal[0] >= robot_clear)
            if h:
                ok = ok & (d_start[1:].amin(0) >= clearance) & (d_goal[1:].amin(0) >= clearance)
            ok = ok & _clear_of_obstacles(cfg, start, goal, seg, episodes, ok, obst_clear)
            rate = max(float(ok.sum()) / max(A * rounds, 1), 1e-3) if first == 0 else rate
            s_pick, hit = _first_valid(start, ok)
            g_pick, _ = _first_valid(goal, ok)
            done = episodes[hit]
            positions[done, h + 1], goals[done, h + 1] = s_pick[hit], g_pick[hit]
            episodes = episodes[~hit]
            first += rounds
    return _start_state(robot_pos, robot_goal, positions, goals, episode_key, human_mask, obstacles, obstacle_mask,
                        assign_human_models(cfg, episode_key, human_mask))


def _obstacle_new_goals(cfg: CrowdConfig, state: CrowdState, needs_goal: Tensor) -> Tensor:
    """:func:`new_human_goals` of the obstacle scenarios: a goal on the other side (corridor: the other
    end; doorway: the other side of the wall; room: a random side, as in square) clear of the obstacles
    with a clear straight path from where the human stands, preferably also clear of every agent; a
    human none of whose ``OBSTACLE_GOAL_ROUNDS`` candidates has a clear path keeps its goal (it asks again on
    the next step, with new draws)."""
    dtype = state.human_goal.dtype
    env, human = needs_goal.nonzero(as_tuple=True)  # [M]
    M = env.shape[0]
    u = _goal_draws(state, env, human, OBSTACLE_GOAL_ROUNDS)
    here = state.human_position[env, human]  # [M, 2]
    if cfg.scenario == "room":
        side = torch.where(u[3] > 0.5, -1.0, 1.0).to(dtype)
    else:  # towards the other end / the other side of the wall
        side = torch.where(here[:, 1:2] > 0, -1.0, 1.0).to(dtype).expand(M, OBSTACLE_GOAL_ROUNDS)
    cand = _human_region(cfg, side, u[0], u[1], goal=True)  # [M, R, 2]
    obs, om = state.obstacles[env], state.obstacle_mask[env]
    clear = cfg.human_radius + cfg.obstacle_clearance_margin
    reachable = (point_obstacle_distance(cand, obs, om) >= clear) & (
        path_obstacle_distance(here.unsqueeze(1).expand_as(cand), cand, obs, om) >= clear)
    others = torch.cat((state.robot_position[env].unsqueeze(1), state.human_position[env],
                        state.robot_goal[env].unsqueeze(1), state.human_goal[env]), 1)
    ok = reachable & _clear_of(cand, others, cfg.spawn_clearance)
    ok = torch.where(ok.any(-1, keepdim=True), ok, reachable)
    chosen, found = _first_valid(cand, ok)
    goals = state.human_goal.clone()
    goals[env, human] = torch.where(found.unsqueeze(-1), chosen, state.human_goal[env, human])
    return goals
