"""Crowd state predictors for online planning (``docs/mdp.md``, "Online planning").

A predictor maps the world-frame observation ``(robot [*, 9], humans [*, N, 5], humans_mask
[*, N]?)`` to each human's observable state one step later, ``[*, N, 5]`` = (px, py, vx, vy, r).
The humans do not see the robot, so one prediction per state serves every robot action.

* :class:`CrowdStatePredictor` (``"learned"``): SG-D3QN's state predictor, a graph attention
  encoder of its own (the architecture of :class:`~crowdrl.models.SGD3QNEncoder`, on world-frame
  states) whose per-human node embeddings go through an MLP 32 → 64 → 5. The MLP's output is
  added to the human's current state (a residual: the network learns the step's change, a
  quantity of the order of ``v·Δt``, not absolute positions); trained by :func:`predictor_loss`.
* :class:`ConstantVelocityPredictor` (``"const_vel"``): ``p + v·Δt``, velocity and radius kept;
  no parameters.

Absent humans (``humans_mask`` False) keep their input row (zeros in the env's observation).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from crowdrl.models.mlp import mlp
from crowdrl.models.sgd3qn import SGD3QNEncoder

ROBOT_DIM = 9
HUMAN_DIM = 5
PREDICTORS = ("learned", "const_vel")


def _keep_absent(predicted: Tensor, humans: Tensor, humans_mask: Tensor | None) -> Tensor:
    if humans_mask is None:
        return predicted
    return torch.where(humans_mask.unsqueeze(-1), predicted, humans)


class CrowdStatePredictor(nn.Module):
    """Learned one-step crowd predictor: ``(robot, humans, humans_mask?) -> next humans [*, N, 5]``."""

    def __init__(self, hidden_dim: int = 64, embedding_dim: int = 32, motion_hidden: int = 64) -> None:
        super().__init__()
        self.graph = SGD3QNEncoder(robot_dim=ROBOT_DIM, human_dim=HUMAN_DIM, hidden_dim=hidden_dim,
                                   embedding_dim=embedding_dim)
        self.motion = mlp([embedding_dim, motion_hidden, HUMAN_DIM], last_relu=False)

    def forward(self, robot: Tensor, humans: Tensor, humans_mask: Tensor | None = None) -> Tensor:
        nodes = self.graph.node_embeddings(robot, humans, humans_mask)  # [*, N+1, D]
        return _keep_absent(humans + self.motion(nodes[..., 1:, :]), humans, humans_mask)


class ConstantVelocityPredictor(nn.Module):
    """Each human keeps its velocity for one step of ``time_step`` seconds (no parameters)."""

    def __init__(self, time_step: float) -> None:
        super().__init__()
        if not time_step > 0:
            raise ValueError(f"time_step must be > 0, got {time_step}")
        self.time_step = float(time_step)

    def forward(self, robot: Tensor, humans: Tensor, humans_mask: Tensor | None = None) -> Tensor:
        moved = torch.cat((humans[..., 0:2] + humans[..., 2:4] * self.time_step, humans[..., 2:]), dim=-1)
        return _keep_absent(moved, humans, humans_mask)


def make_predictor(name: str, time_step: float) -> nn.Module:
    """The predictor called ``name`` (one of :data:`PREDICTORS`) for steps of ``time_step`` seconds."""
    if name == "learned":
        return CrowdStatePredictor()
    if name == "const_vel":
        return ConstantVelocityPredictor(time_step)
    raise ValueError(f"unknown predictor {name!r}; allowed: {', '.join(PREDICTORS)}")


def predictor_loss(predictor: nn.Module, robot: Tensor, humans: Tensor, next_humans: Tensor,
                   humans_mask: Tensor | None = None) -> Tensor:
    """Mean squared error of the predicted next human states against the real ones, over the
    present humans and their 5 values."""
    err = (predictor(robot, humans, humans_mask) - next_humans).pow(2)
    if humans_mask is None:
        return err.mean()
    weight = humans_mask.unsqueeze(-1).to(err.dtype)
    return (err * weight).sum() / (weight.sum() * HUMAN_DIM).clamp_min(1.0)


__all__ = ["PREDICTORS", "ConstantVelocityPredictor", "CrowdStatePredictor", "make_predictor", "predictor_loss"]
