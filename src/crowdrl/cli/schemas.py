"""The typed Hydra schemas of ``evaluate`` and ``export``: the keys each command reads, their types
and defaults (those of ``conf/evaluate.yaml`` and ``conf/export.yaml``, each composed onto its schema).

Each command registers its schema in Hydra's ConfigStore (``evaluate_schema``, ``export_schema``),
the first entry of its config's defaults list, as ``train`` does with
:class:`crowdrl.training.config.RunConfig` (``run_schema``): Hydra then refuses an unknown key or a
value of the wrong type (``eval.episodes=abc``, ``opset=abc``, ``check=maybe``) naming it, and the
command reads the composed config with :func:`crowdrl.schema.read_typed`, which refuses a key added
with ``+``. Ranges and allowed names are checked by the commands. ``reproduce``'s schema is
:class:`crowdrl.reproduction.config.ReproduceConfig` (:func:`crowdrl.reproduction.plan.make_plan` reads it).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from crowdrl.training.config import EVAL_BATCH, EnvConfig


@dataclass
class EvalConfig:
    """``eval.*``: the test cases and the crowd they are played with."""

    seed: int = 0  # test stream seed
    episodes: int = 1000
    num_humans: Optional[int] = None  # default: the checkpoint's (10 for a baseline)
    human_model: Optional[str] = None  # orca | social_force | linear | mixed (default: the checkpoint's; orca for a baseline)
    robot_visible: Optional[bool] = None  # default: the checkpoint's; false for a baseline
    # a mixed crowd's shares (human_model=mixed; ORCA the rest); null: 0 when eval.human_model is given, else the checkpoint's
    social_force_share: Optional[float] = None
    linear_share: Optional[float] = None
    batch: int = EVAL_BATCH  # episodes stepped at once (results do not depend on it)
    record_episode: Optional[int] = 0  # PNG + GIF of this test case (null: none)
    # a ceiling file of the same cases (experiments/ceiling.py): adds avoidable / unavoidable failures and the time
    # over the ceiling to the record
    ceiling: Optional[str] = None
    # act with another planner than the checkpoint's (no retraining; null: the checkpoint's): its depth (0: planning
    # off, greedy on Q), width, run-time safety check (planning.safety_horizon) and progress bias (planning.progress_bias)
    planning_depth: Optional[int] = None
    planning_width: Optional[int] = None
    planning_safety_horizon: Optional[int] = None
    planning_progress_bias: Optional[float] = None


@dataclass
class EvaluateEnvConfig(EnvConfig):
    """``env``: the ``env`` group's keys (``conf/env/<scenario>.yaml``, typed as the run config's
    :class:`~crowdrl.training.config.EnvConfig`), of which evaluate reads ``scenario`` only. It is
    ``None`` (the checkpoint's scenario; circle for a baseline) unless ``env=<scenario>`` selects a file."""

    scenario: Optional[str] = None


@dataclass
class EvaluateConfig:
    """``evaluate``'s config. ``env`` is the ``env`` group (:class:`EvaluateEnvConfig`); the command
    reads only ``env.scenario`` and refuses an override of any other ``env.*`` key (the crowd is ``eval.*``)."""

    checkpoint: Optional[str] = None  # a run folder (its checkpoints/best.pt) or a .pt file
    policy: Optional[str] = None  # a baseline instead of a checkpoint: orca
    env: EvaluateEnvConfig = field(default_factory=EvaluateEnvConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    threads: int = 1
    device: str = "cpu"


@dataclass
class ExportConfig:
    """``export``'s config (``docs/export.md``)."""

    checkpoint: Optional[str] = None  # a run folder (its checkpoints/best.pt) or a .pt file; required
    out: Optional[str] = "policy.onnx"  # the file to write (relative to the current directory); required
    format: str = "onnx"  # crowdrl.export.FORMATS
    opset: int = 17  # ONNX opset of the model, 14..20
    check: bool = True  # run the written model with onnxruntime and compare its Q values with torch's
    overwrite: bool = False  # replace an existing `out` file (refused otherwise)
    # the exported planner's settings (null: the checkpoint's); planning_depth=0 exports a planning checkpoint's
    # greedy Q policy alone (it acts differently; labelled in the model's metadata)
    planning_depth: Optional[int] = None
    planning_width: Optional[int] = None
    planning_safety_horizon: Optional[int] = None
    planning_progress_bias: Optional[float] = None


@dataclass
class CeilingConfig:
    """``ceiling``'s config (:mod:`crowdrl.cli.ceiling`): the stream, the search's settings, the file written.
    ``env`` is the ``env`` group (the crowd; ``robot_visible`` must be false)."""

    env: EnvConfig = field(default_factory=EnvConfig)
    split: str = "test"  # train | val | test
    seed: int = 0  # the stream's seed
    cases: int = 1000  # cases 0 .. cases-1
    widths: list[int] = field(default_factory=lambda: [64, 512, 2048])  # beam widths, each on the cases still unsolved
    cell: float = 0.125  # m, the relaxed time grid's cell (the beam's ranking)
    horizon: int = 3  # steps of the exhaustive search that proves a case infeasible (3 = 0.75 s)
    chunk: int = 50  # cases searched at once
    replay: bool = True  # step every solved path through CrowdNavEnv and refuse the file on a disagreement
    out: Optional[str] = None  # the JSON to write (default: ceiling-<scenario>-<split>-seed<seed>-<cases>.json)
    overwrite: bool = False  # replace an existing `out` file (refused otherwise)
    # the exported planner's settings (null: the checkpoint's); planning_depth=0 exports a planning checkpoint's
    # greedy Q policy alone (it acts differently; labelled in the model's metadata)
    planning_depth: Optional[int] = None
    planning_width: Optional[int] = None
    planning_safety_horizon: Optional[int] = None
    planning_progress_bias: Optional[float] = None
    threads: int = 1


__all__ = ["CeilingConfig", "EvalConfig", "EvaluateConfig", "EvaluateEnvConfig", "ExportConfig"]
