"""What a composed piece adds to the D3QN learner's update, as one interface.

The trainer's update is, for each sampled batch::

    for name, batch in part.batches(sample):        # the gradient steps of this update, in order
        loss = d3qn_loss(batch); optimizer.step()

A part says which replay-buffer keys it reads (:meth:`UpdatePart.stored_keys`), which batches one
update takes a gradient step on (:meth:`UpdatePart.batches`: yielded one at a time, so a later
batch may be built with the network the earlier steps updated), what it logs
(:meth:`UpdatePart.scalars`) and what a checkpoint must hold for an exact resume
(:meth:`UpdatePart.state_dict`). The trainer names no part: :class:`ReplayOnly` is the plain
update, :class:`crowdrl.training.counterfactual.CounterfactualExperience` adds simulated
transitions.
"""

from __future__ import annotations

from typing import Any, Iterator

from tensordict import TensorDictBase
from tensordict.utils import NestedKey


class UpdatePart:
    """A piece of the learner's update; the base class is the plain update (see the module docstring)."""

    def stored_keys(self) -> list[NestedKey]:
        """Replay-buffer keys this part reads beyond the loss's (none)."""
        return []

    def batches(self, sample: TensorDictBase) -> Iterator[tuple[str, TensorDictBase]]:
        """``(name, batch)`` for each gradient step of one update on ``sample``: the sample itself."""
        yield "real", sample

    def scalars(self) -> dict[str, float]:
        """Scalars to log (``train/<name>``) about the last update."""
        return {}

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state:
            raise KeyError(f"{type(self).__name__} holds no state, got {sorted(state)}")


class ReplayOnly(UpdatePart):
    """The plain update: one gradient step on each sampled batch."""


__all__ = ["ReplayOnly", "UpdatePart"]
