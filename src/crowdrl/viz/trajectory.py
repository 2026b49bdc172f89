"""Static plots and animated GIFs of one crowd-navigation episode.

Everything here builds figures as ``matplotlib.figure.Figure`` objects attached to a
``FigureCanvasAgg``: no pyplot, no global backend switch, so the module is safe to use from
training loops, headless workers and notebooks alike, and figures are freed as soon as they
go out of scope.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.animation import PillowWriter
from matplotlib.artist import Artist
from matplotlib.axes import Axes
from matplotlib.backend_bases import RendererBase
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle, Polygon

from crowdrl.evaluation.trajectory import Trajectory
from crowdrl.files import atomic_write_with

__all__ = ["Trajectory", "plot_trajectory", "plot_side_by_side", "animate_trajectory", "TIME_STAMP_GID",
           "OBSTACLE_GID"]

#: ``gid`` given to every time-stamp text artist in :func:`plot_trajectory` (lets callers
#: and tests find them among the other texts).
TIME_STAMP_GID = "time_stamp"

#: ``gid`` of every obstacle artist (a wall's line, a solid polygon's patch).
OBSTACLE_GID = "obstacle"

ROBOT_COLOR = "black"
OBSTACLE_COLOR = "dimgray"
GOAL_COLOR = "gold"
STAMP_PERIOD_S = 5.0  # seconds between the time-stamped circles of the static plot
TRAIL_STEPS = 8  # length of the fading trails of the animation, in steps

PathLike = str | os.PathLike[str]


# ----------------------------------------------------------------------------- helpers


def _format_time(t: float) -> str:
    """One decimal when exact (``5.0``), two otherwise (``6.25``)."""
    return f"{t:.1f}" if abs(round(t, 1) - t) < 1e-9 else f"{t:.2f}"


def _stamp_indices(traj: Trajectory, period_s: float = STAMP_PERIOD_S) -> list[int]:
    """Steps 0, k, 2k, ... with k = round(period_s / time_step), plus the final step."""
    every = max(1, round(period_s / traj.time_step))
    idx = list(range(0, traj.num_steps + 1, every))
    if idx[-1] != traj.num_steps:
        idx.append(traj.num_steps)
    return idx


def human_colors(n: int) -> list[tuple[float, float, float, float]]:
    """Qualitative colours, one per human (tab10, tab20 beyond 10 humans, cycling after)."""
    cmap = colormaps["tab10" if n <= 10 else "tab20"]
    k = cmap.N
    return [cmap(i % k) for i in range(n)]


def _new_figure(size: tuple[float, float]) -> Figure:
    fig = Figure(figsize=size, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _set_limits(ax: Axes, traj: Trajectory, include_human_goals: bool = False) -> None:
    """Equal-aspect bounds around everything drawn, padded by the largest radius."""
    pts = [traj.robot_positions, traj.robot_goal[None], traj.human_positions.reshape(-1, 2), *(traj.obstacles or ())]
    if include_human_goals:
        pts.append(traj.human_goals.reshape(-1, 2))
    allp = np.concatenate(pts, axis=0)
    pad = max(traj.robot_radius, traj.human_radius) + 0.5
    lo, hi = allp.min(axis=0) - pad, allp.max(axis=0) + pad
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal", adjustable="box")


def _title(traj: Trajectory, title: str | None) -> str | None:
    parts = [p for p in (title, f"outcome: {traj.outcome}" if traj.outcome else None) if p]
    return " | ".join(parts) if parts else None


def heading_segment(center: np.ndarray, heading: float, radius: float) -> np.ndarray:
    """The ``[2, 2]`` segment from ``center`` to the rim of a disc of ``radius`` along ``heading`` (the robot's heading mark)."""
    return np.array([center, center + radius * np.array([math.cos(heading), math.sin(heading)])])


# ----------------------------------------------------------------------------- static plot


def draw_obstacles(ax: Axes, polygons) -> None:
    """Obstacle ``polygons`` (``[n_i, 2]`` arrays) on ``ax``: walls (``n_i = 2``) as thick lines,
    solid polygons as filled patches (``gid == OBSTACLE_GID``)."""
    for poly in polygons or ():
        if len(poly) == 2:
            ax.plot(poly[:, 0], poly[:, 1], color=OBSTACLE_COLOR, lw=4.0, solid_capstyle="butt", zorder=2,
                    gid=OBSTACLE_GID)
        else:
            ax.add_patch(Polygon(poly, closed=True, facecolor=OBSTACLE_COLOR, edgecolor="black", lw=0.8,
                                 alpha=0.8, zorder=2, gid=OBSTACLE_GID))


def _draw_episode(ax: Axes, traj: Trajectory) -> None:
    """Obstacles, paths, time-stamped circles, headings and the goal of one episode on ``ax``."""
    draw_obstacles(ax, traj.obstacles)
    colors = human_colors(traj.num_humans)
    stamps = _stamp_indices(traj)

    def draw_agent(xy: np.ndarray, radius: float, color, zorder: float) -> None:
        """Path line plus time-stamped circles; the start circle is dashed."""
        ax.plot(xy[:, 0], xy[:, 1], color=color, lw=2.0 if color == ROBOT_COLOR else 1.2,
                zorder=zorder - 1)
        for i in stamps:
            ax.add_patch(Circle(xy[i], radius, facecolor=color, alpha=0.15, lw=0,
                                zorder=zorder))
            ax.add_patch(Circle(xy[i], radius, fill=False, edgecolor=color, lw=1.2,
                                ls="--" if i == 0 else "-", zorder=zorder + 0.1))
            ax.text(xy[i, 0], xy[i, 1], _format_time(i * traj.time_step), fontsize=6.5,
                    ha="center", va="center", color="black", zorder=zorder + 0.2,
                    gid=TIME_STAMP_GID)

    for h in range(traj.num_humans):
        draw_agent(traj.human_positions[:, h], traj.human_radius, colors[h], zorder=3)
    # The robot goes on top of the humans.
    rxy = traj.robot_positions
    draw_agent(rxy, traj.robot_radius, ROBOT_COLOR, zorder=6)
    if traj.robot_headings is not None:
        for i in stamps:
            seg = heading_segment(rxy[i], traj.robot_headings[i], traj.robot_radius)
            ax.plot(seg[:, 0], seg[:, 1], color=ROBOT_COLOR, lw=1.0, zorder=6.1)
    ax.plot(*traj.robot_goal, marker="*", ms=16, color=GOAL_COLOR, mec="black", mew=0.8,
            ls="none", zorder=7)

    _set_limits(ax, traj)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, lw=0.4, alpha=0.4)


def _episode_legend(fig: Figure, traj: Trajectory) -> None:
    handles = [
        Line2D([], [], color=ROBOT_COLOR, lw=2.0, label="robot"),
        Line2D([], [], marker="*", ms=12, color=GOAL_COLOR, mec="black", ls="none",
               label="robot goal"),
        Line2D([], [], color="0.5", lw=1.2, label=f"humans (N={traj.num_humans})"),
        Line2D([], [], color="0.3", lw=1.0, ls="--", label="start (t = 0)"),
        Line2D([], [], marker="o", ms=10, mfc="none", color="0.3", ls="none",
               label=f"position every {STAMP_PERIOD_S:g} s + end (label: t in s)"),
    ]
    fig.legend(handles=handles, loc="outside lower center", ncols=3, fontsize=8,
               frameon=False)


def plot_side_by_side(trajs: list[Trajectory], titles: list[str], path: PathLike | None = None, *,
                      suptitle: str | None = None) -> Figure:
    """The same test case under several policies, one panel each (the paper's Fig. 1/3 style),
    with 5-s time stamps; saved as PNG to ``path`` if given."""
    if not trajs or len(trajs) != len(titles):
        raise ValueError("plot_side_by_side needs one title per trajectory and at least one trajectory")
    fig = _new_figure((6.2 * len(trajs), 6.8))
    for k, (traj, title) in enumerate(zip(trajs, titles)):
        ax = fig.add_subplot(1, len(trajs), k + 1)
        _draw_episode(ax, traj)
        ax.set_title(_title(traj, title))
    _episode_legend(fig, trajs[0])
    if suptitle:
        fig.suptitle(suptitle)
    if path is not None:
        atomic_write_with(path, lambda tmp: fig.savefig(tmp, format="png", dpi=110), suffix=".png")
    return fig


def plot_trajectory(
    traj: Trajectory, path: PathLike | None = None, *, title: str | None = None
) -> Figure:
    """Draw the whole episode in one figure; save it as PNG to ``path`` if given.

    Paths are lines; agents are drawn as circles of their true radius every 5 s (and at the
    final state), each labelled with its time in seconds, so relative timing — who was where
    when — can be read off directly. Time-stamp texts carry ``gid == TIME_STAMP_GID``.
    """
    fig = _new_figure((7.0, 7.6))
    ax = fig.add_subplot()
    _draw_episode(ax, traj)
    _episode_legend(fig, traj)
    if (full_title := _title(traj, title)) is not None:
        ax.set_title(full_title)

    if path is not None:
        atomic_write_with(path, lambda tmp: fig.savefig(tmp, format="png", dpi=120), suffix=".png")
    return fig


# ----------------------------------------------------------------------------- animation


def _freeze_background(fig: Figure, ax: Axes, dynamic: list, dpi: float) -> None:
    """Render everything but ``dynamic`` once and make it a figure image.

    Each GIF frame is a full ``savefig``; without this, ticks, labels, grid and layout would
    be recomputed on every frame, which costs several times more than the moving agents.
    """
    for a in dynamic:
        a.set_visible(False)
    fig.set_dpi(dpi)
    fig.canvas.draw()  # runs the constrained layout once, fixing the axes position
    background = np.asarray(fig.canvas.buffer_rgba()).copy()
    fig.set_layout_engine("none")
    for a in ax.get_children():
        a.set_visible(False)
    ax.set_axis_off()  # no axes patch, spines, ticks or labels: they are in the background
    for a in dynamic:
        a.set_visible(True)
    fig.add_artist(_PixelBackground(background))


class _PixelBackground(Artist):
    """Pastes a pre-rendered RGBA buffer at the figure origin, pixel for pixel.

    Cheaper than ``Figure.figimage``, which resamples and colour-maps the array per draw.
    """

    def __init__(self, rgba: np.ndarray) -> None:
        super().__init__()
        # Renderers take images with the bottom row first; Agg's buffer has the top row first.
        self._rgba = np.ascontiguousarray(rgba[::-1])
        self.set_zorder(-10)

    def draw(self, renderer: RendererBase) -> None:
        if not self.get_visible():
            return
        gc = renderer.new_gc()
        try:
            renderer.draw_image(gc, 0, 0, self._rgba)
        finally:
            gc.restore()
        self.stale = False


def animate_trajectory(
    traj: Trajectory,
    path: PathLike,
    *,
    fps: float | None = None,
    dpi: int = 80,
    show_human_goals: bool = False,
    title: str | None = None,
) -> Path:
    """Write the episode as an animated GIF (one frame per state, T+1 frames) to ``path``.

    Uses matplotlib's ``PillowWriter`` so no ffmpeg is needed. Agents are circles at the
    current step with short fading trails; ``fps`` defaults to real time (1 / time_step).
    """
    out = Path(path)
    if out.suffix.lower() != ".gif":
        raise ValueError(f"path: expected a .gif file, got {str(path)!r}")
    if fps is None:
        fps = 1.0 / traj.time_step
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps: expected a finite positive number, got {fps}")

    fig = _new_figure((6.0, 6.0))
    ax = fig.add_subplot()
    colors = human_colors(traj.num_humans)
    _set_limits(ax, traj, include_human_goals=show_human_goals)
    draw_obstacles(ax, traj.obstacles)  # static: part of the frozen background
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, lw=0.4, alpha=0.4)
    if (full_title := _title(traj, title)) is not None:
        ax.set_title(full_title)

    (goal_marker,) = ax.plot(*traj.robot_goal, marker="*", ms=16, color=GOAL_COLOR,
                             mec="black", mew=0.8, ls="none", zorder=7)

    # Fading trails: one LineCollection per agent, alpha rising towards the present.
    agent_xy = [traj.robot_positions] + [traj.human_positions[:, h] for h in range(traj.num_humans)]
    agent_rgb = [np.array([0.0, 0.0, 0.0])] + [np.array(c[:3]) for c in colors]
    trails = [ax.add_collection(LineCollection([], lw=lw, zorder=2))
              for lw in [2.0] + [1.5] * traj.num_humans]

    human_circles = [ax.add_patch(Circle(traj.human_positions[0, h], traj.human_radius,
                                         facecolor=(*colors[h][:3], 0.35), edgecolor=colors[h],
                                         lw=1.5, zorder=4))
                     for h in range(traj.num_humans)]
    robot_circle = ax.add_patch(Circle(traj.robot_positions[0], traj.robot_radius,
                                       facecolor=(0.0, 0.0, 0.0, 0.25), edgecolor=ROBOT_COLOR,
                                       lw=2.0, zorder=5))
    heading_line = None
    if traj.robot_headings is not None:
        (heading_line,) = ax.plot([], [], color=ROBOT_COLOR, lw=1.5, zorder=5.5)
    goal_markers = None
    if show_human_goals:
        goal_markers = ax.scatter(traj.human_goals[0, :, 0], traj.human_goals[0, :, 1],
                                  marker="x", s=30, c=colors, linewidths=1.5, zorder=3)
    clock = ax.text(0.02, 0.98, "", transform=ax.transAxes, ha="left", va="top",
                    fontsize=11, family="monospace",
                    bbox=dict(boxstyle="round,pad=0.3", fc="white", ec="0.7", alpha=0.9),
                    zorder=10)

    def update(k: int) -> None:
        lo = max(0, k - TRAIL_STEPS)
        n_seg = k - lo
        for trail, xy, rgb in zip(trails, agent_xy, agent_rgb):
            if n_seg == 0:
                trail.set_segments([])
                continue
            pts = xy[lo:k + 1]
            segs = np.stack([pts[:-1], pts[1:]], axis=1)
            # Oldest segment faintest; alpha is relative to the full trail length so the
            # trail fades the same way whatever its current length.
            alphas = 0.9 * (np.arange(TRAIL_STEPS - n_seg, TRAIL_STEPS) + 1) / TRAIL_STEPS
            trail.set_segments(segs)
            trail.set_color(np.column_stack([np.tile(rgb, (n_seg, 1)), alphas]))
        for h, circ in enumerate(human_circles):
            circ.set_center(traj.human_positions[k, h])
        robot_circle.set_center(traj.robot_positions[k])
        if heading_line is not None:
            seg = heading_segment(traj.robot_positions[k], traj.robot_headings[k], traj.robot_radius)
            heading_line.set_data(seg[:, 0], seg[:, 1])
        if goal_markers is not None:
            goal_markers.set_offsets(traj.human_goals[k])
        clock.set_text(f"t = {k * traj.time_step:.2f} s")

    dynamic = [*trails, *human_circles, robot_circle, goal_marker, clock]
    dynamic += [a for a in (heading_line, goal_markers) if a is not None]
    _freeze_background(fig, ax, dynamic, dpi)

    def write(tmp: str) -> None:
        writer = PillowWriter(fps=fps)
        with writer.saving(fig, tmp, dpi):
            for k in range(traj.num_steps + 1):
                update(k)
                writer.grab_frame()

    return atomic_write_with(out, write, suffix=".gif")
