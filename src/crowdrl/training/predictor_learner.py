"""The planner's learned crowd predictor as an auxiliary learner: one Adam step per update on the
sampled batch, the MSE of its predicted next human states to the real ones
(:class:`~crowdrl.training.predictor_loss.PredictorLoss`)."""

from __future__ import annotations

from typing import Any, Iterable

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor, nn

from crowdrl.auxiliary import AuxiliaryLearner
from crowdrl.training.predictor_loss import PredictorLoss


class PredictorLearner(AuxiliaryLearner):
    """Trains ``predictor`` with ``optimizer`` on the sampled ``robot``, ``humans`` and
    ``("next", "humans")`` (and ``mask_key``, the humans' mask, when given); logs
    ``predictor_loss``; checkpoints ``predictor`` and ``predictor_optimizer``; the best network is
    saved with its ``predictor``."""

    def __init__(self, predictor: nn.Module, optimizer: torch.optim.Optimizer, *, compile: bool = False,
                 mask_key: NestedKey | None = None) -> None:
        self.predictor = predictor
        self.optimizer = optimizer
        self.mask_key = mask_key
        # its loss and gradients: one compiled graph with compile, as the Q update
        self.loss_fn = PredictorLoss(predictor, compile=compile)

    def step(self, sample: TensorDictBase) -> dict[str, float]:
        loss = self.loss_fn.loss_and_grad(sample.get("robot"), sample.get("humans"), sample.get(("next", "humans")),
                                          sample.get(self.mask_key) if self.mask_key is not None else None)
        self.optimizer.step()
        return {"predictor_loss": float(loss)}

    def scalar_names(self) -> tuple[str, ...]:
        return ("predictor_loss",)

    def parameters(self) -> Iterable[Tensor]:
        return self.predictor.parameters()

    def policy_state(self) -> dict[str, Any]:
        return {"predictor": self.predictor.state_dict()}

    def state_dict(self) -> dict[str, Any]:
        return {"predictor": self.predictor.state_dict(), "predictor_optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, payload: dict[str, Any]) -> None:
        self.predictor.load_state_dict(payload["predictor"])
        self.optimizer.load_state_dict(payload["predictor_optimizer"])


__all__ = ["PredictorLearner"]
