"""Metrics and batched evaluation of any TorchRL policy on fixed scenario streams."""

from crowdrl.evaluation.metrics import EpisodeMetrics, average_returns, discount_per_step, episode_metrics
from crowdrl.evaluation.rollout import crowd_env_of, episode_records, evaluate
from crowdrl.evaluation.baseline import evaluate_orca
from crowdrl.evaluation.trajectory import Trajectory

__all__ = [
    "EpisodeMetrics",
    "Trajectory",
    "average_returns",
    "crowd_env_of",
    "discount_per_step",
    "episode_metrics",
    "episode_records",
    "evaluate",
    "evaluate_orca",
]
