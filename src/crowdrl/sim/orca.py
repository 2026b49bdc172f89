"""Batched ORCA (optimal reciprocal collision avoidance), computing what RVO2 2.0 computes.

Every function works on tensors whose leading dimensions are a batch of independent scenes
``[B, N, ...]``; there is no Python loop over scenes or agents. The only Python loops run over
the ORCA lines of an agent (at most ``max_neighbors`` agent lines plus the obstacle lines),
exactly as RVO2's incremental 2-D linear program does, each iteration vectorised over all agents
of all scenes.

Structure (RVO2's ``Agent::computeNewVelocity``):

0. with obstacles (:mod:`crowdrl.sim.obstacles` processes the polygons as RVO2 does): the obstacle
   edges the agent sees (it is right of the edge's line) within ``time_horizon_obst * max_speed +
   radius``, nearest first (ties in RVO2's kd-tree visiting order); one ORCA half-plane per edge
   (collision, legs, cut-off circles or line, with the convexity and "foreign leg" rules), nearest
   first, skipping an edge already covered by the earlier obstacle lines. These lines come first
   and are hard constraints in (4);
1. neighbours: the ``max_neighbors`` nearest other agents with squared distance strictly below
   ``neighbor_dist**2``, nearest first (ties broken by agent index);
2. one ORCA half-plane per neighbour (cut-off circle, left/right leg, or the collision branch
   with the ``1/time_step`` cut-off when the agents overlap);
3. ``linearProgram2``: the velocity closest to the preferred one inside the max-speed disc and
   all half-planes, built incrementally;
4. ``linearProgram3`` when (3) is infeasible: the velocity that minimises the largest agent
   half-plane violation while keeping every obstacle half-plane.

Useful algebra for vectorising (3) and (4): the 1-D program on line ``l`` depends only on
lines ``0..l``, never on the running result, so every line's candidate is computed in
parallel and only the cheap "is the running result violating line l" scan stays sequential.
The same holds for each projected program inside (4), whose start point does not depend on
the running result either.

Bit-level fidelity to RVO2 (float32): square roots are correctly rounded (ATen's CPU ``sqrt``
is not; see :func:`_sqrt`), Vector2 divisions multiply by the reciprocal as RVO2 does, and
neighbour ties go by agent index. Selections use a branch-free bitwise select on large
tensors (ATen's CPU ``where`` mispredicts on irregular masks). :mod:`crowdrl.sim.orca_compiled` is a
compiled backend computing the same thing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import torch
from torch import Tensor

from crowdrl.sim.obstacles import ObstacleEdges, process_obstacles

RVO_EPSILON = 1e-5  # RVO2's RVO_EPSILON (float)

__all__ = ["OrcaParams", "OrcaSolution", "orca_velocities", "orca_solve", "require_finite", "prepare_obstacles",
           "ObstacleEdges", "process_obstacles", "RVO_EPSILON"]


@dataclass(frozen=True)
class OrcaParams:
    """ORCA's constants, RVO2's simulator parameters, the same for every agent of a solve: the one
    argument of :func:`orca_velocities`, :func:`orca_solve` and the compiled backend's
    :func:`~crowdrl.sim.orca_compiled.compiled_orca_solve` that is not a tensor of the scene.

    time_step: simulation step (the collision branch's cut-off is ``1/time_step``).
    neighbor_dist: only agents strictly closer than this are neighbours.
    max_neighbors: at most this many nearest neighbours give ORCA lines.
    time_horizon: ORCA time horizon towards other agents.
    time_horizon_obst: ORCA time horizon towards obstacles (RVO2's ``timeHorizonObst``); an edge is
        an obstacle neighbour within ``time_horizon_obst * max_speed + radius``. ``None``:
        ``time_horizon`` (:attr:`obstacle_horizon`). Unused without obstacles.

    A non-positive time step or horizon, a negative neighbour distance or count are refused
    (``ValueError`` naming the field).
    """

    time_step: float
    neighbor_dist: float
    max_neighbors: int
    time_horizon: float
    time_horizon_obst: float | None = None

    def __post_init__(self) -> None:
        if not self.time_step > 0:
            raise ValueError(f"time_step must be > 0, got {self.time_step}")
        if not self.time_horizon > 0:
            raise ValueError(f"time_horizon must be > 0, got {self.time_horizon}")
        if not self.neighbor_dist >= 0:
            raise ValueError(f"neighbor_dist must be >= 0, got {self.neighbor_dist}")
        if int(self.max_neighbors) != self.max_neighbors or self.max_neighbors < 0:
            raise ValueError(f"max_neighbors must be a non-negative integer, got {self.max_neighbors}")
        if not self.obstacle_horizon > 0:
            raise ValueError(f"time_horizon_obst must be > 0, got {self.time_horizon_obst}")

    @property
    def obstacle_horizon(self) -> float:
        """The time horizon towards obstacles: ``time_horizon_obst``, or ``time_horizon`` if ``None``."""
        return self.time_horizon if self.time_horizon_obst is None else self.time_horizon_obst

    @classmethod
    def from_config(cls, cfg: Any) -> OrcaParams:
        """The humans' ORCA constants of a :class:`~crowdrl.sim.config.CrowdConfig` (its ``time_step``
        and ``orca_*`` fields)."""
        return cls(cfg.time_step, cfg.orca_neighbor_dist, cfg.orca_max_neighbors, cfg.orca_time_horizon,
                   cfg.orca_time_horizon_obst)


class OrcaSolution(NamedTuple):
    """Result of :func:`orca_solve`.

    velocities: ``[B, N, 2]`` new velocities.
    lp_infeasible: ``[B, N]`` bool, the 2-D program was infeasible and RVO2's 3-D fallback ran.
    num_neighbors: ``[B, N]`` number of agent ORCA lines (agent neighbours) of each agent.
    num_obstacle_lines: ``[B, N]`` number of obstacle ORCA lines (RVO2's ``numObstLines``), or
        ``None`` when no obstacles were given.
    """

    velocities: Tensor
    lp_infeasible: Tensor
    num_neighbors: Tensor
    num_obstacle_lines: Tensor | None = None


def _det(ax: Tensor, ay: Tensor, bx: Tensor, by: Tensor) -> Tensor:
    return ax * by - ay * bx


_INT_OF = {torch.float64: torch.int64, torch.float32: torch.int32, torch.float16: torch.int16,
           torch.bfloat16: torch.int16}


def _select(cond: Tensor, a: Tensor, b: Tensor | float) -> Tensor:
    """``torch.where(cond, a, b)``, bit for bit, without branches.

    ATen's CPU ``where`` is a scalar loop whose branch mispredicts on irregular masks (much
    slower than a vectorised op; docs/benchmarks.md); this selects through the integer bit patterns instead.
    """
    if cond.numel() < 4096:  # small: the op count matters more than the mispredictions
        return torch.where(cond, a, b)
    itype = _INT_OF[a.dtype]
    if not isinstance(b, Tensor):
        b = torch.full((), b, dtype=a.dtype, device=a.device)
    bi = b.view(itype)
    m = cond.to(itype).neg_()
    return (a.view(itype) ^ bi).bitwise_and_(m).bitwise_xor_(bi).view(a.dtype)


def _sqrt(x: Tensor) -> Tensor:
    """Correctly rounded square root (IEEE ``sqrt``, what RVO2's ``std::sqrt`` computes).

    ATen's CPU ``sqrt`` goes through MKL's vector math, which is not correctly rounded in
    float32 (it is off by one ulp now and then); the float64 root rounded to float32 is exact
    (double rounding is innocuous for square roots).
    """
    if x.dtype == torch.float32:
        return x.double().sqrt_().float()
    return torch.sqrt(x)


def require_finite(**tensors: Tensor) -> None:
    """Refuse NaN or infinite values with a ``ValueError`` naming the first such argument.

    One ``isfinite().all()`` over all of them at once and one host sync (a small share of a CPU step of
    ``crowd.step``; a check per tensor costs more at small batches: docs/benchmarks.md), once per
    public call, never inside a kernel. Only on failure is each tensor checked alone, to name it."""
    if bool(torch.isfinite(torch.cat([t.reshape(-1) for t in tensors.values()])).all()):
        return
    name = next(name for name, t in tensors.items() if not bool(torch.isfinite(t).all()))
    raise ValueError(f"{name} holds NaN or infinite values; the simulator takes finite inputs only")


def check_orca_inputs(
    positions: Tensor,
    velocities: Tensor,
    pref_velocities: Tensor,
    radius: Tensor,
    max_speed: Tensor,
    mask: Tensor | None,
    params: OrcaParams,
) -> None:
    """Refuse what :func:`orca_solve` and the compiled path cannot take, naming the argument: wrong
    shapes, devices or dtypes (``TypeError``), ``params`` that are not :class:`OrcaParams` (which
    validate themselves), non-finite values."""
    if not isinstance(params, OrcaParams):
        raise TypeError(f"params must be OrcaParams, got {type(params).__name__}")
    if positions.dim() != 3 or positions.shape[-1] != 2:
        raise ValueError(f"positions must be shaped [B, N, 2], got {tuple(positions.shape)}")
    if not positions.is_floating_point():
        raise TypeError(f"positions must be a floating tensor, got {positions.dtype}")
    shape = positions.shape
    for name, t in (("velocities", velocities), ("pref_velocities", pref_velocities)):
        if t.shape != shape:
            raise ValueError(f"{name} must be shaped {tuple(shape)} like positions, got {tuple(t.shape)}")
    for name, t in (("radius", radius), ("max_speed", max_speed)):
        if t.shape != shape[:2]:
            raise ValueError(f"{name} must be shaped {tuple(shape[:2])} ([B, N]), got {tuple(t.shape)}")
    if mask is not None and (mask.shape != shape[:2] or mask.dtype != torch.bool):
        raise ValueError(f"mask must be a bool tensor shaped {tuple(shape[:2])}, got {mask.dtype} {tuple(mask.shape)}")
    for name, t in (
        ("velocities", velocities),
        ("pref_velocities", pref_velocities),
        ("radius", radius),
        ("max_speed", max_speed),
    ) + ((("mask", mask),) if mask is not None else ()):
        if t.device != positions.device:
            raise ValueError(f"{name} is on {t.device} but positions is on {positions.device}")
        if name != "mask" and t.dtype != positions.dtype:
            raise TypeError(f"{name} has dtype {t.dtype} but positions has {positions.dtype}")
    require_finite(positions=positions, velocities=velocities, pref_velocities=pref_velocities, radius=radius,
                   max_speed=max_speed)


# ---------------------------------------------------------------------------------------------
# Layout: every per-line quantity is a contiguous ``[K, A]`` tensor (line slot outer, the
# ``A = B*N`` agents of all scenes inner), so each elementwise op runs over contiguous memory
# with its broadcast operands as whole rows, and a loop over lines slices whole rows.
# ---------------------------------------------------------------------------------------------


def _neighbor_table(
    positions: Tensor, mask: Tensor | None, neighbor_dist: float, max_neighbors: int
) -> tuple[Tensor, Tensor]:
    """Flat indices ``[K, A]`` (into the ``A = B*N`` agents) of each agent's neighbours, nearest
    first with ties by agent index, and their validity ``[K, A]``."""
    B, N, _ = positions.shape
    K = min(int(max_neighbors), N - 1)
    if K <= 0:
        empty = torch.zeros(0, B * N, dtype=torch.long, device=positions.device)
        return empty, empty.bool()
    rel = positions.unsqueeze(1) - positions.unsqueeze(2)  # [B, i, j, 2] = p_j - p_i
    dist_sq = rel[..., 0] * rel[..., 0] + rel[..., 1] * rel[..., 1]
    excluded = ~(dist_sq < neighbor_dist * neighbor_dist)
    excluded.diagonal(dim1=1, dim2=2).fill_(True)
    if mask is not None:
        excluded = excluded | ~mask.unsqueeze(1) | ~mask.unsqueeze(2)
    dist_sq.masked_fill_(excluded, float("inf"))
    sorted_d, order = torch.sort(dist_sq, dim=-1, stable=True)
    order = order[..., :K] + (torch.arange(B, device=positions.device) * N).view(B, 1, 1)
    flat = order.permute(2, 0, 1).reshape(K, B * N)
    valid = torch.isfinite(sorted_d[..., :K]).permute(2, 0, 1).reshape(K, B * N)
    return flat, valid


def agent_line_math(px, py, vx, vy, comb_r, own_vx, own_vy, inv_th, inv_ts, where=_select, sqrt=_sqrt):
    """ORCA half-plane ``(dir_x, dir_y, point_x, point_y)`` from the neighbour's relative
    position ``p``, relative velocity ``v = v_self - v_other`` and combined radius, elementwise
    (RVO2's ``computeNewVelocity`` without obstacles)."""
    dist_sq = px * px + py * py
    comb_r_sq = comb_r * comb_r
    # No collision: project on the cut-off circle or on a leg of the velocity obstacle.
    wx = vx - inv_th * px
    wy = vy - inv_th * py
    w_len_sq = wx * wx + wy * wy
    dot1 = wx * px + wy * py
    on_cutoff = (dot1 < 0) & (dot1 * dot1 > comb_r_sq * w_len_sq)
    w_len = sqrt(w_len_sq)
    inv_w_len = 1.0 / w_len  # RVO2 divides a Vector2 by multiplying with the reciprocal
    ux_hat = wx * inv_w_len
    uy_hat = wy * inv_w_len
    cut_s = comb_r * inv_th - w_len
    leg = sqrt(torch.clamp(dist_sq - comb_r_sq, min=0))
    left = _det(px, py, wx, wy) > 0
    inv_dist_sq = 1.0 / dist_sq
    leg_dx = where(left, (px * leg - py * comb_r) * inv_dist_sq, -(px * leg + py * comb_r) * inv_dist_sq)
    leg_dy = where(left, (px * comb_r + py * leg) * inv_dist_sq, -(-px * comb_r + py * leg) * inv_dist_sq)
    dot2 = vx * leg_dx + vy * leg_dy
    free_dx = where(on_cutoff, uy_hat, leg_dx)
    free_dy = where(on_cutoff, -ux_hat, leg_dy)
    free_ux = where(on_cutoff, cut_s * ux_hat, dot2 * leg_dx - vx)
    free_uy = where(on_cutoff, cut_s * uy_hat, dot2 * leg_dy - vy)
    # Collision: project on the cut-off circle of time time_step.
    cwx = vx - inv_ts * px
    cwy = vy - inv_ts * py
    cw_len = sqrt(cwx * cwx + cwy * cwy)
    inv_cw_len = 1.0 / cw_len
    cux_hat = cwx * inv_cw_len
    cuy_hat = cwy * inv_cw_len
    col_s = comb_r * inv_ts - cw_len
    colliding = ~(dist_sq > comb_r_sq)
    dx = where(colliding, cuy_hat, free_dx)
    dy = where(colliding, -cux_hat, free_dy)
    ux = where(colliding, col_s * cux_hat, free_ux)
    uy = where(colliding, col_s * cuy_hat, free_uy)
    return dx, dy, own_vx + 0.5 * ux, own_vy + 0.5 * uy


def _lines_t(
    positions: Tensor, velocities: Tensor, radius: Tensor, flat: Tensor, time_step: float, time_horizon: float
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """ORCA half-planes, each ``[K, A]``, of the neighbours ``flat`` (``[K, A]``)."""
    K, A = flat.shape
    own = torch.cat((positions.reshape(A, 2).t(), velocities.reshape(A, 2).t(), radius.reshape(1, A)), 0)
    other = own.index_select(1, flat.reshape(-1)).view(5, K, A)
    one = torch.ones((), dtype=positions.dtype, device=positions.device)
    return agent_line_math(
        other[0] - own[0], other[1] - own[1], own[2] - other[2], own[3] - other[3], own[4] + other[4],
        own[2], own[3], one / time_horizon, one / time_step,
    )


def _per_agent(t: Tensor, N: int) -> Tensor:
    """Edge attribute ``t`` (``[B, E]`` or ``[B, E, 2]``) for each of the ``A = B*N`` agents of the
    scenes: ``[E, A]`` or ``[2, E, A]`` (contiguous, agents innermost)."""
    B, E = t.shape[:2]
    if t.dim() == 2:
        return t.t().unsqueeze(-1).expand(E, B, N).reshape(E, B * N)
    return t.permute(2, 1, 0).unsqueeze(-1).expand(2, E, B, N).reshape(2, E, B * N)


def _obstacle_neighbor_table(
    positions: Tensor, radius: Tensor, max_speed: Tensor, mask: Tensor | None, edges: ObstacleEdges,
    time_horizon_obst: float,
) -> tuple[Tensor, Tensor]:
    """RVO2's ``computeObstacleNeighbors`` for every agent: the edge indices ``[O, A]`` (into its
    scene's ``E`` edges) of each agent's obstacle neighbours, nearest first, and their validity,
    ``O`` the largest neighbour count.

    An edge is a neighbour when the agent is strictly right of its line (it sees the edge's outer
    side) and the squared point-segment distance is below ``(time_horizon_obst*max_speed + radius)**2``;
    the kd-tree query's pruning is applied too, and equal distances keep the query's visiting order
    (at each tree node: the subtree on the agent's side, the node, then the other subtree)."""
    B, N, _ = positions.shape
    A, E, D = B * N, edges.num_edges, edges.ancestors.shape[-1]
    device = positions.device
    a, b = _per_agent(edges.start, N), _per_agent(edges.end, N)  # [2, E, A]
    pos = positions.reshape(A, 2).t()
    ex, ey = b[0] - a[0], b[1] - a[1]
    left_of = _det(a[0] - pos[0], a[1] - pos[1], ex, ey)  # RVO2's leftOf(start, end, position)
    e_sq = ex * ex + ey * ey
    line_sq = left_of * left_of / e_sq
    tho = torch.tensor(time_horizon_obst, dtype=positions.dtype, device=device)
    reach = tho * max_speed.reshape(A) + radius.reshape(A)
    range_sq = reach * reach
    # Agent::insertObstacleNeighbor's point-segment distance
    apx, apy = pos[0] - a[0], pos[1] - a[1]
    r = (apx * ex + apy * ey) / e_sq
    bpx, bpy = pos[0] - b[0], pos[1] - b[1]
    fx, fy = pos[0] - (a[0] + r * ex), pos[1] - (a[1] + r * ey)
    dist_sq = _select(r < 0, apx * apx + apy * apy, _select(r > 1, bpx * bpx + bpy * bpy, fx * fx + fy * fy))
    found = _per_agent(edges.valid, N) & (left_of < 0) & (line_sq < range_sq) & (dist_sq < range_sq)
    if mask is not None:
        found &= mask.reshape(A)
    key = torch.zeros(E, A, dtype=torch.long, device=device)
    depth = _per_agent(edges.depth, N)
    for k in range(D):  # the query reaches the edge's node, and its visiting-order key (base 3)
        anc = _per_agent(edges.ancestors[..., k], N)
        near = (left_of.gather(0, anc) >= 0) == _per_agent(edges.in_left[..., k], N)
        deep = depth > k
        found &= ~deep | near | (line_sq.gather(0, anc) < range_sq)
        key = key * 3 + 1 + deep * (1 - 2 * near.long())
    visit = torch.sort(key, dim=0).indices
    d = _select(found, dist_sq, float("inf"))
    sorted_d, by_dist = torch.sort(d.gather(0, visit), dim=0, stable=True)
    O = int(found.sum(0).max()) if found.numel() else 0
    return visit.gather(0, by_dist[:O]), torch.isfinite(sorted_d[:O])


def obstacle_line_math(r1x, r1y, r2x, r2y, ex, ey, ux, uy, pvx, pvy, nvx, nvy, convex1, convex2,
                       vx, vy, radius, inv_tho, where=_select, sqrt=_sqrt):
    """ORCA half-plane ``(dir_x, dir_y, point_x, point_y)`` of an obstacle edge, elementwise, and
    whether RVO2 adds one (RVO2's ``computeNewVelocity``, obstacle part, before the
    "already covered" test).

    ``r1``, ``r2``: edge start and end relative to the agent; ``e``: end - start; ``u``, ``pv``,
    ``nv``: directions of the edge, of the vertex before and of the end vertex; ``convex1``,
    ``convex2``: the two vertices' convexity; ``v``: the agent's velocity."""
    dist_sq1 = r1x * r1x + r1y * r1y
    dist_sq2 = r2x * r2x + r2y * r2y
    r_sq = radius * radius
    s = (-r1x * ex + -r1y * ey) / (ex * ex + ey * ey)
    lx, ly = -r1x - s * ex, -r1y - s * ey
    dist_sq_line = lx * lx + ly * ly
    # Collisions: with the start vertex, the end vertex, or the segment.
    hit1 = (s < 0) & (dist_sq1 <= r_sq)
    hit2 = ~hit1 & (s > 1) & (dist_sq2 <= r_sq)
    hit_seg = ~hit1 & ~hit2 & (s >= 0) & (s <= 1) & (dist_sq_line <= r_sq)
    hit = hit1 | hit2 | hit_seg
    inv1 = 1.0 / sqrt(dist_sq1)
    inv2 = 1.0 / sqrt(dist_sq2)
    hit_dx = where(hit1, -r1y * inv1, where(hit2, -r2y * inv2, -ux))
    hit_dy = where(hit1, r1x * inv1, where(hit2, r2x * inv2, -uy))
    hit_line = (hit1 & convex1) | (hit2 & convex2 & (_det(r2x, r2y, nvx, nvy) >= 0)) | hit_seg
    # No collision: legs (both from one vertex when the edge is seen obliquely).
    oblique1 = (s < 0) & (dist_sq_line <= r_sq)
    oblique2 = ~oblique1 & (s > 1) & (dist_sq_line <= r_sq)
    ignored = (oblique1 & ~convex1) | (oblique2 & ~convex2)
    single = oblique1 | oblique2
    leg1 = sqrt(torch.clamp(dist_sq1 - r_sq, min=0))
    leg2 = sqrt(torch.clamp(dist_sq2 - r_sq, min=0))
    id1, id2 = 1.0 / dist_sq1, 1.0 / dist_sq2
    l1x, l1y = (r1x * leg1 - r1y * radius) * id1, (r1x * radius + r1y * leg1) * id1  # left leg, start vertex
    g1x, g1y = (r1x * leg1 + r1y * radius) * id1, (-r1x * radius + r1y * leg1) * id1  # right leg, start vertex
    l2x, l2y = (r2x * leg2 - r2y * radius) * id2, (r2x * radius + r2y * leg2) * id2
    g2x, g2y = (r2x * leg2 + r2y * radius) * id2, (-r2x * radius + r2y * leg2) * id2
    # the effective obstacle1/obstacle2 (both the start vertex, both the end vertex, or as given)
    left_x = where(oblique1, l1x, where(oblique2, l2x, where(convex1, l1x, -ux)))
    left_y = where(oblique1, l1y, where(oblique2, l2y, where(convex1, l1y, -uy)))
    right_x = where(oblique1, g1x, where(oblique2, g2x, where(convex2, g2x, ux)))
    right_y = where(oblique1, g1y, where(oblique2, g2y, where(convex2, g2y, uy)))
    c1x, c1y = where(oblique2, r2x, r1x), where(oblique2, r2y, r1y)
    c2x, c2y = where(oblique1, r1x, r2x), where(oblique1, r1y, r2y)
    o1_convex = torch.where(oblique2, convex2, convex1)
    o2_convex = torch.where(oblique1, convex1, convex2)
    o1_px, o1_py = where(oblique2, ux, pvx), where(oblique2, uy, pvy)  # direction of obstacle1's previous
    o1_ux, o1_uy = where(oblique2, nvx, ux), where(oblique2, nvy, uy)  # obstacle1's direction
    o2_ux, o2_uy = where(oblique1, ux, nvx), where(oblique1, uy, nvy)  # obstacle2's direction
    # Legs never point into the neighbouring edge of a convex vertex: take that edge instead
    # ("foreign" leg: projecting on it adds no line).
    left_foreign = o1_convex & (_det(left_x, left_y, -o1_px, -o1_py) >= 0)
    left_x, left_y = where(left_foreign, -o1_px, left_x), where(left_foreign, -o1_py, left_y)
    right_foreign = o2_convex & (_det(right_x, right_y, o2_ux, o2_uy) <= 0)
    right_x, right_y = where(right_foreign, o2_ux, right_x), where(right_foreign, o2_uy, right_y)
    # Cut-off centres and the projection of the velocity on the velocity obstacle.
    lcx, lcy = inv_tho * c1x, inv_tho * c1y
    rcx, rcy = inv_tho * c2x, inv_tho * c2y
    cvx, cvy = rcx - lcx, rcy - lcy
    wlx, wly = vx - lcx, vy - lcy
    wrx, wry = vx - rcx, vy - rcy
    t = where(~single, (wlx * cvx + wly * cvy) / (cvx * cvx + cvy * cvy), 0.5)
    t_left = wlx * left_x + wly * left_y
    t_right = wrx * right_x + wry * right_y
    on_left = ((t < 0) & (t_left < 0)) | (single & (t_left < 0) & (t_right < 0))
    on_right = ~on_left & (t > 1) & (t_right < 0)
    wx, wy = where(on_left, wlx, wrx), where(on_left, wly, wry)
    inv_w = 1.0 / sqrt(wx * wx + wy * wy)
    uwx, uwy = wx * inv_w, wy * inv_w
    ri = radius * inv_tho
    inf = float("inf")
    kx, ky = vx - (lcx + t * cvx), vy - (lcy + t * cvy)
    d_cut = where(~((t < 0) | (t > 1) | single), kx * kx + ky * ky, inf)
    kx, ky = vx - (lcx + t_left * left_x), vy - (lcy + t_left * left_y)
    d_left = where(~(t_left < 0), kx * kx + ky * ky, inf)
    kx, ky = vx - (rcx + t_right * right_x), vy - (rcy + t_right * right_y)
    d_right = where(~(t_right < 0), kx * kx + ky * ky, inf)
    on_cut = (d_cut <= d_left) & (d_cut <= d_right)
    on_leg_left = ~on_cut & (d_left <= d_right)
    circle = on_left | on_right
    # the line's direction and the unit normal the point is offset along (radius/tau_obst)
    dx = where(circle, uwy, where(on_cut, -o1_ux, where(on_leg_left, left_x, -right_x)))
    dy = where(circle, -uwx, where(on_cut, -o1_uy, where(on_leg_left, left_y, -right_y)))
    nx = where(circle, uwx, where(on_cut, o1_uy, where(on_leg_left, -left_y, right_y)))
    ny = where(circle, uwy, where(on_cut, -o1_ux, where(on_leg_left, left_x, -right_x)))
    base_x = where(on_right | (~circle & ~on_cut & ~on_leg_left), rcx, lcx)
    base_y = where(on_right | (~circle & ~on_cut & ~on_leg_left), rcy, lcy)
    qx, qy = base_x + ri * nx, base_y + ri * ny
    free_line = ~ignored & (circle | on_cut | (on_leg_left & ~left_foreign) | (~on_leg_left & ~on_cut & ~right_foreign))
    dx, dy = where(hit, hit_dx, dx), where(hit, hit_dy, dy)
    qx, qy = where(~hit, qx, 0.0), where(~hit, qy, 0.0)
    return dx, dy, qx, qy, torch.where(hit, hit_line, free_line)


def _obstacle_lines_t(
    positions: Tensor, velocities: Tensor, radius: Tensor, edges: ObstacleEdges, slot: Tensor, found: Tensor,
    time_horizon_obst: float,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Obstacle ORCA lines ``[O, A]`` of the neighbour edges ``slot`` (``[O, A]``, from
    :func:`_obstacle_neighbor_table`) and which are kept: RVO2's lines, minus those of edges
    "already covered" by earlier (nearer) obstacle lines.

    The covered test is sequential over the ``O`` slots (the padded largest neighbour count): a
    Python loop over slots in distance order, each iteration vectorised over all agents."""
    O, A = slot.shape
    N = positions.shape[1]
    slot2 = slot.unsqueeze(0).expand(2, O, A)
    take = lambda t: _per_agent(t, N).gather(-2, slot if t.dim() == 2 else slot2)  # noqa: E731
    a, b, u, pv, nv = (take(t) for t in (edges.start, edges.end, edges.direction, edges.prev_direction,
                                         edges.next_direction))
    pos = positions.reshape(A, 2).t()
    vel = velocities.reshape(A, 2).t()
    r1x, r1y = a[0] - pos[0], a[1] - pos[1]
    r2x, r2y = b[0] - pos[0], b[1] - pos[1]
    one = torch.ones((), dtype=positions.dtype, device=positions.device)
    inv_tho = one / time_horizon_obst
    rad = radius.reshape(A)
    dx, dy, qx, qy, has = obstacle_line_math(
        r1x, r1y, r2x, r2y, b[0] - a[0], b[1] - a[1], u[0], u[1], pv[0], pv[1], nv[0], nv[1],
        take(edges.start_convex), take(edges.end_convex), vel[0], vel[1], rad, inv_tho,
    )
    has &= found
    # covers[j, o]: both ends of edge o are beyond line j by the radius (up to RVO_EPSILON)
    ri = inv_tho * rad
    covers = None
    for rx_, ry_ in ((r1x, r1y), (r2x, r2y)):
        gx = inv_tho * rx_.unsqueeze(0) - qx.unsqueeze(1)
        gy = inv_tho * ry_.unsqueeze(0) - qy.unsqueeze(1)
        beyond = _det(gx, gy, dx.unsqueeze(1), dy.unsqueeze(1)) - ri >= -RVO_EPSILON
        covers = beyond if covers is None else covers & beyond
    kept = has.clone()
    for o in range(1, O):
        kept[o] &= ~(covers[:o, o] & kept[:o]).any(0)
    dx, dy = _select(kept, dx, 1.0), _select(kept, dy, 0.0)  # harmless where not kept
    qx, qy = _select(kept, qx, 0.0), _select(kept, qy, 0.0)
    return dx, dy, qx, qy, kept


def _lp1_candidates_t(
    dx: Tensor, dy: Tensor, qx: Tensor, qy: Tensor, keep: Tensor, radius: Tensor,
    opt_x: Tensor, opt_y: Tensor, direction_opt: bool,
) -> tuple[Tensor, Tensor, Tensor]:
    """RVO2's ``linearProgram1`` for every line ``l`` at once, against the kept lines ``i < l``.

    Lines are ``[L, ...]`` (first dimension); ``radius``, ``opt_*`` broadcast against ``[...]``.
    Returns candidate ``(x, y)`` and ``feasible``, each ``[L, ...]``."""
    L = dx.shape[0]
    dot = qx * dx + qy * dy
    disc = dot * dot + radius * radius - (qx * qx + qy * qy)
    sq = _sqrt(torch.clamp(disc, min=0))
    t_left = -dot - sq
    t_right = dot.neg_().add_(sq)
    feasible = disc >= 0
    for i in range(L - 1):
        # earlier line i against every later line l > i
        dxl, dyl = dx[i + 1 :], dy[i + 1 :]
        denom = _det(dxl, dyl, dx[i], dy[i])
        numer = _det(dx[i], dy[i], qx[i + 1 :] - qx[i], qy[i + 1 :] - qy[i])
        parallel = torch.abs(denom) <= RVO_EPSILON
        act = keep[i]
        feasible[i + 1 :] &= ~(parallel & (numer < 0) & act)
        t = numer.div_(denom)  # masked below wherever parallel
        bounding = ~parallel & act
        pos = denom >= 0
        torch.minimum(t_right[i + 1 :], _select(bounding & pos, t, float("inf")), out=t_right[i + 1 :])
        torch.maximum(t_left[i + 1 :], _select(bounding & ~pos, t, float("-inf")), out=t_left[i + 1 :])
    feasible &= ~(t_left > t_right)
    if direction_opt:
        t_opt = _select((opt_x * dx + opt_y * dy) > 0, t_right, t_left)
    else:
        t_opt = dx * (opt_x - qx) + dy * (opt_y - qy)
        t_opt = _select(t_opt < t_left, t_left, _select(t_opt > t_right, t_right, t_opt))
    return qx + t_opt * dx, qy + t_opt * dy, feasible


def _lp2_scan_t(
    dx: Tensor, dy: Tensor, qx: Tensor, qy: Tensor, keep: Tensor,
    cand_x: Tensor, cand_y: Tensor, cand_ok: Tensor, start_x: Tensor, start_y: Tensor,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """RVO2's ``linearProgram2`` loop given the per-line candidates (lines ``[L, ...]``).

    Returns the result ``(x, y)``, ``failed`` and the index of the failing line (``L`` if none).
    On failure the result is the one before the failing line, as in RVO2."""
    L = dx.shape[0]
    rx, ry = start_x.clone(), start_y.clone()
    failed = torch.zeros_like(rx, dtype=torch.bool)
    fail_line = torch.full_like(rx, L, dtype=torch.long)
    for l in range(L):
        violated = _det(dx[l], dy[l], qx[l] - rx, qy[l] - ry) > 0
        violated &= keep[l]
        violated &= ~failed
        move = violated & cand_ok[l]
        rx = _select(move, cand_x[l], rx)
        ry = _select(move, cand_y[l], ry)
        new_fail = violated & ~cand_ok[l]
        fail_line.masked_fill_(new_fail, l)
        failed |= new_fail
    return rx, ry, failed, fail_line


def _lp3_t(
    dx: Tensor, dy: Tensor, qx: Tensor, qy: Tensor, keep: Tensor, begin: Tensor,
    radius: Tensor, rx: Tensor, ry: Tensor, n_obst: int = 0,
) -> tuple[Tensor, Tensor]:
    """RVO2's ``linearProgram3``: lines ``[L, M]`` for agents ``[M]``, the first ``n_obst`` obstacle lines.

    Obstacle lines are hard constraints: every projected program keeps them as they are (all of
    them, also for a line ``i < n_obst``) and only the later agent lines ``j < i`` are projected."""
    L = dx.shape[0]
    i0 = int(begin.min())  # lines i < i0 are never violated in the loop below: no projected program
    # Projected lines for every (j, i) with j < i, i >= i0: [j, i - i0, M].
    dxi, dyi, qxi, qyi = (t[i0:].unsqueeze(0) for t in (dx, dy, qx, qy))
    dxj, dyj, qxj, qyj = (t.unsqueeze(1) for t in (dx, dy, qx, qy))
    determinant = _det(dxi, dyi, dxj, dyj)
    parallel = torch.abs(determinant) <= RVO_EPSILON
    same_dir = (dxi * dxj + dyi * dyj) > 0
    safe_det = torch.where(parallel, torch.ones_like(determinant), determinant)
    s = _det(dxj, dyj, qxi - qxj, qyi - qyj) / safe_det
    px_ = torch.where(parallel, 0.5 * (qxi + qxj), qxi + s * dxi)
    py_ = torch.where(parallel, 0.5 * (qyi + qyj), qyi + s * dyi)
    ddx = dxj - dxi
    ddy = dyj - dyi
    dlen = _sqrt(ddx * ddx + ddy * ddy)
    inv_dlen = 1.0 / dlen
    pdx = ddx * inv_dlen
    pdy = ddy * inv_dlen
    earlier = torch.ones(L, L, dtype=torch.bool, device=dx.device).triu(1)[:, i0:].unsqueeze(-1)  # j < i
    pkeep = earlier & keep[i0:].unsqueeze(0) & keep.unsqueeze(1) & ~(parallel & same_dir)
    if n_obst > 0:  # rows j < n_obst: the obstacle line j itself, for every i
        O = n_obst
        shape = (O,) + pdx.shape[1:]
        pdx, pdy, px_, py_ = (torch.cat((t[:O].unsqueeze(1).expand(shape), p[O:]), 0)
                              for t, p in ((dx, pdx), (dy, pdy), (qx, px_), (qy, py_)))
        pkeep = torch.cat((keep[:O].unsqueeze(1).expand(shape), pkeep[O:]), 0)

    # Direction-optimising LP2 for each i, all at once: optimise towards (-dir_i.y, dir_i.x).
    opt_x, opt_y = -dy[i0:], dx[i0:]  # [i - i0, M]
    r = radius.unsqueeze(0)
    cx, cy, cok = _lp1_candidates_t(pdx, pdy, px_, py_, pkeep, r, opt_x, opt_y, direction_opt=True)
    sol_x, sol_y, sol_fail, _ = _lp2_scan_t(pdx, pdy, px_, py_, pkeep, cx, cy, cok, opt_x * r, opt_y * r)

    distance = torch.zeros_like(rx)
    for i in range(i0, L):
        violation = _det(dx[i], dy[i], qx[i] - rx, qy[i] - ry)
        active = keep[i] & (begin <= i) & (violation > distance)
        take = active & ~sol_fail[i - i0]
        rx = torch.where(take, sol_x[i - i0], rx)
        ry = torch.where(take, sol_y[i - i0], ry)
        new_distance = _det(dx[i], dy[i], qx[i] - rx, qy[i] - ry)
        distance = torch.where(active, new_distance, distance)
    return rx, ry


def prepare_obstacles(
    positions: Tensor,
    obstacles: Tensor | ObstacleEdges | None,
    obstacle_mask: Tensor | None,
) -> ObstacleEdges | None:
    """Validate the obstacle arguments of :func:`orca_solve` against the agents' ``positions``;
    returns the processed edges (``None`` without obstacles)."""
    if obstacles is None:
        if obstacle_mask is not None:
            raise ValueError("obstacle_mask is given but obstacles is None")
        return None
    B = positions.shape[0]
    if isinstance(obstacles, ObstacleEdges):
        if obstacle_mask is not None:
            raise ValueError("obstacle_mask must be None when obstacles are ObstacleEdges (already processed)")
        edges = obstacles
    else:
        if isinstance(obstacles, Tensor) and obstacles.device != positions.device:
            raise ValueError(f"obstacles is on {obstacles.device} but positions is on {positions.device}")
        if isinstance(obstacle_mask, Tensor) and obstacle_mask.device != positions.device:
            raise ValueError(f"obstacle_mask is on {obstacle_mask.device} but positions is on {positions.device}")
        edges = process_obstacles(obstacles, obstacle_mask)
    if edges.start.device != positions.device:
        raise ValueError(f"obstacles is on {edges.start.device} but positions is on {positions.device}")
    if edges.start.dtype != positions.dtype:
        raise TypeError(f"obstacles has dtype {edges.start.dtype} but positions has {positions.dtype}")
    if edges.start.shape[0] != B:
        raise ValueError(f"obstacles has {edges.start.shape[0]} scenes but positions has {B}")
    return edges


def orca_solve(
    positions: Tensor,
    velocities: Tensor,
    pref_velocities: Tensor,
    radius: Tensor,
    max_speed: Tensor,
    params: OrcaParams,
    *,
    mask: Tensor | None = None,
    obstacles: Tensor | ObstacleEdges | None = None,
    obstacle_mask: Tensor | None = None,
) -> OrcaSolution:
    """ORCA new velocities with diagnostics; see :func:`orca_velocities` for the arguments."""
    check_orca_inputs(positions, velocities, pref_velocities, radius, max_speed, mask, params)
    edges = prepare_obstacles(positions, obstacles, obstacle_mask)
    tho = params.obstacle_horizon
    B, N, _ = positions.shape
    A = B * N
    flat, valid = _neighbor_table(positions, mask, params.neighbor_dist, params.max_neighbors)
    K = flat.shape[0]
    n_obst_lines = None
    O = 0
    if edges is not None:
        slot, found = _obstacle_neighbor_table(positions, radius, max_speed, mask, edges, tho)
        O = slot.shape[0]
        if O > 0:
            odx, ody, oqx, oqy, okeep = _obstacle_lines_t(positions, velocities, radius, edges, slot, found, tho)
            n_obst_lines = okeep.sum(0).view(B, N)
        else:
            n_obst_lines = torch.zeros(B, N, dtype=torch.long, device=positions.device)

    # linearProgram2 towards the preferred velocity (clipped to the max-speed disc).
    pref = pref_velocities.reshape(A, 2).t()
    ox, oy = pref[0], pref[1]
    ms = max_speed.reshape(A)
    o_sq = ox * ox + oy * oy
    outside = o_sq > ms * ms
    inv_o_len = 1.0 / _sqrt(o_sq)
    start_x = _select(outside, ox * inv_o_len * ms, ox)
    start_y = _select(outside, oy * inv_o_len * ms, oy)
    if K + O == 0:
        rx, ry, failed = start_x, start_y, torch.zeros_like(outside)
    else:
        if K > 0:
            dx, dy, qx, qy = _lines_t(positions, velocities, radius, flat, params.time_step, params.time_horizon)
            keep = valid
        if O > 0:  # obstacle lines first (RVO2's numObstLines)
            if K > 0:
                dx, dy, qx, qy = (torch.cat(p, 0) for p in ((odx, dx), (ody, dy), (oqx, qx), (oqy, qy)))
                keep = torch.cat((okeep, valid), 0)
            else:
                dx, dy, qx, qy, keep = odx, ody, oqx, oqy, okeep
        cx, cy, cok = _lp1_candidates_t(dx, dy, qx, qy, keep, ms, ox, oy, direction_opt=False)
        rx, ry, failed, fail_line = _lp2_scan_t(dx, dy, qx, qy, keep, cx, cy, cok, start_x, start_y)
        if bool(failed.any()):
            idx = failed.nonzero().squeeze(1)
            sub = lambda t: t.index_select(-1, idx)
            fx, fy = _lp3_t(sub(dx), sub(dy), sub(qx), sub(qy), sub(keep), sub(fail_line), sub(ms), sub(rx), sub(ry),
                            n_obst=O)
            rx = rx.index_copy(0, idx, fx)
            ry = ry.index_copy(0, idx, fy)

    new_v = torch.stack((rx, ry), dim=-1).view(B, N, 2)
    failed = failed.view(B, N)
    if mask is not None:
        new_v = torch.where(mask.unsqueeze(-1), new_v, velocities)
        failed = failed & mask
    return OrcaSolution(new_v, failed, valid.sum(0).view(B, N), n_obst_lines)


def orca_velocities(
    positions: Tensor,
    velocities: Tensor,
    pref_velocities: Tensor,
    radius: Tensor,
    max_speed: Tensor,
    params: OrcaParams,
    *,
    mask: Tensor | None = None,
    obstacles: Tensor | ObstacleEdges | None = None,
    obstacle_mask: Tensor | None = None,
) -> Tensor:
    """The velocities RVO2 computes in one ``doStep`` for a batch of scenes.

    Args:
        positions, velocities, pref_velocities: ``[B, N, 2]`` current state and preferences.
        radius, max_speed: ``[B, N]`` per-agent radius and speed limit.
        params: the constants (:class:`OrcaParams`: time step, neighbour distance and count, time
            horizons towards agents and obstacles).
        mask: optional ``[B, N]`` bool, ``False`` marks an absent agent: it is nobody's neighbour
            and its velocity is returned unchanged.
        obstacles: optional static obstacles, RVO2 polygons ``[B, P, V, 2]`` (counter-clockwise
            vertices for a solid polygon, 2 vertices for a wall segment; see
            :mod:`crowdrl.sim.obstacles`), or the :class:`~crowdrl.sim.obstacles.ObstacleEdges` that
            :func:`~crowdrl.sim.obstacles.process_obstacles` made of them (process static obstacles
            once, not on every step). ``None``: open space.
        obstacle_mask: ``[B, P, V]`` bool with polygon tensors: polygon ``(b, p)`` has the vertices
            ``obstacle_mask[b, p]`` marks, valid ones first; all-false is no polygon. ``None``: all valid.

    Returns:
        ``[B, N, 2]`` new velocities, the dtype and device of the inputs.
    """
    return orca_solve(positions, velocities, pref_velocities, radius, max_speed, params, mask=mask, obstacles=obstacles,
                      obstacle_mask=obstacle_mask).velocities
