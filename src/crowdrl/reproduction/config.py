"""The typed settings of a reproduction: the schema of ``conf/reproduce.yaml``.

``crowdrl-reproduce`` registers :class:`ReproduceConfig` in Hydra's ConfigStore (``reproduce_schema``,
the first entry of ``conf/reproduce.yaml``'s defaults list), so Hydra refuses an unknown key or a
value of the wrong type naming it; :func:`crowdrl.reproduction.plan.make_plan` reads a settings dict
into it (:func:`crowdrl.schema.read_typed`: a key added with ``+`` is refused too) and checks the
values (allowed names, ranges).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Optional

from omegaconf import MISSING

from crowdrl.training.config import TrainConfig


@dataclass
class LearnerCounterfactualConfig:
    """Every run's ``train.counterfactual``: ``train.py``'s keys and meanings; ``mode`` null takes the
    learner's (:attr:`ReproduceConfig.train_learner`)."""

    mode: Optional[str] = None  # off | second_update | merged (null: the learner's)
    actions: str = "topk"
    k: int = 5
    weight: float = 0.5


@dataclass
class LeverConfig:
    """The stability levers every run of a reproduction trains with: ``train.py``'s ``train.*`` keys of
    the same names and meanings; ``target_tau`` null takes the learner's (0.005 recommended, 1.0 hard
    copies), the others are off by default. A manifest written before this section ran with every lever
    off (``LEVERS_OFF``)."""

    target_tau: Optional[float] = None  # Polyak target updates after every update (1: hard copies; null: the learner's)
    huber_delta: Optional[float] = TrainConfig.huber_delta  # a Huber loss of this delta (null: squared error)
    grad_clip_norm: Optional[float] = TrainConfig.grad_clip_norm  # the Q gradients' norm clipped (null: not)
    lr_end: Optional[float] = TrainConfig.lr_end  # the learning rate decayed linearly to this (null: constant)
    q_layer_norm: bool = TrainConfig.q_layer_norm  # LayerNorm in the Q head's hidden layers


@dataclass
class ReproduceConfig:
    """One reproduction's settings; the defaults are ``conf/reproduce.yaml``'s (``out`` comes from it:
    ``results/<budget>`` plus the planning, counterfactual and Polyak suffixes: the learner that ran)."""

    budget: str = "smoke"  # conf/preset/<budget>.yaml: the budget every run trains with
    encoders: List[str] = field(default_factory=lambda: ["sgd3qn"])  # each variant is trained with each encoder
    variants: List[str] = field(default_factory=lambda: ["egreedy", "noisy", "dropout", "icm", "re3"])
    seeds: List[int] = field(default_factory=lambda: [0, 1, 2])
    train_scenario: str = "circle"  # or mix: every scenario in one batch (conf/env/mix.yaml)
    scenarios: List[str] = field(default_factory=lambda: ["circle", "square"])  # test scenarios
    episodes: int = 1000  # test cases per scenario (test seed 0), also for ORCA
    jobs: int = 2  # runs at a time on this machine (launcher=local)
    launcher: str = "local"  # local | slurm
    threads: int = 1  # torch threads per run
    reps: int = 2000  # bootstrap resamples for the confidence intervals
    planning: bool = True  # every run acts with SG-D3QN's online planning (planning.enabled)
    # every run's network reads the lidar scan (encoder.lidar: off | mlp | conv) of lidar_rays rays (env.lidar_rays)
    lidar: str = "off"
    lidar_rays: int = 72
    # every run's learner (conf/learner/): recommended | paper | plain; null: the budget preset's (paper for
    # budget=paper, else recommended); counterfactual.* and train.* below set its keys one by one
    train_learner: Optional[str] = None
    counterfactual: LearnerCounterfactualConfig = field(default_factory=LearnerCounterfactualConfig)  # train.counterfactual
    train: LeverConfig = field(default_factory=LeverConfig)  # every run's stability levers (train.target_tau, ...)
    # a folder of ceiling files <scenario>.json (experiments/ceiling.py, test seed 0, `episodes` cases): the table adds
    # each method's failures where a path exists and its time over the ceiling, and a ceiling row (null: none)
    ceiling: Optional[str] = None
    out: str = MISSING  # the results folder


__all__ = ["LearnerCounterfactualConfig", "LeverConfig", "ReproduceConfig"]
