"""One RGB frame of the current simulator state (the Gymnasium face's ``render_mode="rgb_array"``).

Like :mod:`crowdrl.viz.trajectory`, figures are built on a ``FigureCanvasAgg``: no pyplot and no
global backend switch.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Circle

from crowdrl.viz.trajectory import GOAL_COLOR, ROBOT_COLOR, heading_segment, human_colors, draw_obstacles

__all__ = ["render_frame"]


def render_frame(
    robot_position: np.ndarray,
    robot_goal: np.ndarray,
    robot_radius: float,
    human_positions: np.ndarray,
    human_radius: float,
    *,
    robot_heading: float | None = None,
    half_width: float = 6.0,
    size_px: int = 400,
    title: str | None = None,
    obstacles: Sequence[np.ndarray] = (),
) -> np.ndarray:
    """Draw the robot, its goal, the humans and any obstacle polygons (``[n_i, 2]`` arrays: a
    wall has 2 vertices); return a ``[size_px, size_px, 3]`` uint8 image.

    The view is the square ``[-half_width, half_width]^2`` (fixed, so frames of an episode line
    up); ``human_positions`` is ``[N, 2]``.
    """
    robot_position = np.asarray(robot_position, dtype=np.float64).reshape(-1)
    robot_goal = np.asarray(robot_goal, dtype=np.float64).reshape(-1)
    humans = np.asarray(human_positions, dtype=np.float64)
    if robot_position.shape != (2,) or robot_goal.shape != (2,):
        raise ValueError(f"robot_position and robot_goal must have shape [2], got "
                         f"{robot_position.shape} and {robot_goal.shape}")
    if humans.ndim != 2 or humans.shape[-1] != 2:
        raise ValueError(f"human_positions must have shape [N, 2], got {humans.shape}")
    if not (half_width > 0):
        raise ValueError(f"half_width must be > 0, got {half_width}")
    if isinstance(size_px, bool) or int(size_px) != size_px or size_px < 16:
        raise ValueError(f"size_px must be an integer >= 16, got {size_px!r}")

    dpi = 100
    fig = Figure(figsize=(size_px / dpi, size_px / dpi), dpi=dpi)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.set_xlim(-half_width, half_width)
    ax.set_ylim(-half_width, half_width)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.grid(False)
    draw_obstacles(ax, [np.asarray(p, dtype=np.float64) for p in obstacles])
    for h, (xy, color) in enumerate(zip(humans, human_colors(len(humans)))):
        ax.add_patch(Circle(xy, human_radius, facecolor=(*color[:3], 0.35), edgecolor=color, lw=1.5))
        ax.text(*xy, str(h), fontsize=7, ha="center", va="center")
    ax.add_patch(Circle(robot_position, robot_radius, facecolor=(0.0, 0.0, 0.0, 0.25),
                        edgecolor=ROBOT_COLOR, lw=2.0, zorder=5))
    if robot_heading is not None:
        seg = heading_segment(robot_position, float(robot_heading), robot_radius)
        ax.plot(seg[:, 0], seg[:, 1], color=ROBOT_COLOR, lw=1.5, zorder=5.5)
    ax.plot(*robot_goal, marker="*", ms=14, color=GOAL_COLOR, mec="black", mew=0.8, ls="none", zorder=6)
    if title:
        ax.text(0.02, 0.98, title, transform=ax.transAxes, ha="left", va="top", fontsize=9,
                family="monospace", bbox=dict(boxstyle="round,pad=0.3", fc="white", ec="0.7", alpha=0.9))
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()
