"""Intrinsic Curiosity Module (Pathak et al., 2017) as an :class:`IntrinsicBonus`.

Networks (``docs/mdp.md``, "Exploration variants"; ``A`` = number of actions, ``D`` = the feature
encoder's width):

* features ``phi(s) = head(encoder(obs...))``, ``head`` = Linear(D, 256)-ReLU-Linear(256, 128);
* inverse model ``[phi(s), phi(s')]`` -> Linear(256, 256)-ReLU-Linear(256, 128)-ReLU-Linear(128, A),
  cross-entropy on the action taken;
* forward model ``[phi(s), onehot(a)]`` -> Linear(128 + A, 256)-ReLU-Linear(256, 128)-ReLU-Linear(128, 128),
  mean squared error to ``phi(s')``;
* loss ``0.8 * inverse + 0.2 * forward``, its own Adam (lr 1e-4), one step per :meth:`ICM.update`.

``r_in = mean_features (phi_hat(s') - phi(s'))**2`` with the current networks, no gradient.

Feature scale (``feature_norm``): with ``"none"`` (the authors' network) nothing bounds the scale of
``phi``; the inverse loss inflates it (2,000 updates on fixed crowd transitions took ``||phi||``
from 2 to ~30), and the forward error, the bonus, grows with it. ``"layernorm"`` ends ``phi`` with a
LayerNorm without learned gain or bias, so every ``phi`` has zero mean and unit variance over its
128 features (``||phi|| = sqrt(128)``) and the bonus stays on a fixed scale.

Gradient choice: the forward loss's *target* ``phi(s')`` is detached (``detach_target=True``,
the default), its input ``phi(s)`` is not. Pathak et al.'s code lets the forward loss pull the
target towards the prediction too, which rewards shrinking or collapsing the features (the error,
hence the bonus, falls without learning any dynamics); with the target detached the features are
shaped by the inverse loss and by the forward model's need to predict, never by moving the target.
``detach_target=False`` gives the original gradient.
"""

from __future__ import annotations

from typing import Callable, Sequence

import torch
import torch.nn.functional as F
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor, nn

from crowdrl.exploration.intrinsic import IntrinsicBonus, feature_dim_of, seeded_init

PHI_DIM = 128
FEATURE_NORMS = ("none", "layernorm")


class ICM(IntrinsicBonus):
    """Curiosity bonus: the forward model's error in a learned feature space.

    Args:
        feature_encoder: a module of its own (not shared with the value network, since ICM's
            optimizer trains it) mapping the observation tensors, in ``in_keys`` order, to
            ``[*B, D]``; e.g. ``crowdrl.models.make_encoder("sgd3qn")`` with keys
            ``("robot_rc", "humans_rc")``, or an MLP on ``"observation"``.
        num_actions: size of the discrete action set (``>= 2``).
        in_keys: observation keys fed to ``feature_encoder``.
        feature_dim: ``D``; defaults to ``feature_encoder.embedding_dim``.
        lr: Adam learning rate. inverse_weight: weight of the inverse loss (forward gets ``1 - w``).
        detach_target: detach ``phi(s')`` in the forward loss (see the module docstring).
        feature_norm: ``"none"`` or ``"layernorm"`` (see the module docstring).
        seed: if given, the heads are initialised from this seed without touching the global RNG.

    Actions may be indices (``[*B]`` or ``[*B, 1]``, any dtype) or one-hot (``[*B, A]``).

    Examples:
        A bonus for a batch of eight transitions with 4-d observations and 3 actions:

        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torch import nn
        >>> from crowdrl.exploration import ICM
        >>> _ = torch.manual_seed(0)
        >>> batch = TensorDict({"observation": torch.randn(8, 4), "action": torch.randint(0, 3, (8,)),
        ...                     ("next", "observation"): torch.randn(8, 4)}, batch_size=[8])
        >>> icm = ICM(nn.Linear(4, 16), num_actions=3, feature_dim=16, seed=0)
        >>> r_in = icm.bonus(batch)
        >>> r_in.shape, bool(torch.isfinite(r_in).all()), bool((r_in >= 0).all())
        (torch.Size([8]), True, True)
        >>> sorted(icm.update(batch))  # one Adam step; the scalars to log
        ['icm_feature_norm', 'icm_forward_loss', 'icm_inverse_accuracy', 'icm_inverse_loss', 'icm_loss']
    """

    def __init__(
        self,
        feature_encoder: nn.Module,
        num_actions: int,
        in_keys: Sequence[NestedKey] = ("observation",),
        *,
        feature_dim: int | None = None,
        lr: float = 1e-4,
        inverse_weight: float = 0.8,
        detach_target: bool = True,
        feature_norm: str = "none",
        seed: int | None = None,
    ) -> None:
        super().__init__(in_keys)
        if isinstance(num_actions, bool) or int(num_actions) != num_actions or num_actions < 2:
            raise ValueError(f"num_actions must be an integer >= 2, got {num_actions!r}")
        if not 0.0 <= inverse_weight <= 1.0:
            raise ValueError(f"inverse_weight must lie in [0, 1], got {inverse_weight}")
        if feature_norm not in FEATURE_NORMS:
            raise ValueError(f"feature_norm: unknown {feature_norm!r}; allowed: {', '.join(FEATURE_NORMS)}")
        dim = feature_dim_of(feature_encoder, feature_dim)
        self.feature_norm = feature_norm
        self.num_actions = int(num_actions)
        self.inverse_weight = float(inverse_weight)
        self.detach_target = bool(detach_target)
        self.encoder = feature_encoder
        a = self.num_actions
        with seeded_init(seed):
            self.head = nn.Sequential(nn.Linear(dim, 256), nn.ReLU(), nn.Linear(256, PHI_DIM))
            if feature_norm == "layernorm":
                self.head.append(nn.LayerNorm(PHI_DIM, elementwise_affine=False))
            self.inverse_model = nn.Sequential(nn.Linear(2 * PHI_DIM, 256), nn.ReLU(), nn.Linear(256, 128), nn.ReLU(),
                                               nn.Linear(128, a))
            self.forward_model = nn.Sequential(nn.Linear(PHI_DIM + a, 256), nn.ReLU(), nn.Linear(256, 128), nn.ReLU(),
                                               nn.Linear(128, PHI_DIM))
        self.optimizer = torch.optim.Adam([p for p in self.parameters() if p.requires_grad], lr=lr)

    def features(self, obs: Sequence[Tensor]) -> Tensor:
        """``phi``: ``[*B, 128]``."""
        return self.head(self.encoder(*obs))

    def action_index(self, action: Tensor, batch_shape: torch.Size) -> Tensor:
        """Integer actions ``[*B]`` from indices ``[*B]``/``[*B, 1]`` or one-hot ``[*B, A]``."""
        lead = tuple(batch_shape)
        shape = tuple(action.shape)
        if shape == lead + (self.num_actions,):
            return (action if action.is_floating_point() else action.long()).argmax(-1)
        if shape == lead + (1,):
            action = action.squeeze(-1)
        elif shape != lead:
            raise ValueError(f"action shaped {shape} is neither an index {lead} / {lead + (1,)} "
                             f"nor one-hot {lead + (self.num_actions,)}")
        return action.long()

    def _errors(self, td: TensorDictBase) -> tuple[Tensor, Tensor, Tensor]:
        """Per-sample forward errors ``[*B]``, inverse logits ``[*B, A]`` and action indices ``[*B]``."""
        idx = self.action_index(td.get("action"), td.batch_size)
        # s and s' through the feature net as one batch (one pass, half the kernel launches)
        if not td.batch_dims:
            raise ValueError("ICM needs a batch of transitions (batch_size [*B] with at least one dim)")
        n = td.batch_size[0]
        both = self.features([torch.cat((a, b)) for a, b in zip(self.obs(td), self.obs(td, next_=True))])
        phi, phi_next = both[:n], both[n:]
        self._last_feature_norm = phi.detach().norm(dim=-1).mean()
        errors = self.forward_errors(phi, idx, phi_next.detach() if self.detach_target else phi_next)
        logits = self.inverse_model(torch.cat((phi, phi_next), dim=-1))
        return errors, logits, idx

    def forward_errors(self, phi: Tensor, idx: Tensor, phi_next: Tensor) -> Tensor:
        """``mean_j (f(phi, a)_j - phi'_j)^2`` ``[*B]``: the forward model's error, the bonus."""
        pred = self.forward_model(torch.cat((phi, F.one_hot(idx, self.num_actions).to(phi.dtype)), dim=-1))
        return (pred - phi_next).pow(2).mean(-1)

    def bonus(self, td: TensorDictBase) -> Tensor:
        with torch.no_grad():
            return self._errors(td)[0]

    @torch.no_grad()
    def grouped_bonus(self, td: TensorDictBase) -> Tensor:
        """The forward errors ``[n, g]`` of ``g`` transitions from each of ``n`` states, each state's features
        computed once (``n + n·g`` rows through the feature net instead of ``2·n·g``)."""
        n, g = self.group_shape(td)
        states = [o[:, 0] for o in self.obs(td)]
        successors = [o.reshape(n * g, *o.shape[2:]) for o in self.obs(td, next_=True)]
        both = self.features([torch.cat((a, b)) for a, b in zip(states, successors)])
        return self.forward_errors(both[:n].unsqueeze(1).expand(n, g, -1), self.action_index(td.get("action"), td.batch_size),
                                   both[n:].reshape(n, g, -1))

    def _step(self, errors: Tensor, logits: Tensor, idx: Tensor, feature_norm: Tensor) -> dict[str, float]:
        forward_loss = errors.mean()
        inverse_loss = F.cross_entropy(logits.reshape(-1, self.num_actions), idx.reshape(-1))
        loss = self.inverse_weight * inverse_loss + (1.0 - self.inverse_weight) * forward_loss
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        accuracy = (logits.detach().argmax(-1) == idx).float().mean()
        return {"icm_loss": float(loss.detach()), "icm_forward_loss": float(forward_loss.detach()),
                "icm_inverse_loss": float(inverse_loss.detach()), "icm_inverse_accuracy": float(accuracy),
                "icm_feature_norm": float(feature_norm)}

    def update(self, td: TensorDictBase) -> dict[str, float]:
        """One Adam step on ``0.8 * inverse + 0.2 * forward`` over the batch."""
        return self._step(*self._errors(td), self._last_feature_norm)

    def bonus_then_step(self, td: TensorDictBase) -> tuple[Tensor, Callable[[], dict[str, float]]]:
        """Same result as ``bonus`` and then ``update``, with one pass through the networks (the step
        reuses its graph)."""
        errors, logits, idx = self._errors(td)
        r_in = errors.detach().clone()  # computed before the step changes the weights
        feature_norm = self._last_feature_norm
        return r_in, lambda: self._step(errors, logits, idx, feature_norm)
