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

    ``layer_norm=True`` puts a ``LayerNorm(hidden)`` between each hidden Linear and its ReLU (4 of them),
    a standard lever against drifting Q values; off (the paper's head), the layers and their
    ``state_dict`` keys are as above.
    """

    def __init__(self, embedding_dim: int = 32, num_actions: int = 81, hidden: int = 128,
                 layer_norm: bool = False) -> None:
        super().__init__()
        self.embedding_dim = int(embedding_dim)
        self.num_actions = int(num_actions)

        def hidden_layer(n_in: int) -> list[nn.Module]:
            return [nn.Linear(n_in, hidden), *([nn.LayerNorm(hidden)] if layer_norm else []), nn.ReLU()]

        self.trunk = nn.Sequential(*hidden_layer(embedding_dim), *hidden_layer(hidden))
        self.value = nn.Sequential(*hidden_layer(hidden), nn.Linear(hidden, 1))
        self.advantage = nn.Sequential(*hidden_layer(hidden), nn.Linear(hidden, num_actions))

    def forward(self, embedding: Tensor) -> Tensor:
        z = self.trunk(embedding)
        adv = self.advantage(z)
        return self.value(z) + adv - adv.mean(dim=-1, keepdim=True)
