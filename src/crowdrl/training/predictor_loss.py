"""The crowd predictor's training step for online planning: its loss and gradients on a batch.

The math is :func:`crowdrl.models.predictor.predictor_loss` (MSE of the predicted next human
states against the real ones). :meth:`PredictorLoss.loss_and_grad` writes its gradients into
the predictor's ``.grad``: with ``compile=True`` the forward and backward passes run as one
``torch.compile`` graph (``torch.func.grad_and_value`` of the same loss through
``functional_call``, as :class:`~crowdrl.training.loss.D3QNLoss` does for the Q update),
otherwise ``loss.backward()``. Tests keep the two equal to float tolerance.

Example::

    step = PredictorLoss(predictor, compile=True)
    loss = step.loss_and_grad(robot, humans, next_humans)   # gradients now in predictor's .grad
    optimizer.step()
"""

from __future__ import annotations

from torch import Tensor, nn
from torch.func import functional_call, grad_and_value

from crowdrl.compile import CPP_WRAPPER, LazyCompiled
from crowdrl.models.predictor import predictor_loss


class PredictorLoss:
    """Loss and gradients of a learned crowd predictor (``predictor(robot, humans, humans_mask?)``)."""

    def __init__(self, predictor: nn.Module, compile: bool = False) -> None:
        self.predictor = predictor
        self.compile = bool(compile)
        self._gradients_fn = LazyCompiled(self.gradients, dynamic=False, what="the predictor update", options=CPP_WRAPPER,
                                          enabled=self.compile)

    def gradients(self, params: dict[str, Tensor], robot: Tensor, humans: Tensor, next_humans: Tensor,
                  humans_mask: Tensor | None) -> tuple[dict[str, Tensor], Tensor]:
        """``(d loss / d params, loss)``: what :meth:`loss_and_grad` compiles."""
        def loss_of(p: dict[str, Tensor]) -> Tensor:
            return predictor_loss(lambda *x: functional_call(self.predictor, p, x), robot, humans, next_humans,
                                  humans_mask)

        return grad_and_value(loss_of)(params)

    def loss_and_grad(self, robot: Tensor, humans: Tensor, next_humans: Tensor,
                      humans_mask: Tensor | None = None) -> Tensor:
        """The loss (detached), its gradients written into the predictor's ``.grad`` (replacing what
        was there). Then step the predictor's optimiser."""
        if not self.compile or not self._gradients_fn.enabled:
            for p in self.predictor.parameters():
                p.grad = None
            loss = predictor_loss(self.predictor, robot, humans, next_humans, humans_mask)
            loss.backward()
            return loss.detach()
        params = {k: v.detach() for k, v in self.predictor.named_parameters()}
        grads, loss = self._gradients_fn(params, robot, humans, next_humans, humans_mask)
        for name, p in self.predictor.named_parameters():
            p.grad = grads[name]
        return loss.detach()


__all__ = ["PredictorLoss"]
