"""The main job on a small default: train SG-D3QN, test it against ORCA, render it (``crowdrl-demo``,
``python -m crowdrl.cli.demo``, or ``python experiments/demo.py`` / ``make demo`` in a checkout).

Trains the default configuration (SG-D3QN with its online planning, ε-greedy, circle, the recommended learner:
counterfactual experience and Polyak targets) for the ``demo`` preset's budget,
evaluates the best validation checkpoint deterministically (ε = 0) on the scenario's fixed test cases (1000 by
default, test seed 0), runs the ORCA robot baseline on the same cases, prints both side by side,
and writes the learning curves, a PNG and a GIF of test case 0 into the run folder (printed).

    python experiments/demo.py                                  # preset=demo, seed 0
    python experiments/demo.py seed=1 out=runs/demo-s1          # any Hydra override of conf/; out=: the run folder
    python experiments/demo.py preset=smoke                     # a 30-second wiring check
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from crowdrl.cli import exit_with_error, one_line_errors
from crowdrl.resources import config_dir

CONF_DIR = config_dir()


def compose_run(overrides: list[str]):
    """The validated :class:`RunConfig` for ``conf/config.yaml`` plus Hydra ``overrides``; at the ``demo``
    preset the acting network is compiled (``train.compile_acting``, off in the schema and conf/:
    speed only, same Q to float rounding) unless an override sets it."""
    from hydra import compose, initialize_config_dir
    from hydra.core.config_store import ConfigStore

    from crowdrl.training.config import RunConfig
    from crowdrl.training.validation import validate

    ConfigStore.instance().store(name="run_schema", node=RunConfig)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides)
    if cfg.preset == "demo" and not any(o.lstrip("+~").startswith("train.compile_acting=") for o in overrides):
        cfg.train.compile_acting = True  # the demo's speed (docs/benchmarks.md), unless the command line sets it
    return cfg, validate(cfg)


def default_out(run) -> Path:
    """``runs/demo-<time>-<scenario>-s<seed>-<uid>`` (in the current directory): demos started in the same
    second never share a folder."""
    from crowdrl.training.resolvers import run_uid

    return Path("runs") / time.strftime(f"demo-%Y%m%d-%H%M%S-{run.env.scenario}-s{run.seed}-{run_uid()}")


def format_comparison(agent: dict, orca: dict, label: str) -> str:
    rows = [(label, agent), ("ORCA (same cases)", orca)]
    lines = [f"{'policy':<28} {'success':>8} {'collision':>9} {'timeout':>8} {'nav time':>9} {'return':>8}"]
    for name, m in rows:
        nav = m["navigation_time"]  # null (or NaN): no case reached the goal, shown as a dash
        nav_cell = f"{'–':>9}" if nav is None or math.isnan(nav) else f"{nav:8.2f}s"
        lines.append(f"{name:<28} {m['success_rate']:8.3f} {m['collision_rate']:9.3f} {m['timeout_rate']:8.3f} "
                     f"{nav_cell} {m['average_return']:8.4f}")
    return "\n".join(lines)


@one_line_errors("demo")
def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("overrides", nargs="*", metavar="key=value",
                   help="Hydra overrides of conf/config.yaml, e.g. seed=1; out=<folder>: the run folder "
                        "(default runs/demo-<time>-<scenario>-s<seed>-<uid>)")
    args = p.parse_args(argv)
    outs = [o.split("=", 1)[1] for o in args.overrides if o.startswith("out=")]
    args.overrides = [o for o in args.overrides if not o.startswith("out=")]
    if len(outs) > 1 or (outs and not outs[0]):
        p.error(f"out: give one run folder, got {outs}")
    from omegaconf import OmegaConf

    from crowdrl.training import CheckpointError, ConfigError

    try:
        cfg, run = compose_run(args.overrides)
    except ConfigError as exc:
        p.error(f"invalid configuration: {exc}")
    import torch

    from crowdrl.evaluation import evaluate_orca
    from crowdrl.files import atomic_write_json
    from crowdrl.training.config import crowd_config
    from crowdrl.training import run_training

    from crowdrl.training.run_folder import RunFolderRefused

    out = Path(outs[0]) if outs else default_out(run)
    method = f"{run.encoder.name} + {run.exploration.name}" + (" + planning" if run.planning.enabled else "")
    print(f"training {method} on {run.env.scenario}, preset {run.preset}, "
          f"seed {run.seed}: {run.train.total_frames} frames -> {out}", flush=True)
    start = time.perf_counter()
    try:  # config.yaml is written under the folder's lock, once every check has passed
        summary = run_training(run, out, prepare=lambda: (out / "config.yaml").write_text(OmegaConf.to_yaml(cfg)))
    except (CheckpointError, RunFolderRefused) as exc:
        exit_with_error("demo", f"cannot run in {out}: {exc}")
    if run.logger.render:
        from crowdrl.cli.train import render

        render(run, out)
    train_s = time.perf_counter() - start
    agent = summary["test"]["metrics"]

    torch.set_num_threads(run.threads)
    orca, _ = evaluate_orca(crowd_config(run), seed=summary["test"]["test_seed"], episodes=run.train.test_episodes)
    orca = orca.as_dict()
    result = {"agent": agent, "orca": orca, "beats_orca": agent["success_rate"] > orca["success_rate"],
              "frames": summary["frames"], "updates": summary["updates"], "best_frames": summary["best_frames"],
              "wall_s": train_s, "test_cases": run.train.test_episodes, "test_seed": summary["test"]["test_seed"]}
    atomic_write_json(out / "demo.json", result)
    print()
    print(f"{run.train.test_episodes} {run.env.scenario} test cases (test seed {result['test_seed']}); "
          f"{summary['frames']} frames, {summary['updates']} updates, {train_s / 60:.1f} min incl. validation and test")
    print(format_comparison(agent, orca, f"{method} (best@{summary['best_frames']})"))
    verdict = "beats" if result["beats_orca"] else "does NOT beat"
    print(f"\nthe trained policy {verdict} ORCA on success rate")
    print(f"run folder (learning_curves.png, test_case0.png/.gif, eval.json, demo.json): {out.resolve()}")
    return result


if __name__ == "__main__":  # python -m crowdrl.cli.demo
    main(sys.argv[1:])
