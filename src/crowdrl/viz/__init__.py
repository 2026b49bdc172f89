"""Rendering: episode PNG summaries, animated GIFs, single RGB frames, learning curves."""

from crowdrl.viz.curves import plot_learning_curves
from crowdrl.viz.frame import render_frame
from crowdrl.viz.trajectory import (
    TIME_STAMP_GID,
    Trajectory,
    animate_trajectory,
    plot_trajectory,
)

__all__ = ["Trajectory", "plot_trajectory", "animate_trajectory", "plot_learning_curves", "render_frame",
           "TIME_STAMP_GID"]
