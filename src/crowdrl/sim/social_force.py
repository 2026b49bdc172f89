"""Batched Helbing–Molnár social force: what the ``socialforce`` package (0.2.3, S. Kreiss, MIT; the
package CrowdNav's social-force agents call) computes in one ``Simulator`` call, for B scenes at once.

Per pedestrian ``a`` with position ``r_a``, velocity ``v_a``, preferred speed ``v0_a`` and desired
direction ``e_a`` (the unit vector to its destination; without one, its velocity's direction; zero at the
destination), one call of ``substeps`` sub-steps of ``dt = time_step / substeps`` does, each sub-step:

* driving term ``F0_a = (v0_a e_a - v_a) / tau``;
* repulsion from every other pedestrian ``b``: the potential ``V(b) = v0 exp(-b / sigma)`` of the
  semi-minor axis ``2b = sqrt((|r_ab| + |r_ab - s_b e_b|)^2 - s_b^2)`` of the ellipse through
  ``a`` with foci ``r_b`` and ``r_b + s_b e_b``, ``r_ab = r_a - r_b``, ``s_b = 0.4 s * |v_b|``
  (the package's fixed 0.4 s step; the argument of the root floored at 1e-8, where the force is
  zero); the force is ``f_ab = -grad_{r_ab} V``, weighted 1 when ``b`` lies within ``a``'s field of
  view (200 degrees about ``e_a``, strictly) and 0.5 otherwise;
* leapfrog integration of ``F = F0 + sum_b w_ab f_ab`` (``r += v dt + F dt^2 / 2``,
  ``v += (a_prev + F) dt / 2`` with ``a_prev`` the previous sub-step's ``F``, zero at the first),
  then the speed capped at 1.3 ``v0_a``.

The answer is the velocity after the last sub-step (the positions inside the call are discarded: the
simulator moves every human with its new velocity, as CrowdNav moves an agent with its policy's
velocity). Pure torch, no Python loop over scenes or agents; the gradient is written out (the package
takes it with autograd).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

# The package's constants (socialforce 0.2.3): facts of the reference, not tuning knobs.
FIELD_OF_VIEW_DEG = 200.0  # FieldOfView(twophi=200)
OUT_OF_VIEW_FACTOR = 0.5  # FieldOfView.out_of_view_factor
MAX_SPEED_MULTIPLIER = 1.3  # Simulator.max_speed_multiplier
POTENTIAL_STEP = 0.4  # PedPedPotential.delta_t_step, s
SQRT_FLOOR = 1e-8  # PedPedPotential.b clamps the root's argument at this

__all__ = ["social_force_velocities", "FIELD_OF_VIEW_DEG", "OUT_OF_VIEW_FACTOR", "MAX_SPEED_MULTIPLIER",
           "POTENTIAL_STEP"]


def _desired_directions(position: Tensor, velocity: Tensor, goal: Tensor, has_goal: Tensor | None) -> Tensor:
    """Unit vectors to the goals (to the velocity's direction where ``has_goal`` is false), zero at the goal."""
    to = goal - position
    if has_goal is not None:
        to = torch.where(has_goal.unsqueeze(-1), to, velocity)
    norm = torch.linalg.vector_norm(to, dim=-1, keepdim=True)
    return to / torch.where(norm == 0, torch.ones_like(norm), norm)


def _repulsion(position: Tensor, speed: Tensor, e: Tensor, pair: Tensor, v0: float, sigma: float) -> Tensor:
    """``sum_b w_ab f_ab`` per pedestrian ``[B, M, 2]``; ``pair [B, M, M]`` marks the pairs that interact.

    Written in the package's order of float operations (its autograd backward included), so that float32
    answers agree to the last bit (``experiments/human_model_agreement.py``)."""
    r = position.unsqueeze(2) - position.unsqueeze(1)  # r_ab = r_a - r_b  [B, a, b, 2]
    s = (POTENTIAL_STEP * speed).unsqueeze(1)  # s_b  [B, 1, b]
    q = r - s.unsqueeze(-1) * e.unsqueeze(1)  # r_ab - s_b e_b
    n1 = torch.linalg.vector_norm(r, dim=-1)
    n2 = torch.linalg.vector_norm(q, dim=-1)
    total = n1 + n2
    inner = total ** 2 - s ** 2
    root = torch.sqrt(inner.clamp_min(SQRT_FLOOR))  # 2b
    value = v0 * torch.exp(-(0.5 * root) / sigma)
    # f_ab = -dV/dr_ab, the chain rule in autograd's order: V -> b -> root -> inner -> n1 + n2 -> r_ab
    g = -(value / sigma) * 0.5 / (2 * root) * (2 * total)
    live = pair & (inner >= SQRT_FLOOR)
    g = g.unsqueeze(-1)
    grad = r / n1.unsqueeze(-1) * g + q / n2.unsqueeze(-1) * g
    force = torch.where(live.unsqueeze(-1), -grad, 0.0)
    # field of view: b (at -r_ab from a) in sight of a when e_a . (-r_ab) > |r_ab| cos(phi)
    cos_phi = math.cos(FIELD_OF_VIEW_DEG / 2.0 / 180.0 * math.pi)
    ahead = torch.einsum("zaj,zabj->zab", e, -r)
    w = torch.where(ahead > n1 * cos_phi, 1.0, OUT_OF_VIEW_FACTOR)
    return torch.sum(w.unsqueeze(-1) * force, dim=2)


def social_force_velocities(
    position: Tensor,
    velocity: Tensor,
    goal: Tensor,
    preferred_speed: Tensor,
    *,
    time_step: float,
    substeps: int,
    tau: float,
    v0: float,
    sigma: float,
    has_goal: Tensor | None = None,
    mask: Tensor | None = None,
) -> Tensor:
    """New velocities ``[B, M, 2]`` of ``M`` pedestrians per scene after one social-force call.

    Args:
        position, velocity, goal: ``[B, M, 2]``; a pedestrian starts the call at rest in acceleration.
        preferred_speed: ``[B, M]``; the speed cap is 1.3 times it.
        time_step: the call's duration, split into ``substeps`` leapfrog sub-steps.
        tau: relaxation time (s); ``v0`` (m²/s²) and ``sigma`` (m): the repulsive potential.
        has_goal: ``[B, M]`` bool, false where a pedestrian has no destination (its desired direction is
            its velocity's: the package's NaN destination). ``None``: all have one.
        mask: ``[B, M]`` bool, false marks an absent pedestrian: it exerts no force and keeps its velocity.
    """
    B, M, _ = position.shape
    dt = time_step / substeps
    eye = torch.eye(M, dtype=torch.bool, device=position.device)
    pair = ~eye if mask is None else ~eye & mask.unsqueeze(1) & mask.unsqueeze(2)
    pair = pair.expand(B, M, M)
    max_speed = preferred_speed * MAX_SPEED_MULTIPLIER
    pos, vel = position, velocity
    acc = torch.zeros_like(velocity)
    inv_tau = 1.0 / torch.tensor(tau, dtype=position.dtype, device=position.device)
    for _ in range(int(substeps)):
        e = _desired_directions(pos, vel, goal, has_goal)
        drive = inv_tau * (preferred_speed.unsqueeze(-1) * e - vel)
        speed = torch.linalg.vector_norm(vel, dim=-1)
        force = drive + _repulsion(pos, speed, e, pair, v0, sigma)
        pos = pos + vel * dt + 0.5 * force * dt ** 2
        vel = vel + 0.5 * (acc + force) * dt
        acc = force
        vel = vel * (max_speed.unsqueeze(-1) / torch.linalg.vector_norm(vel, dim=-1, keepdim=True)).clamp(max=1.0)
    if mask is not None:
        vel = torch.where(mask.unsqueeze(-1), vel, velocity)
    return vel


def _scenes_last_substep(x: Tensor, y: Tensor, vx: Tensor, vy: Tensor, ax: Tensor, ay: Tensor, gx: Tensor, gy: Tensor,
                         v_pref: Tensor, has_goal: Tensor, present: Tensor, dt: float, tau: float, v0: float,
                         sigma: float) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """One of :func:`social_force_velocities`' sub-steps on components laid out scenes last (``[M, B]``;
    ``present [M, B]``: who takes part, the pairs of two present pedestrians interacting): ``(x, y, vx, vy,
    ax, ay)`` after it, ``a`` the force it applied (the next sub-step's ``a_prev``). The same terms as
    :func:`_repulsion` and the eager loop, arranged for inductor to fuse the whole sub-step into loops
    vectorised over the scenes: the sum over the other pedestrians ``b`` is written out (``M`` terms of
    ``[M, B]``, no reduction to materialise), the terms of ``b`` alone (``s_b e_b``, ``s_b²``) are formed once,
    and the force's constant factors are folded (three square roots, one exponential and two divisions per
    pair):

        f_ab = w_ab · (v0 / 2σ) exp(-root / 2σ) · (n1 + n2) / root · (r_ab / n1 + q_ab / n2),

    with ``n1 = |r_ab|``, ``q_ab = r_ab - s_b e_b``, ``n2 = |q_ab|``, ``root = 2b``."""
    cos_phi = math.cos(FIELD_OF_VIEW_DEG / 2.0 / 180.0 * math.pi)
    scale, rate = v0 / (2.0 * sigma), -0.5 / sigma
    tx, ty = torch.where(has_goal, gx - x, vx), torch.where(has_goal, gy - y, vy)
    norm = torch.sqrt(tx * tx + ty * ty)
    norm = torch.where(norm == 0, torch.ones_like(norm), norm)
    ex, ey = tx / norm, ty / norm
    s = POTENTIAL_STEP * torch.sqrt(vx * vx + vy * vy)  # s_b  [b, B]
    sex, sey, ss = s * ex, s * ey, s * s
    push_x, push_y = torch.zeros_like(x), torch.zeros_like(y)
    index = torch.arange(x.shape[0], device=x.device).unsqueeze(1)  # a  [M, 1]
    for b in range(x.shape[0]):
        rx, ry = x - x[b], y - y[b]  # r_ab for every a  [a, B]
        qx, qy = rx - sex[b], ry - sey[b]
        n1 = torch.sqrt(rx * rx + ry * ry)
        n2 = torch.sqrt(qx * qx + qy * qy)
        total = n1 + n2
        inner = total * total - ss[b]
        root = torch.sqrt(inner.clamp_min(SQRT_FLOOR))
        # field of view: b in sight of a when e_a . (-r_ab) > |r_ab| cos(phi)
        w = torch.where(ex * rx + ey * ry < -(n1 * cos_phi), 1.0, OUT_OF_VIEW_FACTOR)
        live = present & present[b] & (index != b)  # pairs (a, b) of two present pedestrians, a != b
        coef = torch.where(live & (inner >= SQRT_FLOOR), w * torch.exp(rate * root) * (scale * total / root), 0.0)
        c1, c2 = coef / torch.where(live, n1, 1.0), coef / torch.where(live, n2, 1.0)  # a = b: no force, no 0/0
        push_x = push_x + (c1 * rx + c2 * qx)
        push_y = push_y + (c1 * ry + c2 * qy)
    fx = (1.0 / tau) * (v_pref * ex - vx) + push_x
    fy = (1.0 / tau) * (v_pref * ey - vy) + push_y
    x, y = x + vx * dt + 0.5 * fx * dt ** 2, y + vy * dt + 0.5 * fy * dt ** 2
    vx, vy = vx + 0.5 * (ax + fx) * dt, vy + 0.5 * (ay + fy) * dt
    cap = (v_pref * MAX_SPEED_MULTIPLIER / torch.sqrt(vx * vx + vy * vy)).clamp(max=1.0)
    return x, y, vx * cap, vy * cap, fx, fy


_COMPILED: dict[str, object] = {}


def compiled_social_force_velocities(
    position: Tensor,
    velocity: Tensor,
    goal: Tensor,
    preferred_speed: Tensor,
    *,
    time_step: float,
    substeps: int,
    tau: float,
    v0: float,
    sigma: float,
    has_goal: Tensor | None = None,
    mask: Tensor | None = None,
) -> Tensor:
    """:func:`social_force_velocities` through ``torch.compile`` (the simulator's ``orca_backend="compiled"``):
    one sub-step (:func:`_scenes_last_substep`, components laid out scenes last) compiled and fused into loops
    vectorised over the scenes, called ``substeps`` times. Compiled on first use (eager fallback with a
    warning): a static graph for the first shape, one with dynamic sizes if another comes (torch.compile's
    default). The same terms, but the norms are square roots of sums of squares (eager's ``vector_norm`` rounds
    differently), the force's constant factors are folded and inductor fuses the sums: float32 answers differ
    from the eager function's by rounding, which the sub-steps carry on
    (``experiments/human_model_agreement.py --backend compiled`` measures it against the package)."""
    from crowdrl.compile import CPP_WRAPPER, LazyCompiled

    fn = _COMPILED.get("fn")
    if fn is None:
        fn = _COMPILED["fn"] = LazyCompiled(_scenes_last_substep, dynamic=None, what="the social-force humans",
                                              options={"max_fusion_size": 4096, **CPP_WRAPPER})
    B, M, _ = position.shape
    present = torch.ones(M, B, dtype=torch.bool, device=position.device) if mask is None else mask.t().contiguous()
    has_goal = torch.ones(B, M, dtype=torch.bool, device=position.device) if has_goal is None else has_goal
    x, y = position.permute(2, 1, 0).contiguous()  # [M, B] each
    vx, vy = velocity.permute(2, 1, 0).contiguous()
    gx, gy = goal.permute(2, 1, 0).contiguous()
    v_pref, has_goal = preferred_speed.t().contiguous(), has_goal.t().contiguous()
    ax, ay = torch.zeros_like(x), torch.zeros_like(y)  # at rest in acceleration (two tensors: one graph, not an aliased one)
    dt = float(time_step) / int(substeps)
    for _ in range(int(substeps)):  # one compiled sub-step, called substeps times: a small graph, compiled once
        x, y, vx, vy, ax, ay = fn(x, y, vx, vy, ax, ay, gx, gy, v_pref, has_goal, present, dt, float(tau),
                                  float(v0), float(sigma))
    vel = torch.stack((vx, vy), -1).transpose(0, 1)  # [B, M, 2]
    if mask is not None:
        vel = torch.where(mask.unsqueeze(-1), vel, velocity)
    return vel

