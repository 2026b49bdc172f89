"""The ceiling of a stream of cases, and how far a policy falls short of it.

:func:`compute_ceiling` labels each case of a stream (scenario, split, seed, cases ``0 .. n-1``, the crowd's
config) with :mod:`crowdrl.sim.oracle`, which knows the humans' futures:

* ``solved``: a collision-free path reaches the goal, in ``steps`` (its actions are kept, and
  :func:`replay` steps them through :class:`~crowdrl.envs.CrowdNavEnv`);
* ``infeasible``: every action sequence collides within ``horizon`` steps (exhaustive search);
* ``unknown``: neither (the beam found no path, and the short horizon proves nothing).

The beam runs at ``widths[0]`` on every case, then at each wider width on the cases still unsolved, so
the solved count at each width comes with the labels.

:func:`gap` compares a policy's per-case outcomes (:class:`~crowdrl.evaluation.metrics.EpisodeMetrics`'
``events`` and ``lengths``) with the labels: failures where a path exists (avoidable), where none does
(unavoidable), and the mean time over the ceiling on the cases both solve. A ceiling file of another
stream is refused by :func:`check_stream`, naming the mismatch.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import torch

from crowdrl.files import atomic_write_json
from crowdrl.sim import rng
from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.crowd import EVENT_NAMES, SUCCESS
from crowdrl.sim.obstacles import process_obstacles, select_edges
from crowdrl.sim.oracle import INFEASIBLE, LABELS, SOLVED, UNKNOWN, beam_search, check_searchable, exhaustive
from crowdrl.sim.scenarios import initial_states

FORMAT = 1
DEFAULT_WIDTHS = (64, 512, 2048)
DEFAULT_CELL = 0.125
DEFAULT_HORIZON = 3  # steps of the exhaustive proof (0.75 s): 81**2 nodes a case at its last depth
# config fields that change no case: the backend (the same ORCA), what the robot observes, and its kinematics (the
# ORCA baseline plays the same cases with a holonomic robot; the ceiling is the unicycle's)
_NOT_STREAM = ("orca_backend", "obstacle_tokens", "lidar_rays", "lidar_range", "robot_kinematics")


def crowd_identity(cfg: CrowdConfig) -> dict[str, Any]:
    """The config fields that define a stream's episodes (every :class:`CrowdConfig` field but the backend)."""
    return {k: v for k, v in dataclasses.asdict(cfg).items() if k not in _NOT_STREAM}


@dataclass
class Ceiling:
    """The labels of cases ``0 .. cases-1`` of one stream (see the module docstring)."""

    scenario: str
    split: str
    seed: int
    crowd: dict[str, Any]  # crowd_identity of the config
    labels: list[str]
    steps: list[int]  # per case: steps of the path found (-1: none)
    actions: list[list[int]]  # per case: the path's actions (empty: none)
    settings: dict[str, Any] = field(default_factory=dict)  # widths, cell, horizon
    solved_by_width: dict[str, int] = field(default_factory=dict)  # cumulative solved count per width
    seconds: float = 0.0

    @property
    def cases(self) -> int:
        return len(self.labels)

    @property
    def time_step(self) -> float:
        return float(self.crowd["time_step"])

    def counts(self) -> dict[str, int]:
        return {label: self.labels.count(label) for label in LABELS}

    def mean_time(self) -> float:
        """Mean time to the goal (s) over the solved cases (nan: none)."""
        solved = [s for s, lab in zip(self.steps, self.labels) if lab == SOLVED]
        return sum(solved) * self.time_step / len(solved) if solved else math.nan

    def to_json(self) -> dict[str, Any]:
        return {"format": FORMAT, "scenario": self.scenario, "split": self.split, "seed": self.seed,
                "cases": self.cases, "crowd": self.crowd, "settings": self.settings,
                "solved_by_width": self.solved_by_width, "seconds": self.seconds, "counts": self.counts(),
                "mean_time": self.mean_time(), "labels": list(self.labels), "steps": list(self.steps),
                "actions": [list(a) for a in self.actions]}  # copies: editing the dict leaves the ceiling as it is


def compute_ceiling(cfg: CrowdConfig, *, split: str = "test", seed: int = 0, cases: int = 1000,
                    widths: tuple[int, ...] = DEFAULT_WIDTHS, cell: float = DEFAULT_CELL,
                    horizon: int = DEFAULT_HORIZON, chunk: int = 50,
                    progress: Callable[[int], None] | None = None) -> Ceiling:
    """Label cases ``0 .. cases-1`` of the ``split`` stream of ``seed`` under ``cfg`` (see the module docstring).

    ``chunk``: cases searched at once (memory: ``chunk x widths[0] x 81`` children a depth); ``progress`` is
    called with the number of cases done after each chunk. Bad arguments raise ``ValueError`` naming them."""
    check_searchable(cfg)
    check_settings(split=split, seed=seed, cases=cases, widths=widths, cell=cell, horizon=horizon)
    began = time.perf_counter()
    labels, steps, actions = [UNKNOWN] * cases, [-1] * cases, [[] for _ in range(cases)]
    solved_by_width = {str(w): 0 for w in widths}
    for first in range(0, cases, chunk):
        ids = torch.arange(first, min(cases, first + chunk))
        start = initial_states(cfg, rng.episode_keys(split, seed, ids))
        edges = process_obstacles(start.obstacles, start.obstacle_mask) if start.has_obstacles else None
        todo = torch.arange(ids.shape[0])
        for w in widths:
            if todo.numel() == 0:
                break
            part = start.index(todo)
            found = beam_search(cfg, part, width=w, cell=cell,
                                edges=None if edges is None else select_edges(edges, todo))
            for j, c in enumerate(todo.tolist()):
                if found.steps[j] > 0:
                    i = first + c
                    labels[i], steps[i], actions[i] = SOLVED, found.steps[j], found.actions[j]
                    solved_by_width[str(w)] += 1
            todo = torch.tensor([c for j, c in enumerate(todo.tolist()) if found.steps[j] <= 0], dtype=torch.long)
        for c in todo.tolist():  # one at a time: the last depth holds 81**(horizon-1) nodes
            one = start.index(torch.tensor([c]))
            if exhaustive(cfg, one, horizon, edges=None if edges is None else select_edges(edges, torch.tensor([c])))[0]:
                labels[first + c] = INFEASIBLE
        if progress is not None:
            progress(int(ids.shape[0]))
    running = 0
    for w in widths:  # cumulative: solved at this width or a narrower one
        running += solved_by_width[str(w)]
        solved_by_width[str(w)] = running
    return Ceiling(cfg.scenario, split, int(seed), crowd_identity(cfg), labels, steps, actions,
                   settings={"widths": list(widths), "cell": cell, "horizon": horizon},
                   solved_by_width=solved_by_width, seconds=round(time.perf_counter() - began, 1))


def check_settings(*, split: str, seed: int, cases: int, widths: tuple[int, ...], cell: float, horizon: int) -> None:
    """Refuse bad ceiling settings, naming the key (``ValueError``)."""
    if split not in rng.STREAMS:
        raise ValueError(f"split: must be one of {tuple(rng.STREAMS)}, got {split!r}")
    for name, value, low in (("seed", seed, 0), ("cases", cases, 1), ("horizon", horizon, 1)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(f"{name}: must be an integer >= {low}, got {value!r}")
    if seed > rng.MAX_SEED:
        raise ValueError(f"seed: must lie in 0..2**63-1, got {seed}")
    if cases > rng.MAX_SEED:
        raise ValueError(f"cases: the stream holds episode ids 0..2**63-1, got {cases}")
    if horizon > 4:
        raise ValueError(f"horizon: at most 4 steps (81**3 nodes a case at the last depth), got {horizon}")
    if not widths or any(isinstance(w, bool) or not isinstance(w, int) or w < 1 for w in widths):
        raise ValueError(f"width: every width must be an integer >= 1, got {list(widths)!r}")
    if list(widths) != sorted(set(widths)):
        raise ValueError(f"width: widths must increase, got {list(widths)!r}")
    if isinstance(cell, bool) or not isinstance(cell, (int, float)) or not 0.01 <= cell <= 1.0:
        raise ValueError(f"cell: the grid's cell must lie in 0.01..1.0 m, got {cell!r}")


def write_ceiling(path: Path | str, ceiling: Ceiling) -> None:
    """Write ``ceiling`` as JSON, atomically."""
    atomic_write_json(path, ceiling.to_json())


def read_ceiling(path: Path | str) -> Ceiling:
    """A ceiling file back; ``ValueError`` naming the file and the field when it is not one."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"ceiling file {path}: cannot be read as JSON ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise ValueError(f"ceiling file {path}: not a crowdrl ceiling of format {FORMAT}")
    try:
        c = Ceiling(str(data["scenario"]), str(data["split"]), int(data["seed"]), dict(data["crowd"]),
                    list(data["labels"]), [int(s) for s in data["steps"]], [list(map(int, a)) for a in data["actions"]],
                    dict(data.get("settings", {})), dict(data.get("solved_by_width", {})),
                    float(data.get("seconds", 0.0)))
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"ceiling file {path}: malformed field ({exc!r})") from None
    n = len(c.labels)
    if len(c.steps) != n or len(c.actions) != n or int(data.get("cases", n)) != n:
        raise ValueError(f"ceiling file {path}: labels, steps and actions differ in length")
    bad = sorted(set(c.labels) - set(LABELS))
    if bad:
        raise ValueError(f"ceiling file {path}: unknown labels {bad}; allowed: {list(LABELS)}")
    for i, (lab, s, a) in enumerate(zip(c.labels, c.steps, c.actions)):
        if (lab == SOLVED) != (s > 0) or (lab == SOLVED and len(a) != s):
            raise ValueError(f"ceiling file {path}: case {i} is {lab!r} with steps {s} and {len(a)} actions")
    return c


def check_stream(ceiling: Ceiling, cfg: CrowdConfig, *, split: str, seed: int, cases: int) -> None:
    """Refuse ``ceiling`` unless it labels exactly this stream: ``ValueError`` naming the mismatch."""
    asked = {"scenario": cfg.scenario, "split": split, "seed": int(seed), "cases": int(cases)}
    have = {"scenario": ceiling.scenario, "split": ceiling.split, "seed": ceiling.seed, "cases": ceiling.cases}
    for key in asked:
        if asked[key] != have[key]:
            raise ValueError(f"ceiling: its {key} is {have[key]!r}, the evaluation's {asked[key]!r}")
    mine = crowd_identity(cfg)
    diff = sorted(k for k in set(mine) | set(ceiling.crowd) if mine.get(k) != ceiling.crowd.get(k))
    if diff:
        shown = ", ".join(f"{k}: ceiling {ceiling.crowd.get(k)!r} vs evaluation {mine.get(k)!r}" for k in diff[:4])
        raise ValueError(f"ceiling: another crowd ({shown})")


def gap(ceiling: Ceiling, events: tuple[int, ...] | list[int], lengths: tuple[int, ...] | list[int]) -> dict[str, Any]:
    """A policy's per-case ``events`` and ``lengths`` (steps) against the ceiling: failures where a path
    exists (``avoidable_failures``), where every sequence collides (``unavoidable_failures``), where the
    ceiling is unknown (``unknown_failures``); the policy's successes where the ceiling found none
    (``beyond_ceiling``: should be 0 bar unknown cases); and ``time_over_ceiling``, the mean of the
    policy's time minus the ceiling's (s) over the ``both_solved`` cases."""
    if len(events) != ceiling.cases or len(lengths) != ceiling.cases:
        raise ValueError(f"ceiling: it labels {ceiling.cases} cases, the evaluation ran {len(events)}")
    out = {"avoidable_failures": 0, "unavoidable_failures": 0, "unknown_failures": 0, "beyond_ceiling": 0}
    over = []
    for lab, s, ev, n in zip(ceiling.labels, ceiling.steps, events, lengths):
        if ev != SUCCESS:
            out[{SOLVED: "avoidable_failures", INFEASIBLE: "unavoidable_failures",
                 UNKNOWN: "unknown_failures"}[lab]] += 1
        elif lab != SOLVED:
            out["beyond_ceiling"] += 1
        else:
            over.append((int(n) - s) * ceiling.time_step)
    out["both_solved"] = len(over)
    out["time_over_ceiling"] = sum(over) / len(over) if over else math.nan
    out["ceiling_success"] = ceiling.counts()[SOLVED] / ceiling.cases
    return out


@torch.no_grad()
def replay(ceiling: Ceiling, cfg: CrowdConfig, case_ids: list[int] | None = None, batch: int = 256) -> list[str]:
    """Step each solved path (of ``case_ids``, default all) through :class:`~crowdrl.envs.CrowdNavEnv`;
    the list of disagreements (empty: every path succeeds at its step, with no event before)."""
    from crowdrl.envs.crowd_nav import CrowdNavEnv

    ids = [i for i in (range(ceiling.cases) if case_ids is None else case_ids) if ceiling.labels[i] == SOLVED]
    wrong = []
    for a in range(0, len(ids), batch):
        part = ids[a:a + batch]
        env = CrowdNavEnv(cfg.scenario, num_envs=len(part), num_humans=cfg.num_humans, split=ceiling.split,
                          seed=ceiling.seed, config=cfg)
        env.load_episodes(torch.tensor(part))
        td = env.reset()
        longest = max(ceiling.steps[i] for i in part)
        plans = torch.zeros(len(part), longest, dtype=torch.long)
        for j, i in enumerate(part):
            plans[j, :ceiling.steps[i]] = torch.tensor(ceiling.actions[i])
        ended = torch.zeros(len(part), dtype=torch.long)
        event = torch.zeros(len(part), dtype=torch.long)
        for t in range(longest):
            td["action"] = plans[:, t]
            td = env.step(td)["next"]
            ev = td["event"].reshape(-1)
            fresh = (ended == 0) & (ev != 0)
            ended = torch.where(fresh, t + 1, ended)
            event = torch.where(fresh, ev, event)
        for j, i in enumerate(part):
            if int(event[j]) != SUCCESS or int(ended[j]) != ceiling.steps[i]:
                wrong.append(f"case {i}: {EVENT_NAMES[int(event[j])]} at step {int(ended[j])}, "
                             f"the search's success at step {ceiling.steps[i]}")
    return wrong
