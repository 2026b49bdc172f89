"""MP-RGL's relational graph encoder (Chen et al. 2020, "Relational graph learning for crowd
navigation"), as a state encoder.

Architecture (``../shared/SPEC.md`` §2: 32-d nodes, embedded-Gaussian similarity, 2 layers):

* ``w_r``: Linear(9, 64)-ReLU-Linear(64, 32)-ReLU on the robot state, ``w_h``:
  Linear(5, 64)-ReLU-Linear(64, 32)-ReLU on each human; node features
  ``X = [w_r(robot); w_h(humans)]`` ``[N+1, 32]``, the robot being node 0;
* relation matrix (embedded Gaussian), computed once from ``X``:
  ``A = softmax_j((X W_a)(X W_b)^T)`` with ``W_a``, ``W_b`` 32x32 (no bias); a complete graph
  (every node, the robot included, relates to every node);
* two message-passing layers with skip connections, ``H0 = X``,
  ``H_{l+1} = ReLU(A H_l W_l) + H_l`` with ``W_l`` 32x32 (no bias);
* the robot node's row of ``H2`` (32 values) is the embedding.

Upstream's value network on that row is dropped: the embedding feeds the dueling head. With
``humans_mask`` absent humans are removed from the graph (their columns of ``A`` get weight 0;
their own rows are never read). Only the robot's row of the second layer is computed.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from crowdrl.models.masking import HUMAN_RC_DIM, ROBOT_RC_DIM, flatten_crowd
from crowdrl.models.mlp import mlp
from crowdrl.models.registry import register_encoder


@register_encoder("mp_rgl")
class MPRGLEncoder(nn.Module):
    """Relational graph encoder: ``(robot_rc [*, 9], humans_rc [*, N, 5], humans_mask [*, N]?) -> [*, 32]``.

    Works for any ``N >= 1`` and any leading batch dims (including none); invariant to the
    order of the humans. See the module docstring for the architecture.

    Example::

        enc = MPRGLEncoder()
        emb = enc(torch.zeros(4, 9), torch.randn(4, 10, 5))   # [4, 32]
        a = enc.relation_matrix(torch.zeros(9), torch.randn(10, 5))  # [11, 11], rows sum to 1
    """

    def __init__(
        self,
        robot_dim: int = ROBOT_RC_DIM,
        human_dim: int = HUMAN_RC_DIM,
        hidden_dim: int = 64,
        embedding_dim: int = 32,
        num_layers: int = 2,
    ) -> None:
        super().__init__()
        if num_layers < 1:
            raise ValueError(f"num_layers must be >= 1, got {num_layers}")
        self.robot_dim = int(robot_dim)
        self.human_dim = int(human_dim)
        self.embedding_dim = int(embedding_dim)
        self.w_r = mlp([self.robot_dim, hidden_dim, self.embedding_dim])
        self.w_h = mlp([self.human_dim, hidden_dim, self.embedding_dim])
        self.w_a = nn.Linear(self.embedding_dim, self.embedding_dim, bias=False)
        self.w_b = nn.Linear(self.embedding_dim, self.embedding_dim, bias=False)
        self.layers = nn.ModuleList(nn.Linear(self.embedding_dim, self.embedding_dim, bias=False)
                                    for _ in range(num_layers))

    def _graph(self, robot_rc: Tensor, humans_rc: Tensor, humans_mask: Tensor | None
               ) -> tuple[torch.Size, Tensor, Tensor]:
        """``(lead, X [B, N+1, D], A [B, N+1, N+1])``."""
        lead, robot, humans, mask = flatten_crowd("MPRGLEncoder", robot_rc, humans_rc, humans_mask,
                                                  self.robot_dim, self.human_dim)
        x = torch.cat((self.w_r(robot).unsqueeze(-2), self.w_h(humans)), dim=-2)
        logits = torch.matmul(self.w_a(x), self.w_b(x).transpose(-1, -2))
        if mask is not None:  # the robot's column is always present: no row is fully masked
            nodes = torch.cat((mask.new_ones(mask.shape[0], 1), mask), dim=-1)
            logits = logits.masked_fill(~nodes.unsqueeze(-2), float("-inf"))
        return lead, x, torch.softmax(logits, dim=-1)

    def forward(self, robot_rc: Tensor, humans_rc: Tensor, humans_mask: Tensor | None = None) -> Tensor:
        lead, h, a = self._graph(robot_rc, humans_rc, humans_mask)
        *hidden, last = self.layers
        for w in hidden:
            h = torch.relu(w(torch.matmul(a, h))) + h
        robot = torch.relu(last(torch.matmul(a[:, :1], h))) + h[:, :1]  # the robot's row only
        return robot[:, 0].reshape(*lead, self.embedding_dim)

    def relation_matrix(self, robot_rc: Tensor, humans_rc: Tensor, humans_mask: Tensor | None = None) -> Tensor:
        """The normalised relation matrix ``A`` ``[*, N+1, N+1]`` (node 0 is the robot)."""
        lead, _, a = self._graph(robot_rc, humans_rc, humans_mask)
        return a.reshape(*lead, *a.shape[-2:])


__all__ = ["MPRGLEncoder"]
