"""Swapping layers of a built network in place (noisy and dropout heads)."""

from __future__ import annotations

from typing import Callable

from torch import nn


def replace_children(root: nn.Module, match: Callable[[nn.Module], bool],
                     build: Callable[[nn.Module], nn.Module]) -> int:
    """Replace every descendant ``child`` of ``root`` with ``match(child)`` by ``build(child)``,
    keeping its attribute name (so parameter names elsewhere do not move); returns how many."""
    replaced = 0
    for parent in list(root.modules()):
        for name, child in list(parent.named_children()):
            if match(child):
                setattr(parent, name, build(child))
                replaced += 1
    return replaced
