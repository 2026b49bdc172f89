"""Rendering: episode PNG summaries, animated GIFs, single RGB frames, learning curves."""

try:
    import matplotlib  # noqa: F401
except ImportError as exc:
    from crowdrl._extras import missing

    raise missing("matplotlib", "train", "crowdrl.viz (figures, GIFs, render_mode='rgb_array'; "
                  "logger.render=false does without)") from exc

from crowdrl.viz.curves import plot_learning_curves
from crowdrl.viz.frame import render_frame
from crowdrl.viz.results import ema, plot_intervals, plot_seed_curves
from crowdrl.viz.run_folder import render_run_folder
from crowdrl.viz.trajectory import (
    TIME_STAMP_GID,
    Trajectory,
    animate_trajectory,
    plot_side_by_side,
    plot_trajectory,
)

__all__ = ["Trajectory", "plot_trajectory", "plot_side_by_side", "animate_trajectory", "plot_learning_curves",
           "render_frame", "render_run_folder", "ema", "plot_seed_curves", "plot_intervals", "TIME_STAMP_GID"]
