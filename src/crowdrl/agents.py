"""Any agent on test cases, by path or by name: a trained checkpoint (a run folder or ``.pt``), an exported
ONNX model, or a baseline (``orca``), evaluated through the one rollout path with the same ``eval.json``
record (:func:`evaluate_spec`, what ``evaluate.py`` runs); an exported model against its checkpoint
(:func:`compare_on_test_cases`).

It sits above training and export: it loads what they write and runs it, and neither imports it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from crowdrl.evaluation import Trajectory, evaluate
from crowdrl.evaluation.report import eval_record
from crowdrl.sim.config import MIXED, SHARE_KEYS, CrowdConfig
from crowdrl.training.checkpoint import checkpoint_path, load_trained_network, load_trained_predictor
from crowdrl.training.config import EVAL_BATCH, RunConfig
from crowdrl.training.config import crowd_config, trained_on
from crowdrl.training.factories import make_actor, make_env
from crowdrl.training.pipeline import TEST_SEED, act_with, evaluate_network, policy_name

BASELINES = ("orca",)


def _eval_crowd(scenario: str, humans: dict[str, Any], *, given: bool = True) -> CrowdConfig:
    """The evaluation's crowd constants with the humans' keys of ``eval.*`` (``given``) or a checkpoint's own
    humans (not ``given``: then ``scenario`` is the ``env=`` asked for), refused naming the key to change."""
    try:
        return CrowdConfig(scenario=scenario, **humans)
    except ValueError as exc:
        if given:
            raise ValueError(f"eval.{exc}") from None
        raise ValueError(f"env={scenario}: the checkpoint's humans (trained with env.human_model={humans['human_model']}"
                         f") cannot run there: {exc}; evaluate it there with other humans: eval.human_model=<model>"
                         ) from None


def is_onnx(checkpoint: Path | str | None) -> bool:
    """Whether ``checkpoint`` names an exported ONNX model (a ``.onnx`` file) rather than a checkpoint."""
    return checkpoint is not None and str(checkpoint).lower().endswith(".onnx")


def acted(run: RunConfig, key: str) -> float:
    """The planner setting ``key`` (of :data:`ACT_KEYS`) ``run`` acts with, for a record: 0 for ``depth`` and
    ``safety_horizon`` (0.0 for ``progress_bias``) when it acts without planning."""
    if run.planning.enabled or key == "width":
        return getattr(run.planning, key)
    return 0.0 if key == "progress_bias" else 0


def _read_ceiling(path: Path | str | None, cfg: CrowdConfig, seed: int, episodes: int):
    """The ceiling file ``path`` if given, checked to label test cases ``0 .. episodes-1`` of ``seed`` under ``cfg``."""
    if path is None:
        return None
    from crowdrl.evaluation.ceiling import check_stream, read_ceiling

    try:
        labels = read_ceiling(path)
        check_stream(labels, cfg, split="test", seed=seed, cases=episodes)
    except ValueError as exc:
        raise ValueError(f"eval.ceiling: {exc}") from None
    return labels


def _gap_fields(labels, path: Path | str | None, metrics) -> dict[str, Any]:
    """The record's gap to the ceiling (none without one)."""
    if labels is None:
        return {}
    from crowdrl.evaluation.ceiling import gap

    return {**gap(labels, metrics.events, metrics.lengths), "ceiling": str(path)}


def _humans_shown(humans: dict[str, Any]) -> dict[str, Any]:
    """The humans' keys an ``eval.json`` record shows: the model and visibility, and a mixed crowd's shares."""
    shown = {"human_model": humans["human_model"], "robot_visible": humans["robot_visible"]}
    if humans["human_model"] == MIXED:
        shown.update({k: humans[k] for k in SHARE_KEYS})
    return shown


def evaluate_spec(*, checkpoint: Path | str | None = None, policy: str | None = None, scenario: str | None = None,
                  seed: int = TEST_SEED, episodes: int = 1000, num_humans: int | None = None, batch: int = EVAL_BATCH,
                  record_episode: int | None = None, device: str = "cpu", human_model: str | None = None,
                  robot_visible: bool | None = None, social_force_share: float | None = None,
                  linear_share: float | None = None, ceiling: Path | str | None = None,
                  planning: dict[str, float | None] | None = None) -> tuple[dict[str, Any], Trajectory | None]:
    """Evaluate a trained ``checkpoint`` (run folder or ``.pt``) or a baseline ``policy`` by name on
    test cases ``0 .. episodes-1`` of test stream ``seed``; returns the ``eval.json`` record and the
    recorded trajectory. ``human_model``/``robot_visible`` (``None``: the checkpoint's; ORCA humans blind to
    the robot for a baseline) change how the humans move; ``social_force_share``/``linear_share``: a mixed
    crowd's shares (``None``: 0 where ``human_model`` is given, else the checkpoint's; a share other than 0
    needs ``human_model="mixed"``, given or the checkpoint's). Bad names and values raise ``ValueError`` naming
    the argument. ``ceiling``: a ceiling file of the same test cases (:mod:`crowdrl.evaluation.ceiling`); the
    record then adds the avoidable and unavoidable failures and the time over the ceiling (a file of another
    stream is refused before anything runs, naming the mismatch). ``planning``: act with these of the
    checkpoint's planner settings changed (``depth``, ``width``, ``safety_horizon``, ``progress_bias``; no
    retraining; ``depth`` 0: greedy on Q, planning off); the record then shows them. A ``checkpoint`` ending in
    ``.onnx`` is a model written by ``crowdrl-export``, evaluated through onnxruntime (:class:`~crowdrl.onnx_policy.OnnxPolicy`)
    on the same cases and through the same rollout, with the same record (its policy name ending in ``+onnx``);
    its planning is fixed at export (``planning`` refused), and it runs on the CPU."""
    from dataclasses import replace

    from crowdrl.evaluation import evaluate_orca
    from crowdrl.evaluation.rollout import kept_bytes
    from crowdrl.sim.config import MAX_HUMANS, SCENARIOS
    from crowdrl.sim.rng import MAX_SEED
    from crowdrl.training.resources import available_memory, planned_states, planner_bytes

    if (checkpoint is None) == (policy is None):
        raise ValueError("give exactly one of checkpoint=PATH or policy=NAME")
    if policy is not None and policy not in BASELINES:
        raise ValueError(f"policy: unknown baseline {policy!r}; allowed: {', '.join(BASELINES)}")
    if scenario is not None and scenario not in SCENARIOS:
        raise ValueError(f"env: unknown scenario {scenario!r}; allowed: {', '.join(SCENARIOS)}")
    for name, value, low in (("eval.episodes", episodes, 1), ("eval.seed", seed, 0), ("eval.batch", batch, 1)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(f"{name}: must be an integer >= {low}, got {value!r}")
    if seed > MAX_SEED:  # never reduced modulo 2**64 (seed 5 + 2**64 would replay seed 5's cases)
        raise ValueError(f"eval.seed: must lie in 0..2**63-1 ({MAX_SEED}), got {seed}")
    if num_humans is not None and not (isinstance(num_humans, int) and not isinstance(num_humans, bool)
                                       and 1 <= num_humans <= MAX_HUMANS):
        raise ValueError(f"eval.num_humans: must be an integer in 1..{MAX_HUMANS} or null, got {num_humans!r}")
    if record_episode is not None and not (isinstance(record_episode, int) and 0 <= record_episode < episodes):
        raise ValueError(f"eval.record_episode: must lie in 0..{episodes - 1} or be null, got {record_episode!r}")
    humans = {k: v for k, v in (("human_model", human_model), ("robot_visible", robot_visible),
                                ("social_force_share", social_force_share), ("linear_share", linear_share))
              if v is not None}
    if human_model is not None:  # another model: the shares are the ones given (none: 0), not the checkpoint's
        humans = {**{k: getattr(CrowdConfig, k) for k in SHARE_KEYS}, **humans}
    # the metrics keep a row per episode: refuse a count whose records would not fit in memory
    max_steps = max(CrowdConfig(scenario=s).max_steps for s in ([scenario] if scenario else SCENARIOS))
    kept, free = kept_bytes(episodes, max_steps), available_memory(device if device.startswith("cuda") else "cpu")
    if free is not None and kept > free:
        raise ValueError(f"eval.episodes: {episodes} episodes keep ~{kept / 2**30:,.1f} GiB of per-episode records "
                         f"(up to {max_steps} rewards each), more than the {free / 2**30:,.1f} GiB of memory available; "
                         f"lower eval.episodes (another eval.seed gives other cases)")
    acting = {k: v for k, v in (planning or {}).items() if v is not None}
    if policy == "orca" and acting:
        raise ValueError(f"eval.planning_{next(iter(acting))}: the ORCA baseline has no planner")
    if policy == "orca":
        cfg = _eval_crowd(scenario or "circle", humans)
        cfg = replace(cfg, num_humans=num_humans or cfg.num_humans)
        labels = _read_ceiling(ceiling, cfg, seed, episodes)
        metrics, traj = evaluate_orca(cfg, seed=seed, episodes=episodes, batch=batch, device=device,
                                      record_episode=record_episode)
        shown = _humans_shown(vars(cfg)) if humans else {}
        return eval_record(metrics, scenario=cfg.scenario, seed=seed, policy="orca", **shown,
                           **_gap_fields(labels, ceiling, metrics)), traj
    exported = None
    if is_onnx(checkpoint):  # an exported policy, evaluated through onnxruntime
        from crowdrl.export import read_exported

        if device != "cpu":
            raise ValueError(f"device: an ONNX model ({checkpoint}) is evaluated on the CPU through onnxruntime; "
                             f"got {device!r}")
        exported = read_exported(checkpoint)
        if acting:
            key = next(iter(acting))
            m = exported.metadata
            raise ValueError(f"eval.planning_{key}: {checkpoint}'s planning is fixed at export (planning_depth="
                             f"{m.get('crowdrl.planning_depth', 0)}, planning_width={m.get('crowdrl.planning_width', 0)}, "
                             f"planning_safety_horizon={m.get('crowdrl.planning_safety_horizon', 0)}, "
                             f"planning_progress_bias={m.get('crowdrl.planning_progress_bias', 0.0)}); export it again "
                             f"with planning_{key}=..., or evaluate the checkpoint")
        run, net, data = exported.run, None, {"frames": exported.frames}
    else:
        run, net, data = load_trained_network(checkpoint)
    if device != run.device:
        run = replace(run, device=device)
    if humans or scenario is not None:  # the checkpoint's humans, with those given, in the scenario asked for
        trained = {k: getattr(run.env, k) for k in ("human_model", *SHARE_KEYS)}
        _eval_crowd(scenario or run.env.scenario, trained | humans, given=bool(humans))
    if acting:  # checked against the run as it trained: the humans' change below is the test's, not training's
        run = act_with(run, acting)
    if humans:
        run = replace(run, env=replace(run.env, **humans))
    planner, free = planner_bytes(run, min(episodes, batch)), available_memory(device)
    if free is not None and planner > free:
        raise ValueError(f"eval.batch: the planner of {checkpoint} expands {planned_states(run, min(episodes, batch))} "
                         f"states per step at {min(episodes, batch)} episodes at once, ~{planner / 2**30:,.1f} GiB, more "
                         f"than the {free / 2**30:,.1f} GiB of memory available; lower eval.batch")
    labels = _read_ceiling(ceiling, crowd_config(run, scenario=scenario, num_humans=num_humans), seed, episodes)
    scenario = scenario or run.env.scenario
    if exported is not None:
        from crowdrl.onnx_policy import OnnxPolicy

        env = make_env(run, split="test", num_envs=min(episodes, batch), seed=seed, scenario=scenario,
                       num_humans=num_humans)
        acting_policy = OnnxPolicy(exported, threads=torch.get_num_threads())
        acting_policy.check_env(env)
        metrics, traj = evaluate(env, acting_policy, num_episodes=episodes, record_episode=record_episode)
        path = exported.path
    else:
        net.to(device)
        predictor = load_trained_predictor(run, data, checkpoint_path(checkpoint))
        if predictor is not None:
            predictor.to(device)
        metrics, traj = evaluate_network(run, net, scenario=scenario, seed=seed, episodes=episodes,
                                         num_humans=num_humans, record_episode=record_episode, batch=batch,
                                         predictor=predictor)
        path = checkpoint_path(checkpoint)
    record = eval_record(metrics, scenario=scenario, seed=seed, policy=policy_name(run, onnx=exported is not None),
                         checkpoint=str(path), checkpoint_frames=data.get("frames"),
                         train_scenario=trained_on(run), train_seed=run.seed,
                         **({f"planning_{k}": acted(run, k) for k in acting}),
                         **(_humans_shown(vars(run.env)) if humans else {}), **_gap_fields(labels, ceiling, metrics))
    return record, traj


def compare_on_test_cases(checkpoint: Path | str, model: Path | str, *, scenario: str | None = None, seed: int = 0,
                          episodes: int = 1000, batch: int = 1000, threads: int = 1) -> dict:
    """The torch checkpoint (acting with the model's planner settings) and its exported ``model`` on test cases
    ``0 .. episodes-1`` of ``scenario`` (the checkpoint's by default): both evaluation records (the model's
    through ``evaluate.py``'s path, :func:`evaluate_spec`) and, along the torch
    policy's own trajectories, the steps where the model's action is identical (``identical``), differs by
    float rounding (``rounding``) or otherwise (``differ``), of ``steps`` acted in running episodes."""
    from crowdrl.export import planner_settings
    from crowdrl.onnx_policy import ComparedPolicy, OnnxPolicy

    exported = OnnxPolicy(model, threads=threads)
    run, net, data = load_trained_network(checkpoint)
    settings = planner_settings(exported.model.metadata) if exported.model.plans else {}
    if exported.model.plans and not run.planning.enabled:
        raise ValueError(f"model: {exported.model.path} holds a planner, {checkpoint_path(checkpoint)} acts without "
                         "one: not its export")
    # the torch policy acts with the model's planner settings (a planning_* export; depth 0: greedy on Q)
    run = act_with(run, settings if exported.model.plans else {"depth": 0}, prefix="model planning_")
    scenario = scenario or run.env.scenario
    env = make_env(run, split="test", num_envs=min(episodes, batch), seed=seed, scenario=scenario)
    exported.check_env(env, scenario_key="scenario")
    compared = ComparedPolicy(make_actor(run, env, net, load_trained_predictor(run, data, checkpoint_path(checkpoint))),
                              exported)
    metrics, _ = evaluate(env, compared, num_episodes=episodes)
    torch_record = eval_record(metrics, scenario=scenario, seed=seed, policy=f"{run.encoder.name}+{run.exploration.name}"
                               + ("+planning" if run.planning.enabled else ""))
    onnx_record, _ = evaluate_spec(checkpoint=model, scenario=scenario, seed=seed, episodes=episodes, batch=batch,
                                   record_episode=None)
    c = compared
    return {"scenario": scenario, "episodes": episodes, "seed": seed, "torch": torch_record, "onnx": onnx_record,
            "steps": c.steps, "identical": c.identical, "rounding": c.rounding,
            "differ": c.steps - c.identical - c.rounding}


__all__ = ["BASELINES", "acted", "compare_on_test_cases", "evaluate_spec", "is_onnx"]
