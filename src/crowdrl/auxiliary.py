"""A model trained beside the Q network on the same sampled batches, with its own optimiser.

The trainer's update, for each sampled batch::

    for learner in learners:                        # e.g. ICM's forward/inverse models, a crowd predictor
        learner.step(sample)
    d3qn_update(sample)

A learner says what one step does (:meth:`AuxiliaryLearner.step`, returning scalars to log), which
weights the trainer checks for finiteness (:meth:`AuxiliaryLearner.parameters`), what the greedy
policy saved with the best network needs (:meth:`AuxiliaryLearner.policy_state`) and what a
checkpoint must hold for an exact resume (:meth:`AuxiliaryLearner.state_dict`: top-level keys of
the checkpoint, read back by :meth:`AuxiliaryLearner.load_state_dict` from the whole payload).
"""

from __future__ import annotations

from typing import Any, Iterable

from tensordict import TensorDictBase
from torch import Tensor


class AuxiliaryLearner:
    """Interface of an auxiliary learner (see the module docstring); the base class learns nothing."""

    def step(self, sample: TensorDictBase) -> dict[str, float]:
        """One optimiser step on ``sample``; the step's scalars (named by :meth:`scalar_names`)."""
        return {}

    def scalar_names(self) -> tuple[str, ...]:
        """The keys :meth:`step` returns (the trainer logs each as its mean over a collected batch's
        updates, NaN when it had none)."""
        return ()

    def parameters(self) -> Iterable[Tensor]:
        """Weights whose finiteness the trainer checks after each collected batch's updates."""
        return ()

    def policy_state(self) -> dict[str, Any]:
        """What the acting policy needs from this learner, saved with the best network (top-level keys)."""
        return {}

    def state_dict(self) -> dict[str, Any]:
        """Top-level checkpoint keys this learner writes."""
        return {}

    def load_state_dict(self, payload: dict[str, Any]) -> None:
        """Restore from a checkpoint ``payload`` the keys :meth:`state_dict` wrote."""


__all__ = ["AuxiliaryLearner"]
