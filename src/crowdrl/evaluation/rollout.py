"""Batched evaluation of a robot policy on fixed scenario streams, straight on the simulator."""

from __future__ import annotations

from typing import Callable, Protocol

import numpy as np
import torch
from torch import Tensor

from crowdrl.evaluation.metrics import EpisodeMetrics, discount_per_step, episode_metrics
from crowdrl.sim import rng
from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.crowd import EVENT_NAMES, RUNNING, step
from crowdrl.sim.kinematics import action_table, unicycle_step
from crowdrl.sim.scenarios import initial_states
from crowdrl.sim.state import CrowdState
from crowdrl.viz.trajectory import Trajectory


class RobotPolicy(Protocol):
    """Maps the batched state to the robot's velocity ``[B, 2]`` and heading ``[B]`` (or None)."""

    def __call__(self, cfg: CrowdConfig, state: CrowdState) -> tuple[Tensor, Tensor | None]: ...


class DiscreteActionPolicy:
    """Adapts ``choose(cfg, state) -> action indices [B]`` to the unicycle robot."""

    def __init__(self, choose: Callable[[CrowdConfig, CrowdState], Tensor]) -> None:
        self.choose = choose

    def __call__(self, cfg: CrowdConfig, state: CrowdState) -> tuple[Tensor, Tensor]:
        table = action_table(cfg.robot_v_pref, dtype=state.robot_position.dtype, device=state.device)
        a = self.choose(cfg, state)
        return unicycle_step(state.robot_heading, table[a, 0], table[a, 1])[::-1]


def evaluate_policy(
    cfg: CrowdConfig,
    policy: RobotPolicy,
    *,
    split: str = "test",
    seed: int = 0,
    num_episodes: int = 1000,
    batch_size: int = 1000,
    device: torch.device | str = "cpu",
    record_episode: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> tuple[EpisodeMetrics, Trajectory | None]:
    """Run episodes ``0 .. num_episodes-1`` of ``split``/``seed`` and aggregate the metrics.

    Episodes are run in batches of ``batch_size``; episode ``i`` is the same whatever the batch
    size. When ``record_episode`` is given, that episode's trajectory is returned too.
    """
    if num_episodes < 1 or batch_size < 1:
        raise ValueError("num_episodes and batch_size must be >= 1")
    if record_episode is not None and not 0 <= record_episode < num_episodes:
        raise ValueError(f"record_episode must lie in 0..{num_episodes - 1}, got {record_episode}")
    T = cfg.max_steps
    records: dict[str, list[Tensor]] = {k: [] for k in ("events", "lengths", "rewards", "disc", "disc_sep")}
    trajectory = None
    for first in range(0, num_episodes, batch_size):
        ids = torch.arange(first, min(first + batch_size, num_episodes), device=device)
        B = ids.shape[0]
        state = initial_states(cfg, rng.episode_keys(split, seed, ids))
        alive = torch.ones(B, dtype=torch.bool, device=device)
        events = torch.full((B,), RUNNING, dtype=torch.int64, device=device)
        lengths = torch.zeros(B, dtype=torch.int64, device=device)
        rewards = torch.zeros(B, T, dtype=torch.float64, device=device)
        disc = torch.zeros(B, dtype=torch.int64, device=device)
        disc_sep = torch.zeros(B, dtype=torch.float64, device=device)
        rec = None
        if record_episode is not None and first <= record_episode < first + B:
            rec = (record_episode - first, [state.index(record_episode - first)])
        for t in range(T):
            velocity, heading = policy(cfg, state)
            state, res = step(cfg, state, velocity, heading)
            rewards[:, t] = torch.where(alive, res.reward.double(), 0.0)
            in_disc = alive & (res.discomfort_count > 0)
            disc += in_disc.long()
            disc_sep += torch.where(in_disc, res.min_separation.double(), 0.0)
            lengths += alive.long()
            ended = alive & (res.event != RUNNING)
            events = torch.where(ended, res.event, events)
            if rec is not None and bool(alive[rec[0]]):
                rec[1].append(state.index(rec[0]))
            alive = alive & ~ended
            if not bool(alive.any()):
                break
        for k, v in zip(records, (events, lengths, rewards, disc, disc_sep)):
            records[k].append(v)
        if rec is not None:
            trajectory = _trajectory(cfg, rec[1], EVENT_NAMES[int(events[rec[0]])])
        if progress is not None:
            progress(B)
    metrics = episode_metrics(
        torch.cat(records["events"]),
        torch.cat(records["lengths"]),
        torch.cat(records["rewards"]),
        torch.cat(records["disc"]),
        torch.cat(records["disc_sep"]),
        time_step=cfg.time_step,
        discount=discount_per_step(cfg.time_step, cfg.robot_v_pref),
    )
    return metrics, trajectory


def _trajectory(cfg: CrowdConfig, states: list[CrowdState], outcome: str) -> Trajectory:
    def arr(name: str) -> np.ndarray:
        return torch.stack([getattr(s, name) for s in states]).double().cpu().numpy()

    return Trajectory(
        robot_positions=arr("robot_position"),
        robot_goal=states[0].robot_goal.double().cpu().numpy(),
        robot_radius=cfg.robot_radius,
        human_positions=arr("human_position"),
        human_goals=arr("human_goal"),
        human_radius=cfg.human_radius,
        time_step=cfg.time_step,
        outcome=outcome,
        robot_headings=arr("robot_heading"),
    )
