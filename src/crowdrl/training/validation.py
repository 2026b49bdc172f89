"""Validation of a run configuration: ``validate(cfg)`` turns a Hydra/OmegaConf tree, a dict of
overrides or a :class:`~crowdrl.training.config.RunConfig` into a checked ``RunConfig``, and every
refusal is a :class:`~crowdrl.training.config.ConfigError` naming the key and what is allowed."""

from __future__ import annotations

import dataclasses
import math
import re
from typing import Any

from omegaconf import DictConfig, OmegaConf

from crowdrl.models import ENCODERS
from crowdrl.models.predictor import PREDICTORS
from crowdrl.models.scan import SCAN_KINDS
from crowdrl.envs.mix import mix_rows
from crowdrl.schema import SchemaError, check_bools
from crowdrl.sim.config import MAX_HUMANS, ORCA_BACKENDS, SCENARIOS, CrowdConfig
from crowdrl.sim.kinematics import NUM_ACTIONS
from crowdrl.sim.rng import MAX_SEED
from crowdrl.training.config import (COUNTERFACTUAL_ACTIONS, COUNTERFACTUAL_MODES, LOGGERS, WANDB_MODES, ConfigError,
                                     RunConfig, crowd_config, crowd_range, trained_scenarios)
from crowdrl.training.resources import check_resources


def check(cond: bool, key: str, msg: str) -> None:
    """Raise :class:`ConfigError` ``"<key>: <msg>"`` unless ``cond``."""
    if not cond:
        raise ConfigError(f"{key}: {msg}")


def one_of(value: Any, key: str, allowed: tuple | list) -> None:
    """Raise :class:`ConfigError` naming ``key`` and the ``allowed`` values unless ``value`` is one of them.

    >>> one_of("csv", "logger.name", ("wandb", "csv"))
    >>> one_of("tensorboard", "logger.name", ("wandb", "csv"))
    Traceback (most recent call last):
        ...
    crowdrl.training.config.ConfigError: logger.name: got 'tensorboard'; allowed: wandb, csv
    """
    check(value in allowed, key, f"got {value!r}; allowed: {', '.join(map(str, allowed))}")


def validate(cfg: DictConfig | dict | RunConfig, *, resources: bool = True) -> RunConfig:
    """Check a config tree against the schema and the allowed values; return it typed.

    With ``resources`` (the default) also what the run would need of this machine's memory
    (:func:`~crowdrl.training.resources.check_resources`); a checkpoint's stored config is read with ``resources=False``."""
    if isinstance(cfg, RunConfig):
        cfg = OmegaConf.structured(cfg)
    schema = OmegaConf.structured(RunConfig)
    raw = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else cfg
    try:
        merged = OmegaConf.merge(schema, raw)
    except Exception as exc:  # omegaconf's messages name the key; keep them
        raise ConfigError(str(exc).splitlines()[0] + _hint(exc)) from None
    run: RunConfig = OmegaConf.to_object(merged)
    try:  # a bool key given 2 or "yes" (OmegaConf makes any integer a bool): refused, naming it
        check_bools(run, raw)
    except SchemaError as exc:
        raise ConfigError(str(exc)) from None
    for key, value in _floats(run):
        check(math.isfinite(value), key, f"must be a finite number, got {value}")
    e, t = run.env, run.train
    one_of(e.scenario, "env.scenario", SCENARIOS)
    check(1 <= e.num_humans <= MAX_HUMANS, "env.num_humans", f"must lie in 1..{MAX_HUMANS}, got {e.num_humans}")
    for key in ("min_humans", "max_humans"):
        value = getattr(e, key)
        check(value is None or 1 <= value <= MAX_HUMANS, f"env.{key}", f"must lie in 1..{MAX_HUMANS} or be null, got {value}")
    low, high = crowd_range(e)
    check(low <= high, "env.min_humans/env.max_humans",
          f"need min_humans <= max_humans, got {low} > {high} (each defaults to env.num_humans = {e.num_humans})")
    one_of(e.orca_backend, "env.orca_backend", ORCA_BACKENDS)
    try:  # the obstacle geometry, the lidar, the humans' model: CrowdConfig's checks, whose messages start with the key
        # the largest crowd too: an obstacle scenario refuses one its geometry cannot spawn reliably
        crowd = crowd_config(run)  # built once here: the checks below read it
    except ValueError as exc:
        raise ConfigError(f"env.{exc}") from None
    one_of(run.encoder.name, "encoder.name", sorted(ENCODERS))
    one_of(run.encoder.lidar, "encoder.lidar", SCAN_KINDS)
    check(run.encoder.lidar == "off" or e.lidar_rays >= 1, "encoder.lidar",
          f"({run.encoder.lidar}) reads the lidar scan, but env.lidar_rays is {e.lidar_rays} (no scan): "
          f"set env.lidar_rays (e.g. 72) or encoder.lidar=off")
    check_exploration(run)
    one_of(run.logger.name, "logger.name", LOGGERS)
    one_of(run.logger.mode, "logger.mode", WANDB_MODES)
    for key in ("num_envs", "steps_per_batch", "total_frames", "buffer_size", "batch_size", "n_step",
                "target_update_frames", "val_every_frames", "val_episodes", "checkpoint_every_frames", "test_episodes"):
        value = getattr(t, key)
        check(value >= 1, f"train.{key}", f"must be >= 1, got {value}")
    check(t.warmup_frames >= 0, "train.warmup_frames", f"must be >= 0, got {t.warmup_frames}")
    check(t.n_step <= t.steps_per_batch, "train.n_step",
          f"({t.n_step}) must not exceed train.steps_per_batch ({t.steps_per_batch}): windows end with the batch")
    check(t.batch_size <= t.buffer_size, "train.batch_size",
          f"({t.batch_size}) must not exceed train.buffer_size ({t.buffer_size})")
    check(0 < t.gamma <= 1, "train.gamma", f"must lie in (0, 1], got {t.gamma}")
    check(t.lr > 0, "train.lr", f"must be > 0, got {t.lr}")
    check(t.updates_per_frame >= 0, "train.updates_per_frame", f"must be >= 0, got {t.updates_per_frame}")
    check(0 < t.target_tau <= 1, "train.target_tau", f"must lie in (0, 1], got {t.target_tau}")
    for key in ("huber_delta", "grad_clip_norm"):
        value = getattr(t, key)
        check(value is None or value > 0, f"train.{key}", f"must be > 0 or null, got {value}")
    check(t.lr_end is None or 0 <= t.lr_end <= t.lr, "train.lr_end", f"must lie in [0, train.lr] or be null, got {t.lr_end}")
    check_counterfactual(run, crowd)
    check_demonstrations(run, crowd)
    p = run.planning
    check(p.depth >= 1, "planning.depth", f"must be >= 1, got {p.depth}")
    check(1 <= p.width <= NUM_ACTIONS, "planning.width", f"must lie in 1..{NUM_ACTIONS}, got {p.width}")
    one_of(p.predictor, "planning.predictor", PREDICTORS)
    check(p.lr > 0, "planning.lr", f"must be > 0, got {p.lr}")
    check(0 <= p.safety_horizon <= 20, "planning.safety_horizon", f"must lie in 0..20 (steps; 0: off), got {p.safety_horizon}")
    check(p.safety_horizon == 0 or p.enabled, "planning.safety_horizon",
          "checks the planner's actions: needs planning.enabled=true")
    check(not isinstance(p.progress_bias, bool) and isinstance(p.progress_bias, (int, float))
          and math.isfinite(p.progress_bias) and p.progress_bias >= 0, "planning.progress_bias",
          f"must be a finite number >= 0 (0: off), got {p.progress_bias!r}")
    check(p.progress_bias == 0 or p.enabled, "planning.progress_bias",
          "weights the planner's scores: needs planning.enabled=true")
    check_mix(run)
    check(0 <= run.seed <= MAX_SEED, "seed", f"must lie in 0..2**63-1 ({MAX_SEED}), got {run.seed}")
    check_threads(run.threads)
    check(t.updates_per_frame == 0 or t.total_frames > max(t.batch_size, t.warmup_frames), "train.total_frames",
          f"({t.total_frames}) must exceed train.batch_size ({t.batch_size}) and train.warmup_frames "
          f"({t.warmup_frames}): with this budget not a single update could run")
    check(run.resume is None or run.resume.strip() != "", "resume",
          "is empty (resume= with nothing after it, e.g. resume=$RUN with RUN unset): give the run folder to "
          "continue, resume=runs/<folder>, or leave resume out to start a new run")
    check(run.run_dir is None, "run_dir", f"is not used (got {run.run_dir!r}): choose the run folder with "
          f"hydra.run.dir=<folder> (train.py), out=<folder> (demo.py) or resume=<folder>")
    check_device(run.device)
    if resources:
        check_resources(run)
        check_logger(run)
    return run


def check_logger(run: RunConfig) -> None:
    """Refuse (naming ``logger.mode``) a wandb run to start online without credentials: wandb would
    fail, or wait for a key, once the run folder is written."""
    from crowdrl.training.scalars import has_wandb_credentials, wandb_mode

    if run.logger.name == "wandb" and wandb_mode(run.logger.mode) == "online" and not has_wandb_credentials():
        raise ConfigError("logger.mode: online, but wandb has no credentials (no WANDB_API_KEY, no netrc entry): "
                          "run `wandb login` first, or use logger.mode=offline and `wandb sync` later")


def check_exploration(run: RunConfig) -> None:
    """The exploration section, checked by the strategies that own its keys
    (:func:`crowdrl.exploration.strategy.check_exploration`); :class:`ConfigError` naming ``exploration.<key>``."""
    from crowdrl.exploration.strategy import Limits
    from crowdrl.exploration.strategy import check_exploration as check_section

    try:
        check_section(run.exploration, Limits(batch_size=run.train.batch_size, gamma=run.train.gamma))
    except ValueError as exc:
        raise ConfigError(f"exploration.{exc}") from None


def check_counterfactual(run: RunConfig, humans: CrowdConfig) -> None:
    """``train.counterfactual``'s keys; it needs ``humans`` (the run's crowd config) that ignore the robot
    (their real next state is then the next state after any action) and the unicycle's discrete actions."""
    c = run.train.counterfactual
    one_of(c.mode, "train.counterfactual.mode", COUNTERFACTUAL_MODES)
    one_of(c.actions, "train.counterfactual.actions", COUNTERFACTUAL_ACTIONS)
    check(isinstance(c.k, int) and 1 <= c.k <= NUM_ACTIONS, "train.counterfactual.k",
          f"must be an integer in 1..{NUM_ACTIONS}, got {c.k!r}")
    check(0 <= c.weight <= 1, "train.counterfactual.weight", f"must lie in [0, 1], got {c.weight}")
    if c.mode != "off" and humans.humans_react_to_robot:
        who = " and ".join(m for m in humans.human_models_present if m != "linear")
        raise ConfigError(f"train.counterfactual.mode: counterfactual experience replays the humans' real next state "
                          f"after another action, which is exact only while they ignore the robot; with "
                          f"env.robot_visible=true the {who} humans react to it (set "
                          f"learner=plain, train.counterfactual.mode=off or env.robot_visible=false)")


MAX_DEMO_WIDTH = 2048  # the ceiling's widest default beam: wider ones hold chunk x width x 81 children a depth


def check_demonstrations(run: RunConfig, crowd: CrowdConfig) -> None:
    """``train.demonstrations``: a case count in ``0..train.buffer_size`` (0: off; a case stores at least one
    transition, so more cases than slots would overwrite each other), increasing beam widths in
    ``1..MAX_DEMO_WIDTH``; on, it needs humans that ignore the robot (the oracle knows a case's crowd in
    advance only then; ``crowd``: the run's crowd config)."""
    d, t = run.train.demonstrations, run.train
    check(isinstance(d.cases, int) and not isinstance(d.cases, bool) and 0 <= d.cases <= t.buffer_size,
          "train.demonstrations.cases", f"must be an integer in 0..train.buffer_size ({t.buffer_size}; 0: off), "
          f"got {d.cases!r}")
    widths = list(d.widths)
    check(len(widths) > 0 and all(isinstance(w, int) and not isinstance(w, bool) and 1 <= w <= MAX_DEMO_WIDTH
                                  for w in widths), "train.demonstrations.widths",
          f"must be a non-empty list of integers in 1..{MAX_DEMO_WIDTH}, got {widths!r}")
    check(widths == sorted(set(widths)), "train.demonstrations.widths", f"must increase, got {widths!r}")
    if d.cases > 0:
        check(not crowd.humans_react_to_robot, "train.demonstrations.cases",
              "the oracle solves a case only when its crowd is known in advance, i.e. the humans ignore the robot; "
              "set env.robot_visible=false or train.demonstrations.cases=0")


def check_mix(run: RunConfig) -> None:
    """``env.mix`` (one agent for several scenarios): known scenarios, proportions >= 0 not all 0, a row of
    ``train.num_envs`` and of ``train.val_episodes`` for each, every scenario's crowd buildable, ``env.scenario``
    among them (tests default to it), and no oracle demonstrations (they search one scenario's cases)."""
    e, t = run.env, run.train
    if not e.mix:
        return
    try:
        mix_rows(e.mix, t.num_envs)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    try:
        mix_rows(e.mix, t.val_episodes)
    except ValueError:
        raise ConfigError(f"train.val_episodes ({t.val_episodes}) leaves a scenario of env.mix without a validation "
                          "case; raise it") from None
    names = trained_scenarios(run)
    check(e.scenario in names, "env.scenario", f"({e.scenario}) must be one of env.mix's scenarios ({', '.join(names)}): "
          "tests and evaluations default to it")
    for name in names:
        try:
            crowd_config(run, scenario=name)
        except ValueError as exc:
            raise ConfigError(f"env.{exc} (scenario {name} of env.mix)") from None
    check(run.train.demonstrations.cases == 0, "train.demonstrations.cases",
          "oracle demonstrations search one scenario's cases; leave them off (0) with env.mix")


def check_threads(threads: Any, key: str = "threads") -> None:
    """An integer >= 1 (torch threads), otherwise a :class:`ConfigError` naming ``key``."""
    check(isinstance(threads, int) and not isinstance(threads, bool) and threads >= 1, key,
          f"must be an integer >= 1, got {threads!r}")


def check_device(device: str, key: str = "device") -> None:
    """``cpu``, or a CUDA device that exists on this machine; otherwise a :class:`ConfigError`."""
    import torch

    check(device == "cpu" or re.fullmatch(r"cuda(:\d+)?", device) is not None, key,
          f"got {device!r}; allowed: cpu, cuda, cuda:<index>")
    if device.startswith("cuda"):
        check(torch.cuda.is_available(), key, f"{device!r} requested but CUDA is not available on this machine "
                                              f"(torch.cuda.is_available() is False); use {key}=cpu")
        index = int(device.split(":")[1]) if ":" in device else 0
        count = torch.cuda.device_count()
        check(index < count, key, f"{device!r} does not exist: this machine has {count} CUDA device(s)")


def _floats(node: Any, prefix: str = "") -> list[tuple[str, float]]:
    """Every float field of a (nested) config dataclass, with its dotted key."""
    out = []
    for f in dataclasses.fields(node):
        value, key = getattr(node, f.name), f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            out += _floats(value, f"{key}.")
        elif isinstance(value, float):
            out.append((key, value))
    return out


def keys_beside(key: str) -> list[str]:
    """The run config's keys at the level of the dotted ``key`` (its parent section's fields), what a
    misspelt key could have meant; empty when that parent is not a section.

    >>> keys_beside("train.lrr")[:3]
    ['train.num_envs', 'train.steps_per_batch', 'train.total_frames']
    """
    parent = key.rsplit(".", 1)[0] if "." in key else ""
    node: Any = RunConfig()
    for part in filter(None, parent.split(".")):
        node = getattr(node, part, None)
    if not dataclasses.is_dataclass(node):
        return []
    return [f"{parent}.{f.name}" if parent else f.name for f in dataclasses.fields(node)]


def _hint(exc: Exception) -> str:
    key = getattr(exc, "full_key", None)
    if not key:
        return ""
    beside = [k.rsplit(".", 1)[-1] for k in keys_beside(key)]
    return f" (key {key!r}; allowed keys here: {', '.join(beside)})" if beside else f" (key {key!r})"
