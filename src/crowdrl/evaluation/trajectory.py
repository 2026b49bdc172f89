"""One recorded episode as plain arrays (:class:`Trajectory`): what evaluation records and the
plotting code in :mod:`crowdrl.viz` draws. Numpy only, no drawing code here."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["Trajectory"]


def _as_float_array(name: str, value: object) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: cannot be converted to a float array ({exc})") from exc
    return arr


def _positive_scalar(name: str, value: object) -> float:
    try:
        x = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: expected a number, got {value!r}") from exc
    if not (math.isfinite(x) and x > 0):
        raise ValueError(f"{name}: expected a finite positive number, got {x}")
    return x


@dataclass(frozen=True, eq=False)
class Trajectory:
    """One recorded episode: the robot and N humans over T steps (T+1 states, t=0..T).

    Arrays are converted to float64 numpy arrays and their shapes checked on construction, so
    the plotting code can rely on them; a mismatch raises ``ValueError`` naming the field.
    ``human_goals`` is per step because humans are given new goals during an episode.
    Compared by identity (``eq=False``): element-wise array equality has no single truth value.
    """

    robot_positions: np.ndarray  # [T+1, 2]
    robot_goal: np.ndarray  # [2]
    robot_radius: float
    human_positions: np.ndarray  # [T+1, N, 2]
    human_goals: np.ndarray  # [T+1, N, 2]
    human_radius: float
    time_step: float
    outcome: str = ""
    robot_headings: np.ndarray | None = None  # [T+1], radians
    # static obstacles: polygons [n_i, 2] (n_i = 2: a wall segment; 3+: a counter-clockwise solid), or None
    obstacles: tuple[np.ndarray, ...] | None = None

    def __post_init__(self) -> None:
        def put(name: str, value: object) -> None:
            object.__setattr__(self, name, value)

        rp = _as_float_array("robot_positions", self.robot_positions)
        if rp.ndim != 2 or rp.shape[-1] != 2:
            raise ValueError(f"robot_positions: expected shape [T+1, 2], got {rp.shape}")
        if rp.shape[0] < 1:
            raise ValueError("robot_positions: needs at least one state (T >= 0)")
        n_states = rp.shape[0]

        goal = _as_float_array("robot_goal", self.robot_goal)
        if goal.shape != (2,):
            raise ValueError(f"robot_goal: expected shape [2], got {goal.shape}")

        hp = _as_float_array("human_positions", self.human_positions)
        if hp.ndim != 3 or hp.shape[-1] != 2:
            raise ValueError(f"human_positions: expected shape [T+1, N, 2], got {hp.shape}")
        if hp.shape[0] != n_states:
            raise ValueError(
                f"human_positions: has {hp.shape[0]} states but robot_positions has {n_states}"
            )
        if hp.shape[1] < 1:
            raise ValueError("human_positions: needs at least one human (N >= 1)")

        hg = _as_float_array("human_goals", self.human_goals)
        if hg.shape != hp.shape:
            raise ValueError(
                f"human_goals: expected shape {hp.shape} (as human_positions), got {hg.shape}"
            )

        headings = self.robot_headings
        if headings is not None:
            headings = _as_float_array("robot_headings", headings)
            if headings.shape != (n_states,):
                raise ValueError(
                    f"robot_headings: expected shape [{n_states}] (T+1), got {headings.shape}"
                )

        for name, arr in (("robot_positions", rp), ("robot_goal", goal),
                          ("human_positions", hp), ("human_goals", hg)):
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{name}: contains non-finite values")

        obstacles = self.obstacles
        if obstacles is not None:
            polys = []
            for i, poly in enumerate(obstacles):
                poly = _as_float_array(f"obstacles[{i}]", poly)
                if poly.ndim != 2 or poly.shape[-1] != 2 or poly.shape[0] < 2:
                    raise ValueError(f"obstacles[{i}]: expected shape [n >= 2, 2], got {poly.shape}")
                if not np.all(np.isfinite(poly)):
                    raise ValueError(f"obstacles[{i}]: contains non-finite values")
                polys.append(poly)
            obstacles = tuple(polys)

        if not isinstance(self.outcome, str):
            raise ValueError(f"outcome: expected a str, got {type(self.outcome).__name__}")

        put("robot_positions", rp)
        put("robot_goal", goal)
        put("robot_radius", _positive_scalar("robot_radius", self.robot_radius))
        put("human_positions", hp)
        put("human_goals", hg)
        put("human_radius", _positive_scalar("human_radius", self.human_radius))
        put("time_step", _positive_scalar("time_step", self.time_step))
        put("robot_headings", headings)
        put("obstacles", obstacles)

    @property
    def num_steps(self) -> int:
        """T, the number of steps (there are T+1 states)."""
        return int(self.robot_positions.shape[0]) - 1

    @property
    def num_humans(self) -> int:
        """N, the number of humans."""
        return int(self.human_positions.shape[1])

    @property
    def duration(self) -> float:
        """Episode length in seconds (T * time_step)."""
        return self.num_steps * self.time_step

    def to_dict(self) -> dict:
        """Plain lists and numbers (JSON); :meth:`from_dict` rebuilds the trajectory, its checks included."""
        def plain(value):
            return None if value is None else np.asarray(value).tolist()

        return {"format": "crowdrl.trajectory", "version": 1,
                "robot_positions": plain(self.robot_positions), "robot_goal": plain(self.robot_goal),
                "robot_radius": self.robot_radius, "human_positions": plain(self.human_positions),
                "human_goals": plain(self.human_goals), "human_radius": self.human_radius,
                "time_step": self.time_step, "outcome": self.outcome, "robot_headings": plain(self.robot_headings),
                "obstacles": None if self.obstacles is None else [plain(p) for p in self.obstacles]}

    @classmethod
    def from_dict(cls, data: dict) -> "Trajectory":
        """The trajectory of :meth:`to_dict`'s output; ``ValueError`` for another format or a bad field."""
        if not isinstance(data, dict) or data.get("format") != "crowdrl.trajectory":
            raise ValueError("not a crowdrl trajectory (its 'format' is not 'crowdrl.trajectory')")
        if data.get("version") != 1:
            raise ValueError(f"trajectory version {data.get('version')!r} is not one this code reads (1)")
        fields = {k: v for k, v in data.items() if k not in ("format", "version")}
        if fields.get("obstacles") is not None:
            fields["obstacles"] = tuple(fields["obstacles"])
        try:
            return cls(**fields)
        except TypeError as exc:
            raise ValueError(f"trajectory fields: {exc}") from None

    def save(self, path: str | Path) -> Path:
        """Write :meth:`to_dict` as JSON, atomically; :meth:`load` reads it back."""
        from crowdrl.files import atomic_write_json

        atomic_write_json(Path(path), self.to_dict())
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> "Trajectory":
        """A trajectory :meth:`save` wrote; ``ValueError`` naming the file for anything else."""
        import json

        try:
            return cls.from_dict(json.loads(Path(path).read_text(encoding="utf-8")))
        except (OSError, ValueError) as exc:
            raise ValueError(f"{path}: {exc}") from None
