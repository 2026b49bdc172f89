"""The typed settings of a reproduction: the schema of ``conf/reproduce.yaml``.

``crowdrl-reproduce`` registers :class:`ReproduceConfig` in Hydra's ConfigStore (``reproduce_schema``,
the first entry of ``conf/reproduce.yaml``'s defaults list), so Hydra refuses an unknown key or a
value of the wrong type naming it; :func:`crowdrl.reproduction.plan.make_plan` reads a settings dict
into it (:func:`crowdrl.schema.read_typed`: a key added with ``+`` is refused too) and checks the
values (allowed names, ranges).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import List

from omegaconf import MISSING

from crowdrl.training.config import CounterfactualConfig


@dataclass
class ReproduceConfig:
    """One reproduction's settings; the defaults are ``conf/reproduce.yaml``'s (``out`` comes from it:
    ``results/<budget>`` plus the planning and counterfactual suffixes)."""

    budget: str = "smoke"  # conf/preset/<budget>.yaml: the budget every run trains with
    encoders: List[str] = field(default_factory=lambda: ["sgd3qn"])  # each variant is trained with each encoder
    variants: List[str] = field(default_factory=lambda: ["egreedy", "noisy", "dropout", "icm", "re3"])
    seeds: List[int] = field(default_factory=lambda: [0, 1, 2])
    train_scenario: str = "circle"
    scenarios: List[str] = field(default_factory=lambda: ["circle", "square"])  # test scenarios
    episodes: int = 1000  # test cases per scenario (test seed 0), also for ORCA
    jobs: int = 2  # runs at a time on this machine (launcher=local)
    launcher: str = "local"  # local | slurm
    threads: int = 1  # torch threads per run
    reps: int = 2000  # bootstrap resamples for the confidence intervals
    planning: bool = True  # every run acts with SG-D3QN's online planning (planning.enabled)
    counterfactual: CounterfactualConfig = field(default_factory=CounterfactualConfig)  # every run's train.counterfactual
    out: str = MISSING  # the results folder


__all__ = ["ReproduceConfig"]
