"""The figures of a run folder, drawn from its files: ``learning_curves.png`` from ``scalars.jsonl``, and
``test_case<k>.png`` / ``.gif`` from each ``test_case<k>.trajectory.json`` the final test recorded."""

from __future__ import annotations

from pathlib import Path

from crowdrl.evaluation.trajectory import Trajectory
from crowdrl.files import read_json_lines

TRAJECTORY_SUFFIX = ".trajectory.json"


def render_run_folder(run_dir: Path | str, *, title: str | None = None) -> list[Path]:
    """Draw the run's figures into ``run_dir``; returns the files written (none for a folder without records);
    ``FileNotFoundError`` naming ``run_dir`` when it is no folder."""
    from crowdrl.viz.curves import plot_learning_curves
    from crowdrl.viz.trajectory import animate_trajectory, plot_trajectory

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"run_dir: {run_dir} is not a folder")
    written = []
    scalars = run_dir / "scalars.jsonl"
    if scalars.exists():
        written.append(plot_learning_curves(read_json_lines(scalars), run_dir / "learning_curves.png", title=title))
    for path in sorted(run_dir.glob(f"test_case*{TRAJECTORY_SUFFIX}")):
        stem = path.name.removesuffix(TRAJECTORY_SUFFIX)
        traj = Trajectory.load(path)
        plot_trajectory(traj, run_dir / f"{stem}.png", title=f"test case {stem.removeprefix('test_case')}")
        written.append(run_dir / f"{stem}.png")
        written.append(animate_trajectory(traj, run_dir / f"{stem}.gif"))
    return written


__all__ = ["TRAJECTORY_SUFFIX", "render_run_folder"]
