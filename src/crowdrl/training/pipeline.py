"""A whole run: train, then evaluate the best checkpoint on the test cases and render it."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import torch

from crowdrl.evaluation import evaluate_policy
from crowdrl.training.checkpoint import atomic_write_bytes, load_checkpoint
from crowdrl.training.config import RunConfig
from crowdrl.training.trainer import Trainer, greedy_policy
from crowdrl.training.variants import make_network
from crowdrl.viz import animate_trajectory, plot_learning_curves, plot_trajectory


def run_training(run: RunConfig, run_dir: Path | str, *, render: bool = True) -> dict[str, Any]:
    """Train (or resume) in ``run_dir``, then test the best policy; returns the summary."""
    run_dir = Path(run_dir)
    trainer = Trainer(run, run_dir)
    start = time.perf_counter()
    try:
        summary = trainer.train()
        result = evaluate_best(run, run_dir, render=render)
        summary = {**summary, "test": result, "wall_s": time.perf_counter() - start}
        trainer._emit({"kind": "test", "frames": trainer.counters.frames,
                       **{f"test/{k}": v for k, v in result["metrics"].items()}})
        trainer._write_status("completed", **summary)
        atomic_write_bytes(run_dir / "summary.json", json.dumps(summary, indent=1, default=str).encode())
    except BaseException as exc:
        trainer._write_status("failed" if not isinstance(exc, KeyboardInterrupt) else "interrupted",
                              error=repr(exc), frames=trainer.counters.frames)
        raise
    finally:
        trainer.close()
    if render:
        plot_learning_curves(trainer.log.rows(), run_dir / "learning_curves.png",
                             title=f"{run.encoder.name} + {run.exploration.name}, {run.env.scenario}, seed {run.seed}")
    return summary


def evaluate_best(run: RunConfig, run_dir: Path, *, render: bool = True, record_episode: int = 0) -> dict[str, Any]:
    """Greedy evaluation of ``checkpoints/best.pt`` on the test cases of the run's scenario."""
    from crowdrl.sim.config import CrowdConfig

    best = load_checkpoint(run_dir / "checkpoints" / "best.pt")
    net = make_network(run)
    net.load_state_dict(best["net"])
    net.eval()  # noise and dropout off: the greedy policy of the mean network
    cfg = CrowdConfig(scenario=run.env.scenario, num_humans=run.env.num_humans)
    metrics, traj = evaluate_policy(cfg, greedy_policy(net), split="test", seed=0,
                                    num_episodes=run.train.test_episodes,
                                    batch_size=min(run.train.test_episodes, 1000), record_episode=record_episode)
    out = {"checkpoint_frames": best["frames"], "test_seed": 0, "metrics": metrics.as_dict()}
    if render and traj is not None:
        plot_trajectory(traj, run_dir / f"test_case{record_episode}.png", title=f"test case {record_episode}")
        animate_trajectory(traj, run_dir / f"test_case{record_episode}.gif")
    atomic_write_bytes(run_dir / "eval.json", json.dumps(out, indent=1).encode())
    return out


