"""LSTM-RL's encoder (Everett et al. 2018, as in CrowdNav's ``lstm_rl``), as a state encoder.

Architecture (``../shared/SPEC.md`` §2: LSTM hidden 50):

* per human ``i`` the joint state ``s_i = [robot_rc, human_rc_i]`` (9 + 5 = 14 values);
* the humans sorted by distance to the robot, **farthest first, closest last** (the distance is
  ``|(px, py)|`` of ``human_rc``, the robot being at the origin of the robot-centric frame), so the
  closest human is the LSTM's last input and weighs most on its final state;
* one LSTM layer, input 14, hidden 50, zero initial state; ``h_N`` its final hidden state;
* embedding ``[robot_rc, h_N]``: 9 + 50 = 59 values.

Upstream's value layer on that vector is dropped: the embedding feeds the dueling head.

The LSTM is written out step by step (gates in ``nn.LSTM``'s order ``i, f, g, o``; the input
projection of every step is one matmul): with ``humans_mask``, absent humans sort first (as if
infinitely far) and their steps leave the state unchanged, so the state is still zero when the
first present human arrives and the output equals that of the unpadded crowd. The same code
runs with and without a mask, under ``torch.compile`` and ``torch.func`` transforms.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from crowdrl.models.masking import HUMAN_RC_DIM, ROBOT_RC_DIM, flatten_crowd
from crowdrl.models.registry import register_encoder


def sort_far_to_near(humans: Tensor, mask: Tensor | None) -> tuple[Tensor, Tensor | None]:
    """``humans [B, N, 5]`` reordered farthest first, closest last (absent humans first of all),
    and the mask in the same order. Ties keep the input order."""
    dist2 = humans[..., :2].detach().pow(2).sum(-1)  # the order only: no gradient through it
    if mask is not None:
        dist2 = dist2.masked_fill(~mask, float("inf"))
    if torch.onnx.is_in_onnx_export():  # ONNX has no stable sort; its TopK puts the lower index first among
        # equals, which is the stable descending order (crowdrl.export)
        order = torch.topk(dist2, dist2.shape[-1], dim=-1, largest=True, sorted=True).indices
    else:
        order = torch.argsort(dist2, dim=-1, descending=True, stable=True)
    humans = torch.gather(humans, -2, order.unsqueeze(-1).expand_as(humans))
    return humans, None if mask is None else torch.gather(mask, -1, order)


@register_encoder("lstm_rl")
class LSTMRLEncoder(nn.Module):
    """LSTM-RL encoder: ``(robot_rc [*, 9], humans_rc [*, N, 5], humans_mask [*, N]?) -> [*, 59]``.

    Works for any ``N >= 1`` and any leading batch dims (including none); the order of the
    input humans does not matter (they are sorted by distance). Parameters: ``input`` =
    Linear(14, 4H) (nn.LSTM's ``weight_ih_l0`` with one bias), ``hidden`` = Linear(H, 4H, bias=False)
    (``weight_hh_l0``). See the module docstring for the architecture.

    Example::

        enc = LSTMRLEncoder()
        emb = enc(torch.zeros(4, 9), torch.randn(4, 10, 5))   # [4, 59]
    """

    def __init__(self, robot_dim: int = ROBOT_RC_DIM, human_dim: int = HUMAN_RC_DIM, hidden_dim: int = 50) -> None:
        super().__init__()
        self.robot_dim = int(robot_dim)
        self.human_dim = int(human_dim)
        self.hidden_dim = int(hidden_dim)
        self.input = nn.Linear(self.robot_dim + self.human_dim, 4 * self.hidden_dim)
        self.hidden = nn.Linear(self.hidden_dim, 4 * self.hidden_dim, bias=False)
        self.embedding_dim = self.robot_dim + self.hidden_dim
        bound = 1.0 / math.sqrt(self.hidden_dim)  # nn.LSTM's initialisation
        for p in self.parameters():
            nn.init.uniform_(p, -bound, bound)

    def forward(self, robot_rc: Tensor, humans_rc: Tensor, humans_mask: Tensor | None = None) -> Tensor:
        lead, robot, humans, mask = flatten_crowd("LSTMRLEncoder", robot_rc, humans_rc, humans_mask,
                                                  self.robot_dim, self.human_dim)
        humans, mask = sort_far_to_near(humans, mask)
        n = humans.shape[-2]
        joint = torch.cat((robot.unsqueeze(-2).expand(-1, n, -1), humans), dim=-1)
        x = self.input(joint)  # [B, N, 4H]: every step's input projection at once
        h = c = robot.new_zeros(robot.shape[0], self.hidden_dim)
        for t in range(n):
            i, f, g, o = (x[:, t] + self.hidden(h)).chunk(4, dim=-1)
            c_new = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
            h_new = torch.sigmoid(o) * torch.tanh(c_new)
            if mask is None:
                h, c = h_new, c_new
            else:
                present = mask[:, t].unsqueeze(-1)
                h, c = torch.where(present, h_new, h), torch.where(present, c_new, c)
        return torch.cat((robot, h), dim=-1).reshape(*lead, self.embedding_dim)


__all__ = ["LSTMRLEncoder", "sort_far_to_near"]
