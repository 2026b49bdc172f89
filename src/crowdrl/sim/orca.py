"""Batched ORCA (optimal reciprocal collision avoidance), computing what RVO2 2.0 computes.

Every function works on tensors whose leading dimensions are a batch of independent scenes
``[B, N, ...]``; there is no Python loop over scenes or agents. The only Python loops run over
the at most ``max_neighbors`` ORCA lines of an agent, exactly as RVO2's incremental 2-D linear
program does, each iteration vectorised over all agents of all scenes.

Structure (RVO2's ``Agent::computeNewVelocity`` without obstacles):

1. neighbours: the ``max_neighbors`` nearest other agents with squared distance strictly below
   ``neighbor_dist**2``, nearest first (ties broken by agent index);
2. one ORCA half-plane per neighbour (cut-off circle, left/right leg, or the collision branch
   with the ``1/time_step`` cut-off when the agents overlap);
3. ``linearProgram2``: the velocity closest to the preferred one inside the max-speed disc and
   all half-planes, built incrementally;
4. ``linearProgram3`` when (3) is infeasible: the velocity that minimises the largest
   half-plane violation.

Useful algebra for vectorising (3) and (4): the 1-D program on line ``l`` depends only on
lines ``0..l``, never on the running result, so every line's candidate is computed in
parallel and only the cheap "is the running result violating line l" scan stays sequential.
The same holds for each projected program inside (4), whose start point does not depend on
the running result either.

Bit-level fidelity to RVO2 (float32): square roots are correctly rounded (ATen's CPU ``sqrt``
is not; see :func:`_sqrt`), Vector2 divisions multiply by the reciprocal as RVO2 does, and
neighbour ties go by agent index. Selections use a branch-free bitwise select on large
tensors (ATen's CPU ``where`` mispredicts on irregular masks). :mod:`crowdrl.sim.fast` is a
compiled backend computing the same thing.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

RVO_EPSILON = 1e-5  # RVO2's RVO_EPSILON (float)

__all__ = ["OrcaSolution", "orca_velocities", "orca_solve", "require_finite", "RVO_EPSILON"]


class OrcaSolution(NamedTuple):
    """Result of :func:`orca_solve`.

    velocities: ``[B, N, 2]`` new velocities.
    lp_infeasible: ``[B, N]`` bool, the 2-D program was infeasible and RVO2's 3-D fallback ran.
    num_neighbors: ``[B, N]`` number of ORCA lines (neighbours) of each agent.
    """

    velocities: Tensor
    lp_infeasible: Tensor
    num_neighbors: Tensor


def _det(ax: Tensor, ay: Tensor, bx: Tensor, by: Tensor) -> Tensor:
    return ax * by - ay * bx


_INT_OF = {torch.float64: torch.int64, torch.float32: torch.int32, torch.float16: torch.int16,
           torch.bfloat16: torch.int16}


def _select(cond: Tensor, a: Tensor, b: Tensor | float) -> Tensor:
    """``torch.where(cond, a, b)``, bit for bit, without branches.

    ATen's CPU ``where`` is a scalar loop whose branch mispredicts on irregular masks (about
    10x slower than a vectorised op); this selects through the integer bit patterns instead.
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

    One ``isfinite().all()`` over all of them at once and one host sync (~1-3 % of a CPU step of
    ``crowd.step`` at B = 64..1024; a check per tensor costs ~3x more at small batches), once per
    public call, never inside a kernel. Only on failure is each tensor checked alone, to name it."""
    if bool(torch.isfinite(torch.cat([t.reshape(-1) for t in tensors.values()])).all()):
        return
    name = next(name for name, t in tensors.items() if not bool(torch.isfinite(t).all()))
    raise ValueError(f"{name} holds NaN or infinite values; the simulator takes finite inputs only")


def _check_inputs(
    positions: Tensor,
    velocities: Tensor,
    pref_velocities: Tensor,
    radius: Tensor,
    max_speed: Tensor,
    mask: Tensor | None,
    time_step: float,
    neighbor_dist: float,
    max_neighbors: int,
    time_horizon: float,
) -> None:
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
    if not time_step > 0:
        raise ValueError(f"time_step must be > 0, got {time_step}")
    if not time_horizon > 0:
        raise ValueError(f"time_horizon must be > 0, got {time_horizon}")
    if not neighbor_dist >= 0:
        raise ValueError(f"neighbor_dist must be >= 0, got {neighbor_dist}")
    if int(max_neighbors) != max_neighbors or max_neighbors < 0:
        raise ValueError(f"max_neighbors must be a non-negative integer, got {max_neighbors}")
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


def _line_math(px, py, vx, vy, comb_r, own_vx, own_vy, inv_th, inv_ts, where=_select, sqrt=_sqrt):
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
    return _line_math(
        other[0] - own[0], other[1] - own[1], own[2] - other[2], own[3] - other[3], own[4] + other[4],
        own[2], own[3], one / time_horizon, one / time_step,
    )


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
    radius: Tensor, rx: Tensor, ry: Tensor,
) -> tuple[Tensor, Tensor]:
    """RVO2's ``linearProgram3`` (no obstacle lines): lines ``[L, M]`` for agents ``[M]``."""
    L = dx.shape[0]
    # Projected lines for every (j, i) with j < i: [j, i, M].
    dxi, dyi, qxi, qyi = (t.unsqueeze(0) for t in (dx, dy, qx, qy))
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
    earlier = torch.ones(L, L, dtype=torch.bool, device=dx.device).triu(1).unsqueeze(-1)  # j < i
    pkeep = earlier & keep.unsqueeze(0) & keep.unsqueeze(1) & ~(parallel & same_dir)

    # Direction-optimising LP2 for each i, all at once: optimise towards (-dir_i.y, dir_i.x).
    opt_x, opt_y = -dy, dx  # [i, M]
    r = radius.unsqueeze(0)
    cx, cy, cok = _lp1_candidates_t(pdx, pdy, px_, py_, pkeep, r, opt_x, opt_y, direction_opt=True)
    sol_x, sol_y, sol_fail, _ = _lp2_scan_t(pdx, pdy, px_, py_, pkeep, cx, cy, cok, opt_x * r, opt_y * r)

    distance = torch.zeros_like(rx)
    for i in range(L):
        violation = _det(dx[i], dy[i], qx[i] - rx, qy[i] - ry)
        active = keep[i] & (begin <= i) & (violation > distance)
        take = active & ~sol_fail[i]
        rx = torch.where(take, sol_x[i], rx)
        ry = torch.where(take, sol_y[i], ry)
        new_distance = _det(dx[i], dy[i], qx[i] - rx, qy[i] - ry)
        distance = torch.where(active, new_distance, distance)
    return rx, ry


def orca_solve(
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
    """ORCA new velocities with diagnostics; see :func:`orca_velocities` for the arguments."""
    _check_inputs(
        positions, velocities, pref_velocities, radius, max_speed, mask,
        time_step, neighbor_dist, max_neighbors, time_horizon,
    )
    B, N, _ = positions.shape
    A = B * N
    flat, valid = _neighbor_table(positions, mask, neighbor_dist, max_neighbors)
    K = flat.shape[0]

    # linearProgram2 towards the preferred velocity (clipped to the max-speed disc).
    pref = pref_velocities.reshape(A, 2).t()
    ox, oy = pref[0], pref[1]
    ms = max_speed.reshape(A)
    o_sq = ox * ox + oy * oy
    outside = o_sq > ms * ms
    inv_o_len = 1.0 / _sqrt(o_sq)
    start_x = _select(outside, ox * inv_o_len * ms, ox)
    start_y = _select(outside, oy * inv_o_len * ms, oy)
    if K == 0:
        rx, ry, failed = start_x, start_y, torch.zeros_like(outside)
    else:
        dx, dy, qx, qy = _lines_t(positions, velocities, radius, flat, time_step, time_horizon)
        cx, cy, cok = _lp1_candidates_t(dx, dy, qx, qy, valid, ms, ox, oy, direction_opt=False)
        rx, ry, failed, fail_line = _lp2_scan_t(dx, dy, qx, qy, valid, cx, cy, cok, start_x, start_y)
        if bool(failed.any()):
            idx = failed.nonzero().squeeze(1)
            sub = lambda t: t.index_select(-1, idx)
            fx, fy = _lp3_t(sub(dx), sub(dy), sub(qx), sub(qy), sub(valid), sub(fail_line), sub(ms), sub(rx), sub(ry))
            rx = rx.index_copy(0, idx, fx)
            ry = ry.index_copy(0, idx, fy)

    new_v = torch.stack((rx, ry), dim=-1).view(B, N, 2)
    failed = failed.view(B, N)
    if mask is not None:
        new_v = torch.where(mask.unsqueeze(-1), new_v, velocities)
        failed = failed & mask
    return OrcaSolution(new_v, failed, valid.sum(0).view(B, N))


def orca_velocities(
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
) -> Tensor:
    """The velocities RVO2 computes in one ``doStep`` for a batch of scenes.

    Args:
        positions, velocities, pref_velocities: ``[B, N, 2]`` current state and preferences.
        radius, max_speed: ``[B, N]`` per-agent radius and speed limit.
        time_step: simulation step (the collision branch's cut-off is ``1/time_step``).
        neighbor_dist: only agents strictly closer than this are neighbours.
        max_neighbors: at most this many nearest neighbours give ORCA lines.
        time_horizon: ORCA time horizon towards other agents.
        mask: optional ``[B, N]`` bool, ``False`` marks an absent agent: it is nobody's neighbour
            and its velocity is returned unchanged.

    Returns:
        ``[B, N, 2]`` new velocities, the dtype and device of the inputs.
    """
    return orca_solve(
        positions, velocities, pref_velocities, radius, max_speed,
        time_step=time_step, neighbor_dist=neighbor_dist, max_neighbors=max_neighbors,
        time_horizon=time_horizon, mask=mask,
    ).velocities
