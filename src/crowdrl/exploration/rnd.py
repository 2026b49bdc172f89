"""Random Network Distillation (RND, Burda et al., 2018) as a third intrinsic reward, ``exploration=rnd``.

A frozen random *target* network ``f`` and a trained *predictor* ``f̂`` embed the successor ``s'`` of each
sampled transition; the bonus is the predictor's error ``r_in = mean_j (f̂(s')_j - f(s')_j)^2``: high on states
the predictor has seen little of. Both are the user's feature encoder (the agent's architecture, fresh
parameters) followed by a head (the target: ``Linear(D, 64)``; the predictor: ``Linear(D, 128)-ReLU-Linear(128, 64)``).
The predictor is trained on the same sampled batch by TorchRL's :class:`~torchrl.objectives.rnd.RNDLoss`
(MSE to the target on every sample, ``update_fraction=1``: no random mask drawn from the global RNG) with its
own Adam. The bonus then goes through :class:`~crowdrl.exploration.intrinsic.IntrinsicRewardTransform` as
ICM's and RE3's do, with the shared intrinsic keys: ``conf/exploration/rnd.yaml`` whitens the inputs
(``obs_norm``) and divides ``r_in`` by its running std (``reward_norm: std``), as the paper does.

This module, its yaml and its import in ``crowdrl/exploration/__init__.py`` are all that adding RND took.

Examples:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from torch import nn
    >>> batch = TensorDict({"observation": torch.randn(8, 4), "action": torch.zeros(8, dtype=torch.long),
    ...                     ("next", "observation"): torch.randn(8, 4)}, batch_size=[8])
    >>> rnd = RND(nn.Linear(4, 16), nn.Linear(4, 16), feature_dim=16, seed=0)
    >>> r_in = rnd.bonus(batch)
    >>> r_in.shape, bool((r_in >= 0).all())
    (torch.Size([8]), True)
    >>> before = float(r_in.mean())
    >>> for _ in range(50):
    ...     _ = rnd.update(batch)
    >>> float(rnd.bonus(batch).mean()) < before  # a state seen again earns less
    True
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor, nn
from torchrl.objectives.rnd import RNDLoss

from crowdrl.exploration.intrinsic import IntrinsicBonus, feature_dim_of, seeded_init
from crowdrl.exploration.intrinsic_strategy import IntrinsicConfig, IntrinsicExploration
from crowdrl.exploration.strategy import ReplayContext, register_strategy

EMBED_DIM = 64
PACKED = "rnd_obs"  # where the successor's observation tensors are packed for RNDLoss (one key)


class _Embedding(nn.Module):
    """``head(encoder(*obs))`` on a packed tensordict of the observation keys (RNDLoss passes one input, cast to
    float: the boolean keys, masks, are restored)."""

    def __init__(self, encoder: nn.Module, head: nn.Module, keys: Sequence[NestedKey]) -> None:
        super().__init__()
        self.encoder, self.head, self.keys = encoder, head, list(keys)
        self.bool_keys: set = set()

    def forward(self, packed: TensorDictBase) -> Tensor:
        args = [packed.get(k) > 0.5 if k in self.bool_keys else packed.get(k) for k in self.keys]
        return self.head(self.encoder(*args))


class RND(IntrinsicBonus):
    """RND's bonus and its predictor's training step (see the module docstring).

    Args:
        target_encoder, predictor_encoder: two modules of their own (fresh, not the value network's) mapping
            the observation tensors, in ``in_keys`` order, to ``[*B, D]``; the target is frozen in place.
        in_keys: observation keys fed to the encoders.
        feature_dim: ``D``; defaults to the encoders' ``embedding_dim``.
        lr: the predictor's Adam learning rate.
        seed: if given, the heads are drawn from this seed without touching the global RNG.
    """

    def __init__(self, target_encoder: nn.Module, predictor_encoder: nn.Module,
                 in_keys: Sequence[NestedKey] = ("observation",), *, feature_dim: int | None = None,
                 lr: float = 1e-4, seed: int | None = None) -> None:
        super().__init__(in_keys)
        dim = feature_dim_of(target_encoder, feature_dim)
        with seeded_init(seed):
            target_head = nn.Linear(dim, EMBED_DIM)
            predictor_head = nn.Sequential(nn.Linear(dim, 128), nn.ReLU(), nn.Linear(128, EMBED_DIM))
        self.target = _Embedding(target_encoder, target_head, self.in_keys)
        self.predictor = _Embedding(predictor_encoder, predictor_head, self.in_keys)
        self.target.requires_grad_(False)
        self.target.eval()
        self.loss = RNDLoss(self.predictor, self.target, update_fraction=1.0)
        self.loss.set_keys(observation=("next", PACKED))
        self.optimizer = torch.optim.Adam(self.predictor.parameters(), lr=lr)

    def _packed(self, td: TensorDictBase) -> TensorDictBase:
        """The successor's observation tensors as one tensordict (its boolean keys recorded for the networks)."""
        obs = dict(zip(self.in_keys, self.obs(td, next_=True)))
        for key, value in obs.items():
            if value.dtype == torch.bool:
                self.target.bool_keys.add(key)
                self.predictor.bool_keys.add(key)
        return TensorDict(obs, batch_size=td.batch_size)

    def errors(self, td: TensorDictBase) -> Tensor:
        """``mean_j (f̂(s')_j - f(s')_j)^2`` per sample ``[*B]`` (with gradients to the predictor)."""
        packed = self._packed(td)
        with torch.no_grad():
            target = self.target(packed)
        return (self.predictor(packed) - target).pow(2).mean(-1)

    def bonus(self, td: TensorDictBase) -> Tensor:
        with torch.no_grad():
            return self.errors(td)

    def update(self, td: TensorDictBase) -> dict[str, float]:
        """One Adam step of the predictor on TorchRL's ``RNDLoss`` over the batch's successors."""
        loss = self.loss(TensorDict({("next", PACKED): self._packed(td)}, batch_size=td.batch_size))["loss_predictor"]
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        return {"rnd_loss": float(loss.detach())}


@dataclass
class RNDConfig(IntrinsicConfig):
    """``exploration=rnd``: the shared intrinsic keys and the predictor's Adam learning rate."""

    rnd_lr: float = 1e-4

    @staticmethod
    def check(x: Any, limits: Any, active: bool) -> None:
        IntrinsicConfig.check(x, limits, active)
        if x.rnd_lr <= 0:
            raise ValueError(f"rnd_lr: must be > 0, got {x.rnd_lr}")


def rnd_bonus(x: Any, encoder: nn.Module, context: ReplayContext) -> RND:
    """RND on ``encoder`` (the target's trunk) and a second fresh encoder (the predictor's)."""
    with seeded_init(context.seed + 2):
        predictor_encoder = context.make_encoder()
    return RND(encoder, predictor_encoder, context.obs_keys, lr=x.rnd_lr, seed=context.seed + 1)


register_strategy("rnd", lambda config: IntrinsicExploration(config, rnd_bonus), RNDConfig)

__all__ = ["RND", "RNDConfig", "rnd_bonus"]
