"""Rendering: episode PNG summaries, animated GIFs, learning curves."""

from crowdrl.viz.curves import plot_learning_curves
from crowdrl.viz.trajectory import (
    TIME_STAMP_GID,
    Trajectory,
    animate_trajectory,
    plot_trajectory,
)

__all__ = ["Trajectory", "plot_trajectory", "animate_trajectory", "plot_learning_curves", "TIME_STAMP_GID"]
