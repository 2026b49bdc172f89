"""A 2-D lidar scan: the distance to the first obstacle edge or human disc along evenly spaced rays.

Conventions: ``R`` rays evenly spaced over 360°, ray ``r`` at angle ``heading + 2π r / R`` (ray 0
along the heading, counter-clockwise from there, world frame: the scan is egocentric, rotating with
the robot). A ray reads the distance from the origin (the robot's centre, not its surface) to the
first segment or disc surface it meets, ``max_range`` when it meets nothing within ``max_range``
(readings are clipped to it). An origin on a segment reads 0 on the rays that cross it; an
origin inside (or on the boundary of) a disc reads 0 on every ray. A segment lying along a ray's
line reads its nearest point ahead. Masked segments and discs are ignored whatever they hold.

Segments are the ``(start [B, E, 2], end [B, E, 2], valid [B, E])`` triple of
:func:`crowdrl.sim.obstacles.obstacle_segments` (the edges of the obstacle polygons; a solid
polygon's edges stop the ray at its boundary). Everything is batched: the rays meet all segments
and discs at once as ``[B, R, E]`` and ``[B, R, N]`` tensors.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.obstacles import obstacle_segments
from crowdrl.sim.state import CrowdState

__all__ = ["lidar_angles", "lidar_scan", "observe_lidar", "robot_scan"]


def lidar_angles(heading: Tensor, num_rays: int) -> Tensor:
    """The rays' world-frame angles ``[B, R]``: ``heading [B] + 2π r / R`` for ``r = 0 .. R-1``."""
    offsets = torch.arange(num_rays, dtype=heading.dtype, device=heading.device) * (2 * math.pi / num_rays)
    return heading.unsqueeze(-1) + offsets


def _check(origin: Tensor, heading: Tensor, num_rays: int, max_range: float) -> None:
    if not isinstance(origin, Tensor) or origin.dim() != 2 or origin.shape[-1] != 2 or not origin.is_floating_point():
        raise ValueError(f"origin must be a floating tensor shaped [B, 2], got "
                         f"{tuple(origin.shape) if isinstance(origin, Tensor) else type(origin).__name__}")
    if not isinstance(heading, Tensor) or heading.shape != origin.shape[:1]:
        raise ValueError(f"heading must be a tensor shaped [B] = {tuple(origin.shape[:1])}, got "
                         f"{tuple(heading.shape) if isinstance(heading, Tensor) else type(heading).__name__}")
    if isinstance(num_rays, bool) or int(num_rays) != num_rays or num_rays < 1:
        raise ValueError(f"num_rays must be an integer >= 1, got {num_rays!r}")
    if isinstance(max_range, bool) or not (isinstance(max_range, (int, float)) and math.isfinite(max_range)
                                           and max_range > 0):
        raise ValueError(f"max_range must be a finite number > 0, got {max_range!r}")


def _segment_hits(ox: Tensor, oy: Tensor, dx: Tensor, dy: Tensor, segments: tuple[Tensor, Tensor, Tensor]) -> Tensor:
    """Distance along each ray to each segment, ``[B, R, E]`` (``inf``: missed or masked)."""
    start, end, valid = segments
    ax, ay = start[..., 0].unsqueeze(1), start[..., 1].unsqueeze(1)  # [B, 1, E]
    ux, uy = end[..., 0].unsqueeze(1) - ax, end[..., 1].unsqueeze(1) - ay
    wx, wy = ax - ox, ay - oy  # origin -> segment start
    denom = dx * uy - dy * ux  # cross(d, u)
    safe = torch.where(denom == 0, torch.ones_like(denom), denom)
    t = (wx * uy - wy * ux) / safe  # along the ray
    s = (wx * dy - wy * dx) / safe  # along the segment
    inf = torch.full_like(t, math.inf)
    hit = torch.where((denom != 0) & (t >= 0) & (s >= 0) & (s <= 1), t, inf)
    # a segment on the ray's line (parallel and collinear): its nearest point ahead, 0 if the origin is on it
    ta = wx * dx + wy * dy
    tb = ta + ux * dx + uy * dy
    near = torch.where(ta * tb <= 0, torch.zeros_like(ta), torch.minimum(ta, tb))
    collinear = (denom == 0) & (wx * dy - wy * dx == 0) & (near >= 0)
    hit = torch.where(collinear, near, hit)
    return hit.masked_fill(~valid.unsqueeze(1), math.inf)


def _disc_hits(ox: Tensor, oy: Tensor, dx: Tensor, dy: Tensor, discs: tuple[Tensor, Tensor | float, Tensor]) -> Tensor:
    """Distance along each ray to each disc's surface, ``[B, R, N]`` (0 from inside; ``inf``: missed or masked)."""
    centres, radii, mask = discs
    radii = torch.as_tensor(radii, dtype=centres.dtype, device=centres.device).expand(mask.shape).unsqueeze(1)
    wx, wy = ox - centres[..., 0].unsqueeze(1), oy - centres[..., 1].unsqueeze(1)  # centre -> origin, [B, 1, N]
    b = wx * dx + wy * dy  # t^2 + 2 b t + c = 0
    c = wx * wx + wy * wy - radii * radii
    disc = b * b - c
    root = disc.clamp_min(0).sqrt()
    # the nearer root -b - sqrt(disc) written as c / (-b + sqrt(disc)): no cancellation near the surface
    ahead = (disc >= 0) & (b < 0)
    t = c / torch.where(ahead, root - b, torch.ones_like(b))
    hit = torch.where(ahead, t, torch.full_like(t, math.inf))
    hit = torch.where(c <= 0, torch.zeros_like(hit), hit)  # the origin inside or on the disc
    return hit.masked_fill(~mask.unsqueeze(1), math.inf)


def lidar_scan(origin: Tensor, heading: Tensor, num_rays: int, max_range: float, *,
               segments: tuple[Tensor, Tensor, Tensor] | None = None,
               discs: tuple[Tensor, Tensor | float, Tensor] | None = None) -> Tensor:
    """Lidar readings ``[B, R]`` from ``origin [B, 2]`` with ``heading [B]`` (conventions: the module docstring).

    Args:
        origin: ``[B, 2]`` the scan's centre (world frame).
        heading: ``[B]`` the direction of ray 0 (radians, counter-clockwise from +x).
        num_rays: ``R >= 1`` rays, evenly spaced over 360°, counter-clockwise from the heading.
        max_range: readings are clipped to it; a ray that meets nothing reads ``max_range``.
        segments: ``(start [B, E, 2], end [B, E, 2], valid [B, E])``, as from
            :func:`~crowdrl.sim.obstacles.obstacle_segments`; ``None``: no segments.
        discs: ``(centres [B, N, 2], radii (a number or broadcastable to [B, N]), mask [B, N])``;
            ``None``: no discs.

    Returns:
        ``[B, R]`` distances in ``[0, max_range]``, in the dtype of ``origin``.

    Examples:
        A wall 2 m ahead, a disc of radius 0.5 centred 3 m to the left:

        >>> import torch
        >>> wall = (torch.tensor([[[2.0, -1.0]]]), torch.tensor([[[2.0, 1.0]]]), torch.ones(1, 1, dtype=torch.bool))
        >>> disc = (torch.tensor([[[0.0, 3.0]]]), 0.5, torch.ones(1, 1, dtype=torch.bool))
        >>> lidar_scan(torch.zeros(1, 2), torch.zeros(1), 4, 4.0, segments=wall, discs=disc)
        tensor([[2.0000, 2.5000, 4.0000, 4.0000]])
    """
    _check(origin, heading, num_rays, max_range)
    angles = lidar_angles(heading.to(origin.dtype), int(num_rays))
    dx, dy = angles.cos().unsqueeze(-1), angles.sin().unsqueeze(-1)  # [B, R, 1]
    ox, oy = origin[:, 0, None, None], origin[:, 1, None, None]  # [B, 1, 1]
    out = origin.new_full((origin.shape[0], int(num_rays)), float(max_range))
    if segments is not None and segments[0].shape[1] > 0:
        out = torch.minimum(out, _segment_hits(ox, oy, dx, dy, segments).amin(-1))
    if discs is not None and discs[0].shape[1] > 0:
        out = torch.minimum(out, _disc_hits(ox, oy, dx, dy, discs).amin(-1))
    return out


def robot_scan(config: CrowdConfig, position: Tensor, heading: Tensor, human_position: Tensor,
               human_mask: Tensor | None = None, segments: tuple[Tensor, Tensor, Tensor] | None = None) -> Tensor:
    """The robot's scan ``[B, config.lidar_rays]`` from ``position [B, 2]`` along ``heading [B]``, against the
    humans' discs at ``human_position [B, N, 2]`` (radius ``config.human_radius``; ``human_mask`` ``[B, N]``, the
    present ones, ``None``: all) and the wall ``segments`` (``None``: none), clipped at ``config.lidar_range``:
    what :func:`observe_lidar` observes, and what the planner and counterfactual experience compute for a pose
    the env did not visit."""
    if human_mask is None:
        human_mask = torch.ones(human_position.shape[:2], dtype=torch.bool, device=human_position.device)
    return lidar_scan(position, heading, config.lidar_rays, config.lidar_range, segments=segments,
                      discs=(human_position, config.human_radius, human_mask))


def observe_lidar(config: CrowdConfig, state: CrowdState) -> Tensor:
    """The robot's scan ``[B, config.lidar_rays]`` in ``state`` (:func:`robot_scan`): against the obstacle edges
    and the present humans. The ``"lidar"`` observation of :class:`~crowdrl.envs.CrowdNavEnv`."""
    segments = obstacle_segments(state.obstacles, state.obstacle_mask) if state.has_obstacles else None
    return robot_scan(config, state.robot_position, state.robot_heading, state.human_position, state.human_mask,
                      segments)
