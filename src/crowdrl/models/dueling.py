"""The dueling Q head shared by every encoder (``docs/mdp.md``, "Models")."""

from __future__ import annotations

from torch import Tensor, nn


class DuelingHead(nn.Module):
    """``Q = V + A - mean_a A`` from a state embedding ``[*, embedding_dim]`` to ``[*, num_actions]``.

    trunk: Linear(embedding_dim, hidden)-ReLU-Linear(hidden, hidden)-ReLU;
    value: Linear(hidden, hidden)-ReLU-Linear(hidden, 1);
    advantage: Linear(hidden, hidden)-ReLU-Linear(hidden, num_actions).
    The advantage mean is taken per sample over the actions (upstream averaged over the whole
    batch, which made a sample's Q depend on the other samples of its batch).
    """

    def __init__(self, embedding_dim: int = 32, num_actions: int = 81, hidden: int = 128) -> None:
        super().__init__()
        self.embedding_dim = int(embedding_dim)
        self.num_actions = int(num_actions)
        self.trunk = nn.Sequential(
            nn.Linear(embedding_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU()
        )
        self.value = nn.Sequential(nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, 1))
        self.advantage = nn.Sequential(nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, num_actions))

    def forward(self, embedding: Tensor) -> Tensor:
        z = self.trunk(embedding)
        adv = self.advantage(z)
        return self.value(z) + adv - adv.mean(dim=-1, keepdim=True)
