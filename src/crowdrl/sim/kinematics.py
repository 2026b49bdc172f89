"""The robot's unicycle kinematics and its 81-action table (``SPEC.md`` §1)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

NUM_SPEEDS = 5
NUM_ROTATIONS = 16
NUM_ACTIONS = 1 + NUM_SPEEDS * NUM_ROTATIONS  # 81
MAX_ROTATION = math.pi / 6


def action_table(v_pref: float = 1.0, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> Tensor:
    """``[81, 2]`` table of (speed, rotation): index 0 stops, ``1 + 5*i_rot + j_speed`` else.

    Speeds are ``(j+1)/5 * v_pref``; rotations ``linspace(-pi/6, pi/6, 16)`` (no zero rotation).
    """
    speeds = torch.arange(1, NUM_SPEEDS + 1, dtype=torch.float64) / NUM_SPEEDS * v_pref
    rotations = torch.linspace(-MAX_ROTATION, MAX_ROTATION, NUM_ROTATIONS, dtype=torch.float64)
    rot, spd = torch.meshgrid(rotations, speeds, indexing="ij")
    table = torch.stack((spd.reshape(-1), rot.reshape(-1)), dim=-1)
    table = torch.cat((torch.zeros(1, 2, dtype=torch.float64), table), dim=0)
    return table.to(dtype=dtype, device=device)


def check_actions(action: Tensor, batch_size: int) -> Tensor:
    """Validate a ``[B]`` tensor of action indices in ``0..80`` and return it as int64."""
    if action.dtype.is_floating_point or action.dtype == torch.bool or action.is_complex():
        raise TypeError(f"action must be an integer tensor of indices, got {action.dtype}")
    if action.shape != (batch_size,):
        raise ValueError(f"action must be shaped [{batch_size}], got {tuple(action.shape)}")
    if action.numel() and (int(action.min()) < 0 or int(action.max()) >= NUM_ACTIONS):
        raise ValueError(
            f"action indices must lie in 0..{NUM_ACTIONS - 1}, got values in "
            f"[{int(action.min())}, {int(action.max())}]"
        )
    return action.long()


def unicycle_step(heading: Tensor, speed: Tensor, rotation: Tensor) -> tuple[Tensor, Tensor]:
    """Rotate first, then move straight: returns the new heading ``[B]`` and velocity ``[B, 2]``."""
    new_heading = heading + rotation
    velocity = torch.stack((speed * torch.cos(new_heading), speed * torch.sin(new_heading)), dim=-1)
    return new_heading, velocity
