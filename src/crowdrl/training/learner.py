"""The D3QN learner: one update of the Q network on a sampled batch, as one object.

:meth:`D3QNLearner.step` is one update, in this order:

1. each auxiliary learner (:class:`~crowdrl.auxiliary.AuxiliaryLearner`: the planner's crowd predictor,
   ICM's models) takes its own step on the sample, so that a simulated batch may read what they learn;
2. the exploration strategy's hook before the Q steps (noisy nets draw new noise);
3. for each batch the update part yields (:mod:`crowdrl.training.parts`: the sample; with counterfactual
   experience, its simulated transitions after it), a gradient step on the double-DQN TD loss

       y = r + γ^m (1 - terminated) Q_target(s', argmax_a Q(s', a)),   loss = mean (Q(s, a) - y)²

   (:class:`~crowdrl.training.loss.D3QNLoss` states every term of ``y`` and where it is computed),
   its gradients clipped to ``grad_clip_norm`` (``train.grad_clip_norm``; ``None``: unclipped), then Adam;
4. the target network: a Polyak step ``θ' ← θ' + τ (θ - θ')`` after every update when ``target_tau`` < 1,
   else a hard copy every ``updates_per_copy`` updates (``train.target_update_frames`` of data);
5. a non-finite loss raises :class:`NonFiniteError`; :meth:`check_finite_weights` checks the weights.

The learning rate follows :meth:`set_frames` (``train.lr``, decayed linearly to ``train.lr_end`` over
``train.total_frames`` when that is set). What a checkpoint holds of the learner keeps the trainer's
keys of before (``loss``, ``optimizer``, ``part_losses``, ``update_part``), so stored runs resume.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Sequence

import torch
from tensordict import TensorDictBase

from crowdrl.auxiliary import AuxiliaryLearner
from crowdrl.exploration.schedule import linear_schedule
from crowdrl.training.loss import D3QNLoss
from crowdrl.training.parts import UpdatePart


class NonFiniteError(FloatingPointError):
    """Training produced a non-finite loss or non-finite weights: the run fails, it is never tested."""


class D3QNLearner:
    """The Q network's update with everything it owns (see the module docstring).

    Args:
        loss: the TD loss, holding the online and target networks.
        optimizer: the online network's optimiser.
        part: the batches of one update (:class:`~crowdrl.training.parts.ReplayOnly`: the sample alone).
        learners: the auxiliary learners that step on each sample first.
        before_update: called with ``loss`` before the Q steps (the exploration strategy's hook).
        grad_clip_norm: the gradients' largest norm, or ``None``.
        target_tau: Polyak τ after every update (< 1), or 1 for hard copies.
        updates_per_copy: the hard copy's cadence, in updates (τ = 1 only).
        lr: the learning rate, or ``(lr, lr_end, frames)`` for a linear decay over ``frames``.

    Examples:
        >>> import torch
        >>> from crowdrl.training.loss import D3QNLoss
        >>> from crowdrl.training.parts import ReplayOnly
        >>> net = torch.nn.Linear(2, 3)
        >>> learner = D3QNLearner(D3QNLoss(net, ["obs"], gamma=0.9), torch.optim.SGD(net.parameters(), lr=0.1),
        ...                       ReplayOnly(), target_tau=0.5, lr=(0.1, 0.0, 100))
        >>> learner.set_frames(50); round(learner.optimizer.param_groups[0]["lr"], 6)  # halfway down to 0
        0.05
        >>> sorted(learner.state_dict())  # the checkpoint keys stored runs hold
        ['loss', 'optimizer', 'part_losses', 'update_part']
    """

    def __init__(self, loss: D3QNLoss, optimizer: torch.optim.Optimizer, part: UpdatePart,
                 learners: Sequence[AuxiliaryLearner] = (), *,
                 before_update: Callable[[D3QNLoss], None] | None = None, grad_clip_norm: float | None = None,
                 target_tau: float = 1.0, updates_per_copy: int = 1,
                 lr: float | tuple[float, float, int] | None = None) -> None:
        if not 0.0 < target_tau <= 1.0:
            raise ValueError(f"target_tau must lie in (0, 1], got {target_tau}")
        if updates_per_copy < 1:
            raise ValueError(f"updates_per_copy must be >= 1, got {updates_per_copy}")
        self.loss = loss
        self.optimizer = optimizer
        self.part = part
        self.learners = list(learners)
        self.before_update = before_update
        self.grad_clip_norm = grad_clip_norm
        self.target_tau = target_tau
        self.updates_per_copy = updates_per_copy
        self.lr = lr
        self._aux_sums: dict[str, float] = {}
        self._aux_steps = 0
        self._part_losses: dict[str, list[float]] = {}  # the later batches' losses since the last log row

    @property
    def net(self) -> torch.nn.Module:
        """The online Q network."""
        return self.loss.net

    def set_frames(self, frames: int) -> None:
        """Set the learning rate of the frame count reached (a constant rate stays as it is)."""
        if not isinstance(self.lr, tuple):
            return
        start, end, total = self.lr
        for group in self.optimizer.param_groups:
            group["lr"] = linear_schedule(start, end, total, frames)

    def step(self, sample: TensorDictBase, update: int) -> float:
        """Update ``update`` (its number from 1, for the hard copy's cadence) on ``sample``: the
        auxiliary steps, a gradient step per batch of the part, the target update; returns the loss of
        the first batch (the sample's)."""
        for learner in self.learners:
            for name, value in learner.step(sample).items():
                self._aux_sums[name] = self._aux_sums.get(name, 0.0) + value
        self._aux_steps += 1
        if self.before_update is not None:
            self.before_update(self.loss)
        first = None
        for name, batch in self.part.batches(sample):
            value = self.loss.loss_and_grad(batch)["loss"]  # gradients into the Q network's .grad
            if self.grad_clip_norm is not None:
                torch.nn.utils.clip_grad_norm_(self.net.parameters(), self.grad_clip_norm)
            self.optimizer.step()
            if first is None:
                first = value
            else:
                self._part_losses.setdefault(name, []).append(float(value))
        if self.target_tau < 1:
            self.loss.update_target_polyak(self.target_tau)
        elif update % self.updates_per_copy == 0:
            self.loss.update_target()
        loss = float(first.detach())
        if not math.isfinite(loss):
            raise NonFiniteError(f"the loss became non-finite ({loss}) at update {update}")
        return loss

    def check_finite_weights(self, update: int) -> None:
        """:class:`NonFiniteError` when a weight of the Q network or of an auxiliary learner is not finite
        (one synchronisation)."""
        params = [*self.net.parameters(), *(p for learner in self.learners for p in learner.parameters())]
        if not bool(torch.stack([torch.isfinite(p).all() for p in params]).all()):
            raise NonFiniteError(f"the weights of the Q network or of an auxiliary learner became non-finite "
                                 f"by update {update}")

    # ------------------------------------------------------------------ what it logs
    def scalar_names(self) -> list[str]:
        """The auxiliary learners' scalar names."""
        return [name for learner in self.learners for name in learner.scalar_names()]

    def reset_scalars(self) -> None:
        """Start a new window of auxiliary scalars (the trainer: at each collected batch)."""
        self._aux_sums, self._aux_steps = {}, 0

    def scalars(self) -> dict[str, float]:
        """The auxiliary learners' scalars, means over the steps since :meth:`reset_scalars` (NaN: none)."""
        return {name: self._aux_sums.get(name, 0.0) / self._aux_steps if self._aux_steps else math.nan
                for name in self.scalar_names()}

    def pop_part_losses(self) -> dict[str, float]:
        """``loss_<part>``: the mean loss of each later batch since the last call (the sample's is the step's
        return value); the window starts anew."""
        out = {f"loss_{name}": sum(v) / len(v) for name, v in self._part_losses.items() if v}
        self._part_losses.clear()
        return out

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        """The checkpoint keys of the learner (the trainer's names: stored runs load)."""
        return {"loss": self.loss.state_dict(), "optimizer": self.optimizer.state_dict(),
                "part_losses": {name: list(values) for name, values in self._part_losses.items()},
                "update_part": self.part.state_dict()}

    def load_state_dict(self, data: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`'s keys from a checkpoint (one written before ``part_losses`` or
        ``update_part`` existed has neither: read as empty)."""
        self.loss.load_state_dict(data["loss"])
        self.optimizer.load_state_dict(data["optimizer"])
        self._part_losses = {str(name): [float(v) for v in values] for name, values in data.get("part_losses", {}).items()}
        self.part.load_state_dict(data.get("update_part", {}))


__all__ = ["D3QNLearner", "NonFiniteError"]
