"""The multilayer perceptron every encoder builds its per-node and scoring networks from."""

from __future__ import annotations

from typing import Sequence

from torch import nn


def mlp(dims: Sequence[int], last_relu: bool = True) -> nn.Sequential:
    """Linear layers through ``dims`` with a ReLU between them (and after the last if ``last_relu``,
    upstream's ``mlp(..., last_relu=True)``).

    Example: ``mlp([5, 64, 32])`` is Linear(5, 64)-ReLU-Linear(64, 32)-ReLU.
    """
    if len(dims) < 2:
        raise ValueError(f"mlp needs at least an input and an output size, got dims={list(dims)}")
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(dims[:-1], dims[1:])):
        layers.append(nn.Linear(a, b))
        if last_relu or i < len(dims) - 2:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


__all__ = ["mlp"]
