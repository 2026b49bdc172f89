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


__all__ = ["EvalConfig", "EvaluateConfig", "EvaluateEnvConfig", "ExportConfig"]
