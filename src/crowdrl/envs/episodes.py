"""The episodes that ended in a collected batch of :class:`~crowdrl.envs.CrowdNavEnv`, and their
statistics as training logs them (``train/*``): what a learner's loop needs to know of the crowd.

>>> import torch
>>> from crowdrl.envs import CrowdNavEnv
>>> env = CrowdNavEnv("circle", num_envs=2, num_humans=2, seed=0)
>>> batch = env.rollout(200, break_when_any_done=False)
>>> ended = finished_episodes(batch)
>>> len(ended) > 0, sorted(episode_statistics(ended, 0.25))[:2]
(True, ['collision_rate', 'episode_length'])
"""

from __future__ import annotations

import math
from typing import NamedTuple

from tensordict import TensorDictBase

from crowdrl.sim.crowd import COLLISION, SUCCESS, TIMEOUT


class FinishedEpisode(NamedTuple):
    """One episode that ended: its event code, undiscounted return, steps and its robot's final distance
    to the goal (metres)."""

    event: int
    ret: float
    steps: int
    goal_distance: float


def finished_episodes(batch: TensorDictBase) -> list[FinishedEpisode]:
    """The episodes that ended in ``batch`` (a collector's ``[B, T]`` batch with ``("next", "done")``,
    ``event``, ``episode_reward``, ``step_count`` and the world-frame ``robot``), in batch order."""
    nxt = batch.get("next")
    done = nxt.get("done").reshape(-1)
    if not bool(done.any()):
        return []
    events = nxt.get("event").reshape(-1)[done].tolist()
    returns = nxt.get("episode_reward").reshape(-1)[done].tolist()
    steps = nxt.get("step_count").reshape(-1)[done].tolist()
    robot = nxt.get("robot")  # world frame: px, py, vx, vy, radius, gx, gy, ...
    robot = robot.reshape(-1, robot.shape[-1])[done]
    dist = (robot[:, 5:7] - robot[:, 0:2]).norm(dim=-1).tolist()
    return [FinishedEpisode(*row) for row in zip(events, returns, steps, dist)]


def episode_statistics(episodes: list[FinishedEpisode], time_step: float) -> dict[str, float]:
    """Rates of each outcome, the mean return and length, the mean navigation time of the successes
    (seconds) and the mean goal distance of the timeouts (hovering near the goal, or gone far away);
    a mean over no episode is NaN."""
    n = len(episodes)
    if n == 0:
        raise ValueError("episode_statistics: no episode")
    events = [e.event for e in episodes]
    succ_steps = [e.steps for e in episodes if e.event == SUCCESS]
    timeout_dist = [e.goal_distance for e in episodes if e.event == TIMEOUT]
    return {
        "success_rate": events.count(SUCCESS) / n,
        "collision_rate": events.count(COLLISION) / n,
        "timeout_rate": events.count(TIMEOUT) / n,
        "return": sum(e.ret for e in episodes) / n,
        "episode_length": sum(e.steps for e in episodes) / n,
        "timeout_goal_distance": sum(timeout_dist) / len(timeout_dist) if timeout_dist else math.nan,
        "navigation_time": sum(succ_steps) / len(succ_steps) * time_step if succ_steps else math.nan,
    }


__all__ = ["FinishedEpisode", "episode_statistics", "finished_episodes"]
