"""Dropout exploration for the head of a Q-network: dropout after each hidden ReLU of the head
**during action selection**, ``p`` decaying linearly (0.5 -> 0.01 in crowdrl's trainer, see
``docs/mdp.md``, "Exploration variants"), no ε-greedy. :func:`add_action_dropout` takes any
``nn.Module``; crowdrl's trainer passes the dueling head of its Q-network.

When dropout is on, and why:

* **action selection (collection)** — on. A fresh mask per forward, i.e. per env step and per
  env of the batch (each of the ``B`` envs explores with its own thinned network).
* **loss and target** — off: the variant applies dropout "during action selection", so the TD target
  and ``Q(s, a)`` are those of the full network the greedy policy uses, and the update is
  deterministic given the batch.
* **evaluation** — off (greedy policy).

Gating. A :class:`ScheduledDropout` drops iff ``p > 0``, the module is in training mode, and it is
*acting*: either its ``acting`` flag is ``True`` (:func:`acting`, :func:`set_acting`), or the flag
is ``None`` (the default, "auto") and the torchrl exploration type is ``RANDOM``. torchrl's
``Collector`` runs the policy under ``set_exploration_type(RANDOM)`` (its default) while
``LossModule.forward`` sets ``DETERMINISTIC`` and plain calls (``greedy_policy``, the crowdrl
evaluator) run with no exploration type, so in auto mode the trainer needs no wiring: dropout is
on in the collector's policy call and off in the loss, the target and validation (a loss that
sets no exploration type, like ``crowdrl.training.loss.D3QNLoss``, is off as long as it is not
called inside a ``RANDOM`` block; wrap it in ``acting(net, False)`` to be explicit). Plain
``train()``/``eval()`` alone cannot express this (the loss runs the same modules in training
mode), so ``eval()`` only acts as an extra global "off".

Layout. Each hidden ``nn.ReLU`` is replaced by ``nn.Sequential(ReLU, ScheduledDropout)`` rather
than inserting a module into the ``nn.Sequential`` stacks, so the Linear layers keep their
indices: the ``state_dict`` of a dropout head loads into the plain head (and back)
unchanged, and the greedy test policy can be a plain network.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Iterator, TypeVar

import torch.nn.functional as F
from torch import Tensor, nn
from torchrl.envs.utils import ExplorationType, exploration_type

from crowdrl.exploration._surgery import replace_children
from crowdrl.exploration.schedule import linear_schedule
from crowdrl.exploration.strategy import ExplorationStrategy, register_strategy

M = TypeVar("M", bound=nn.Module)


def _check_p(p: float) -> float:
    p = float(p)
    if not 0.0 <= p < 1.0:
        raise ValueError(f"dropout probability p must lie in [0, 1), got p={p}")
    return p


class ScheduledDropout(nn.Module):
    """Element-wise (inverted) dropout with a runtime-settable ``p``, active only while acting.

    ``acting``: ``True`` forces it on, ``False`` off, ``None`` (default) follows torchrl's
    exploration type (on under ``ExplorationType.RANDOM``, which collectors set around the policy).
    Never active in ``eval()`` mode or with ``p == 0``.
    """

    def __init__(self, p: float = 0.5) -> None:
        super().__init__()
        self.p = _check_p(p)
        self.acting: bool | None = None

    def is_active(self) -> bool:
        if not self.training:
            return False
        acting = exploration_type() is ExplorationType.RANDOM if self.acting is None else self.acting
        # p is read last: a compiled loss (never acting) then does not specialise on a p that changes every batch
        return acting and self.p > 0.0

    def forward(self, x: Tensor) -> Tensor:
        return F.dropout(x, self.p, training=True) if self.is_active() else x

    def extra_repr(self) -> str:
        return f"p={self.p}, acting={self.acting}"


def dropout_layers(module: nn.Module) -> list[ScheduledDropout]:
    """The :class:`ScheduledDropout` modules of ``module``'s tree."""
    return [m for m in module.modules() if isinstance(m, ScheduledDropout)]


def add_action_dropout(head: M, p: float = 0.5) -> M:
    """Put a :class:`ScheduledDropout` ``p`` after every ``nn.ReLU`` under ``head`` (any module), in
    place; returns ``head``. For crowdrl's dueling head these are its 4 hidden ReLUs (trunk 2,
    value 1, advantage 1); its output layers have no activation. Parameter names are unchanged.
    Only ``nn.ReLU`` child modules are seen (not ``F.relu`` calls); a ``head`` with none is a
    ``ValueError``."""
    p = _check_p(p)
    if dropout_layers(head):
        raise ValueError(f"{type(head).__name__} already has action dropout")
    added = replace_children(head, lambda m: isinstance(m, nn.ReLU), lambda m: nn.Sequential(m, ScheduledDropout(p)))
    if added == 0:
        raise ValueError(f"{type(head).__name__} has no nn.ReLU child module after which to put dropout")
    return head


def set_dropout_p(module: nn.Module, p: float) -> None:
    """Set ``p`` of every :class:`ScheduledDropout` under ``module`` (e.g. once per collected batch)."""
    p = _check_p(p)
    for layer in dropout_layers(module):
        layer.p = p


def set_acting(module: nn.Module, flag: bool | None) -> None:
    """Set the ``acting`` flag of every :class:`ScheduledDropout` under ``module``
    (``True`` on, ``False`` off, ``None`` follow the torchrl exploration type)."""
    if flag is not None and not isinstance(flag, bool):
        raise TypeError(f"acting flag must be True, False or None, got {flag!r}")
    for layer in dropout_layers(module):
        layer.acting = flag


@contextmanager
def acting(module: nn.Module, flag: bool = True) -> Iterator[nn.Module]:
    """Within the block every :class:`ScheduledDropout` under ``module`` is forced on
    (``flag=True``, action selection outside a collector) or off (``flag=False``); the previous
    flags are restored after."""
    layers = dropout_layers(module)
    previous = [layer.acting for layer in layers]
    try:
        set_acting(module, flag)
        yield module
    finally:
        for layer, prev in zip(layers, previous):
            layer.acting = prev


class DropoutExploration(ExplorationStrategy):
    """Action dropout as an exploration strategy: dropout after each hidden ReLU of the Q network's
    ``head``, ``p`` from ``config.dropout_start`` to ``config.dropout_end`` linearly over
    ``config.anneal_frames`` frames (with ε, see :class:`ExplorationStrategy`)."""

    def __init__(self, config: Any) -> None:
        super().__init__(config)
        self.net: nn.Module | None = None

    def modify_network(self, net: nn.Module) -> nn.Module:
        add_action_dropout(net.head, self.config.dropout_start)
        self.net = net
        return net

    def schedule(self, frames: int) -> None:
        super().schedule(frames)
        x = self.config
        set_dropout_p(self.net, linear_schedule(x.dropout_start, x.dropout_end, x.anneal_frames, frames))


@dataclass
class DropoutConfig:
    """``exploration=dropout``'s own keys: the dropout probability decays linearly from ``dropout_start`` to
    ``dropout_end`` over ``anneal_frames``."""

    dropout_start: float = 0.5
    dropout_end: float = 0.01

    @staticmethod
    def check(config: Any, limits: Any, active: bool) -> None:
        for key in ("dropout_start", "dropout_end"):
            if not 0 <= getattr(config, key) < 1:
                raise ValueError(f"{key}: must lie in [0, 1), got {getattr(config, key)}")


register_strategy("dropout", DropoutExploration, DropoutConfig)

__all__ = [
    "DropoutExploration",
    "ScheduledDropout",
    "acting",
    "add_action_dropout",
    "dropout_layers",
    "set_acting",
    "set_dropout_p",
]
