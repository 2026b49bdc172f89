"""The robot's kinematics: the unicycle with its 81-action table, or a holonomic robot that
takes its velocity directly (``docs/mdp.md``). :func:`decode_action` is the one place where an
action becomes a velocity and heading; the TorchRL env, the Gymnasium face and the benchmarks
all call it."""

from __future__ import annotations

import math

import torch
from torch import Tensor

NUM_SPEEDS = 5
NUM_ROTATIONS = 16
NUM_ACTIONS = 1 + NUM_SPEEDS * NUM_ROTATIONS  # 81
MAX_ROTATION = math.pi / 6
KINEMATICS = ("unicycle", "holonomic")


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


def wrap_angle(angle: Tensor) -> Tensor:
    """``angle`` wrapped to ``[-pi, pi)``: how the simulator stores the robot's heading (cos and sin unchanged)."""
    return torch.remainder(angle + math.pi, 2 * math.pi) - math.pi


def check_velocities(action: Tensor, batch_size: int) -> Tensor:
    """Validate a ``[B, 2]`` floating tensor of finite robot velocities (holonomic actions)."""
    if not action.dtype.is_floating_point:
        raise TypeError(f"a holonomic action must be a floating [B, 2] velocity, got {action.dtype}")
    if action.shape != (batch_size, 2):
        raise ValueError(f"a holonomic action must be shaped [{batch_size}, 2], got {tuple(action.shape)}")
    if not bool(torch.isfinite(action).all()):
        raise ValueError("a holonomic action must be finite (got NaN or inf)")
    return action


def clip_speed(velocity: Tensor, v_pref: float) -> Tensor:
    """Scale each ``[..., 2]`` velocity faster than ``v_pref`` down to ``v_pref`` in its direction
    (others unchanged), a finite one whose norm overflows (``[1e20, 1e20]`` in float32) included.

    >>> clip_speed(torch.tensor([[1e20, 1e20], [0.3, 0.4]]), 1.0).tolist()
    [[0.7071067690849304, 0.7071067690849304], [0.30000001192092896, 0.4000000059604645]]
    """
    speed = torch.linalg.vector_norm(velocity, dim=-1, keepdim=True)
    # an overflowing norm: the direction from the velocity divided by its largest component first
    scale = velocity.abs().amax(-1, keepdim=True).clamp_min(torch.finfo(velocity.dtype).tiny)
    unit = velocity / scale
    huge = unit * (v_pref / torch.linalg.vector_norm(unit, dim=-1, keepdim=True).clamp_min(1e-12))
    fast = torch.where(torch.isfinite(speed), velocity * (v_pref / speed.clamp_min(1e-12)), huge)
    return torch.where(speed > v_pref, fast, velocity)


def decode_action(kinematics: str, action: Tensor, heading: Tensor, table: Tensor | None = None,
                  v_pref: float = 1.0) -> tuple[Tensor, Tensor | None]:
    """The robot's velocity ``[B, 2]`` during a step and its heading ``[B]`` after it.

    ``unicycle``: ``action [B]`` indexes ``table`` (:func:`action_table`): rotate, then move.
    ``holonomic``: ``action [B, 2]`` is the velocity, clipped to ``v_pref``; the heading is
    ``None`` (the simulator takes the velocity's direction, unchanged when stopped).

    >>> v, h = decode_action("unicycle", torch.tensor([0]), torch.zeros(1), action_table())
    >>> v.tolist(), h.tolist()
    ([[0.0, 0.0]], [0.0])
    """
    B = heading.shape[0]
    if kinematics == "unicycle":
        if table is None:
            raise ValueError("decode_action: the unicycle needs its action table")
        speed_rot = table[check_actions(action, B)]
        new_heading, velocity = unicycle_step(heading, speed_rot[:, 0], speed_rot[:, 1])
        return velocity, new_heading
    if kinematics == "holonomic":
        return clip_speed(check_velocities(action, B).to(heading.dtype), v_pref), None
    raise ValueError(f"kinematics must be one of {KINEMATICS}, got {kinematics!r}")
