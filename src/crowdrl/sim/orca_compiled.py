"""Compiled (``torch.compile`` / inductor) backend of the batched ORCA of :mod:`crowdrl.sim.orca`.

:func:`compiled_orca_solve` computes what :func:`crowdrl.sim.orca.orca_solve` computes (and so
what RVO2 2.0 computes) for the same inputs, returning the same
:class:`~crowdrl.sim.orca.OrcaSolution`; ``CrowdConfig(orca_backend="compiled")`` makes the simulator step with it.

Design (what makes inductor's C++ backend produce fast code on a CPU):

* **Scenes innermost.** The inputs are packed once into a contiguous ``[8, N, B]`` tensor and
  every per-agent quantity inside the graph is ``[N, B]``, so the fused loops are vectorised
  (AVX2/AVX-512) over the ``B`` independent scenes, all lanes running the same instructions.
* **Everything else unrolled in Python.** The loops over the ``K = min(max_neighbors, N-1)``
  ORCA lines (neighbour slots, the pairwise 1-D programs of ``linearProgram2``, its incremental
  scan) are Python loops over lists of ``[N, B]`` tensors: the traced graph is elementwise.
* **No sort, no gather, no data-dependent shapes in the main graph.** Neighbour order comes
  from ranks (``j`` goes to slot ``#{k : (d_k, k) < (d_j, j)}``, exactly a stable sort by
  distance) followed by per-slot selects.
* **One big fusion group.** ``max_fusion_size`` is raised far above inductor's default of 64
  nodes; with the default the graph is cut into many kernels streaming every intermediate
  through memory.
* **Obstacles in the same graph.** With obstacles the processed edges (eager
  :func:`~crowdrl.sim.obstacles.process_obstacles`, once per call unless given as
  :class:`~crowdrl.sim.obstacles.ObstacleEdges`) are packed ``[F, E, B]``; the graph finds each
  agent's obstacle neighbours and their kd-tree visiting order, ranks them (no sort), selects them
  into ``O`` static slots (:data:`OBSTACLE_SLOTS`, grown and recompiled when an agent has more),
  builds their lines with the eager path's :func:`~crowdrl.sim.orca.obstacle_line_math`, applies
  the "already covered" rule and puts the kept lines first, hard in ``linearProgram3``.
* **The rare 3-D fallback apart.** ``linearProgram3`` (``O(K^3)`` work) runs in a second compiled
  graph over only the agents whose 2-D program failed (gathered eagerly, padded to a multiple
  of 16 lanes), compiled once with a dynamic agent count; in crowd scenes few agents need it.

Exactness: the per-element arithmetic is the eager path's, in the same order (and RVO2's:
multiplication by reciprocals where RVO2 divides a ``Vector2``, ties by agent index); inductor
compiles without floating-point contraction or unsafe-math flags and with IEEE ``sqrt`` (the
eager path uses a correctly rounded ``sqrt`` too), so the two agree bit for bit in practice
(tested to ``|dv| <= 1e-5``).

Cost: compilation is lazy, on the first call of each static configuration
``(B, N, dtype, device, ORCA parameters, mask given or not, torch.get_num_threads())``, with
obstacles also the padded edge count, the kd-tree depth, ``time_horizon_obst`` and the slots, and kept
in a process-wide cache (inductor specialises its OpenMP code on the thread count). The graphs
have thousands of nodes: with a cold inductor cache one configuration takes minutes (tracing,
fusion scheduling and a large C++ translation unit; docs/benchmarks.md); with inductor's on-disk
cache warm (same torch, same configuration, cache directory kept, e.g. ``TORCHINDUCTOR_CACHE_DIR``)
it takes seconds. Keep the batch shape static.
"""

from __future__ import annotations

import math
import threading
import types
from typing import Callable

import torch
from torch import Tensor

from crowdrl.sim.obstacles import ObstacleEdges
from crowdrl.sim.orca import (
    RVO_EPSILON,
    OrcaParams,
    OrcaSolution,
    check_orca_inputs,
    agent_line_math,
    obstacle_line_math,
    prepare_obstacles,
)

__all__ = ["compiled_orca_solve", "clear_compiled_cache", "INDUCTOR_OPTIONS"]

# Inductor options for the ORCA graph (see the module docstring).
INDUCTOR_OPTIONS: dict = {
    "max_fusion_size": 4096,
}

_CACHE: dict[tuple, Callable] = {}
_LOCK = threading.Lock()


def clear_compiled_cache() -> None:
    """Forget every compiled function built by this module (inductor's disk cache stays)."""
    with _LOCK:
        _CACHE.clear()


def _det(ax, ay, bx, by):
    return ax * by - ay * bx


def _f(value: float, dtype: torch.dtype) -> float:
    """``value`` rounded to ``dtype`` (the eager path computes these scalars in the tensor dtype)."""
    return float(torch.tensor(value, dtype=torch.float64).to(dtype))


def _build(N: int, K: int, dtype: torch.dtype, time_step: float, neighbor_dist: float,
           time_horizon: float, has_mask: bool, obst: tuple | None = None) -> Callable:
    """The uncompiled solver for one static configuration (``K`` agent lines per agent; with
    ``obst = (E, D, O, time_horizon_obst)``: ``E`` edges, kd-tree depth ``D``, ``O`` obstacle slots)."""
    inv_th = _f(1.0 / _f(time_horizon, dtype), dtype) if dtype != torch.float64 else 1.0 / time_horizon
    inv_ts = _f(1.0 / _f(time_step, dtype), dtype) if dtype != torch.float64 else 1.0 / time_step
    E, D, O, tho = obst if obst is not None else (0, 0, 0, 1.0)
    inv_tho = _f(1.0 / _f(tho, dtype), dtype) if dtype != torch.float64 else 1.0 / tho
    tho = _f(tho, dtype)
    L = O + K  # lines per agent: obstacle slots first
    range_sq = neighbor_dist * neighbor_dist
    inf = math.inf
    eps = RVO_EPSILON

    def lp1(dxs, dys, qxs, qys, keeps, r, opt_x, opt_y, direction_opt):
        """linearProgram1 candidate of every line l against the kept lines before it."""
        out = []
        r_sq = r * r
        for l in range(len(dxs)):
            dx, dy, qx, qy = dxs[l], dys[l], qxs[l], qys[l]
            dot = qx * dx + qy * dy
            disc = dot * dot + r_sq - (qx * qx + qy * qy)
            sq = torch.sqrt(torch.clamp(disc, min=0))
            t_left = -dot - sq
            t_right = -dot + sq
            feasible = disc >= 0
            lo = hi = None
            for i in range(l):
                denom = _det(dx, dy, dxs[i], dys[i])
                numer = _det(dxs[i], dys[i], qx - qxs[i], qy - qys[i])
                parallel = torch.abs(denom) <= eps
                act = keeps[i]
                if act is None:  # statically kept
                    feasible = feasible & ~(parallel & (numer < 0))
                    bounding = ~parallel
                else:
                    feasible = feasible & ~(act & parallel & (numer < 0))
                    bounding = act & ~parallel
                t = numer / torch.where(parallel, 1.0, denom)
                h = torch.where(bounding & (denom >= 0), t, inf)
                g = torch.where(bounding & (denom < 0), t, -inf)
                hi = h if hi is None else torch.minimum(hi, h)
                lo = g if lo is None else torch.maximum(lo, g)
            if hi is not None:
                t_right = torch.minimum(t_right, hi)
                t_left = torch.maximum(t_left, lo)
                feasible = feasible & ~(t_left > t_right)
            if direction_opt:
                take_right = (opt_x * dx + opt_y * dy) > 0
                t_opt = torch.where(take_right, t_right, t_left)
            else:
                t_opt = dx * (opt_x - qx) + dy * (opt_y - qy)
                t_opt = torch.where(t_opt < t_left, t_left, torch.where(t_opt > t_right, t_right, t_opt))
            out.append((qx + t_opt * dx, qy + t_opt * dy, feasible))
        return out

    def scan(dxs, dys, qxs, qys, keeps, cands, rx, ry):
        """linearProgram2's incremental loop; returns result, failed, failing line (or K)."""
        failed = None
        fail_line = None
        for l in range(len(dxs)):
            viol = _det(dxs[l], dys[l], qxs[l] - rx, qys[l] - ry) > 0
            if keeps[l] is not None:
                viol = keeps[l] & viol
            if failed is not None:
                viol = viol & ~failed
            cx, cy, ok = cands[l]
            move = viol & ok
            rx = torch.where(move, cx, rx)
            ry = torch.where(move, cy, ry)
            new_fail = viol & ~ok
            if failed is None:
                failed = new_fail
                fail_line = torch.where(new_fail, l, len(dxs))
            else:
                fail_line = torch.where(new_fail, l, fail_line)
                failed = failed | new_fail
        return rx, ry, failed, fail_line

    def lines_of(X, Y, VX, VY, R, M):
        """Neighbour slots and their ORCA lines, each a list of K ``[N, B]`` tensors."""
        agent = torch.arange(N, device=X.device).unsqueeze(1)  # [N, 1]
        rel_x, rel_y, dist = [], [], []
        for j in range(N):
            rx_ = X[j] - X
            ry_ = Y[j] - Y
            d = rx_ * rx_ + ry_ * ry_
            excluded = (agent == j) | ~(d < range_sq)
            if M is not None:
                excluded = excluded | ~M[j] | ~M
            rel_x.append(rx_)
            rel_y.append(ry_)
            dist.append(torch.where(excluded, inf, d))
        # rank of j among i's candidates: #{k : (d_k, k) < (d_j, j)} (a stable sort's position)
        ranks = []
        for j in range(N):
            rank = None
            for k in range(N):
                if k == j:
                    continue
                c = ((dist[k] <= dist[j]) if k < j else (dist[k] < dist[j])).to(X.dtype)
                rank = c if rank is None else rank + c
            ranks.append(rank)

        def select(vals, s):
            out = vals[N - 1]
            for j in range(N - 2, -1, -1):
                out = torch.where(ranks[j] == s, vals[j], out)
            return out

        dxs, dys, qxs, qys, keeps = [], [], [], [], []
        for s in range(K):
            px = select(rel_x, s)
            py = select(rel_y, s)
            keeps.append(select(dist, s) < inf)
            o_vx = select([VX[j] for j in range(N)], s)
            o_vy = select([VY[j] for j in range(N)], s)
            o_r = select([R[j] for j in range(N)], s)
            dx, dy, qx, qy = agent_line_math(px, py, VX - o_vx, VY - o_vy, R + o_r, VX, VY, inv_th, inv_ts, torch.where)
            dxs.append(dx)
            dys.append(dy)
            qxs.append(qx)
            qys.append(qy)
        return dxs, dys, qxs, qys, keeps

    def obstacle_lines_of(X, Y, VX, VY, R, MS, M, EP):
        """Obstacle neighbours (ranked as in the eager path) and their kept ORCA lines, each a list
        of ``O`` ``[N, B]`` tensors, and the number of edges found per agent."""
        reach = tho * MS + R
        range_sq = reach * reach
        d, key, attrs = [], [], []
        n_found = None
        for e in range(E):
            f = lambda i: EP[i, e:e + 1]  # noqa: E731  [1, B]
            ax, ay, bx, by = f(0), f(1), f(2), f(3)
            ex, ey = bx - ax, by - ay
            left_of = _det(ax - X, ay - Y, ex, ey)
            e_sq = ex * ex + ey * ey
            apx, apy = X - ax, Y - ay
            r = (apx * ex + apy * ey) / e_sq
            bpx, bpy = X - bx, Y - by
            fx, fy = X - (ax + r * ex), Y - (ay + r * ey)
            dist_sq = torch.where(r < 0, apx * apx + apy * apy,
                                  torch.where(r > 1, bpx * bpx + bpy * bpy, fx * fx + fy * fy))
            found = (f(12) > 0.5) & (left_of < 0) & (left_of * left_of / e_sq < range_sq) & (dist_sq < range_sq)
            if M is not None:
                found = found & M
            k_e = None
            for k in range(D):  # the kd-tree query reaches the edge; its visiting-order key
                c = 14 + 5 * k
                sx, sy, tx, ty = f(c), f(c + 1), f(c + 2), f(c + 3)
                ux, uy = tx - sx, ty - sy
                a_left = _det(sx - X, sy - Y, ux, uy)
                near = (a_left >= 0) == (f(c + 4) > 0.5)
                deep = f(13) > k
                found = found & (~deep | near | (a_left * a_left / (ux * ux + uy * uy) < range_sq))
                digit = torch.where(deep, torch.where(near, 0, 2), 1)
                k_e = digit if k_e is None else k_e * 3 + digit
            d.append(torch.where(found, dist_sq, inf))
            key.append(torch.zeros_like(X, dtype=torch.int64) if k_e is None else k_e)
            attrs.append((ax, ay, bx, by, f(4), f(5), f(6), f(7), f(8), f(9), f(10) > 0.5, f(11) > 0.5, found))
            n_found = found.to(torch.int64) if n_found is None else n_found + found.to(torch.int64)
        # rank of edge e: #{f : (d_f, key_f) < (d_e, key_e)} (the eager path's two sorts)
        ranks = []
        for e in range(E):
            rank = None
            for g in range(E):
                if g != e:
                    c = ((d[g] < d[e]) | ((d[g] == d[e]) & (key[g] < key[e]))).to(torch.int64)
                    rank = c if rank is None else rank + c
            ranks.append(rank if rank is not None else torch.zeros_like(X, dtype=torch.int64))
        odx, ody, oqx, oqy, okeep = [], [], [], [], []
        ri = inv_tho * R
        for slot in range(O):
            sel = []
            for i in range(13):
                out = attrs[E - 1][i]
                for e in range(E - 2, -1, -1):
                    out = torch.where(ranks[e] == slot, attrs[e][i], out)
                sel.append(out)
            ax, ay, bx, by, ux, uy, pvx, pvy, nvx, nvy, c1, c2, found = sel
            r1x, r1y, r2x, r2y = ax - X, ay - Y, bx - X, by - Y
            dx, dy, qx, qy, has = obstacle_line_math(
                r1x, r1y, r2x, r2y, bx - ax, by - ay, ux, uy, pvx, pvy, nvx, nvy, c1, c2, VX, VY, R, inv_tho,
                torch.where, torch.sqrt)
            kept = has & found
            for j in range(slot):  # "already covered" by an earlier kept obstacle line
                g1x, g1y = inv_tho * r1x - oqx[j], inv_tho * r1y - oqy[j]
                g2x, g2y = inv_tho * r2x - oqx[j], inv_tho * r2y - oqy[j]
                covers = ((_det(g1x, g1y, odx[j], ody[j]) - ri >= -eps)
                          & (_det(g2x, g2y, odx[j], ody[j]) - ri >= -eps))
                kept = kept & ~(okeep[j] & covers)
            odx.append(torch.where(kept, dx, 1.0))
            ody.append(torch.where(kept, dy, 0.0))
            oqx.append(torch.where(kept, qx, 0.0))
            oqy.append(torch.where(kept, qy, 0.0))
            okeep.append(kept)
        return odx, ody, oqx, oqy, okeep, n_found

    def solve_main(inp: Tensor, mask: Tensor | None = None, ep: Tensor | None = None):
        """``inp``: ``[8, N, B]`` (x, y, vx, vy, pref x, pref y, radius, max speed); ``ep``: the
        packed obstacle edges ``[14 + 5 D, E, B]`` (see :func:`_pack_edges`) when ``O > 0``."""
        X, Y, VX, VY, OX, OY, R, MS = inp.unbind(0)
        M = mask
        # ---- linearProgram2 towards the preferred velocity, clipped to the max-speed disc.
        o_sq = OX * OX + OY * OY
        outside = o_sq > MS * MS
        inv_o_len = 1.0 / torch.sqrt(o_sq)
        start_x = torch.where(outside, OX * inv_o_len * MS, OX)
        start_y = torch.where(outside, OY * inv_o_len * MS, OY)
        if O == 0 and K == 0:
            failed = torch.zeros_like(outside)
            return start_x, start_y, failed, torch.zeros_like(X, dtype=torch.int64), None, None, None
        dxs, dys, qxs, qys, keeps = lines_of(X, Y, VX, VY, R, M) if K > 0 else ([], [], [], [], [])
        if O > 0:
            odx, ody, oqx, oqy, okeep, n_found = obstacle_lines_of(X, Y, VX, VY, R, MS, M, ep)
            dxs, dys, qxs, qys, keeps = odx + dxs, ody + dys, oqx + qxs, oqy + qys, okeep + keeps
        cands = lp1(dxs, dys, qxs, qys, keeps, MS, OX, OY, False)
        rx, ry, failed, fail_line = scan(dxs, dys, qxs, qys, keeps, cands, start_x, start_y)
        n_nb = torch.zeros_like(X, dtype=torch.int64) if K == 0 else keeps[O].to(torch.int64)
        for s in range(O + 1, L):
            n_nb = n_nb + keeps[s].to(torch.int64)
        lines = torch.stack([torch.stack(t) for t in (dxs, dys, qxs, qys)])  # [4, L, N, B]
        out = rx, ry, failed, n_nb, lines, torch.stack(keeps), fail_line
        if O > 0:
            n_obst = keeps[0].to(torch.int64)
            for s in range(1, O):
                n_obst = n_obst + keeps[s].to(torch.int64)
            out = out + (n_obst, n_found)
        return out

    def solve_lp3(lines: Tensor, keep: Tensor, begin: Tensor, MS: Tensor, rx: Tensor, ry: Tensor):
        """linearProgram3 for ``[S]`` agents: lines ``[4, L, S]``, keep ``[L, S]``, the first ``O``
        obstacle lines (kept as they are in every projected program)."""
        dxs, dys, qxs, qys = (list(t.unbind(0)) for t in lines.unbind(0))
        keeps = list(keep.unbind(0))
        sols = []
        for i in range(L):
            pdx, pdy, pqx, pqy, pkeep = dxs[:O], dys[:O], qxs[:O], qys[:O], keeps[:O]
            if O == 0 and i == 0:  # no lines: RVO2's LP2 on zero lines keeps opt*radius
                sols.append(None)
                continue
            for j in range(O, i):
                determinant = _det(dxs[i], dys[i], dxs[j], dys[j])
                parallel = torch.abs(determinant) <= eps
                same_dir = (dxs[i] * dxs[j] + dys[i] * dys[j]) > 0
                safe_det = torch.where(parallel, 1.0, determinant)
                sj = _det(dxs[j], dys[j], qxs[i] - qxs[j], qys[i] - qys[j]) / safe_det
                pqx.append(torch.where(parallel, 0.5 * (qxs[i] + qxs[j]), qxs[i] + sj * dxs[i]))
                pqy.append(torch.where(parallel, 0.5 * (qys[i] + qys[j]), qys[i] + sj * dys[i]))
                ddx = dxs[j] - dxs[i]
                ddy = dys[j] - dys[i]
                dlen = torch.sqrt(ddx * ddx + ddy * ddy)
                inv_dlen = 1.0 / dlen
                pdx.append(ddx * inv_dlen)
                pdy.append(ddy * inv_dlen)
                pkeep.append(keeps[i] & keeps[j] & ~(parallel & same_dir))
            opt_x, opt_y = -dys[i], dxs[i]
            pc = lp1(pdx, pdy, pqx, pqy, pkeep, MS, opt_x, opt_y, True)
            sx, sy, sfail, _ = scan(pdx, pdy, pqx, pqy, pkeep, pc, opt_x * MS, opt_y * MS)
            sols.append((sx, sy, sfail))
        distance = torch.zeros_like(rx)
        for i in range(L):
            violation = _det(dxs[i], dys[i], qxs[i] - rx, qys[i] - ry)
            active = keeps[i] & (begin <= i) & (violation > distance)
            if sols[i] is None:  # no earlier lines: RVO2's LP2 on zero lines keeps opt*radius
                take = active
                sx, sy = -dys[i] * MS, dxs[i] * MS
            else:
                sx, sy, sfail = sols[i]
                take = active & ~sfail
            rx = torch.where(take, sx, rx)
            ry = torch.where(take, sy, ry)
            new_distance = _det(dxs[i], dys[i], qxs[i] - rx, qys[i] - ry)
            distance = torch.where(active, new_distance, distance)
        return rx, ry

    return solve_main, solve_lp3


def _fresh(fn: Callable, tag: str) -> Callable:
    """``fn`` with its own code object: Dynamo caches compiled graphs per code object (and
    caps recompilations per code object), so each static configuration gets a separate one."""
    code = fn.__code__.replace(co_name=f"{fn.__name__}_{tag}")
    new = types.FunctionType(code, fn.__globals__, code.co_name, fn.__defaults__, fn.__closure__)
    new.__doc__ = fn.__doc__
    return new


def _get_compiled(B: int, N: int, K: int, dtype: torch.dtype, device: torch.device, time_step: float,
                  neighbor_dist: float, time_horizon: float, has_mask: bool,
                  obst: tuple | None = None) -> tuple[Callable, Callable]:
    threads = torch.get_num_threads()
    key = (None if DYNAMIC_BATCH else B, N, K, dtype, str(device), float(time_step), float(neighbor_dist),
           float(time_horizon), has_mask, threads, obst)
    fns = _CACHE.get(key)
    if fns is None:
        with _LOCK:
            fns = _CACHE.get(key)
            if fns is None:
                main, lp3 = _build(N, K, dtype, float(time_step), float(neighbor_dist), float(time_horizon), has_mask,
                                   obst)
                tag = f"{len(_CACHE)}"
                main, lp3 = _fresh(main, tag), _fresh(lp3, tag)
                # linearProgram3 depends only on (K, O, dtype, threads); one dynamic-size compile serves all.
                lp3_key = ("lp3", K, dtype, str(device), threads) + ((obst[2],) if obst is not None else ())
                lp3_c = _CACHE.get(lp3_key)
                if lp3_c is None:
                    lp3_c = torch.compile(lp3, fullgraph=True, dynamic=None, options=dict(INDUCTOR_OPTIONS))
                    _CACHE[lp3_key] = lp3_c
                main_c = torch.compile(main, fullgraph=True, dynamic=None if DYNAMIC_BATCH else False,
                                       options=dict(INDUCTOR_OPTIONS))
                fns = _CACHE[key] = (main_c, lp3_c)
    return fns


# Compile the main graph once per N for every batch size (the batch is the innermost, vectorised
# dimension either way); False gives one static compile per B.
DYNAMIC_BATCH = True

_LP3_ALIGN = 16  # the infeasible subset is padded to a multiple of this (>= 2 avoids size-1 specialisation)

OBSTACLE_SLOTS = 4  # obstacle-neighbour slots per agent compiled first (grown, and recompiled, when exceeded)
_EDGE_ALIGN = 4  # the edge count is padded to a multiple of this (fewer recompilations)
_SLOTS: dict[tuple, int] = {}  # obstacle slots per configuration, once grown


def _pack_edges(edges: ObstacleEdges, size: int) -> Tensor:
    """The edges as ``[14 + 5 D, size, B]``: start, end, direction, previous and next direction (2
    each), start/end convexity, validity, depth, then per tree level the ancestor's start and end
    and whether the edge is in its left subtree; padding edges are invalid."""
    B, E = edges.valid.shape
    D = edges.ancestors.shape[-1]
    dtype = edges.start.dtype
    idx = edges.ancestors.reshape(B, E * D, 1).expand(B, E * D, 2)
    anc_start = edges.start.gather(1, idx).view(B, E, D, 2)
    anc_end = edges.end.gather(1, idx).view(B, E, D, 2)
    per_level = torch.cat((anc_start, anc_end, edges.in_left.unsqueeze(-1).to(dtype)), -1).reshape(B, E, 5 * D)
    flags = torch.stack((edges.start_convex, edges.end_convex, edges.valid), -1).to(dtype)
    feats = torch.cat((edges.start, edges.end, edges.direction, edges.prev_direction, edges.next_direction, flags,
                       edges.depth.unsqueeze(-1).to(dtype), per_level), -1)  # [B, E, F]
    if size > E:
        pad = feats.new_zeros(B, size - E, feats.shape[-1])
        pad[..., 2] = 1.0  # a unit edge (0, 0) -> (1, 0), invalid
        feats = torch.cat((feats, pad), 1)
    return feats.permute(2, 1, 0).contiguous()


def compiled_orca_solve(
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
    """:func:`crowdrl.sim.orca.orca_solve`, compiled; same arguments, result and dtypes.

    The first call for a new static configuration (batch shape, dtype, device, ORCA parameters,
    whether ``mask`` is given, ``torch.get_num_threads()``; with obstacles also the edge count
    rounded up to a multiple of 4, the obstacle kd-tree depth, ``time_horizon_obst`` and the number
    of obstacle-neighbour slots) compiles (see the module docstring). The slots start at
    :data:`OBSTACLE_SLOTS`; a call where an agent has more obstacle neighbours is computed again with
    more slots (one more compilation), kept for that configuration from then on.
    """
    check_orca_inputs(positions, velocities, pref_velocities, radius, max_speed, mask, params)
    edges = prepare_obstacles(positions, obstacles, obstacle_mask)
    B, N, _ = positions.shape
    K = min(int(params.max_neighbors), N - 1)
    inp = torch.cat(
        (positions, velocities, pref_velocities, radius.unsqueeze(-1), max_speed.unsqueeze(-1)), -1
    ).permute(2, 1, 0).contiguous()  # [8, N, B]
    margs = (inp,) if mask is None else (inp, mask.t().contiguous())
    obst = None
    n_obst = None
    if edges is not None and edges.num_edges == 0:
        n_obst = torch.zeros(B, N, dtype=torch.long, device=positions.device)
    elif edges is not None:
        size = -(-edges.num_edges // _EDGE_ALIGN) * _EDGE_ALIGN
        ep = _pack_edges(edges, size)
        margs = (inp, None if mask is None else margs[1], ep)
        base = (size, edges.ancestors.shape[-1], float(params.obstacle_horizon))
        slots = _SLOTS.get(base, min(size, OBSTACLE_SLOTS))
    if DYNAMIC_BATCH and B > 1:
        for t in margs:
            if t is not None:
                torch._dynamo.mark_dynamic(t, t.dim() - 1)
    while True:
        if edges is not None and edges.num_edges > 0:
            obst = base[:2] + (slots, base[2])
        main, lp3 = _get_compiled(B, N, K, positions.dtype, positions.device, params.time_step, params.neighbor_dist,
                                  params.time_horizon, mask is not None, obst)
        out = main(*margs)
        if obst is None:
            break
        n_found = int(out[8].max())
        if n_found <= slots:
            n_obst = out[7].t().contiguous()
            break
        slots = _SLOTS[base] = min(size, max(2 * slots, n_found))
    rx, ry, failed, n_nb, lines, keep, fail_line = out[:7]
    L = K + (obst[2] if obst is not None else 0)
    if L > 0 and bool(failed.any()):
        A = N * B
        idx = failed.view(A).nonzero().squeeze(1)
        count = idx.numel()
        size = max(_LP3_ALIGN, -(-count // _LP3_ALIGN) * _LP3_ALIGN)
        if size > count:
            idx_p = torch.cat((idx, idx[:1].expand(size - count)))
        else:
            idx_p = idx
        sub = lambda t: t.reshape(t.shape[:-2] + (A,)).index_select(-1, idx_p)
        args = (sub(lines), sub(keep), sub(fail_line), sub(inp[7]), sub(rx), sub(ry))
        for t in args:
            torch._dynamo.mark_dynamic(t, t.dim() - 1)
        fx, fy = lp3(*args)
        rx = rx.reshape(A).index_copy(0, idx, fx[:count]).view(N, B)
        ry = ry.reshape(A).index_copy(0, idx, fy[:count]).view(N, B)
    new_v = torch.stack((rx, ry), -1).transpose(0, 1).contiguous()
    failed = failed.t().contiguous()
    if mask is not None:
        new_v = torch.where(mask.unsqueeze(-1), new_v, velocities)
        failed = failed & mask
    return OrcaSolution(new_v, failed, n_nb.t().contiguous(), n_obst)


