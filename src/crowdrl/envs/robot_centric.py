"""The robot-centric state (``docs/mdp.md``, "Observations") as a pure function and as a TorchRL
``Transform``."""

from __future__ import annotations

import math
from typing import Sequence

import torch
from tensordict import TensorDictBase
from torch import Tensor
from torchrl.data import Composite, Unbounded
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


class RobotCentric(Transform):
    """Writes the robot-centric robot and human states next to the world-frame ones.

    Works on env outputs (``step``/``reset``) and on sampled replay batches (``forward``).
    """

    def __init__(
        self,
        in_keys: Sequence[str] = ("robot", "humans"),
        out_keys: Sequence[str] = ("robot_rc", "humans_rc"),
    ) -> None:
        if len(in_keys) != 2 or len(out_keys) != 2:
            raise ValueError("RobotCentric takes exactly two in_keys (robot, humans) and two out_keys")
        super().__init__(in_keys=list(in_keys), out_keys=list(out_keys))

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        robot_key, humans_key = self.in_keys
        for key in self.in_keys:
            if key not in next_tensordict.keys(include_nested=True):
                raise KeyError(f"RobotCentric: key {key!r} missing from the tensordict")
        robot_rc, humans_rc = robot_centric(next_tensordict.get(robot_key), next_tensordict.get(humans_key))
        next_tensordict.set(self.out_keys[0], robot_rc)
        next_tensordict.set(self.out_keys[1], humans_rc)
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
        return observation_spec
