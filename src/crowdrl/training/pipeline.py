"""A whole run: train, then evaluate the best checkpoint on the test cases and render it."""

from __future__ import annotations

import json
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable

from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

import torch
from filelock import FileLock, Timeout

from crowdrl.evaluation import EpisodeMetrics, Trajectory, evaluate
from crowdrl.evaluation.report import eval_record, write_records
from crowdrl.files import atomic_write_json, remove_stale_temporaries
from crowdrl.sim.config import MIXED, SHARE_KEYS, CrowdConfig
from crowdrl.training.checkpoint import checkpoint_path, config_fingerprint, load_trained_network, load_trained_predictor
from crowdrl.training.config import EVAL_BATCH, ConfigError, RunConfig, to_dict
from crowdrl.training.factories import crowd_config, make_actor, make_env
from crowdrl.training.run_folder import RunFolderBusy, check_run_folder
from crowdrl.training.trainer import Trainer

TEST_SEED = 0  # the fixed test cases: episodes 0.. of the test stream of seed 0


def run_training(run: RunConfig, run_dir: Path | str, *, render: bool | None = None,
                 prepare: Callable[[], None] | None = None) -> dict[str, Any]:
    """Train (or resume) in ``run_dir``, then test the best policy; returns the summary.

    Every refusal comes before anything in the folder is written: a folder that holds files but is
    no run folder (:class:`RunFolderRefused`), one another process writes (:class:`RunFolderBusy`),
    a checkpoint of another run (:class:`CheckpointError`). A finished run (status ``completed``,
    every frame trained) returns its ``summary.json`` and changes nothing. ``prepare`` runs once
    these checks have passed, under the lock and before the first write, for a run that starts
    from scratch (train.py writes ``config.yaml`` there). ``render`` (default
    ``run.logger.render``) draws the learning curves and test case 0."""
    run_dir = Path(run_dir)
    render = run.logger.render if render is None else render
    check_run_folder(run_dir)
    lock = lock_run_dir(run_dir)  # before the first write: one writer per folder
    try:
        trainer = Trainer(run, run_dir)
        resumed = trainer.restore()  # a refused resume raises here, before anything in the folder changes
        done = completed_summary(run_dir) if trainer.counters.frames >= run.train.total_frames else None
        if done is not None:
            trainer.close()
            lock.release()
            return done
        if prepare is not None and resumed is None:
            prepare()
        if resumed is not None:  # a checkpoint write that a kill cut short left its temporary
            for name in ("last.pt", "best.pt"):
                remove_stale_temporaries(run_dir / "checkpoints" / name)
    except BaseException:
        lock.release()
        raise
    start = time.perf_counter()
    try:
        with stop_signals(trainer):
            summary = trainer.train()
        result = evaluate_best(run, run_dir, render=render)
        summary = {**summary, "test": result, "wall_s": time.perf_counter() - start}
        trainer.emit({"kind": "test", "frames": trainer.counters.frames,
                      **{f"test/{k}": v for k, v in result["metrics"].items()}})
        trainer.write_status("completed", **summary)
        atomic_write_json(run_dir / "summary.json", summary, default=str)
    except BaseException as exc:
        trainer.write_status("failed" if not isinstance(exc, KeyboardInterrupt) else "interrupted",
                             error=repr(exc), frames=trainer.counters.frames)
        raise
    finally:
        trainer.close()
        lock.release()
    if render:
        from crowdrl.viz import plot_learning_curves

        plot_learning_curves(trainer.log.rows(), run_dir / "learning_curves.png",
                             title=f"{run.encoder.name} + {run.exploration.name}, {run.env.scenario}, seed {run.seed}")
    return summary


def lock_run_dir(run_dir: Path) -> FileLock:
    """An exclusive lock on ``run_dir/.lock`` (``filelock``'s OS lock: released when this process
    exits, even on a kill; ``.release()`` frees it earlier): a second writer to the same run folder,
    in this process or another, fails at once instead of mixing files. The ``.lock`` file stays,
    marking the folder as a run folder."""
    run_dir.mkdir(parents=True, exist_ok=True)
    # no soft-lock fallback: a soft lock outlives a killed process and would refuse every resume
    lock = FileLock(run_dir / ".lock", timeout=0, thread_local=False, fallback_to_soft=False, preserve_lock_file=True)
    try:
        lock.acquire()
    except Timeout:
        raise RunFolderBusy(f"{run_dir} is being written by another process; give this run its own folder") from None
    return lock


def completed_summary(run_dir: Path | str) -> dict[str, Any] | None:
    """The ``summary.json`` of a finished run (``status.json`` says ``completed``), else ``None``."""
    run_dir = Path(run_dir)
    try:
        status = json.loads((run_dir / "status.json").read_text())
        summary = json.loads((run_dir / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    if not (isinstance(status, dict) and status.get("state") == "completed" and isinstance(summary, dict)
            and "test" in summary):
        return None
    return summary


@contextmanager
def stop_signals(trainer: Trainer):
    """SIGTERM (sent by ``timeout``, ``kill`` and SLURM) and SIGINT ask the trainer to stop at the end
    of its current batch, after a checkpoint; the run is then marked "interrupted" and resumable. A
    second signal interrupts at once. Only in the main thread (signal handlers live there)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}

    def handler(signum, frame):
        if trainer.stop_requested:
            raise KeyboardInterrupt(f"signal {signum}")
        trainer.request_stop()

    for sig in previous:
        signal.signal(sig, handler)
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def evaluate_network(run: RunConfig, net: torch.nn.Module, *, scenario: str | None = None, seed: int = TEST_SEED,
                     episodes: int = 1000, num_humans: int | None = None, record_episode: int | None = None,
                     batch: int = EVAL_BATCH, predictor: torch.nn.Module | None = None
                     ) -> tuple[EpisodeMetrics, Trajectory | None]:
    """Test ``net`` on ``episodes`` cases of the test stream ``seed`` (the run's scenario by default);
    with ``planning.enabled`` through the planner of ``net`` and ``predictor``."""
    env = make_env(run, split="test", num_envs=min(episodes, batch), seed=seed, scenario=scenario,
                   num_humans=num_humans)
    return evaluate(env, make_actor(run, env, net, predictor), num_episodes=episodes, record_episode=record_episode)


def load_agent(checkpoint: Path | str, *, scenario: str | None = None, num_envs: int = 1, split: str = "test",
               seed: int = TEST_SEED, device: str = "cpu") -> tuple[EnvBase, TensorDictModuleBase]:
    """A trained agent (a run folder, a ``best.pt``, or a ``pretrained/`` folder) and an env to act in: the same
    ``make_env`` and actor (its planner included) that training and ``evaluate.py`` use. Act deterministically
    (``ExplorationType.DETERMINISTIC``), as in evaluation.

    Example::

        from torchrl.envs.utils import ExplorationType, set_exploration_type
        env, actor = load_agent("pretrained/sgd3qn-planning-egreedy-counterfactual-polyak-episodes-s0", num_envs=4)
        with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
            episode = env.rollout(117, policy=actor)  # test cases 0..3 of test seed 0
    """
    from dataclasses import replace

    from crowdrl.training.validation import check_device

    if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
        raise ValueError(f"num_envs: must be an integer >= 1, got {num_envs!r}")
    try:
        check_device(device)
    except ConfigError as exc:
        raise ValueError(str(exc)) from None
    run, net, data = load_trained_network(checkpoint)
    run = replace(run, device=device)
    predictor = load_trained_predictor(run, data, checkpoint_path(checkpoint))
    env = make_env(run, split=split, num_envs=num_envs, seed=seed, scenario=scenario)
    return env, make_actor(run, env, net.to(device), None if predictor is None else predictor.to(device))


def evaluate_best(run: RunConfig, run_dir: Path, *, render: bool = True, record_episode: int = 0) -> dict[str, Any]:
    """Greedy evaluation of ``checkpoints/best.pt`` on the test cases of the run's scenario."""
    _, net, best = load_trained_network(run_dir, config_fingerprint(to_dict(run)), config=to_dict(run))
    predictor = load_trained_predictor(run, best, checkpoint_path(run_dir))
    metrics, traj = evaluate_network(run, net, episodes=run.train.test_episodes, record_episode=record_episode,
                                     predictor=predictor)
    out = {"checkpoint_frames": best["frames"], "test_seed": TEST_SEED, "metrics": metrics.as_dict()}
    if render and traj is not None:
        from crowdrl.viz import animate_trajectory, plot_trajectory

        plot_trajectory(traj, run_dir / f"test_case{record_episode}.png", title=f"test case {record_episode}")
        animate_trajectory(traj, run_dir / f"test_case{record_episode}.gif")
    write_records(run_dir, [eval_record(metrics, scenario=run.env.scenario, seed=TEST_SEED, policy=policy_name(run),
                                        checkpoint=str(Path("checkpoints") / "best.pt"), checkpoint_frames=best["frames"],
                                        train_scenario=run.env.scenario, train_seed=run.seed)])
    return out


def policy_name(run: RunConfig, *, onnx: bool = False) -> str:
    """The ``policy`` an ``eval.json`` record names: ``<encoder>+<exploration>[+planning][+onnx]``."""
    return (f"{run.encoder.name}+{run.exploration.name}" + ("+planning" if run.planning.enabled else "")
            + ("+onnx" if onnx else ""))


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


ACT_KEYS = ("depth", "width", "safety_horizon")  # the planner settings an evaluation may change (eval.planning_*)


def act_with(run: RunConfig, acting: dict[str, int], prefix: str = "eval.planning_") -> RunConfig:
    """``run`` acting with the planner settings ``acting`` (names in :data:`ACT_KEYS`), checked as train checks
    them; ``ValueError`` naming ``<prefix><key>``. ``depth`` 0 turns planning off: the checkpoint then acts
    greedily on Q (with no other planner setting given)."""
    from dataclasses import replace

    from crowdrl.training.validation import validate

    unknown = sorted(set(acting) - set(ACT_KEYS))
    if unknown:
        raise ValueError(f"planning: unknown {unknown}; allowed: {', '.join(ACT_KEYS)}")
    depth = acting.get("depth")
    if depth is not None and (isinstance(depth, bool) or not isinstance(depth, int) or depth < 0):
        raise ValueError(f"{prefix}depth: must be an integer >= 0 (0: planning off, greedy on Q), got {depth!r}")
    if depth == 0:
        others = sorted(set(acting) - {"depth"})
        if others:
            raise ValueError(f"{prefix}{others[0]}: planning is off ({prefix}depth=0); leave {prefix}{others[0]} out")
        return replace(run, planning=replace(run.planning, enabled=False, safety_horizon=0))
    if not run.planning.enabled:
        raise ValueError(f"{prefix}{next(iter(acting))}: the checkpoint acts without planning (planning.enabled "
                         "was false when it trained)")
    changed = replace(run, planning=replace(run.planning, **acting))
    try:
        validate(changed, resources=False)
    except ConfigError as exc:
        raise ValueError(str(exc).replace("planning.", prefix, 1)) from None
    return changed


def is_onnx(checkpoint: Path | str | None) -> bool:
    """Whether ``checkpoint`` names an exported ONNX model (a ``.onnx`` file) rather than a checkpoint."""
    return checkpoint is not None and str(checkpoint).lower().endswith(".onnx")


def acted(run: RunConfig, key: str) -> int:
    """The planner setting ``key`` (of :data:`ACT_KEYS`) ``run`` acts with, for a record: 0 for ``depth`` and
    ``safety_horizon`` when it acts without planning."""
    return getattr(run.planning, key) if run.planning.enabled or key == "width" else 0


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
                  planning: dict[str, int] | None = None) -> tuple[dict[str, Any], Trajectory | None]:
    """Evaluate a trained ``checkpoint`` (run folder or ``.pt``) or a baseline ``policy`` by name on
    test cases ``0 .. episodes-1`` of test stream ``seed``; returns the ``eval.json`` record and the
    recorded trajectory. ``human_model``/``robot_visible`` (``None``: the checkpoint's; ORCA humans blind to
    the robot for a baseline) change how the humans move; ``social_force_share``/``linear_share``: a mixed
    crowd's shares (``None``: 0 where ``human_model`` is given, else the checkpoint's; a share other than 0
    needs ``human_model="mixed"``, given or the checkpoint's). Bad names and values raise ``ValueError`` naming
    the argument. ``ceiling``: a ceiling file of the same test cases (:mod:`crowdrl.evaluation.ceiling`); the
    record then adds the avoidable and unavoidable failures and the time over the ceiling (a file of another
    stream is refused before anything runs, naming the mismatch). ``planning``: act with these of the
    checkpoint's planner settings changed (``depth``, ``width``, ``safety_horizon``; no retraining; ``depth`` 0:
    greedy on Q, planning off); the record then shows them. A ``checkpoint`` ending in ``.onnx`` is a model
    written by ``crowdrl-export``, evaluated through onnxruntime (:class:`~crowdrl.policies.onnx_policy.OnnxPolicy`)
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
                             f"planning_safety_horizon={m.get('crowdrl.planning_safety_horizon', 0)}); export it again "
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
        from crowdrl.policies.onnx_policy import OnnxPolicy

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
                         train_scenario=run.env.scenario, train_seed=run.seed,
                         **({f"planning_{k}": acted(run, k) for k in acting}),
                         **(_humans_shown(vars(run.env)) if humans else {}), **_gap_fields(labels, ceiling, metrics))
    return record, traj
