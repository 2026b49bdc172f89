"""Episode metrics of the paper (``docs/mdp.md``, "Evaluation"), computed from per-step records."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import torch
from torch import Tensor

from crowdrl.sim.crowd import COLLISION, SUCCESS, TIMEOUT


def discount_per_step(time_step: float = 0.25, v_pref: float = 1.0, gamma: float = 0.9) -> float:
    """Upstream's per-step discount ``gamma ** (time_step * v_pref)`` (0.974 by default)."""
    return gamma ** (time_step * v_pref)


def average_returns(rewards: Tensor, lengths: Tensor, discount: float) -> Tensor:
    """Per episode, the mean over steps t of ``sum_k discount**k r_{t+k}``.

    ``rewards [E, T]`` (zero-padded after each episode's end), ``lengths [E]`` >= 1.
    """
    E, T = rewards.shape
    returns = torch.zeros_like(rewards)
    running = torch.zeros(E, dtype=rewards.dtype, device=rewards.device)
    for t in range(T - 1, -1, -1):
        running = rewards[:, t] + discount * running
        returns[:, t] = running
    steps = torch.arange(T, device=rewards.device).unsqueeze(0)
    inside = steps < lengths.unsqueeze(1)
    return (returns * inside).sum(1) / lengths.clamp_min(1).to(rewards.dtype)


@dataclass(frozen=True)
class EpisodeMetrics:
    """Aggregate metrics over a set of episodes."""

    episodes: int
    success_rate: float
    collision_rate: float
    timeout_rate: float
    navigation_time: float  # mean over successful episodes, seconds (nan if none)
    average_return: float
    discomfort_frequency: float  # steps with a human within the discomfort distance / all steps
    discomfort_min_separation: float  # mean min separation over those steps (nan if none)
    # per episode, in episode order: the final event code and the length in steps (what a ceiling is compared
    # with, crowdrl.evaluation.ceiling); empty for metrics read back from a record
    events: tuple[int, ...] = field(default=(), repr=False, compare=False)
    lengths: tuple[int, ...] = field(default=(), repr=False, compare=False)

    def as_dict(self) -> dict[str, float]:
        """The aggregate metrics (not the per-episode ``events`` and ``lengths``)."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("events", "lengths")}

    def summary(self) -> str:
        return (
            f"success {self.success_rate:.3f}  collision {self.collision_rate:.3f}  "
            f"timeout {self.timeout_rate:.3f}  nav time {seconds(self.navigation_time)}  "
            f"return {self.average_return:.4f}  discomfort {self.discomfort_frequency:.4f}  "
            f"({self.episodes} episodes)"
        )


def seconds(value: float | None) -> str:
    """A mean time for a console line: ``11.53 s``, or ``– (no case reached the goal)`` where it is undefined
    (``None`` read back from JSON, or NaN)."""
    return "– (no case reached the goal)" if value is None or math.isnan(value) else f"{value:.2f} s"


def episode_metrics(
    events: Tensor,
    lengths: Tensor,
    rewards: Tensor,
    discomfort_steps: Tensor,
    discomfort_separation_sum: Tensor,
    *,
    time_step: float,
    discount: float,
    timeout_penalty: float = -0.25,
) -> EpisodeMetrics:
    """Aggregate per-episode records into :class:`EpisodeMetrics`.

    ``events [E]`` final event codes, ``lengths [E]`` steps, ``rewards [E, T]`` zero-padded,
    ``discomfort_steps [E]`` and ``discomfort_separation_sum [E]`` per episode. Timeouts get
    ``timeout_penalty`` added to their last reward for the average return only (as upstream).
    """
    E = events.shape[0]
    if E == 0:
        raise ValueError("no episodes to aggregate")
    rewards = rewards.double().clone()
    timeout = events == TIMEOUT
    last = (lengths - 1).clamp_min(0)
    rewards[torch.arange(E), last] += torch.where(timeout, timeout_penalty, 0.0).double()
    success = events == SUCCESS
    returns = average_returns(rewards, lengths, discount)
    total_steps = int(lengths.sum())
    n_disc = int(discomfort_steps.sum())
    return EpisodeMetrics(
        episodes=E,
        success_rate=float(success.double().mean()),
        collision_rate=float((events == COLLISION).double().mean()),
        timeout_rate=float(timeout.double().mean()),
        navigation_time=float((lengths[success].double() * time_step).mean()) if bool(success.any()) else math.nan,
        average_return=float(returns.mean()),
        discomfort_frequency=n_disc / max(total_steps, 1),
        discomfort_min_separation=float(discomfort_separation_sum.double().sum()) / n_disc if n_disc else math.nan,
        events=tuple(events.tolist()),
        lengths=tuple(lengths.tolist()),
    )
