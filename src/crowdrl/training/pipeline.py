"""A whole run: train, then evaluate the best checkpoint on the test cases (its records, and test case 0 as a trajectory)."""

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
from crowdrl.training.checkpoint import checkpoint_path, config_fingerprint, load_trained_network, load_trained_predictor
from crowdrl.training.config import EVAL_BATCH, ConfigError, RunConfig, to_dict, trained_on
from crowdrl.training.factories import make_actor, make_env
from crowdrl.training.run_folder import RunFolderBusy, check_run_folder
from crowdrl.training.trainer import Trainer

TEST_SEED = 0  # the fixed test cases: episodes 0.. of the test stream of seed 0


def run_training(run: RunConfig, run_dir: Path | str, *, prepare: Callable[[], None] | None = None) -> dict[str, Any]:
    """Train (or resume) in ``run_dir``, then test the best policy; returns the summary.

    Every refusal comes before anything in the folder is written: a folder that holds files but is
    no run folder (:class:`RunFolderRefused`), one another process writes (:class:`RunFolderBusy`),
    a checkpoint of another run (:class:`CheckpointError`). A finished run (status ``completed``,
    every frame trained) returns its ``summary.json`` and changes nothing. ``prepare`` runs once
    these checks have passed, under the lock and before the first write, for a run that starts
    from scratch (train.py writes ``config.yaml`` there). The figures are the commands' (``logger.render``:
    :func:`crowdrl.viz.render_run_folder`), drawn from the folder's files."""
    run_dir = Path(run_dir)
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
        tested = time.perf_counter()
        result = evaluate_best(run, run_dir)
        test_s = time.perf_counter() - tested
        # wall_s: this call (a resumed run: its last segment); run_s: the whole run, every segment's collection,
        # updates and validation (the checkpointed timers) and the test
        summary = {**summary, "test": result, "wall_s": time.perf_counter() - start, "test_s": test_s,
                   "run_s": sum(trainer.counters.timers().values()) + test_s}
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


def evaluate_best(run: RunConfig, run_dir: Path, *, record_episode: int = 0) -> dict[str, Any]:
    """Greedy evaluation of ``checkpoints/best.pt`` on the test cases of the run's scenario: its records in
    ``eval.json``, and test case ``record_episode`` as ``test_case<k>.trajectory.json`` (what the figures draw)."""
    _, net, best = load_trained_network(run_dir, config_fingerprint(to_dict(run)), config=to_dict(run))
    predictor = load_trained_predictor(run, best, checkpoint_path(run_dir))
    metrics, traj = evaluate_network(run, net, episodes=run.train.test_episodes, record_episode=record_episode,
                                     predictor=predictor)
    out = {"checkpoint_frames": best["frames"], "test_seed": TEST_SEED, "metrics": metrics.as_dict()}
    if traj is not None:
        traj.save(run_dir / f"test_case{record_episode}.trajectory.json")
    write_records(run_dir, [eval_record(metrics, scenario=run.env.scenario, seed=TEST_SEED, policy=policy_name(run),
                                        checkpoint=str(Path("checkpoints") / "best.pt"), checkpoint_frames=best["frames"],
                                        train_scenario=trained_on(run), train_seed=run.seed)])
    return out


def policy_name(run: RunConfig, *, onnx: bool = False) -> str:
    """The ``policy`` an ``eval.json`` record names: ``<encoder>+<exploration>[+planning][+onnx]``."""
    return (f"{run.encoder.name}+{run.exploration.name}" + ("+planning" if run.planning.enabled else "")
            + ("+onnx" if onnx else ""))


# the planner settings an evaluation may change (eval.planning_*)
ACT_KEYS = ("depth", "width", "safety_horizon", "progress_bias")


def act_with(run: RunConfig, acting: dict[str, float], prefix: str = "eval.planning_") -> RunConfig:
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
        return replace(run, planning=replace(run.planning, enabled=False, safety_horizon=0, progress_bias=0.0))
    if not run.planning.enabled:
        raise ValueError(f"{prefix}{next(iter(acting))}: the checkpoint acts without planning (planning.enabled "
                         "was false when it trained)")
    changed = replace(run, planning=replace(run.planning, **acting))
    try:
        validate(changed, resources=False)
    except ConfigError as exc:
        raise ValueError(str(exc).replace("planning.", prefix, 1)) from None
    return changed
