"""Rendering of one episode: PNG summary plot and animated GIF."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure
from PIL import Image

from crowdrl.viz import TIME_STAMP_GID, Trajectory, animate_trajectory, plot_trajectory

T, N, DT = 24, 3, 0.25  # 6 s: stamps at 0 s, 5 s (step 20) and the final 6 s


def make_traj(**overrides) -> Trajectory:
    """Robot crossing upwards, humans on straight lines across its path."""
    s = np.linspace(0.0, 1.0, T + 1)
    robot = np.stack([np.zeros_like(s), -4.0 + 8.0 * s], axis=-1)
    starts = np.array([[-4.0, -1.0], [4.0, 0.0], [-4.0, 1.5]])
    goals = -starts
    humans = starts[None] + (goals - starts)[None] * s[:, None, None]
    kwargs = dict(
        robot_positions=robot,
        robot_goal=np.array([0.0, 4.0]),
        robot_radius=0.3,
        human_positions=humans,
        human_goals=np.broadcast_to(goals, humans.shape).copy(),
        human_radius=0.3,
        time_step=DT,
        outcome="success",
        robot_headings=np.full(T + 1, np.pi / 2),
    )
    kwargs.update(overrides)
    return Trajectory(**kwargs)


def stamp_labels(fig: Figure) -> list[str]:
    return [t.get_text() for ax in fig.axes for t in ax.texts if t.get_gid() == TIME_STAMP_GID]


def test_plot_writes_png_and_stamps_times(tmp_path: Path) -> None:
    out = tmp_path / "nested" / "dir" / "episode.png"
    fig = plot_trajectory(make_traj(), out, title="demo")

    assert isinstance(fig, Figure)
    with Image.open(out) as im:
        assert im.format == "PNG"
        assert im.width > 0 and im.height > 0
    assert [p.name for p in out.parent.iterdir()] == ["episode.png"]  # no temp file left

    labels = stamp_labels(fig)
    # One label per agent (robot + N humans) per stamp time.
    assert len(labels) == (N + 1) * 3
    assert sorted(set(labels)) == ["0.0", "5.0", "6.0"]
    assert all(labels.count(t) == N + 1 for t in ("0.0", "5.0", "6.0"))
    assert "success" in fig.axes[0].get_title()


def test_plot_without_path_and_odd_final_time() -> None:
    # T=21 -> stamps at 0 s, 5 s and the final 5.25 s; no outcome -> no outcome in title.
    traj = make_traj(
        robot_positions=make_traj().robot_positions[:22],
        human_positions=make_traj().human_positions[:22],
        human_goals=make_traj().human_goals[:22],
        robot_headings=None,
        outcome="",
    )
    fig = plot_trajectory(traj)
    assert sorted(set(stamp_labels(fig))) == ["0.0", "5.0", "5.25"]
    assert fig.axes[0].get_title() == ""


def test_animation_has_one_frame_per_state(tmp_path: Path) -> None:
    out = animate_trajectory(make_traj(), tmp_path / "ep.gif", dpi=30, show_human_goals=True)

    assert out == tmp_path / "ep.gif"
    with Image.open(out) as im:
        assert im.format == "GIF"
        assert im.n_frames == T + 1
        assert im.info["duration"] == pytest.approx(1000 * DT, abs=10)
    assert [p.name for p in tmp_path.iterdir()] == ["ep.gif"]


def test_animation_rejects_non_gif_path(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="gif"):
        animate_trajectory(make_traj(), tmp_path / "ep.mp4")
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("human_positions", np.zeros((T, N, 2))),  # T differs from robot_positions
        ("human_positions", np.zeros((T + 1, N, 3))),  # wrong last dim
        ("human_positions", np.zeros((T + 1, 0, 2))),  # N < 1
        ("robot_positions", np.zeros((0, 2))),  # T < 0
        ("robot_positions", np.zeros((T + 1, 3))),
        ("human_goals", np.zeros((T + 1, N + 1, 2))),
        ("robot_goal", np.zeros(3)),
        ("robot_headings", np.zeros(T)),
        ("robot_radius", 0.0),
        ("time_step", -0.25),
    ],
)
def test_shape_mismatch_names_the_field(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field):
        make_traj(**{field: value})


def test_a_trajectory_round_trips_through_its_file_and_a_run_folder_is_drawn_from_its_files(tmp_path: Path) -> None:
    import json

    from crowdrl.viz import render_run_folder

    walls = (np.array([[-5.0, 5.0], [5.0, 5.0]]), np.array([[1.0, 1.0], [2.0, 1.0], [2.0, 2.0]]))
    traj = make_traj(obstacles=walls)
    back = Trajectory.load(traj.save(tmp_path / "test_case0.trajectory.json"))
    for name in ("robot_positions", "robot_goal", "human_positions", "human_goals", "robot_headings"):
        np.testing.assert_array_equal(getattr(back, name), getattr(traj, name), err_msg=name)
    assert back.outcome == "success" and back.time_step == DT and len(back.obstacles) == 2
    np.testing.assert_array_equal(back.obstacles[1], walls[1])
    (tmp_path / "scalars.jsonl").write_text(
        "\n".join(json.dumps(r) for r in ({"kind": "train", "frames": 64, "train/success_rate": 0.5,
                                            "train/collision_rate": 0.5},
                                           {"kind": "val", "frames": 64, "val/success_rate": 0.25})) + "\n{cut")
    written = render_run_folder(tmp_path, title="t")
    assert sorted(p.name for p in written) == ["learning_curves.png", "test_case0.gif", "test_case0.png"]
    assert all(p.stat().st_size > 0 for p in written)
    (tmp_path / "bad.trajectory.json").write_text(json.dumps({"format": "other"}))
    with pytest.raises(ValueError, match=r"bad\.trajectory\.json: not a crowdrl trajectory"):
        Trajectory.load(tmp_path / "bad.trajectory.json")


def test_a_run_folder_that_does_not_exist_is_refused_naming_it(tmp_path: Path) -> None:
    from crowdrl.viz import render_run_folder

    with pytest.raises(FileNotFoundError, match=r"run_dir: .*nowhere is not a folder"):
        render_run_folder(tmp_path / "nowhere")
