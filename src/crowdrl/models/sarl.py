"""SARL's socially attentive encoder (Chen et al. 2019, "Crowd-robot interaction"), as a state encoder.

Architecture (dimensions of ``../shared/SPEC.md`` §2: mlp1 150/100, mlp2 100/50, attention 100/100):

* per human ``i`` the joint state ``s_i = [robot_rc, human_rc_i]`` (9 + 5 = 14 values);
* ``e_i = mlp1(s_i)``: Linear(14, 150)-ReLU-Linear(150, 100)-ReLU;
* ``h_i = mlp2(e_i)``: Linear(100, 100)-ReLU-Linear(100, 50);
* attention score ``a_i = attention([e_i, mean_j e_j])``: Linear(200, 100)-ReLU-Linear(100,
  100)-ReLU-Linear(100, 1), weights ``w = softmax_i(a)`` over the humans;
* embedding ``[robot_rc, sum_i w_i h_i]``: 9 + 50 = 59 values.

Upstream's value layer (mlp3 on that vector) is dropped: the embedding feeds the dueling head.
With ``humans_mask`` the mean, the softmax and the weighted sum run over the present humans only.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from crowdrl.models.masking import HUMAN_RC_DIM, ROBOT_RC_DIM, flatten_crowd, masked_mean, masked_softmax
from crowdrl.models.mlp import mlp
from crowdrl.models.registry import register_encoder


@register_encoder("sarl")
class SARLEncoder(nn.Module):
    """SARL attention encoder: ``(robot_rc [*, 9], humans_rc [*, N, 5], humans_mask [*, N]?) -> [*, 59]``.

    Works for any ``N >= 1`` and any leading batch dims (including none); invariant to the
    order of the humans. See the module docstring for the architecture.

    Example::

        enc = SARLEncoder()
        emb = enc(torch.zeros(4, 9), torch.randn(4, 10, 5))     # [4, 59]
        w = enc.attention_weights(torch.zeros(9), torch.randn(10, 5))  # [10], sums to 1
    """

    def __init__(
        self,
        robot_dim: int = ROBOT_RC_DIM,
        human_dim: int = HUMAN_RC_DIM,
        mlp1_dims: tuple[int, ...] = (150, 100),
        mlp2_dims: tuple[int, ...] = (100, 50),
        attention_dims: tuple[int, ...] = (100, 100),
    ) -> None:
        super().__init__()
        self.robot_dim = int(robot_dim)
        self.human_dim = int(human_dim)
        joint = self.robot_dim + self.human_dim
        self.mlp1 = mlp([joint, *mlp1_dims], last_relu=True)
        self.mlp2 = mlp([mlp1_dims[-1], *mlp2_dims], last_relu=False)
        self.attention = mlp([2 * mlp1_dims[-1], *attention_dims, 1], last_relu=False)
        self.embedding_dim = self.robot_dim + int(mlp2_dims[-1])

    def _encode(self, robot_rc: Tensor, humans_rc: Tensor, humans_mask: Tensor | None
                ) -> tuple[torch.Size, Tensor, Tensor, Tensor]:
        """``(lead, robot [B, 9], weights [B, N], features [B, N, 50])``."""
        lead, robot, humans, mask = flatten_crowd("SARLEncoder", robot_rc, humans_rc, humans_mask,
                                                  self.robot_dim, self.human_dim)
        joint = torch.cat((robot.unsqueeze(-2).expand(-1, humans.shape[-2], -1), humans), dim=-1)
        e = self.mlp1(joint)  # [B, N, 100]
        g = masked_mean(e, mask).unsqueeze(-2).expand_as(e)
        scores = self.attention(torch.cat((e, g), dim=-1)).squeeze(-1)  # [B, N]
        return lead, robot, masked_softmax(scores, mask), self.mlp2(e)

    def forward(self, robot_rc: Tensor, humans_rc: Tensor, humans_mask: Tensor | None = None) -> Tensor:
        lead, robot, weights, features = self._encode(robot_rc, humans_rc, humans_mask)
        pooled = torch.matmul(weights.unsqueeze(-2), features).squeeze(-2)  # [B, 50]
        return torch.cat((robot, pooled), dim=-1).reshape(*lead, self.embedding_dim)

    def attention_weights(self, robot_rc: Tensor, humans_rc: Tensor, humans_mask: Tensor | None = None) -> Tensor:
        """The attention weights over the humans ``[*, N]`` (0 for absent humans)."""
        lead, _, weights, _ = self._encode(robot_rc, humans_rc, humans_mask)
        return weights.reshape(*lead, humans_rc.shape[-2])


__all__ = ["SARLEncoder"]
