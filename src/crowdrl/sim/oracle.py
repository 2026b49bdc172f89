"""The ceiling of a case: the fastest collision-free path found for the robot with the humans' true futures.

The humans do not see the robot (``robot_visible`` false), so a case's crowd is known in advance, with one
exception: a non-stop human's *new* goal keeps clear of the robot's position
(:func:`crowdrl.sim.scenarios.new_human_goals`), so the crowd branches where the robot's path changes a
draw. The search carries every branch exactly: nodes that share a crowd share a *crowd variant*, the
humans of each variant move once per step, and :func:`crowdrl.sim.crowd.advance` gives every kept child
the state the simulator would give it (new goals drawn against its own position).

Beam search over the 81 unicycle actions, one depth per time step, every case of a batch at once:

1. the humans of every distinct crowd variant move (:func:`~crowdrl.sim.humans.human_velocities`);
2. each node's 81 children are judged by :func:`~crowdrl.sim.crowd.step_reward`, the simulator's own
   judgement (humans, walls, goal);
3. a child that collides is dropped; a child that reaches the goal ends its case: the first depth
   at which one does is the shortest time the search found;
4. survivors are ranked by a relaxed time-to-go (:class:`TimeToGo`: steps to the goal on a coarse
   space-time grid that avoids the humans' recorded positions and the walls), closer to the goal first
   among equals; one child is kept per (crowd variant, position cell, heading bin), then the best
   ``width`` per case.

A case the beam does not solve can be proven infeasible by :func:`exhaustive` search: every action
sequence collides within a short horizon.

Pure torch; no TorchRL. ``crowdrl.evaluation.ceiling`` runs it over a stream and stores the labels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.crowd import advance, step, step_reward
from crowdrl.sim.humans import human_velocities
from crowdrl.sim.kinematics import NUM_ACTIONS, action_table, decode_action, wrap_angle
from crowdrl.sim.obstacles import ObstacleEdges, point_obstacle_distance, process_obstacles, select_edges
from crowdrl.sim.state import CrowdState

SOLVED, INFEASIBLE, UNKNOWN = "solved", "infeasible", "unknown"
LABELS = (SOLVED, INFEASIBLE, UNKNOWN)
_FAR = 1.0e4  # time-to-go of a cell from which the relaxed grid knows no way to the goal
_HEADING_BINS = 32  # heading bins of the beam's duplicate test (11.25 degrees)
_CHILDREN_PER_CHUNK = 1 << 21  # children x humans judged at once (memory bound of step_reward's temporaries)


def check_searchable(cfg: CrowdConfig) -> None:
    """Refuse a config whose crowd the search cannot know in advance, naming the key."""
    if cfg.humans_react_to_robot:
        raise ValueError("robot_visible: the humans react to the robot, so a case's crowd is not known in advance "
                         "and has no ceiling; use robot_visible=false")
    if cfg.robot_kinematics != "unicycle":
        raise ValueError(f"robot_kinematics: the search plans over the 81 unicycle actions, got "
                         f"{cfg.robot_kinematics!r}")


@dataclass
class SearchResult:
    """Per case: ``steps`` to the goal (``-1``: none found), the ``actions`` of the path (empty: none),
    and the largest number of distinct crowd variants the search carried (``1``: the robot's path never
    changed a human's new goal among the nodes kept)."""

    steps: list[int]
    actions: list[list[int]]
    variants: list[int]


def _region(cfg: CrowdConfig) -> float:
    """Half the side of the square where the scenario's agents walk (the robot's start and goal aside)."""
    return {"circle": cfg.circle_radius + cfg.human_v_pref, "square": cfg.square_width / 2,
            "corridor": max(cfg.corridor_length, cfg.corridor_width) / 2,
            "doorway": max(cfg.doorway_width, cfg.square_width) / 2, "room": cfg.square_width / 2}[cfg.scenario]


class TimeToGo:
    """A relaxed time-to-go, in steps, on a space-time grid of ``cell`` metres: from a cell at step ``t``,
    the fewest moves of at most one cell (8 neighbours, a relaxation of the robot's ``v_pref·Δt``) to a cell
    at the goal, never entering a cell blocked at its step: a cell whose centre lies closer to a human than
    the two radii less half a cell diagonal (the humans' positions along ``futures``), or closer to a wall
    than the robot's radius less half a diagonal. Past the last step only the walls count.

    ``futures [C, T+1, N, 2]`` with ``present [C, N]``; ``obstacles`` as in :class:`CrowdState`."""

    def __init__(self, cfg: CrowdConfig, start: CrowdState, futures: Tensor, cell: float,
                 reach_margin: float = 0.0) -> None:
        C, T1, N, _ = futures.shape
        self.cell = float(cell)
        half = max(cfg.circle_radius, _region(cfg)) + 1.5
        self.origin = -half
        size = int(math.ceil(2 * half / self.cell))
        centres = (torch.arange(size, dtype=torch.float32) + 0.5) * self.cell + self.origin
        gy, gx = torch.meshgrid(centres, centres, indexing="ij")
        grid = torch.stack((gx, gy), -1).reshape(1, -1, 2)  # [1, S*S, 2], row-major in (y, x)
        slack = 0.5 * math.sqrt(2.0) * self.cell
        goal = start.robot_goal.float()
        at_goal = torch.linalg.vector_norm(grid - goal[:, None], dim=-1) < cfg.robot_radius + slack  # [C, S*S]
        walls = torch.zeros(C, size * size, dtype=torch.bool)
        if start.has_obstacles:
            d = point_obstacle_distance(grid.expand(C, -1, -1).to(start.obstacles.dtype), start.obstacles,
                                        start.obstacle_mask)
            walls = d < cfg.robot_radius - slack
        far = torch.full((C, size * size), _FAR)
        static = torch.where(at_goal & ~walls, 0.0, far)
        for _ in range(4 * size):  # walls only: a breadth-first wave to a fixed point
            nxt = torch.where(walls, _FAR, torch.minimum(static, 1.0 + self._min_pool(static, size))).clamp_max(_FAR)
            nxt = torch.where(at_goal & ~walls, 0.0, nxt)
            if torch.equal(nxt, static):
                break
            static = nxt
        values = torch.empty(C, T1, size * size)
        values[:, -1] = static
        reach = cfg.human_radius + cfg.robot_radius + reach_margin
        blocked = self._human_cells(futures, start.human_mask, reach, size)  # [C, T+1, S*S]
        for t in range(T1 - 2, -1, -1):
            v = 1.0 + self._min_pool(values[:, t + 1], size)
            v = torch.where(at_goal, 0.0, v)
            values[:, t] = torch.where(blocked[:, t] | walls, _FAR, v).clamp_max(_FAR)
        self.size = size
        self.values = values  # [C, T+1, S*S]
        self.goal = goal

    def _human_cells(self, futures: Tensor, present: Tensor, reach: float, size: int) -> Tensor:
        """``[C, T+1, S*S]`` bool: the cells whose centre lies within ``reach`` of a present human's cell centre
        (a disc stamped around each human, not a distance to every cell)."""
        C, T1, N, _ = futures.shape
        r = int(math.ceil(reach / self.cell))
        d = torch.arange(-r, r + 1)
        dy, dx = torch.meshgrid(d, d, indexing="ij")
        inside = (dx * dx + dy * dy).double().sqrt() * self.cell <= reach
        off = torch.stack((dx[inside], dy[inside]), -1)  # [K, 2]
        hc = torch.floor((futures.float() - self.origin) / self.cell).long()  # [C, T+1, N, 2]
        cells = hc[:, :, :, None, :] + off  # [C, T+1, N, K, 2]
        ok = ((cells >= 0) & (cells < size)).all(-1) & present[:, None, :, None]
        base = (torch.arange(C)[:, None] * T1 + torch.arange(T1)[None, :]) * (size * size)  # [C, T+1]
        flat = base[:, :, None, None] + cells[..., 1] * size + cells[..., 0]
        blocked = torch.zeros(C * T1 * size * size, dtype=torch.bool)
        blocked[flat[ok]] = True
        return blocked.reshape(C, T1, size * size)

    @staticmethod
    def _min_pool(v: Tensor, size: int) -> Tensor:
        """The least value among each cell's 3x3 neighbourhood, ``[C, S*S]``."""
        x = -v.reshape(-1, 1, size, size)
        x = F.max_pool2d(x, 3, stride=1, padding=1)
        # then the 4 neighbours: offsets up to 2 cells but the corners of the 5x5 square (a disc of ~2 cells)
        x = torch.maximum(torch.maximum(x, F.pad(x, (1, -1, 0, 0), value=-_FAR)), torch.maximum(
            F.pad(x, (-1, 1, 0, 0), value=-_FAR), torch.maximum(F.pad(x, (0, 0, 1, -1), value=-_FAR),
                                                                 F.pad(x, (0, 0, -1, 1), value=-_FAR))))
        return -x.reshape(v.shape)

    def cells(self, position: Tensor) -> Tensor:
        """Flat cell indices of ``position [M, 2]`` (clamped to the grid)."""
        ij = torch.floor((position.float() - self.origin) / self.cell).long().clamp(0, self.size - 1)
        return ij[:, 1] * self.size + ij[:, 0]

    def score(self, case: Tensor, t: int, position: Tensor) -> Tensor:
        """The rank of nodes at step ``t`` (lower is better): time-to-go, then distance to the goal."""
        t = min(t, self.values.shape[1] - 1)
        steps = self.values[case, t, self.cells(position)]
        return steps + 1e-3 * torch.linalg.vector_norm(position.float() - self.goal[case], dim=-1)


def crowd_futures(cfg: CrowdConfig, start: CrowdState, edges: ObstacleEdges | None, steps: int) -> Tensor:
    """The humans' positions ``[C, steps+1, N, 2]`` with the robot standing at its start: the crowd the
    relaxed grid avoids (the robot's path can change new goals; the search itself tracks that exactly)."""
    state, out = start, [start.human_position]
    still = torch.zeros_like(start.robot_position)
    for _ in range(steps):
        state, _ = step(cfg, state, still, start.robot_heading, obstacle_edges=edges)
        out.append(state.human_position)
    return torch.stack(out, 1)


class _Nodes:
    """The beam at one depth: full simulator states, each node's case and crowd variant."""

    def __init__(self, state: CrowdState, case: Tensor, variant: Tensor) -> None:
        self.state, self.case, self.variant = state, case, variant


def _variants(old_variant: Tensor, redrawn: Tensor, state: CrowdState) -> Tensor:
    """Crowd variant ids of nodes: equal where they came from one variant and drew the same new goals
    (``redrawn [M]``: a node's humans drew new goals this step; the others keep their variant's)."""
    out = old_variant.clone()
    if bool(redrawn.any()):
        rows = redrawn.nonzero(as_tuple=True)[0]
        key = torch.cat((old_variant[rows, None].double(), state.human_goal[rows].flatten(1).double()), 1)
        _, inverse = torch.unique(key, dim=0, return_inverse=True)
        out[rows] = inverse + int(old_variant.max()) + 1
    _, out = torch.unique(out, return_inverse=True)
    return out


def _representatives(variant: Tensor) -> Tensor:
    """One node index per variant id ``0 .. V-1`` (the first)."""
    V = int(variant.max()) + 1 if variant.numel() else 0
    idx = torch.arange(variant.shape[0])
    return torch.full((V,), variant.shape[0], dtype=torch.long).scatter_reduce(0, variant, idx, "amin")


class _Expansion:
    """The 81 children of every node at one depth: velocities, headings and the step's judgement."""

    def __init__(self, cfg: CrowdConfig, table: Tensor, nodes: _Nodes, edges: ObstacleEdges | None) -> None:
        s = nodes.state
        M, N = s.batch_size, s.num_humans
        rep = _representatives(nodes.variant)
        crowd = s.index(rep)
        crowd_edges = None if edges is None else select_edges(edges, nodes.case[rep])
        hv, _ = human_velocities(cfg, crowd, crowd_edges)
        self.human_velocity = hv[nodes.variant]  # [M, N, 2]
        check = self.human_velocity if cfg.collision_velocity == "new" else s.human_velocity
        actions = torch.arange(NUM_ACTIONS).repeat(M)
        vel, head = decode_action("unicycle", actions, s.robot_heading.repeat_interleave(NUM_ACTIONS), table,
                                  cfg.robot_v_pref)
        self.velocity, self.heading = vel.reshape(M, NUM_ACTIONS, 2), head.reshape(M, NUM_ACTIONS)
        mask = s.human_mask if cfg.variable_crowd else None
        collided, reached = [], []
        chunk = max(1, _CHILDREN_PER_CHUNK // (NUM_ACTIONS * max(N, 1)))
        for a in range(0, M, chunk):
            b = min(M, a + chunk)
            m = b - a
            judged = step_reward(
                cfg, s.robot_position[a:b, None].expand(m, NUM_ACTIONS, 2), self.velocity[a:b],
                s.robot_goal[a:b, None].expand(m, NUM_ACTIONS, 2),
                s.human_position[a:b, None].expand(m, NUM_ACTIONS, N, 2), check[a:b, None].expand(m, NUM_ACTIONS, N, 2),
                None if mask is None else mask[a:b, None].expand(m, NUM_ACTIONS, N),
                None if s.obstacles is None else s.obstacles[a:b],
                None if s.obstacle_mask is None else s.obstacle_mask[a:b])
            collided.append(judged.collided)
            reached.append(judged.reached)
        self.collided = torch.cat(collided) if collided else torch.zeros(0, NUM_ACTIONS, dtype=torch.bool)
        self.reached = torch.cat(reached) if reached else torch.zeros(0, NUM_ACTIONS, dtype=torch.bool)

    def children(self, cfg: CrowdConfig, nodes: _Nodes, parent: Tensor, action: Tensor) -> _Nodes:
        """The nodes reached by ``action [K]`` from nodes ``parent [K]``: the simulator's next state."""
        pre = nodes.state.index(parent)
        moved = advance(cfg, pre, self.velocity[parent, action], wrap_angle(self.heading[parent, action]),
                        self.human_velocity[parent])
        redrawn = (moved.human_goal != pre.human_goal).any(-1).any(-1)
        return _Nodes(moved, nodes.case[parent], _variants(nodes.variant[parent], redrawn, moved))


def _path(parents: list[Tensor], actions: list[Tensor], last_parent: int, last_action: int) -> list[int]:
    path, node = [last_action], last_parent
    for d in range(len(parents) - 1, -1, -1):
        path.append(int(actions[d][node]))
        node = int(parents[d][node])
    return path[::-1]


def beam_search(cfg: CrowdConfig, start: CrowdState, *, width: int = 256, cell: float = 0.125,
                resolution: float = 0.05, edges: ObstacleEdges | None = None,
                grid: TimeToGo | None = None) -> SearchResult:
    """The fastest collision-free path found for each of the ``C`` cases of ``start`` (initial states).

    ``width``: nodes kept per case and depth; ``cell``: the relaxed grid's cell (m); ``resolution``: the
    position cell (m) of the duplicate test (one node per variant, cell and heading bin).

    Examples:
        Test cases 0 and 1 of circle, five humans; each path found is a list of action indices:

        >>> from crowdrl.sim import rng
        >>> from crowdrl.sim.scenarios import initial_states
        >>> cfg = CrowdConfig(num_humans=5)
        >>> start = initial_states(cfg, rng.episode_keys("test", 0, torch.arange(2)))
        >>> found = beam_search(cfg, start, width=16)
        >>> [s > 0 and len(a) == s for s, a in zip(found.steps, found.actions)]
        [True, True]
    """
    check_searchable(cfg)
    if isinstance(width, bool) or not isinstance(width, int) or width < 1:
        raise ValueError(f"width must be an integer >= 1, got {width!r}")
    C = start.batch_size
    if edges is None and start.has_obstacles:
        edges = process_obstacles(start.obstacles, start.obstacle_mask)
    if grid is None:
        grid = TimeToGo(cfg, start, crowd_futures(cfg, start, edges, cfg.max_steps), cell)
    table = action_table(cfg.robot_v_pref, dtype=start.robot_position.dtype)
    steps, paths, variants = [-1] * C, [[] for _ in range(C)], [1] * C
    nodes = _Nodes(start, torch.arange(C), torch.arange(C))
    parents: list[Tensor] = []
    acts: list[Tensor] = []
    for depth in range(cfg.max_steps):
        if nodes.state.batch_size == 0:
            break
        exp = _Expansion(cfg, table, nodes, edges)
        done = exp.reached & ~exp.collided
        solved_now = torch.zeros(C, dtype=torch.bool)
        if bool(done.any()):
            p, a = done.nonzero(as_tuple=True)
            for pi, ai in zip(p.tolist(), a.tolist()):
                c = int(nodes.case[pi])
                if not solved_now[c]:
                    solved_now[c] = True
                    steps[c] = depth + 1
                    paths[c] = _path(parents, acts, pi, ai)
        alive = ~exp.collided & ~exp.reached & ~solved_now[nodes.case][:, None]
        p, a = alive.nonzero(as_tuple=True)
        if p.numel() == 0 or depth + 1 == cfg.max_steps:
            break
        case = nodes.case[p]
        position = nodes.state.robot_position[p] + exp.velocity[p, a] * cfg.time_step
        score = grid.score(case, depth + 1, position).double()
        # one child per (case, variant, position cell, heading bin): the best-ranked
        ij = torch.floor(position.double() / resolution).long()
        hb = torch.floor((wrap_angle(exp.heading[p, a]).double() + math.pi) / (2 * math.pi) * _HEADING_BINS).long()
        hb = hb.clamp(0, _HEADING_BINS - 1)
        key = ((nodes.variant[p] << 40) | ((ij[:, 0] + (1 << 19)) << 20) | (ij[:, 1] + (1 << 19))) * _HEADING_BINS + hb
        order = torch.argsort(score, stable=True)
        _, inv = torch.unique(key[order], return_inverse=True)
        first = torch.full((int(inv.max()) + 1,), inv.shape[0], dtype=torch.long).scatter_reduce(
            0, inv, torch.arange(inv.shape[0]), "amin")
        keep = order[first]
        # the best `width` per case
        keep = keep[torch.argsort(score[keep], stable=True)]
        keep = keep[torch.argsort(case[keep], stable=True)]
        kc = case[keep]
        start_of = torch.searchsorted(kc, kc, right=False)
        keep = keep[(torch.arange(kc.shape[0]) - start_of) < width]
        parents.append(p[keep])
        acts.append(a[keep])
        nodes = exp.children(cfg, nodes, p[keep], a[keep])
        counts = torch.zeros(C, dtype=torch.long).index_add_(0, nodes.case[_representatives(nodes.variant)],
                                                             torch.ones(int(nodes.variant.max()) + 1, dtype=torch.long))
        variants = [max(v, int(n)) for v, n in zip(variants, counts.tolist())]
    return SearchResult(steps, paths, variants)


def exhaustive(cfg: CrowdConfig, start: CrowdState, horizon: int, *, edges: ObstacleEdges | None = None,
               max_nodes: int = 1 << 22) -> list[bool]:
    """Per case of ``start``: whether every action sequence collides within ``horizon`` steps (proven
    infeasible). ``False`` where some sequence survives (or reaches the goal) through the horizon. Every
    sequence is stepped exactly, crowd branches included; ``max_nodes`` bounds the nodes of one depth
    (a ``ValueError`` names ``horizon`` past it)."""
    check_searchable(cfg)
    if isinstance(horizon, bool) or not isinstance(horizon, int) or horizon < 1:
        raise ValueError(f"horizon must be an integer >= 1, got {horizon!r}")
    if start.batch_size * NUM_ACTIONS ** (horizon - 1) > max_nodes:
        raise ValueError(f"horizon: {horizon} steps keep {start.batch_size * NUM_ACTIONS ** (horizon - 1):,} nodes at "
                         f"the last depth, past the bound of {max_nodes:,}; lower it (or search fewer cases at once)")
    if edges is None and start.has_obstacles:
        edges = process_obstacles(start.obstacles, start.obstacle_mask)
    C = start.batch_size
    table = action_table(cfg.robot_v_pref, dtype=start.robot_position.dtype)
    nodes = _Nodes(start, torch.arange(C), torch.arange(C))
    escaped = torch.zeros(C, dtype=torch.bool)
    for depth in range(min(horizon, cfg.max_steps)):
        if nodes.state.batch_size == 0:
            break
        exp = _Expansion(cfg, table, nodes, edges)
        reached = (exp.reached & ~exp.collided).any(1)
        escaped |= torch.zeros(C, dtype=torch.bool).index_fill_(0, nodes.case[reached], True)
        alive = ~exp.collided & ~exp.reached & ~escaped[nodes.case][:, None]
        p, a = alive.nonzero(as_tuple=True)
        if depth + 1 == horizon:
            escaped |= torch.zeros(C, dtype=torch.bool).index_fill_(0, nodes.case[p], True)
            break
        nodes = exp.children(cfg, nodes, p, a)
    return (~escaped).tolist()
