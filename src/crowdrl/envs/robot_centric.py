"""The robot-centric state (``docs/mdp.md``, "Observations") as a pure function and as a TorchRL
``Transform``; in obstacle scenarios, the humans and the observed obstacle edges as one set of
entity tokens (:func:`entity_tokens`) for the encoders."""

from __future__ import annotations

import math
from typing import Sequence

import torch
from tensordict import TensorDictBase
from torch import Tensor
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import Transform


def robot_centric(robot: Tensor, humans: Tensor) -> tuple[Tensor, Tensor]:
    """Rotate and translate world-frame observations into the robot's goal-aligned frame.

    ``robot [..., 9]`` (px, py, vx, vy, r, gx, gy, v_pref, theta) becomes
    ``[0, 0, (Rv)x, (Rv)y, r, |g - p|, 0, v_pref, wrap(theta - rot)]`` and each human
    ``[..., N, 5]`` (px, py, vx, vy, r_h) becomes ``[(R dp)x, (R dp)y, (R v_h)x, (R v_h)y, r_h + r]``,
    where ``rot = atan2(gy - py, gx - px)`` and ``R`` rotates by ``-rot``.
    """
    if robot.shape[-1] != 9:
        raise ValueError(f"robot observation must end in 9 values, got {tuple(robot.shape)}")
    if humans.shape[-1] != 5 or humans.shape[:-2] != robot.shape[:-1]:
        raise ValueError(f"humans must be shaped [..., N, 5] with batch {tuple(robot.shape[:-1])}, got {tuple(humans.shape)}")
    px, py, vx, vy, r, gx, gy, v_pref, theta = robot.unbind(-1)
    dgx, dgy = gx - px, gy - py
    rot = torch.atan2(dgy, dgx)
    c, s = torch.cos(rot), torch.sin(rot)
    zero = torch.zeros_like(px)
    heading = torch.remainder(theta - rot + math.pi, 2 * math.pi) - math.pi
    robot_rc = torch.stack(
        (zero, zero, vx * c + vy * s, -vx * s + vy * c, r, torch.sqrt(dgx * dgx + dgy * dgy), zero, v_pref, heading),
        dim=-1,
    )
    c_, s_ = c.unsqueeze(-1), s.unsqueeze(-1)
    hx, hy = humans[..., 0] - px.unsqueeze(-1), humans[..., 1] - py.unsqueeze(-1)
    hvx, hvy = humans[..., 2], humans[..., 3]
    humans_rc = torch.stack(
        (hx * c_ + hy * s_, -hx * s_ + hy * c_, hvx * c_ + hvy * s_, -hvx * s_ + hvy * c_, humans[..., 4] + r.unsqueeze(-1)),
        dim=-1,
    )
    return robot_rc, humans_rc


ENTITY_DIM = 10  # an entity token: 5 human features, 4 segment endpoints, 1 obstacle flag


def _rotation(robot: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(px, py, cos rot, sin rot)`` ``[..., 1]`` of the robot's goal-aligned frame."""
    px, py, gx, gy = robot[..., 0:1], robot[..., 1:2], robot[..., 5:6], robot[..., 6:7]
    rot = torch.atan2(gy - py, gx - px)
    return px, py, torch.cos(rot), torch.sin(rot)


def obstacles_centric(robot: Tensor, obstacles: Tensor) -> Tensor:
    """World-frame obstacle edges ``[..., K, 4]`` (ax, ay, bx, by) in the robot's goal-aligned frame
    (the frame of :func:`robot_centric`: the robot at the origin, its goal on the +x axis)."""
    if obstacles.shape[-1] != 4 or obstacles.shape[:-2] != robot.shape[:-1]:
        raise ValueError(f"obstacles must be shaped [..., K, 4] with batch {tuple(robot.shape[:-1])}, "
                         f"got {tuple(obstacles.shape)}")
    px, py, c, s = _rotation(robot)
    x = obstacles[..., 0::2] - px.unsqueeze(-1)  # [..., K, 2]: ax, bx
    y = obstacles[..., 1::2] - py.unsqueeze(-1)
    c, s = c.unsqueeze(-1), s.unsqueeze(-1)
    xr, yr = x * c + y * s, -x * s + y * c
    return torch.stack((xr[..., 0], yr[..., 0], xr[..., 1], yr[..., 1]), -1)


def entity_tokens(robot_rc: Tensor, humans_rc: Tensor, obstacles_rc: Tensor | None = None,
                  humans_mask: Tensor | None = None, obstacles_mask: Tensor | None = None
                  ) -> tuple[Tensor, Tensor]:
    """The humans and the obstacle edges as ``N + K`` tokens ``[..., N+K, 10]`` with a mask
    ``[..., N+K]`` (True = present), for an encoder built with ``human_dim=ENTITY_DIM``.

    A human's token is its robot-centric row (px, py, vx, vy, r_h + r) then five zeros. An edge's
    token reads as a static human at the edge's point nearest to the robot, with the combined
    radius ``r`` (an edge has no thickness), then the edge's endpoints and a 1 (the obstacle flag):
    ``(cx, cy, 0, 0, r, ax, ay, bx, by, 1)``. Any encoder's mask-aware path over humans thus
    serves obstacles too. Masked tokens are zeros. ``obstacles_rc`` ``None`` (or ``K = 0``): the
    humans alone, with five zero columns (a network trained among obstacles, in open space).

    >>> robot = torch.tensor([[0.0, 0, 0, 0, 0.3, 4, 0, 1, 0]])
    >>> wall = torch.tensor([[[-1.0, 2.0, 1.0, 2.0]]])
    >>> tokens, mask = entity_tokens(robot, torch.zeros(1, 1, 5), wall)
    >>> tokens[0, 1].tolist(), mask.tolist()
    ([0.0, 2.0, 0.0, 0.0, 0.30000001192092896, -1.0, 2.0, 1.0, 2.0, 1.0], [[True, True]])
    """
    lead, n = humans_rc.shape[:-2], humans_rc.shape[-2]
    if humans_mask is None:
        humans_mask = torch.ones((*lead, n), dtype=torch.bool, device=humans_rc.device)
    humans = torch.cat((humans_rc, humans_rc.new_zeros((*lead, n, ENTITY_DIM - humans_rc.shape[-1]))), -1)
    humans = torch.where(humans_mask.unsqueeze(-1), humans, 0.0)
    if obstacles_rc is None or obstacles_rc.shape[-2] == 0:
        return humans, humans_mask
    k = obstacles_rc.shape[-2]
    if obstacles_mask is None:
        obstacles_mask = torch.ones((*lead, k), dtype=torch.bool, device=obstacles_rc.device)
    a, b = obstacles_rc[..., 0:2], obstacles_rc[..., 2:4]
    ab = b - a
    t = (-(a * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-12)).clamp(0.0, 1.0)
    closest = a + t.unsqueeze(-1) * ab
    radius = robot_rc[..., 4:5].unsqueeze(-2).expand(*lead, k, 1)
    edges = torch.cat((closest, torch.zeros_like(closest), radius, obstacles_rc, torch.ones_like(radius)), -1)
    edges = torch.where(obstacles_mask.unsqueeze(-1), edges, 0.0)
    return torch.cat((humans, edges), -2), torch.cat((humans_mask, obstacles_mask), -1)


class RobotCentric(Transform):
    """Writes the robot-centric robot and human states next to the world-frame ones.

    Works on env outputs (``step``/``reset``) and on sampled replay batches (``forward``).

    With ``entities=True`` it also writes :func:`entity_tokens` of the humans (their mask
    ``"humans_mask"`` when present) and the observed obstacle edges (``"obstacles"``,
    ``"obstacles_mask"`` when present; none in open space) as ``"entities_rc"`` ``[B, N+K, 10]``
    and ``"entities_mask"`` ``[B, N+K]``: what a network trained among obstacles reads.
    """

    ENTITY_KEYS = ("entities_rc", "entities_mask")

    def __init__(
        self,
        in_keys: Sequence[str] = ("robot", "humans"),
        out_keys: Sequence[str] = ("robot_rc", "humans_rc"),
        *,
        entities: bool = False,
    ) -> None:
        if len(in_keys) != 2 or len(out_keys) != 2:
            raise ValueError("RobotCentric takes exactly two in_keys (robot, humans) and two out_keys")
        super().__init__(in_keys=list(in_keys), out_keys=list(out_keys))
        self.entities = bool(entities)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        robot_key, humans_key = self.in_keys
        for key in self.in_keys:
            if key not in next_tensordict.keys(include_nested=True):
                raise KeyError(f"RobotCentric: key {key!r} missing from the tensordict")
        robot_rc, humans_rc = robot_centric(next_tensordict.get(robot_key), next_tensordict.get(humans_key))
        next_tensordict.set(self.out_keys[0], robot_rc)
        next_tensordict.set(self.out_keys[1], humans_rc)
        if self.entities:
            obstacles = next_tensordict.get("obstacles", None)
            obstacles_rc = None if obstacles is None else obstacles_centric(next_tensordict.get(robot_key), obstacles)
            tokens, mask = entity_tokens(robot_rc, humans_rc, obstacles_rc, next_tensordict.get("humans_mask", None),
                                         next_tensordict.get("obstacles_mask", None))
            next_tensordict.set(self.ENTITY_KEYS[0], tokens)
            next_tensordict.set(self.ENTITY_KEYS[1], mask)
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        self._call(tensordict)
        if ("next", self.in_keys[0]) in tensordict.keys(include_nested=True):
            self._call(tensordict.get("next"))
        return tensordict

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        robot_spec = observation_spec[self.in_keys[0]]
        humans_spec = observation_spec[self.in_keys[1]]
        observation_spec[self.out_keys[0]] = Unbounded(robot_spec.shape, dtype=robot_spec.dtype, device=robot_spec.device)
        observation_spec[self.out_keys[1]] = Unbounded(humans_spec.shape, dtype=humans_spec.dtype, device=humans_spec.device)
        if self.entities:
            k = observation_spec["obstacles"].shape[-2] if "obstacles" in observation_spec.keys() else 0
            *lead, n, _ = humans_spec.shape
            observation_spec[self.ENTITY_KEYS[0]] = Unbounded((*lead, n + k, ENTITY_DIM), dtype=humans_spec.dtype,
                                                              device=humans_spec.device)
            observation_spec[self.ENTITY_KEYS[1]] = Categorical(2, (*lead, n + k), dtype=torch.bool,
                                                                device=humans_spec.device)
        return observation_spec
