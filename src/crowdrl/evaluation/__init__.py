"""Metrics and batched evaluation on fixed scenario streams."""

from crowdrl.evaluation.metrics import EpisodeMetrics, average_returns, discount_per_step, episode_metrics
from crowdrl.evaluation.rollout import DiscreteActionPolicy, RobotPolicy, evaluate_policy

__all__ = [
    "EpisodeMetrics",
    "average_returns",
    "discount_per_step",
    "episode_metrics",
    "DiscreteActionPolicy",
    "RobotPolicy",
    "evaluate_policy",
]
