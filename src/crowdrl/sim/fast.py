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
  through memory, several times slower.
* **The rare 3-D fallback apart.** ``linearProgram3`` (``O(K^3)`` work) runs in a second compiled
  graph over only the agents whose 2-D program failed (gathered eagerly, padded to a multiple
  of 16 lanes), compiled once with a dynamic agent count; in crowd scenes well under 1% of the
  agents need it.

Exactness: the per-element arithmetic is the eager path's, in the same order (and RVO2's:
multiplication by reciprocals where RVO2 divides a ``Vector2``, ties by agent index); inductor
compiles without floating-point contraction or unsafe-math flags and with IEEE ``sqrt`` (the
eager path uses a correctly rounded ``sqrt`` too), so the two agree bit for bit in practice
(tested to ``|dv| <= 1e-5``).

Cost: compilation is lazy, on the first call of each static configuration
``(B, N, dtype, device, ORCA parameters, mask given or not, torch.get_num_threads())``, and kept
in a process-wide cache (inductor specialises its OpenMP code on the thread count). The graphs
have thousands of nodes: with a cold inductor cache one configuration takes minutes (about 2 to
8 min for B=1024, N=10 on a loaded 2-core machine: tracing, fusion scheduling and a large C++
translation unit); with inductor's on-disk cache warm (same torch, same configuration, cache
directory kept, e.g. ``TORCHINDUCTOR_CACHE_DIR``) it takes seconds. Keep the batch shape static.
"""

from __future__ import annotations

import math
import threading
import types
from typing import Callable

import torch
from torch import Tensor

from crowdrl.sim.orca import RVO_EPSILON, OrcaSolution, _check_inputs, _line_math

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
           time_horizon: float, has_mask: bool) -> Callable:
    """The uncompiled solver for one static configuration (``K`` lines per agent)."""
    inv_th = _f(1.0 / _f(time_horizon, dtype), dtype) if dtype != torch.float64 else 1.0 / time_horizon
    inv_ts = _f(1.0 / _f(time_step, dtype), dtype) if dtype != torch.float64 else 1.0 / time_step
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
            dx, dy, qx, qy = _line_math(px, py, VX - o_vx, VY - o_vy, R + o_r, VX, VY, inv_th, inv_ts, torch.where)
            dxs.append(dx)
            dys.append(dy)
            qxs.append(qx)
            qys.append(qy)
        return dxs, dys, qxs, qys, keeps

    def solve_main(inp: Tensor, mask: Tensor | None = None):
        """``inp``: ``[8, N, B]`` (x, y, vx, vy, pref x, pref y, radius, max speed)."""
        X, Y, VX, VY, OX, OY, R, MS = inp.unbind(0)
        M = mask
        # ---- linearProgram2 towards the preferred velocity, clipped to the max-speed disc.
        o_sq = OX * OX + OY * OY
        outside = o_sq > MS * MS
        inv_o_len = 1.0 / torch.sqrt(o_sq)
        start_x = torch.where(outside, OX * inv_o_len * MS, OX)
        start_y = torch.where(outside, OY * inv_o_len * MS, OY)
        if K == 0:
            failed = torch.zeros_like(outside)
            return start_x, start_y, failed, torch.zeros_like(X, dtype=torch.int64), None, None, None
        dxs, dys, qxs, qys, keeps = lines_of(X, Y, VX, VY, R, M)
        cands = lp1(dxs, dys, qxs, qys, keeps, MS, OX, OY, False)
        rx, ry, failed, fail_line = scan(dxs, dys, qxs, qys, keeps, cands, start_x, start_y)
        n_nb = keeps[0].to(torch.int64)
        for s in range(1, K):
            n_nb = n_nb + keeps[s].to(torch.int64)
        lines = torch.stack([torch.stack(t) for t in (dxs, dys, qxs, qys)])  # [4, K, N, B]
        return rx, ry, failed, n_nb, lines, torch.stack(keeps), fail_line

    def solve_lp3(lines: Tensor, keep: Tensor, begin: Tensor, MS: Tensor, rx: Tensor, ry: Tensor):
        """linearProgram3 for ``[S]`` agents: lines ``[4, K, S]``, keep ``[K, S]``."""
        dxs, dys, qxs, qys = (list(t.unbind(0)) for t in lines.unbind(0))
        keeps = list(keep.unbind(0))
        sols = [None]
        for i in range(1, K):
            pdx, pdy, pqx, pqy, pkeep = [], [], [], [], []
            for j in range(i):
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
        for i in range(K):
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
                  neighbor_dist: float, time_horizon: float, has_mask: bool) -> tuple[Callable, Callable]:
    threads = torch.get_num_threads()
    key = (None if DYNAMIC_BATCH else B, N, K, dtype, str(device), float(time_step), float(neighbor_dist),
           float(time_horizon), has_mask, threads)
    fns = _CACHE.get(key)
    if fns is None:
        with _LOCK:
            fns = _CACHE.get(key)
            if fns is None:
                main, lp3 = _build(N, K, dtype, float(time_step), float(neighbor_dist), float(time_horizon), has_mask)
                tag = f"{len(_CACHE)}"
                main, lp3 = _fresh(main, tag), _fresh(lp3, tag)
                # linearProgram3 depends only on (K, dtype, threads); one dynamic-size compile serves all.
                lp3_key = ("lp3", K, dtype, str(device), threads)
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


def compiled_orca_solve(
    positions: Tensor,
    velocities: Tensor,
    pref_velocities: Tensor,
    radius: Tensor,
    max_speed: Tensor,
    *,
    time_step: float,
    neighbor_dist: float,
    max_neighbors: int,
    time_horizon: float,
    mask: Tensor | None = None,
) -> OrcaSolution:
    """:func:`crowdrl.sim.orca.orca_solve`, compiled; same arguments, result and dtypes.

    The first call for a new static configuration (batch shape, dtype, device, ORCA parameters,
    whether ``mask`` is given, ``torch.get_num_threads()``) compiles (see the module docstring).
    """
    _check_inputs(
        positions, velocities, pref_velocities, radius, max_speed, mask,
        time_step, neighbor_dist, max_neighbors, time_horizon,
    )
    B, N, _ = positions.shape
    K = min(int(max_neighbors), N - 1)
    main, lp3 = _get_compiled(B, N, K, positions.dtype, positions.device, time_step, neighbor_dist,
                              time_horizon, mask is not None)
    inp = torch.cat(
        (positions, velocities, pref_velocities, radius.unsqueeze(-1), max_speed.unsqueeze(-1)), -1
    ).permute(2, 1, 0).contiguous()  # [8, N, B]
    margs = (inp,) if mask is None else (inp, mask.t().contiguous())
    if DYNAMIC_BATCH and B > 1:
        for t in margs:
            torch._dynamo.mark_dynamic(t, t.dim() - 1)
    rx, ry, failed, n_nb, lines, keep, fail_line = main(*margs)
    if K > 0 and bool(failed.any()):
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
    return OrcaSolution(new_v, failed, n_nb.t().contiguous())


