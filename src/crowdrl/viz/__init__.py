"""Rendering of crowd-navigation episodes: static PNG summaries and animated GIFs."""

from crowdrl.viz.trajectory import (
    TIME_STAMP_GID,
    Trajectory,
    animate_trajectory,
    plot_trajectory,
)

__all__ = ["Trajectory", "plot_trajectory", "animate_trajectory", "TIME_STAMP_GID"]
