"""Input checks and masked reductions shared by the crowd encoders (SARL, LSTM-RL, MP-RGL).

A crowd is ``humans_rc [*, N, 5]`` with an optional ``humans_mask [*, N]`` (bool, True = the
human is present). Absent humans take no part: :func:`flatten_crowd` zeroes their features (so
whatever padding they hold, even NaN, never reaches a sum), and the reductions below give them
weight exactly 0. A row with no human present is well defined (an empty crowd: zero weights, a
zero mean), though the env always has at least one human.
"""

from __future__ import annotations

import torch
from torch import Tensor

ROBOT_RC_DIM = 9
HUMAN_RC_DIM = 5


def flatten_crowd(
    who: str,
    robot_rc: Tensor,
    humans_rc: Tensor,
    humans_mask: Tensor | None,
    robot_dim: int = ROBOT_RC_DIM,
    human_dim: int = HUMAN_RC_DIM,
) -> tuple[torch.Size, Tensor, Tensor, Tensor | None]:
    """Check shapes and flatten the leading batch dims.

    Returns ``(lead, robot [B, robot_dim], humans [B, N, human_dim], mask [B, N] or None)`` where
    ``lead`` is the leading batch shape (``B = lead.numel()``) and absent humans are zeroed.
    Raises ``ValueError`` naming ``who`` on a bad shape or mask.
    """
    if robot_rc.shape[-1:] != (robot_dim,):
        raise ValueError(f"{who}: robot_rc must be shaped [..., {robot_dim}], got {tuple(robot_rc.shape)}")
    lead = robot_rc.shape[:-1]
    if humans_rc.dim() < 2 or humans_rc.shape[-1] != human_dim or humans_rc.shape[:-2] != lead:
        raise ValueError(f"{who}: humans_rc must be shaped [..., N, {human_dim}] with batch {tuple(lead)}, "
                         f"got {tuple(humans_rc.shape)}")
    n = humans_rc.shape[-2]
    if n < 1:
        raise ValueError(f"{who}: needs at least one human (N >= 1), got N = 0")
    robot = robot_rc.reshape(-1, robot_dim)
    humans = humans_rc.reshape(-1, n, human_dim)
    if humans_mask is None:
        return lead, robot, humans, None
    if humans_mask.dtype != torch.bool or humans_mask.shape != humans_rc.shape[:-1]:
        raise ValueError(f"{who}: humans_mask must be a bool tensor shaped {tuple(humans_rc.shape[:-1])}, "
                         f"got {humans_mask.dtype} {tuple(humans_mask.shape)}")
    mask = humans_mask.reshape(-1, n)
    humans = torch.where(mask.unsqueeze(-1), humans, 0.0)
    return lead, robot, humans, mask


def masked_softmax(logits: Tensor, mask: Tensor | None) -> Tensor:
    """``softmax(logits, -1)`` over the entries where ``mask`` (same shape, or broadcastable) is True.

    Masked entries get weight exactly 0; a row with no entry present gets all zeros (not NaN).
    """
    if mask is None:
        return torch.softmax(logits, dim=-1)
    logits = logits.masked_fill(~mask, torch.finfo(logits.dtype).min)
    e = torch.exp(logits - logits.detach().amax(dim=-1, keepdim=True)) * mask
    return e / e.sum(dim=-1, keepdim=True).clamp_min(torch.finfo(logits.dtype).tiny)


def masked_mean(x: Tensor, mask: Tensor | None) -> Tensor:
    """Mean of ``x [B, N, D]`` over the present rows of ``mask [B, N]`` -> ``[B, D]`` (0 if none)."""
    if mask is None:
        return x.mean(dim=-2)
    m = mask.unsqueeze(-1).to(x.dtype)
    return (x * m).sum(dim=-2) / m.sum(dim=-2).clamp_min(1.0)


__all__ = ["HUMAN_RC_DIM", "ROBOT_RC_DIM", "flatten_crowd", "masked_mean", "masked_softmax"]
