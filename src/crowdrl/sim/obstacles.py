"""Static obstacles for the batched ORCA: RVO2's ``addObstacle`` and ``processObstacles``, batched.

Polygons come batched as ``obstacles [B, P, V, 2]`` with a vertex mask ``obstacle_mask [B, P, V]``:
polygon ``(b, p)`` has ``n = obstacle_mask[b, p].sum()`` vertices, its valid vertices first
(``obstacle_mask[b, p, :n]`` true, the rest false). ``n = 0`` is no polygon, ``n = 2`` a wall segment
(seen from both sides), ``n >= 3`` a solid polygon whose vertices go counter-clockwise (RVO2's
convention; the agents live outside it). Masked vertices are ignored whatever they hold.

:func:`process_obstacles` turns them into :class:`ObstacleEdges`, the edges RVO2 works with after
``processObstacles``: one edge per vertex (to the next vertex; a wall has two, one per side), each
vertex's convexity, and RVO2's obstacle kd-tree. The tree matters for exactness: building it splits
every edge that crosses the line of an edge chosen as a split node (the new vertex is convex), and
its traversal order breaks ties between equally distant obstacle neighbours. The build here is
RVO2's, vectorised over the batch and over each tree level's pending subtrees; its Python loop runs
over the tree's levels (a few for a few dozen edges), never over scenes or edges.

Obstacles are static: process them once per episode and pass the :class:`ObstacleEdges` to
:func:`crowdrl.sim.orca.orca_velocities` (raw polygons work too and are processed on every call).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

__all__ = ["ObstacleEdges", "process_obstacles", "MAX_TREE_DEPTH", "check_obstacles", "obstacle_segments",
           "segment_distance", "point_obstacle_distance", "path_obstacle_distance", "select_edges", "pad_edges",
           "put_edges", "Segments", "segments_of"]

_EPSILON = 1e-5  # RVO2's RVO_EPSILON, as in crowdrl.sim.orca
MAX_TREE_DEPTH = 39  # obstacle kd-tree levels supported (the traversal key is a base-3 int64)


class ObstacleEdges(NamedTuple):
    """Obstacle edges of ``B`` scenes after RVO2's ``processObstacles``, padded to ``E`` edges.

    An edge starts at an RVO2 obstacle vertex (``obstacle1``) and ends at the next one (``obstacle2``).
    ``direction``, ``prev_direction`` and ``next_direction`` are the ``direction_`` of ``obstacle1``,
    of the vertex before it and of ``obstacle2``: the unit direction of the input polygon's edge the
    piece lies on, of the polygon edge before and of the one after (a split piece keeps its edge's).

    start, end, direction, prev_direction, next_direction: ``[B, E, 2]``.
    start_convex, end_convex: ``[B, E]`` bool, RVO2's ``isConvex_`` of the two vertices.
    valid: ``[B, E]`` bool, false for padding (valid edges come first).
    ancestors: ``[B, E, D]`` long, the edge's ancestors in the obstacle kd-tree, root first (edge
        indices; entries at depth ``>= depth`` are 0 and unused).
    in_left: ``[B, E, D]`` bool, the edge lies in that ancestor's left subtree.
    depth: ``[B, E]`` long, the number of ancestors.
    """

    start: Tensor
    end: Tensor
    direction: Tensor
    prev_direction: Tensor
    next_direction: Tensor
    start_convex: Tensor
    end_convex: Tensor
    valid: Tensor
    ancestors: Tensor
    in_left: Tensor
    depth: Tensor

    @property
    def num_edges(self) -> int:
        return self.valid.shape[1]


def _normalize(v: Tensor) -> Tensor:
    """RVO2's ``normalize``: ``v`` times the reciprocal of its correctly rounded length."""
    sq = v[..., 0] * v[..., 0] + v[..., 1] * v[..., 1]
    length = sq.double().sqrt().to(v.dtype) if v.dtype == torch.float32 else sq.sqrt()
    return v * (1.0 / length).unsqueeze(-1)


def _left_of(a: Tensor, b: Tensor, c: Tensor) -> Tensor:
    """RVO2's ``leftOf(a, b, c) = det(a - c, b - a)``: > 0 when ``c`` lies left of ``a -> b``."""
    return (a[..., 0] - c[..., 0]) * (b[..., 1] - a[..., 1]) - (a[..., 1] - c[..., 1]) * (b[..., 0] - a[..., 0])


def _where_polygon(bad: Tensor) -> str:
    b, p = (int(i) for i in bad.nonzero()[0])
    return f"polygon (b={b}, p={p})"


def _check_polygons(obstacles: Tensor, obstacle_mask: Tensor | None) -> Tensor:
    """Validate the polygons; returns the vertex mask (all true when ``obstacle_mask`` is None)."""
    if not isinstance(obstacles, Tensor) or obstacles.dim() != 4 or obstacles.shape[-1] != 2:
        shape = tuple(obstacles.shape) if isinstance(obstacles, Tensor) else type(obstacles).__name__
        raise ValueError(f"obstacles must be a tensor shaped [B, P, V, 2], got {shape}")
    if not obstacles.is_floating_point():
        raise TypeError(f"obstacles must be a floating tensor, got {obstacles.dtype}")
    if obstacle_mask is None:
        obstacle_mask = torch.ones(obstacles.shape[:3], dtype=torch.bool, device=obstacles.device)
    elif (not isinstance(obstacle_mask, Tensor) or obstacle_mask.dtype != torch.bool
          or obstacle_mask.shape != obstacles.shape[:3]):
        got = (f"{obstacle_mask.dtype} {tuple(obstacle_mask.shape)}" if isinstance(obstacle_mask, Tensor)
               else type(obstacle_mask).__name__)
        raise ValueError(f"obstacle_mask must be a bool tensor shaped {tuple(obstacles.shape[:3])} ([B, P, V]), "
                         f"got {got}")
    elif obstacle_mask.device != obstacles.device:
        raise ValueError(f"obstacle_mask is on {obstacle_mask.device} but obstacles is on {obstacles.device}")
    m = obstacle_mask
    if bool((m[..., 1:] & ~m[..., :-1]).any()):
        raise ValueError(f"obstacle_mask: {_where_polygon((m[..., 1:] & ~m[..., :-1]).any(-1))} has a masked vertex "
                         "before a valid one; a polygon's valid vertices must come first")
    n = m.sum(-1)
    if bool((n == 1).any()):
        raise ValueError(f"obstacles: {_where_polygon(n == 1)} has 1 vertex; a polygon needs at least 2 "
                         "(2 is a wall segment)")
    if bool((~torch.isfinite(obstacles).all(-1) & m).any()):
        raise ValueError(f"obstacles: {_where_polygon((~torch.isfinite(obstacles).all(-1) & m).any(-1))} has a "
                         "NaN or infinite vertex")
    v = obstacles.double().masked_fill(~m.unsqueeze(-1), 0.0)
    k = torch.arange(obstacles.shape[2], device=obstacles.device)
    nxt = torch.where(k + 1 < n.unsqueeze(-1), k + 1, 0)  # [B, P, V]
    w = v.gather(2, nxt.unsqueeze(-1).expand_as(v))
    same = (v == w).all(-1) & m & (n >= 2).unsqueeze(-1)
    if bool(same.any()):
        raise ValueError(f"obstacles: {_where_polygon(same.any(-1))} has two equal consecutive vertices "
                         "(a zero-length edge)")
    area2 = (v[..., 0] * w[..., 1] - v[..., 1] * w[..., 0]).masked_fill(~m, 0).sum(-1)  # twice the signed area
    cw = (n >= 3) & ~(area2 > 0)
    if bool(cw.any()):
        b, p = (int(i) for i in cw.nonzero()[0])
        area = 0.5 * float(area2[b, p])
        what = f"is clockwise (signed area {area:.6g})" if area < 0 else "has zero area"
        raise ValueError(f"obstacles: polygon (b={b}, p={p}) {what}; a solid polygon (3 or more vertices) must "
                         "list its vertices counter-clockwise, as in RVO2")
    return m


def _polygon_edges(obstacles: Tensor, m: Tensor) -> tuple[Tensor, ...]:
    """RVO2's ``addObstacle`` for every polygon: per-vertex edge data, ``[B, P*V, ...]``."""
    B, P, V, _ = obstacles.shape
    dtype, device = obstacles.dtype, obstacles.device
    n = m.sum(-1, keepdim=True)  # [B, P, 1]
    k = torch.arange(V, device=device)
    nxt = torch.where(k + 1 < n, k + 1, 0)
    prv = torch.where(k == 0, (n - 1).clamp_min(0), k - 1)
    pts = torch.where(m.unsqueeze(-1), obstacles, torch.zeros((), dtype=dtype, device=device))
    take = lambda t, idx: t.gather(2, idx.unsqueeze(-1).expand(B, P, V, t.shape[-1]))  # noqa: E731
    nxt_pts, prv_pts = take(pts, nxt), take(pts, prv)
    direction = _normalize(nxt_pts - pts)
    wall = n == 2
    convex = wall | (_left_of(prv_pts, pts, nxt_pts) >= 0)
    valid = m & (n >= 2)
    direction = torch.where(valid.unsqueeze(-1), direction, torch.zeros((), dtype=dtype, device=device))
    flat = lambda t: t.reshape(B, P * V, *t.shape[3:])  # noqa: E731
    return (flat(pts), flat(nxt_pts), flat(direction), flat(take(direction, prv)), flat(take(direction, nxt)),
            flat(convex), flat(take(convex.unsqueeze(-1), nxt).squeeze(-1)), flat(valid))


def _build_tree(start, end, direction, prev_dir, next_dir, start_convex, end_convex, valid):
    """RVO2's ``buildObstacleTreeRecursive``, one tree level per iteration for all scenes.

    Each pending edge belongs to a subtree (``group``: 0 for the root, else ``1 + 2*parent + side``).
    In every subtree the split edge is the first one (RVO2's list order, kept by ``order``) with the
    smallest ``(max, min)`` of the left/right counts; the others go left, right, or are split in two
    at the split edge's line (the new piece gets a new slot at the end and the same ``order``).
    """
    B, E = valid.shape
    device = valid.device
    eps = _EPSILON
    order = torch.arange(E, device=device).expand(B, E)
    group = torch.zeros(B, E, dtype=torch.long, device=device)
    placed = ~valid
    depth = torch.zeros(B, E, dtype=torch.long, device=device)
    ancestors: list[Tensor] = []
    sides: list[Tensor] = []
    level = 0
    while True:
        pending = ~placed
        if not bool(pending.any()):
            break
        if level >= MAX_TREE_DEPTH:
            raise ValueError(f"obstacles: the obstacle kd-tree is deeper than {MAX_TREE_DEPTH} levels "
                             "(too many edges crossing each other's lines)")
        E = valid.shape[1]
        eye = torch.eye(E, dtype=torch.bool, device=device)
        same = pending.unsqueeze(2) & pending.unsqueeze(1) & (group.unsqueeze(2) == group.unsqueeze(1)) & ~eye
        # j against i's line: l1[b, i, j] = leftOf(start_i, end_i, start_j), l2 the same for end_j
        si, ei = start.unsqueeze(2), end.unsqueeze(2)
        l1 = _left_of(si, ei, start.unsqueeze(1))
        l2 = _left_of(si, ei, end.unsqueeze(1))
        left = (l1 >= -eps) & (l2 >= -eps)
        right = ~left & (l1 <= eps) & (l2 <= eps)
        n_left = (same & ~right).sum(-1)
        n_right = (same & ~left).sum(-1)
        score = (torch.maximum(n_left, n_right) * (E + 1) + torch.minimum(n_left, n_right)) * (order.max() + 1) + order
        chosen = pending & ~(same & (score.unsqueeze(1) < score.unsqueeze(2))).any(-1)
        # every other pending edge j against its subtree's split edge c(j)
        sel = same & chosen.unsqueeze(2)  # [b, i, j]: i is j's split edge
        moving = sel.any(1)
        c = sel.to(torch.uint8).argmax(1)  # [B, E]
        l1c = l1.gather(1, c.unsqueeze(1)).squeeze(1)
        l2c = l2.gather(1, c.unsqueeze(1)).squeeze(1)
        go_left = (l1c >= -eps) & (l2c >= -eps)
        go_right = ~go_left & (l1c <= eps) & (l2c <= eps)
        split = moving & ~go_left & ~go_right
        side_left = go_left | (split & (l1c > 0))  # the piece keeping the slot (J1's part)
        depth = torch.where(chosen, level, depth)
        placed = placed | chosen
        parent = torch.where(moving, c, 0)
        new_group = 1 + 2 * c + (~side_left).long()
        group = torch.where(moving, new_group, group)
        ancestors.append(parent)
        sides.append(side_left)
        S = int(split.sum(1).max())
        if S > 0:
            # RVO2: t = det(I2 - I1, J1 - I1) / det(I2 - I1, J1 - J2); split point J1 + t (J2 - J1)
            gat = lambda t: t.gather(1, c.unsqueeze(-1).expand_as(t))  # noqa: E731
            i1, i2 = gat(start), gat(end)
            d, a, w = i2 - i1, start - i1, start - end
            t = (d[..., 0] * a[..., 1] - d[..., 1] * a[..., 0]) / (d[..., 0] * w[..., 1] - d[..., 1] * w[..., 0])
            point = start + t.unsqueeze(-1) * (end - start)
            slot = torch.where(split, split.long().cumsum(1) - 1, S)  # new slot E + slot; S: discarded

            def new(values: Tensor, fill) -> Tensor:
                """The new pieces' ``values`` in ``[B, S, ...]`` (slot order)."""
                buf = values.new_full((B, S + 1) + values.shape[2:], fill)
                idx = slot.view(B, E, *([1] * (values.dim() - 2))).expand_as(values)
                return buf.scatter(1, idx, values)[:, :S]

            # the new piece: split point -> J2, a convex start whose previous direction is J1's own
            extra = dict(
                start=new(point, 0.0), end=new(end, 0.0), direction=new(direction, 0.0),
                prev_dir=new(direction, 0.0), next_dir=new(next_dir, 0.0),
                start_convex=new(torch.ones_like(start_convex), True), end_convex=new(end_convex, True),
                valid=new(split, False), order=new(order, 0), group=new(1 + 2 * c + side_left.long(), 0),
                depth=new(depth, 0), placed=new(~split, True),
            )
            # J1's piece keeps its slot and now ends at the split point (convex, with J1's direction)
            sp = split.unsqueeze(-1)
            end = torch.where(sp, point, end)
            next_dir = torch.where(sp, direction, next_dir)
            end_convex = end_convex | split
            cat = lambda old, key: torch.cat((old, extra[key]), 1)  # noqa: E731
            start, end, direction = cat(start, "start"), cat(end, "end"), cat(direction, "direction")
            prev_dir, next_dir = cat(prev_dir, "prev_dir"), cat(next_dir, "next_dir")
            start_convex, end_convex = cat(start_convex, "start_convex"), cat(end_convex, "end_convex")
            valid, order, group = cat(valid, "valid"), cat(order, "order"), cat(group, "group")
            depth, placed = cat(depth, "depth"), cat(placed, "placed")
            sides[-1] = torch.cat((sides[-1], new(~side_left, False)), 1)
            sides[:-1] = [torch.cat((col, new(col, False)), 1) for col in sides[:-1]]
            ancestors = [torch.cat((col, new(col, 0)), 1) for col in ancestors]
        level += 1
    E = valid.shape[1]
    if ancestors:
        anc = torch.stack(ancestors, -1)
        side = torch.stack(sides, -1)
    else:
        anc = torch.zeros(B, E, 0, dtype=torch.long, device=device)
        side = torch.zeros(B, E, 0, dtype=torch.bool, device=device)
    deep = torch.arange(anc.shape[-1], device=device) < depth.unsqueeze(-1)
    anc = torch.where(deep, anc, 0)
    side = side & deep
    return start, end, direction, prev_dir, next_dir, start_convex, end_convex, valid, anc, side, depth


def process_obstacles(obstacles: Tensor, obstacle_mask: Tensor | None = None) -> ObstacleEdges:
    """RVO2's ``addObstacle`` (every polygon) and ``processObstacles``, batched over scenes.

    Args:
        obstacles: ``[B, P, V, 2]`` polygon vertices (see the module docstring for the convention).
        obstacle_mask: ``[B, P, V]`` bool, valid vertices first in each polygon; ``None``: all valid.

    Returns:
        :class:`ObstacleEdges` in the dtype and device of ``obstacles``, the valid edges first.

    Raises:
        ValueError: a polygon with 1 vertex, a clockwise (or zero-area) solid polygon, a NaN or
            infinite vertex, a zero-length edge, or a malformed mask; the message names the polygon.
    """
    m = _check_polygons(obstacles, obstacle_mask)
    B = obstacles.shape[0]
    edges = _polygon_edges(obstacles, m)
    (start, end, direction, prev_dir, next_dir, start_convex, end_convex, valid, anc, side, depth) = _build_tree(*edges)
    # valid edges first, padded to the largest count; ancestor indices follow the move
    perm = torch.sort((~valid).to(torch.uint8), dim=1, stable=True).indices
    E = int(valid.sum(1).max()) if valid.numel() else 0
    perm = perm[:, :E]
    inverse = torch.zeros(B, valid.shape[1], dtype=torch.long, device=valid.device).scatter_(
        1, perm, torch.arange(E, device=valid.device).expand(B, E).contiguous())
    g = lambda t: t.gather(1, perm.view(B, E, *([1] * (t.dim() - 2))).expand(B, E, *t.shape[2:]))  # noqa: E731
    anc = inverse.gather(1, g(anc).reshape(B, -1)).view(B, E, anc.shape[-1]) if anc.shape[-1] else g(anc)
    return ObstacleEdges(g(start), g(end), g(direction), g(prev_dir), g(next_dir), g(start_convex), g(end_convex),
                         g(valid), anc, g(side), g(depth))


def select_edges(edges: ObstacleEdges, idx) -> ObstacleEdges:
    """The scenes ``idx`` (an index or slice of the batch dimension) of ``edges``."""
    return ObstacleEdges(*(t[idx] for t in edges))


def pad_edges(edges: ObstacleEdges, num_edges: int, depth: int) -> ObstacleEdges:
    """``edges`` padded with invalid edges to ``num_edges`` and with unused kd-tree levels to ``depth``
    (padding is ignored by the solver: the same velocities, bit for bit)."""
    B, E = edges.valid.shape
    D = edges.ancestors.shape[-1]
    if num_edges < E or depth < D:
        raise ValueError(f"cannot pad {E} edges of depth {D} to {num_edges} edges of depth {depth}")

    def pad(t: Tensor) -> Tensor:
        if t is edges.ancestors or t is edges.in_left:
            out = t.new_zeros(B, num_edges, depth)
            out[:, :E, :D] = t
            return out
        out = t.new_zeros((B, num_edges) + t.shape[2:])
        out[:, :E] = t
        return out
    return ObstacleEdges(*(pad(t) for t in edges))


def put_edges(edges: ObstacleEdges, idx: Tensor, new: ObstacleEdges) -> ObstacleEdges:
    """``edges`` with the scenes ``idx [K]`` replaced by ``new`` (``K`` scenes), both padded to the
    larger edge count and tree depth."""
    E = max(edges.num_edges, new.num_edges)
    D = max(edges.ancestors.shape[-1], new.ancestors.shape[-1])
    edges, new = pad_edges(edges, E, D), pad_edges(new, E, D)
    out = []
    for t, n in zip(edges, new):
        t = t.clone()
        t[idx] = n
        out.append(t)
    return ObstacleEdges(*out)


# --- plain geometry of the polygons (collision checks and spawn clearance; not ORCA) -------------

def check_obstacles(obstacles: Tensor, obstacle_mask: Tensor | None = None) -> Tensor:
    """Validate polygons as :func:`process_obstacles` does (fewer than 2 vertices, a clockwise or
    zero-area solid polygon, NaN or infinite vertices, zero-length edges, a malformed mask: a
    ``ValueError`` naming the polygon); returns the vertex mask."""
    return _check_polygons(obstacles, obstacle_mask)


def obstacle_segments(obstacles: Tensor, obstacle_mask: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The edges of the polygons as segments ``a -> b``: ``[B, P*V, 2]`` each and ``valid [B, P*V]``.

    A wall (2 vertices) is one segment; a solid polygon of ``n`` vertices has ``n`` (the last
    closing it). Masked vertices give invalid segments (zeros)."""
    B, P, V, _ = obstacles.shape
    m = obstacle_mask
    n = m.sum(-1, keepdim=True)
    k = torch.arange(V, device=obstacles.device)
    nxt = torch.where(k + 1 < n, k + 1, 0)
    a = torch.where(m.unsqueeze(-1), obstacles, torch.zeros((), dtype=obstacles.dtype, device=obstacles.device))
    b = a.gather(2, nxt.unsqueeze(-1).expand(B, P, V, 2))
    valid = m & ((n >= 3) | ((n == 2) & (k == 0)))
    return a.reshape(B, P * V, 2), b.reshape(B, P * V, 2), valid.reshape(B, P * V)


def _point_segment_sq(px: Tensor, py: Tensor, ax: Tensor, ay: Tensor, bx: Tensor, by: Tensor) -> Tensor:
    """Squared distance of points to segments, on separate x/y components (broadcast; faster than ``[..., 2]``)."""
    ux, uy = bx - ax, by - ay
    wx, wy = px - ax, py - ay
    sq = ux * ux + uy * uy
    t = ((wx * ux + wy * uy) / torch.where(sq > 0, sq, torch.ones_like(sq))).clamp_(0.0, 1.0)
    dx, dy = wx - t * ux, wy - t * uy
    return dx * dx + dy * dy


def _segment_distance_xy(p0x, p0y, p1x, p1y, ax, ay, bx, by) -> Tensor:
    d = torch.minimum(torch.minimum(_point_segment_sq(p0x, p0y, ax, ay, bx, by),
                                    _point_segment_sq(p1x, p1y, ax, ay, bx, by)),
                      torch.minimum(_point_segment_sq(ax, ay, p0x, p0y, p1x, p1y),
                                    _point_segment_sq(bx, by, p0x, p0y, p1x, p1y)))
    ux, uy, qx, qy = bx - ax, by - ay, p1x - p0x, p1y - p0y
    d1 = ux * (p0y - ay) - uy * (p0x - ax)
    d2 = ux * (p1y - ay) - uy * (p1x - ax)
    d3 = qx * (ay - p0y) - qy * (ax - p0x)
    d4 = qx * (by - p0y) - qy * (bx - p0x)
    crossing = (d1 * d2 < 0) & (d3 * d4 < 0)
    return d.masked_fill_(crossing, 0.0).sqrt_()


def segment_distance(p0: Tensor, p1: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """Distance between the segments ``p0 -> p1`` and ``a -> b`` (``[..., 2]``, broadcast): 0 when
    they cross, else the smallest endpoint-to-segment distance. A zero-length ``p0 -> p1`` is a point."""
    p0, p1, a, b = torch.broadcast_tensors(p0, p1, a, b)
    return _segment_distance_xy(*p0.unbind(-1), *p1.unbind(-1), *a.unbind(-1), *b.unbind(-1))


class Segments(NamedTuple):
    """The obstacles' edges (:func:`obstacle_segments`) as components ``[B, 1, S]``, with each polygon's
    solidity ``[B, P]`` and ``V``: computed once, reused by the distance functions (``segments=``)."""

    ax: Tensor
    ay: Tensor
    bx: Tensor
    by: Tensor
    valid: Tensor
    solid: Tensor
    V: int

    def select(self, idx) -> "Segments":
        return Segments(*(t[idx] for t in self[:6]), self.V)


def segments_of(obstacles: Tensor, obstacle_mask: Tensor) -> Segments:
    a, b, valid = obstacle_segments(obstacles, obstacle_mask)
    ax, ay = a.unsqueeze(1).unbind(-1)
    bx, by = b.unsqueeze(1).unbind(-1)
    return Segments(ax, ay, bx, by, valid.unsqueeze(1), obstacle_mask.sum(-1) >= 3, obstacles.shape[2])


def _inside_convex(points: Tensor, seg: Segments) -> Tensor:
    """``points [B, M, 2]`` inside (or on) a convex solid polygon (3+ counter-clockwise vertices): ``[B, M]``."""
    B, P = seg.solid.shape
    if not bool(seg.solid.any()):
        return torch.zeros(points.shape[:2], dtype=torch.bool, device=points.device)
    px, py = points.unsqueeze(-1).unbind(-2)  # [B, M, 1]
    left = ((seg.bx - seg.ax) * (py - seg.ay) - (seg.by - seg.ay) * (px - seg.ax) >= 0) | ~seg.valid  # [B, M, S]
    inside = left.view(B, -1, P, seg.V).all(-1) & seg.solid.unsqueeze(1)
    return inside.any(-1)


def point_obstacle_distance(points: Tensor, obstacles: Tensor | None, obstacle_mask: Tensor | None,
                            segments: Segments | None = None) -> Tensor:
    """Distance ``[B, M]`` of ``points [B, M, 2]`` to the obstacles ``[B, P, V, 2]`` (or their
    precomputed ``segments``): to the nearest edge, 0 inside a solid polygon (taken as convex),
    ``inf`` without obstacles."""
    B, M, _ = points.shape
    seg = segments_of(obstacles, obstacle_mask) if segments is None else segments
    if seg.solid.shape[1] == 0:
        return points.new_full((B, M), float("inf"))
    px, py = points.unsqueeze(-1).unbind(-2)
    d = _point_segment_sq(px, py, seg.ax, seg.ay, seg.bx, seg.by).masked_fill_(~seg.valid, float("inf"))
    d = d.amin(-1).sqrt_()
    return d.masked_fill_(_inside_convex(points, seg), 0.0)


def path_obstacle_distance(start: Tensor, end: Tensor, obstacles: Tensor | None, obstacle_mask: Tensor | None,
                           segments: Segments | None = None) -> Tensor:
    """Distance ``[B, M]`` of the straight paths ``start -> end`` (``[B, M, 2]``) to the obstacle
    edges (or their precomputed ``segments``; ``inf`` without obstacles); a path that starts outside
    a polygon and enters it crosses an edge (0)."""
    B, M, _ = start.shape
    seg = segments_of(obstacles, obstacle_mask) if segments is None else segments
    if seg.solid.shape[1] == 0:
        return start.new_full((B, M), float("inf"))
    p0x, p0y = start.unsqueeze(-1).unbind(-2)
    p1x, p1y = end.unsqueeze(-1).unbind(-2)
    d = _segment_distance_xy(p0x, p0y, p1x, p1y, seg.ax, seg.ay, seg.bx, seg.by)
    return d.masked_fill_(~seg.valid, float("inf")).amin(-1)


def nearest_edges(points: Tensor, obstacles: Tensor, obstacle_mask: Tensor, k: int) -> tuple[Tensor, Tensor]:
    """The ``k`` obstacle edges nearest to ``points [B, 2]``, nearest first: their endpoints
    ``[B, k, 4]`` = (ax, ay, bx, by) and a mask ``[B, k]`` (False: fewer than ``k`` edges; the row is
    zeros). Ties go to the lower edge index (:func:`obstacle_segments`' order), so the result is a
    pure function of the state.

    >>> wall = torch.tensor([[[[-1.0, 1.0], [1.0, 1.0]], [[-1.0, 3.0], [1.0, 3.0]]]])
    >>> edges, mask = nearest_edges(torch.zeros(1, 2), wall, torch.ones(1, 2, 2, dtype=torch.bool), 1)
    >>> edges.tolist(), mask.tolist()
    ([[[-1.0, 1.0, 1.0, 1.0]]], [[True]])
    """
    a, b, valid = obstacle_segments(obstacles, obstacle_mask)  # [B, S, 2], [B, S]
    if isinstance(k, bool) or int(k) != k or k < 0:
        raise ValueError(f"k must be an integer >= 0, got {k!r}")
    S = a.shape[1]
    px, py = points[:, None, 0], points[:, None, 1]
    d = _point_segment_sq(px, py, a[..., 0], a[..., 1], b[..., 0], b[..., 1]).masked_fill(~valid, float("inf"))
    # a stable sort: equal distances keep the edges' order (topk's order among ties is unspecified)
    order = torch.sort(d, dim=-1, stable=True).indices[:, :min(k, S)]
    edges = torch.cat((a, b), -1).gather(1, order.unsqueeze(-1).expand(-1, -1, 4))
    mask = valid.gather(1, order)
    edges = torch.where(mask.unsqueeze(-1), edges, 0.0)
    if order.shape[1] < k:  # fewer edges than tokens: padded rows
        pad = k - order.shape[1]
        edges = torch.cat((edges, edges.new_zeros(edges.shape[0], pad, 4)), 1)
        mask = torch.cat((mask, mask.new_zeros(mask.shape[0], pad)), 1)
    return edges, mask
